"""``cdpr-gateway`` command line: ``run | check | demo | sim-plc | record | replicate | diagnose
| calibrate | examples | export | fleet``.

Each command lives in its own module, imported only when that command is chosen. A command
module provides ``configure_parser(command, parser)`` and ``run_command(command, args)``
returning the exit status. Errors of the project (:class:`GatewayError`) end the program
with status 2 and one clear line on stderr, and so do bad command-line arguments: what a
restart cannot fix. A :class:`TemporaryError` (a port another process holds) exits 75
(EX_TEMPFAIL), which a service manager may retry. Anything else is a bug and shows a
traceback. The soft PLC's commands (``demo``, ``sim-plc``,
``record``, ``replicate``, ``calibrate``) live in ``sim_plc`` and are imported only when
chosen: the daemon's modules never import ``sim_plc``.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import sys
from collections.abc import Iterator, Sequence
from typing import NoReturn

from gateway import __version__
from gateway.core.cliopts import add_common_options, resolve_log_level, setup_logging
from gateway.errors import GatewayError, TemporaryError

EX_TEMPFAIL = 75  # sysexits.h: a temporary failure, a retry may succeed

COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("gateway.service.daemon", "run the gateway daemon against the PLC in the config"),
    "check": (
        "gateway.service.check",
        "validate a config; with --connect read once (writes nothing)",
    ),
    "demo": ("sim_plc.commands", "soft PLC and gateway on loopback, then a table of results"),
    "sim-plc": ("sim_plc.cli", "serve the soft PLC (Modbus TCP / CANopen) until stopped"),
    "record": ("sim_plc.cli", "run the soft PLC's plant and write a recording (CSV)"),
    "replicate": ("sim_plc.commands", "reproduce the paper's experiment (JSON, markdown, PNG)"),
    "diagnose": ("gateway.diagnose.cli", "find and model the physics a recording shows"),
    "calibrate": ("sim_plc.commands", "soft PLC loop: record, diagnose, write the model, rerun"),
    "examples": ("gateway.service.examples", "list the bundled configs, or copy them into DIR"),
    "export": ("gateway.recordings.export", "write a recording as MCAP (Foxglove, PlotJuggler)"),
    "fleet": ("gateway.fleet.cli", "diagnose many recordings on dask.distributed, one table"),
}


class _OneLineParser(argparse.ArgumentParser):
    """A bad argument ends the program with one line (no usage block) and status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def _top_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cdpr-gateway",
        description="Pulley-friction compensation gateway for cable-driven parallel robots.",
        epilog="Run 'cdpr-gateway COMMAND --help' for a command's options.",
    )
    parser.add_argument("--version", action="version", version=f"cdpr-gateway {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, help_text) in COMMANDS.items():
        sub.add_parser(name, help=help_text, add_help=False)
    return parser


@contextlib.contextmanager
def _quiet(quiet: bool) -> Iterator[None]:
    """With ``--quiet``, what a command prints on stderr (progress) goes nowhere; the log
    handler keeps the real stderr (warnings), and errors are printed after this ends."""
    if not quiet:
        yield
        return
    with open(os.devnull, "w", encoding="utf-8") as devnull, contextlib.redirect_stderr(devnull):
        yield


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in COMMANDS:
        parser = _top_parser()
        parser.parse_args(argv)  # prints help / version / an error for unknown commands
        parser.print_help()
        return 2
    command = argv[0]
    module_name, help_text = COMMANDS[command]
    module = importlib.import_module(module_name)
    parser = _OneLineParser(prog=f"cdpr-gateway {command}", description=help_text)
    module.configure_parser(command, parser)
    add_common_options(parser)  # --log-level, --quiet: the same on every command
    args = parser.parse_args(argv[1:])
    setup_logging(resolve_log_level(args))
    try:
        with _quiet(args.quiet):
            return int(module.run_command(command, args) or 0)
    except TemporaryError as exc:
        print(f"cdpr-gateway {command}: error: {exc} (temporary: try again)", file=sys.stderr)
        return EX_TEMPFAIL
    except GatewayError as exc:
        print(f"cdpr-gateway {command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
