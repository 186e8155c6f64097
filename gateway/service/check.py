"""``cdpr-gateway check --config FILE [--connect]``: validate a config, optionally read once.

Without ``--connect`` nothing is opened: the config is loaded and validated (every key),
the configured driver is built (the Modbus register map is checked against the geometry:
counts, overlaps, spans), the files the config names are resolved (TLS certificates and
keys, CANopen EDS files, parsed), the home pose is checked against the plausibility
bounds, and legal-but-suspect values are warned about (``tension.max_n`` above the sensor
range, a metrics listener reachable from other hosts).

With ``--connect`` the driver is opened, one cycle's inputs are read and printed, and the
driver is closed: nothing is written to the PLC (over Modbus a function-3 read; no
function 16/23 is sent).

Exit status: 0 valid (and, with ``--connect``, read once); 2 a config problem (one line
per problem, each naming the file and the key); 1 the config is valid but the PLC could
not be reached or read (the line says why).
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from gateway.core.cliopts import add_config_option, setup_logging
from gateway.core.config import (
    Config,
    config_warnings,
    exposure_warning,
    load_config,
)
from gateway.errors import DriverError, DriverTimeoutError, GatewayError
from gateway.service.daemon import build_driver
from gateway.service.exporter import FD_RESERVE, MAX_CONNECTIONS, NOFILE_NEEDED, PROCESS_FDS

# the drivers and the loop load numba: imported where they are used, never for --help
if TYPE_CHECKING:
    from drivers.base import Driver
    from gateway.runtime.plausibility import Plausibility


def configure_parser(command: str, parser: argparse.ArgumentParser) -> None:
    add_config_option(parser, why="the file to check")
    parser.add_argument(
        "--connect", action="store_true", help="also read once from the PLC (writes nothing)"
    )


def file_problems(cfg: Config) -> list[str]:
    """Files the config names that cannot be read, one line each naming file and key."""
    where = f"{cfg.source}: " if cfg.source else ""
    named: list[tuple[str, str | None]] = [
        ("metrics.certfile", cfg.metrics.certfile),
        ("metrics.keyfile", cfg.metrics.keyfile),
    ]
    tls = cfg.bus.modbus_tcp.tls
    if cfg.bus.driver == "modbus_tcp" and tls is not None:
        named += [
            ("bus.modbus_tcp.tls.certfile", tls.certfile),
            ("bus.modbus_tcp.tls.keyfile", tls.keyfile),
            ("bus.modbus_tcp.tls.cafile", tls.cafile),
        ]
    problems = []
    for key, path in named:
        if path is None:
            continue
        p = Path(path)
        if not p.is_file():
            problems.append(f"{where}{key}: {path}: no such file")
        else:
            try:
                with p.open("rb"):
                    pass
            except OSError as exc:
                problems.append(f"{where}{key}: {path}: {exc.strerror or exc}")
    if cfg.bus.driver == "canopen":
        problems += _eds_problems(cfg)
    return problems


def _eds_problems(cfg: Config) -> list[str]:
    where = f"{cfg.source}: " if cfg.source else ""
    try:
        from drivers.canopen_pdo import load_pdo_layouts
    except ImportError as exc:
        return [f"{where}bus.driver: canopen is not available: {exc}"]
    c = cfg.bus.canopen
    problems = []
    for key, path, node in (
        ("gateway_eds", c.gateway_eds, c.gateway_node_id),
        ("analog_eds", c.analog_eds, c.analog_node_id),
    ):
        try:
            load_pdo_layouts(path, node)
        except GatewayError as exc:
            problems.append(f"{where}bus.canopen.{key}: {exc}")
    return problems


def descriptor_warning() -> list[str]:
    """The soft RLIMIT_NOFILE below what the gateway with its exporter needs."""
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or soft >= NOFILE_NEEDED:
        return []
    return [
        f"RLIMIT_NOFILE: the soft limit {soft} is below the {NOFILE_NEEDED} descriptors the "
        f"gateway needs ({MAX_CONNECTIONS} metrics connections, {FD_RESERVE} kept for the "
        f"bus, ~{PROCESS_FDS} for the process): the metrics port would not answer; raise it "
        "(ulimit -n, LimitNOFILE= in the unit)"
    ]


def pose_problems(cfg: Config, bounds: Plausibility) -> list[str]:
    from drivers.base import Inputs

    inputs = Inputs.allocate(cfg.cables)
    inputs.pose[:] = cfg.geometry.home_pose
    if bounds.check(inputs):
        where = f"{cfg.source}: " if cfg.source else ""
        return [f"{where}geometry.home_pose: outside the plausible workspace ({bounds.describe()})"]
    return []


READ_ATTEMPTS_S = 2.0  # `check --connect` retries a read that timed out for this long


def read_once(driver: Driver, cfg: Config) -> list[str]:
    """Open, read one cycle's inputs (a read that times out is tried again for up to
    READ_ATTEMPTS_S: a one-off check is not the 1 kHz loop, and one late reply of a busy
    PLC, or of the soft PLC on a loaded machine, is no answer to 'can you read it'),
    close; the lines that describe what was read."""
    from drivers.base import Inputs
    from gateway.runtime.loop import describe_bus
    from gateway.runtime.plausibility import Plausibility

    inputs = Inputs.allocate(cfg.cables)
    try:
        driver.open()
        deadline = time.monotonic() + READ_ATTEMPTS_S
        while True:
            try:
                driver.read_into(inputs)
                break
            except DriverTimeoutError:
                if time.monotonic() >= deadline:
                    raise
    finally:
        driver.close()

    def fmt(values: np.ndarray, digits: int = 2) -> str:
        return " ".join(f"{v:.{digits}f}" for v in values)

    bounds = Plausibility(cfg)
    implausible = bounds.check(inputs)  # on the copy just read: NaN marks the bad values
    return [
        f"read from {describe_bus(cfg)} (nothing written):",
        f"  tensions N        {fmt(inputs.tension_raw_n)}",
        f"  velocities m/s    {fmt(inputs.velocity_m_s, 4)}",
        f"  lengths m         {fmt(inputs.length_m, 4)}",
        f"  pose              {fmt(inputs.pose, 4)}",
        f"  PLC heartbeat     {inputs.plc_heartbeat}",
        f"  implausible       {implausible} value(s) (NaN above)"
        if implausible
        else "  implausible       none",
    ]


def run_command(command: str, args: argparse.Namespace) -> int:
    from gateway.runtime.loop import describe_bus
    from gateway.runtime.plausibility import Plausibility

    setup_logging(args.log_level)
    cfg = load_config(args.config)
    problems: list[str] = []
    driver: Driver | None = None
    try:
        driver = build_driver(cfg)
    except GatewayError as exc:
        problems.append(str(exc))
    problems += file_problems(cfg)
    bounds = Plausibility(cfg)
    problems += pose_problems(cfg, bounds)
    warnings = config_warnings(cfg)
    if cfg.metrics.enabled:
        exposed = exposure_warning("metrics.host", cfg.metrics.host, cfg.metrics.port, cfg.source)
        warnings += [exposed] if exposed else []
        warnings += descriptor_warning()
    for line in warnings:
        print(f"warning: {line}", file=sys.stderr)
    for line in problems:
        print(f"cdpr-gateway check: error: {line}", file=sys.stderr)
    if problems:
        return 2
    print(f"config {cfg.source}: valid; {cfg.cables} cables, bus {describe_bus(cfg)}")
    print(f"plausible setpoints: {bounds.describe()}")
    if not args.connect or driver is None:
        return 0
    try:
        lines = read_once(driver, cfg)
    except DriverError as exc:
        print(f"cdpr-gateway check: cannot read from the PLC: {exc}", file=sys.stderr)
        return 1
    print("\n".join(lines))
    return 0
