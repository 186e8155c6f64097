"""``cdpr-gateway`` command line: ``run | check | demo | sim-plc | record | replicate | diagnose
| calibrate | export | fleet``.

Each command lives in its own module, imported only when that command is chosen. A command
module provides ``configure_parser(command, parser)`` and ``run_command(command, args)``
returning the exit status. Errors of the project (:class:`GatewayError`) end the program
with status 2 and one clear line on stderr, and so do bad command-line arguments; anything
else is a bug and shows a traceback. The soft PLC's commands (``demo``, ``sim-plc``,
``record``, ``replicate``, ``calibrate``) live in ``sim_plc`` and are imported only when
chosen: the daemon's modules never import ``sim_plc``.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from typing import NoReturn

from gateway import __version__
from gateway.errors import GatewayError

COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("gateway.service.daemon", "run the gateway daemon against the PLC in the config"),
    "check": (
        "gateway.service.check",
        "validate a config; with --connect read once (writes nothing)",
    ),
    "demo": ("sim_plc.demo", "soft PLC and gateway on loopback, then a table of results"),
    "sim-plc": ("sim_plc.cli", "serve the soft PLC (Modbus TCP / CANopen) until stopped"),
    "record": ("sim_plc.cli", "run the soft PLC's plant and write a recording (CSV)"),
    "replicate": ("sim_plc.replicate", "reproduce the paper's experiment (JSON, markdown, PNG)"),
    "diagnose": ("gateway.diagnose.cli", "find and model the physics a recording shows"),
    "calibrate": ("sim_plc.calibrate", "soft PLC loop: record, diagnose, write the model, rerun"),
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
    args = parser.parse_args(argv[1:])
    try:
        return int(module.run_command(command, args) or 0)
    except GatewayError as exc:
        print(f"cdpr-gateway {command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
