"""The shipped configuration files: ``config/*.yaml`` and the CANopen ``*.eds``.

In a source checkout they live in the top-level ``config/`` folder (the user-facing copy);
a wheel ships the same files as the package data ``gateway/data/`` (pyproject.toml maps
``config/`` there). :func:`data_dir` finds whichever is present through
:mod:`importlib.resources`, so ``cdpr-gateway demo`` works from any directory after a
plain ``pip install``.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

PACKAGED = "data"  # gateway/data/ inside an installed wheel


def data_dir() -> Path:
    """The directory holding ``default.yaml``, ``replicate.yaml`` and the EDS files."""
    packaged = Path(str(files("gateway") / PACKAGED))
    if (packaged / "default.yaml").is_file():
        return packaged
    return Path(__file__).resolve().parents[2] / "config"  # source checkout


def data_file(name: str) -> Path:
    """One shipped file by name, e.g. ``data_file("default.yaml")``."""
    return data_dir() / name


def resolve_beside(path: str | Path, config_file: str | Path | None) -> Path:
    """``path`` as given when absolute, else relative to the directory of ``config_file``
    (the shipped data directory when there is no file)."""
    p = Path(path).expanduser()
    if p.is_absolute():
        return p
    base = Path(config_file).resolve().parent if config_file else data_dir()
    return base / p
