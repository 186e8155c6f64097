"""The command lines of ``demo``, ``replicate`` and ``calibrate``: their arguments, parsed
before anything heavy is imported. The command's module (the plant, the loop, the
compiled kernels: numba) is imported only when the command runs, so ``--help`` and a bad
argument answer at once (``tests/test_cli_lazy.py``)."""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path

from gateway.core.cliopts import add_config_option
from gateway.core.config import DEFAULT_CONFIG_PATH
from gateway.core.resources import data_file

MODULES = {
    "demo": "sim_plc.demo",
    "replicate": "sim_plc.replicate",
    "calibrate": "sim_plc.calibrate",
}


def configure_parser(command: str, parser: argparse.ArgumentParser) -> None:
    {"demo": _demo, "replicate": _replicate, "calibrate": _calibrate}[command](parser)


def run_command(command: str, args: argparse.Namespace) -> int:
    return int(importlib.import_module(MODULES[command]).run_command(command, args) or 0)


def _demo(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seconds", type=float, default=10.0, help="how long to run")
    add_config_option(parser, DEFAULT_CONFIG_PATH)
    parser.add_argument(
        "--bus",
        choices=("modbus_tcp", "canopen"),
        default=None,
        help="fieldbus (default: bus.driver of the config)",
    )
    parser.add_argument(
        "--offline", action="store_true", help="plant in process, virtual driver, no sockets"
    )
    parser.add_argument(
        "--stand-in", action="store_true", help="with --offline: sinusoidal stand-in, not the plant"
    )
    parser.add_argument(
        "--no-realtime",
        action="store_true",
        help="do not apply loop.realtime (SCHED_FIFO, mlockall, GC off) to "
        "the gateway's thread and the soft PLC",
    )


def _replicate(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, help="directory for JSON, markdown and PNGs")
    add_config_option(parser, data_file("replicate.yaml"))
    parser.add_argument(
        "--seconds",
        type=float,
        default=None,
        help="cap each run's simulated time, in seconds (default: the config's runs in full)",
    )
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")


def _calibrate(parser: argparse.ArgumentParser) -> None:
    add_config_option(
        parser,
        why="SIM.yaml, a config whose sim_plc: section hides an "
        "effect: 'cdpr-gateway examples' copies one per effect (calibrate/)",
    )
    parser.add_argument("--seconds", type=float, default=30.0, help="length of each gateway run")
    parser.add_argument("--out", type=Path, required=True, help="directory for the results")
    parser.add_argument(
        "--runs",
        type=int,
        default=1,
        help="'before' runs recorded, each another motion and noise draw (the plant's "
        "seeds + 1, + 2, ...), diagnosed jointly for one fitted model",
    )
