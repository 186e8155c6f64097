"""``python -m gateway``: the same as the ``cdpr-gateway`` command."""

from gateway.cli import main

raise SystemExit(main())
