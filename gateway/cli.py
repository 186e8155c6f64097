"""``cdpr-gateway`` command line: ``run | check | demo | sim-plc | record | replicate | diagnose
| calibrate | examples | warmup | export | fleet | top``.

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
import signal
import sys
import threading
from collections.abc import Iterator, Sequence
from typing import NoReturn

from gateway import __version__
from gateway.core.cliopts import (
    add_common_options,
    forget_signals,
    resolve_log_level,
    setup_logging,
    signal_raised,
)
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
    "record": (
        "sim_plc.cli",
        "run the soft PLC's plant (no gateway) and write a recording (CSV, CSV.gz, Parquet)",
    ),
    "replicate": ("sim_plc.commands", "reproduce the paper's experiment (JSON, markdown, PNG)"),
    "diagnose": ("gateway.diagnose.cli", "find and model the physics a recording shows"),
    "calibrate": ("sim_plc.commands", "soft PLC loop: record, diagnose, write the model, rerun"),
    "examples": ("gateway.service.examples", "list the bundled configs, or copy them into DIR"),
    "warmup": ("sim_plc.warmup", "compile the numba kernels ahead (the first run does otherwise)"),
    "export": ("gateway.recordings.export", "write a recording as MCAP (Foxglove, PlotJuggler)"),
    "fleet": ("gateway.fleet.cli", "diagnose many recordings on dask.distributed, one table"),
    "top": ("gateway.service.top", "a live view of a running gateway, from its metrics (q quits)"),
}


# One example per command (a second line: another form), shown under its --help (the
# README's tour uses the same).
EXAMPLES: dict[str, str] = {
    "run": "cdpr-gateway run --config /etc/cdpr-gateway/gateway.yaml",
    "check": "cdpr-gateway check --config yours.yaml --connect",
    "demo": "cdpr-gateway demo --seconds 60 --bus canopen",
    "sim-plc": "cdpr-gateway sim-plc --config config/default.yaml --port 5020",
    "record": "cdpr-gateway record --config config/calibrate/viscous.yaml --seconds 40 "
    "--out rec.csv.gz",
    "replicate": "cdpr-gateway replicate --out replication/",
    "diagnose": "cdpr-gateway diagnose rec.csv.gz --model config/default.yaml --json rep.json "
    "--report rep/\n  cdpr-gateway diagnose run1.csv run2.csv run3.csv --model model.yaml "
    "--json rep.json   # one machine's recordings, jointly",
    "calibrate": "cdpr-gateway calibrate --config config/calibrate/viscous.yaml --seconds 30 "
    "--out cal/\n  cdpr-gateway calibrate --config config/calibrate/viscous.yaml --seconds 30 "
    "--runs 3 --out cal/   # 3 runs, other motions, fitted jointly",
    "examples": "cdpr-gateway examples deploy service/",
    "warmup": "cdpr-gateway warmup --config /etc/cdpr-gateway/gateway.yaml",
    "export": "cdpr-gateway export rec.csv.gz --to mcap rec.mcap",
    "fleet": "cdpr-gateway fleet 'recordings/*.parquet' --model config/default.yaml --out fleet/"
    "\n  cdpr-gateway fleet logs/ --model config/default.yaml --out fleet/ --per-robot"
    "   # each robot's recordings jointly",
    "top": "cdpr-gateway top --metrics http://127.0.0.1:9109/metrics",
}

# One vocabulary of placeholders, by option (dest), for every command's --help.
PLACEHOLDERS: dict[str, str] = {
    "config": "FILE",
    "model": "FILE",
    "json": "FILE",
    "validate": "FILE",
    "write_model": "FILE",
    "record": "FILE",
    "report": "DIR",
    "tls_cert": "FILE",
    "tls_key": "FILE",
    "tls_ca": "FILE",
    "seconds": "SECONDS",
    "cycles": "N",
    "workers": "N",
    "seed": "N",
    "runs": "N",
    "host": "HOST",
    "port": "PORT",
    "scheduler": "ADDRESS",
    "robot": "NAME",
    "columns": "MAP",
}
OUT_IS_DIR = ("replicate", "calibrate", "fleet")  # --out: a directory; elsewhere a file


class _HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Examples as written; each option's default shown when it has one and its help does
    not say it already."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        shown = action.default not in (None, False, argparse.SUPPRESS, [])
        if shown and "default" not in text and action.option_strings:
            text += " (default: %(default)s)"
        return text


def _teach(command: str, parser: argparse.ArgumentParser) -> None:
    """The placeholders of :data:`PLACEHOLDERS` and the command's example."""
    for action in parser._actions:
        if (
            action.nargs == 0
            or action.choices
            or (action.metavar is not None and (not action.option_strings))
        ):
            continue
        word = PLACEHOLDERS.get(action.dest)
        if action.dest == "out":
            word = "DIR" if command in OUT_IS_DIR else "FILE"
        if not action.option_strings:  # positionals: their name, in capitals
            word = "RECORDING" if action.dest == "recordings" else action.dest.upper()
        if word is not None:
            action.metavar = word
    example = f"example:\n  {EXAMPLES[command]}"
    parser.epilog = parser.epilog or example
    parser.formatter_class = _HelpFormatter


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


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM outside the daemon's loop (which handles its own): raised where the
    program is, so that ``finally`` blocks and context managers close files; ends the
    program with one line and 128 + the signal's number. A command that stops in order on
    its own (``record``: the file closed) raises it with ``detail``, the end of that line
    (how much was done)."""

    def __init__(self, signum: int, detail: str = "") -> None:
        super().__init__(signum)
        self.signum = signum
        self.detail = detail


def _interrupt(signum: int, _frame: object) -> None:
    signal_raised(signum)  # if Python swallows the exception, the signal is not lost
    raise Interrupted(signum)


def _signal_within(exc: BaseException) -> Interrupted | None:
    """The signal an exception stands for: ``exc`` itself or the ``Interrupted`` it was
    raised from or while handling. A library can turn the handler's exception into its own:
    a C extension's module initialisation (pybind11: scipy's HiGHS) raises
    ``ImportError: initialization failed`` from it, so a SIGTERM during that import ended
    ``record`` with a traceback and status 1 (CI, 1 run in about 70 under load)."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        if isinstance(current, Interrupted):
            return current
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return None


