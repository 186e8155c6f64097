"""``cdpr-gateway run --config FILE [--cycles N] [--seconds N] [--record OUT.csv.gz]``.

Loads and validates the config, builds the driver named in ``bus.driver``, serves the
Prometheus metrics on ``metrics.host:metrics.port`` and runs the cyclic service until
SIGTERM/SIGINT (or ``--cycles``), then writes the STOPPED state and exits 0. A PLC that
cannot be reached at start is not fatal: the loop retries with backoff and says so.
Configuration problems end the program with one line naming the file and the key.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import signal
import sys
import threading
from typing import Any

from drivers.base import Driver, make_driver
from gateway import __version__
from gateway.config import DEFAULT_CONFIG_PATH, Config, exposure_warning, load_config
from gateway.errors import ConfigError, DriverInitError
from gateway.loop import CyclicService, LoopState
from gateway.metrics import MetricsServer, make_registry
from gateway.recorder import Recorder

log = logging.getLogger("cdpr_gateway")


def configure_parser(command: str, parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", default=str(DEFAULT_CONFIG_PATH), help="YAML config file")
    parser.add_argument("--cycles", type=int, default=None, help="stop after N cycles")
    parser.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING, ...")
    parser.add_argument("--seconds", type=float, default=None, help="stop after N seconds")
    parser.add_argument(
        "--record", default=None, help="record what the gateway sees (CSV, .csv.gz); "
        "overrides record.path",
    )  # fmt: skip


def build_driver(cfg: Config, name: str | None = None, **kwargs: Any) -> Driver:
    """The configured driver; failures become :class:`ConfigError` naming ``bus.*``."""
    name = name or cfg.bus.driver
    try:
        if kwargs:
            from drivers.base import driver_class

            return driver_class(name)(cfg, **kwargs)
        return make_driver(cfg, name)
    except DriverInitError as exc:
        key = "bus.driver" if "unknown driver" in str(exc) else f"bus.{name}"
        raise ConfigError(f"{cfg.source}: {key}: {exc}") from exc
    except ImportError as exc:
        raise ConfigError(
            f"{cfg.source}: bus.driver: driver {name!r} is not available: {exc}"
        ) from exc


def describe_bus(cfg: Config) -> str:
    bus = cfg.bus.driver
    if bus == "modbus_tcp":
        m = cfg.bus.modbus_tcp
        return f"modbus_tcp {m.host}:{m.port} unit {m.unit_id} (bus.modbus_tcp)"
    if bus == "canopen":
        c = cfg.bus.canopen
        return f"canopen {c.interface}:{c.channel} node {c.gateway_node_id} (bus.canopen)"
    return bus


def summary(service: CyclicService) -> str:
    stats = service.stats
    return (
        f"cycles {stats.cycles}, written {stats.written}, overruns {stats.overruns} "
        f"(skipped {stats.skipped}), reconnects {service.reconnects}, "
        f"errors {sum(stats.errors.values())}"
    )


def start_recorder(cfg: Config, override: str | None) -> Recorder | None:
    """The recorder of ``record:`` (``--record`` overrides the path), started; or None."""
    rc = cfg.record if override is None else dataclasses.replace(cfg.record, path=override)
    if rc.path is None:
        return None
    regs = cfg.bus.modbus_tcp.registers
    with_mass = cfg.bus.driver == "modbus_tcp" and regs.platform_mass is not None
    meta = {
        "source": "cdpr-gateway run --record",
        "version": __version__,
        "config": cfg.source,
        "bus": describe_bus(cfg),
        "friction": f"{cfg.friction.model}, {len(cfg.friction.pulleys)} pulleys",
        "period_s": repr(cfg.loop.period_s),
    }
    recorder = Recorder(rc, cfg.cables, with_mass=with_mass, metadata=meta)
    try:
        recorder.start()
    except OSError as exc:
        key = "--record" if override is not None else f"{cfg.source}: record.path"
        raise ConfigError(f"{key}: cannot write {rc.path}: {exc.strerror or exc}") from exc
    log.info("recording to %s (%d columns)", rc.path, len(recorder.columns))
    return recorder


def summary_record(recorder: Recorder) -> str:
    files = ", ".join(str(p) for p in recorder.files)
    failed = f", FAILED: {recorder.failed}" if recorder.failed else ""
    return f"recorded {recorder.rows_written} rows to {files} (dropped {recorder.dropped}{failed})"


def run_command(command: str, args: argparse.Namespace) -> int:
    logging.basicConfig(
        level=args.log_level.upper(), stream=sys.stderr, format="%(levelname)s %(message)s"
    )
    if args.cycles is not None and args.cycles < 1:
        raise ConfigError("--cycles: must be >= 1")
    if args.seconds is not None and not args.seconds > 0:
        raise ConfigError("--seconds: must be > 0")
    cfg = load_config(args.config)
    service = CyclicService(cfg, build_driver(cfg))
    server = None
    if cfg.metrics.enabled:
        server = MetricsServer(cfg.metrics, make_registry(service), cfg.source)
        log.info("metrics on http://%s:%d/metrics", server.host, server.port)
        exposed = exposure_warning("metrics.host", server.host, server.port, cfg.source)
        if exposed:
            log.warning("%s", exposed)
    previous = service.install_signal_handlers()
    timer = None
    try:
        service.recorder = start_recorder(cfg, args.record)
        if args.seconds is not None:
            timer = threading.Timer(args.seconds, service.stop)
            timer.daemon = True
            timer.start()
        service.configure()
        if service.state is LoopState.FAULT:
            log.warning("cannot reach the PLC at %s yet; retrying", describe_bus(cfg))
        else:
            log.info("connected to %s", describe_bus(cfg))
        service.run(args.cycles)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if timer is not None:
            timer.cancel()
        if server is not None:
            server.close()
        if service.recorder is not None:
            service.recorder.close()
    print(f"stopped: {summary(service)}", file=sys.stderr, flush=True)
    if service.recorder is not None:
        print(summary_record(service.recorder), file=sys.stderr, flush=True)
    return 0
