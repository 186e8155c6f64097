"""The bundled default config, edited, written where a test can pass it as ``--config``."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from gateway.core.config import DEFAULT_CONFIG_PATH
from gateway.core.configtypes import read_yaml


def edited_config(
    directory: Path, edit: Callable[[dict[str, Any]], None] | None = None, name: str = "gw.yaml"
) -> Path:
    """``config/default.yaml`` as data, changed in place by ``edit``, written to
    ``directory/name``; returns the path."""
    data = read_yaml(DEFAULT_CONFIG_PATH)
    if edit is not None:
        edit(data)
    path = Path(directory) / name
    path.write_text(yaml.safe_dump(data))
    return path
