"""What every command of the command line shares: ``--log-level``, ``--quiet``, the
``--config`` option and its stated default, the log format, output directories.

:func:`add_common_options` is called by :mod:`gateway.cli` for every command (a command
module never defines ``--log-level`` or ``--quiet`` itself); ``--quiet`` means no progress
or informational lines on stderr (log level WARNING unless ``--log-level`` says otherwise;
warnings and errors still appear). ``--config`` is required where a bundled default would
point the command at the wrong machine (``run``, ``check``) or at nothing to find
(``calibrate``); elsewhere its help names the bundled default.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from gateway.errors import ConfigError

_RAISED: list[int] = []


def signal_raised(signum: int) -> None:
    """Note that the program's handler (:func:`gateway.cli._interrupt`) is raising
    ``signum`` as ``Interrupted``. Python ignores an exception raised where it cannot
    propagate (a weakref callback such as the import lock's, a ``__del__``), and a signal
    handler's exception can land there: the signal would be lost, the command would run
    on. A command that takes SIGINT/SIGTERM over asks :func:`lost_signal` first."""
    _RAISED.append(signum)


def forget_signals() -> None:
    """A new command starts (:func:`gateway.cli.main`, also called in-process by tests and
    tools) or the last one has ended: no signal of an earlier one counts as lost."""
    _RAISED.clear()


def lost_signal() -> int | None:
    """The signal raised as ``Interrupted`` that never unwound the program, or None. Asked
    where a command takes the signals over: had the exception propagated, the program
    would not be there, so a signal noted by then was swallowed and the command stops."""
    return _RAISED[-1] if _RAISED else None


LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
FOREIGN_LOGGERS = ("canopen", "can", "pymodbus")


def log_level(text: str) -> str:
    """argparse type for ``--log-level``: one of :data:`LOG_LEVELS`, any case."""
    level = text.upper()
    if level not in LOG_LEVELS:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a log level (choose from {', '.join(LOG_LEVELS)})"
        )
    return level


def add_common_options(parser: argparse.ArgumentParser) -> None:
    """``--log-level`` and ``--quiet``, the same on every command."""
    parser.add_argument(
        "--log-level",
        type=log_level,
        default=None,
        metavar="LEVEL",
        help="DEBUG, INFO, WARNING, ERROR or CRITICAL (default INFO, WARNING with --quiet)",
    )
    parser.add_argument(
        "--quiet",
        action="store_true",
        help="no progress or informational lines on stderr (warnings and errors still)",
    )


def resolve_log_level(args: argparse.Namespace) -> str:
    """The level ``--log-level`` and ``--quiet`` ask for (stored back into ``args``)."""
    level = args.log_level or ("WARNING" if args.quiet else "INFO")
    args.log_level = level
    return level


def setup_logging(level: str) -> None:
    """The project's log format on stderr; foreign loggers at WARNING unless DEBUG."""
    logging.basicConfig(stream=sys.stderr, format=LOG_FORMAT)  # no-op if already set up
    logging.getLogger().setLevel(level)
    foreign = logging.DEBUG if level == "DEBUG" else logging.WARNING
    for name in FOREIGN_LOGGERS:
        logging.getLogger(name).setLevel(foreign)


def add_config_option(
    parser: argparse.ArgumentParser, default: Path | None = None, why: str = ""
) -> None:
    """``--config FILE``: required when ``default`` is None (``why`` says why), else the
    bundled file ``default`` with the help saying so."""
    if default is None:
        why = f": {why}" if why else ""
        parser.add_argument(
            "--config", metavar="FILE", required=True, help=f"YAML config file (required{why})"
        )
        return
    parser.add_argument(
        "--config",
        metavar="FILE",
        default=str(default),
        help=f"YAML config file (default: the bundled {default.name}, a soft "
        "PLC on 127.0.0.1; 'cdpr-gateway examples' lists and copies the "
        "bundled configs)",
    )


def output_dir(path: str | Path, option: str) -> Path:
    """The directory ``path`` a command will write into, checked (and created, one level:
    its parent must exist) before the work starts; errors name the option and the path."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ConfigError(f"{option} {p}: exists and is not a directory")
    if not p.exists() and not p.parent.is_dir():
        raise ConfigError(f"{option} {p}: directory {p.parent} does not exist")
    try:
        p.mkdir(exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"{option} {p}: cannot create: {exc.strerror or exc}") from exc
    if not os.access(p, os.W_OK | os.X_OK):
        raise ConfigError(f"{option} {p}: is not writable")
    return p
