"""The shipped files: ``config/*.yaml`` and the CANopen ``*.eds``, the service files of
``deploy/`` and the documents of ``docs/``.

In a source checkout they live in the top-level ``config/``, ``deploy/`` and ``docs/``
folders (the user-facing copies); a wheel ships the same files as the package data
``gateway/data/``, ``gateway/data/deploy/`` and ``gateway/data/docs/`` (setup.py maps them
there). :func:`data_dir`, :func:`deploy_dir` and :func:`docs_dir` find whichever is present
through :mod:`importlib.resources`, so ``cdpr-gateway demo`` and ``cdpr-gateway examples
deploy DIR`` work from any directory after a plain ``pip install``.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

PACKAGED = "data"  # gateway/data/ inside an installed wheel


def _bundle(sub: tuple[str, ...], probe: str, checkout: str) -> Path:
    """``gateway/data/<sub>`` of an installed wheel when it holds ``probe``, else the source
    checkout's top-level folder ``checkout``."""
    packaged = Path(str(files("gateway") / PACKAGED)).joinpath(*sub)
    if (packaged / probe).is_file():
        return packaged
    return Path(__file__).resolve().parents[2] / checkout  # source checkout


def data_dir() -> Path:
    """The directory holding ``default.yaml``, ``replicate.yaml`` and the EDS files."""
    return _bundle((), "default.yaml", "config")


def deploy_dir() -> Path:
    """The directory holding the systemd unit, the Prometheus and Alertmanager files and the
    Grafana dashboard (``deploy/`` of a checkout)."""
    return _bundle(("deploy",), "cdpr-gateway.service", "deploy")


def docs_dir() -> Path:
    """The directory holding the documents (``docs/`` of a checkout)."""
    return _bundle(("docs",), "service.md", "docs")


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
