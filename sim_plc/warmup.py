"""``cdpr-gateway warmup [--config FILE]``: compile the numba kernels ahead, once.

The first run after installing compiles the kernels that the gateway's cycle, the soft
PLC's plant and the diagnosis use (numba caches them beside the sources, or in
``NUMBA_CACHE_DIR``; :mod:`gateway.core.firstrun` says so when it happens). This command
does it ahead, saying what it compiles and how long it takes, so that the daemon's first
start, the first ``demo`` and the first ``diagnose`` do not. The systemd unit runs it as
``ExecStartPre`` and ``make demo`` before the demo; warm, it takes a few seconds.
"""

from __future__ import annotations

import argparse
import sys
import time

EPILOG = """example:
  cdpr-gateway warmup --config /etc/cdpr-gateway/gateway.yaml"""


def configure_parser(command: str, parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config",
        metavar="FILE",
        help="the config whose model the kernels are compiled for (default: the bundled "
        "loopback config)",
    )
    parser.epilog = EPILOG
    parser.formatter_class = argparse.RawDescriptionHelpFormatter


def run_command(command: str, args: argparse.Namespace) -> int:
    from drivers.virtual import VirtualDriver
    from gateway.core.config import DEFAULT_CONFIG_PATH, load_config
    from gateway.core.firstrun import compiling
    from gateway.diagnose.engine import load_kernels
    from gateway.model.effects import forms
    from gateway.runtime.loop import CyclicService
    from sim_plc.plant import Plant, make_recording

    def say(line: str) -> None:
        print(f"warmup: {line}", file=sys.stderr, flush=True)

    start = time.monotonic()
    cfg = load_config(args.config or DEFAULT_CONFIG_PATH)
    CyclicService(cfg, VirtualDriver(cfg), history=16)  # its log says when it compiles
    make_recording(cfg, None, 0.01)  # record, calibrate: the batch plant (it says so)
    plant = Plant(cfg, chunk=4)  # demo, sim-plc: the per-cycle plant
    for _ in range(10):
        plant.step()
    with compiling("the diagnosis", [forms._lowpass_kernel], say):
        load_kernels(cfg.friction)
    say(f"every kernel is in numba's cache ({time.monotonic() - start:.1f} s)")
    return 0
