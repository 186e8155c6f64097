"""A fleet's recordings diagnosed on dask.distributed: ``cdpr-gateway fleet``.

One diagnosis per recording is one task (:func:`.task.diagnose_task`, which calls the
diagnosis through its one public entry point, :func:`gateway.diagnose.fromfiles.diagnose_file`,
and returns the report's text exactly as ``diagnose --json`` writes it); the command
(:mod:`.cli`) gathers the reports into the fleet table (:mod:`.table`), ``fleet.md`` and
the plots (:mod:`.plots`). Only :mod:`.cli` and :mod:`.run` import dask (the ``fleet``
extra).
"""