def _signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = argv[0] if argv and argv[0] in COMMANDS else "cdpr-gateway"
    previous = {}
    if threading.current_thread() is threading.main_thread():  # before any heavy import
        for sig in (signal.SIGINT, signal.SIGTERM):
            if signal.getsignal(sig) is not signal.SIG_IGN:  # nohup, a background job
                previous[sig] = signal.signal(sig, _interrupt)
    forget_signals()  # an earlier in-process command's signals are not this one's
    try:
        try:
            status = _main(argv)
            sys.stdout.flush()  # here, where a closed pipe is caught, not at the interpreter's exit
            return status
        except Exception as exc:  # a signal a library wrapped is still the signal
            interrupted = _signal_within(exc)
            if interrupted is None:
                raise
            raise interrupted from None
    except Interrupted as exc:
        # the daemon stops in order from its loop (exit 0); interrupted before or after it,
        # `run` has written nothing yet or has already stopped: an orderly stop as well
        code = 0 if command == "run" else 128 + exc.signum
        what = "stopped" if command == "run" else "interrupted"
        line = f"cdpr-gateway {command}: {what} ({_signal_name(exc.signum)}){exc.detail}"
        print(line, file=sys.stderr)
        return code
    except KeyboardInterrupt:  # raised by a handler of the command's own
        print(f"cdpr-gateway {command}: interrupted (SIGINT)", file=sys.stderr)
        return 0 if command == "run" else 130
    except BrokenPipeError:
        # the reader of our output went away (`examples | head -1`): end quietly, as a
        # process that SIGPIPE ended; stdout is pointed at /dev/null so that the
        # interpreter's final flush does not fail again
        with contextlib.suppress(OSError):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        forget_signals()


def _main(argv: list[str]) -> int:
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
    _teach(command, parser)
    args = parser.parse_args(argv[1:])
    setup_logging(resolve_log_level(args))
    try:
        with _quiet(args.quiet):
            return int(module.run_command(command, args) or 0)
    except GatewayError as exc:
        if (interrupted := _signal_within(exc)) is not None:  # our error, made by the signal
            raise interrupted from None
        if isinstance(exc, TemporaryError):
            print(f"cdpr-gateway {command}: error: {exc} (temporary: try again)", file=sys.stderr)
            return EX_TEMPFAIL
        print(f"cdpr-gateway {command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
