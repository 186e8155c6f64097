"""``cdpr-gateway run --config FILE [--cycles N] [--seconds N] [--record OUT.csv.gz|.parquet]
[--log-level LEVEL]``: the gateway daemon.

Loads and validates the config, builds the driver named in ``bus.driver``, serves the
Prometheus metrics on ``metrics.host:metrics.port`` and runs the cyclic service until a
terminating signal (SIGTERM, SIGINT, SIGHUP, SIGQUIT, SIGUSR1, SIGUSR2, SIGALRM) or
``--cycles``, then writes the STOPPED state and exits 0. A PLC that cannot be reached at
start is not fatal: the loop retries with backoff and says why. Configuration problems end
the program with one line naming the file and the key (exit 2).

Real time: ``loop.realtime`` (on by default) is applied to the thread that runs the cycle
just before it starts, and one line says what was applied and what was refused (never
fatal); ``enabled: false`` leaves the process as started.

Logging: ``TIME LEVEL LOGGER: message`` on stderr; a start-up banner (version, config
file, bus, model, whether real time is tried); the loop logs each state change once (connected,
active, disconnected/fault with the cause, recovered). Foreign libraries' loggers
(canopen, can, pymodbus) are quieted to WARNING unless ``--log-level DEBUG``. Under systemd
(``NOTIFY_SOCKET`` set) the loop sends READY=1 once configured (before the PLC answers: it
retries) and WATCHDOG=1 while it cycles, retries included.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import logging
import signal
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gateway import __version__
from gateway.core.cliopts import (
    LOG_FORMAT,
    add_config_option,
    lost_signal,
    setup_logging,
)
from gateway.core.config import (
    Config,
    config_warnings,
    exposure_warning,
    load_config,
)
from gateway.errors import ConfigError, DriverInitError

# The drivers, the loop, the metrics and the recorder load numba and the compiled kernels:
# they are imported where a command runs, so that `--help` and a bad argument never pay
# for them (tests/test_cli_lazy.py).
if TYPE_CHECKING:
    from drivers.base import Driver
    from gateway.runtime.loop import CyclicService
    from gateway.runtime.realtime import RealtimeReport
    from gateway.service.exporter_proc import ExporterProcess
    from gateway.service.metrics_shm import MetricsBlock
    from gateway.service.recorder import Recorder

log = logging.getLogger("cdpr_gateway")


def configure_parser(command: str, parser: argparse.ArgumentParser) -> None:
    add_config_option(
        parser,
        why="the PLC to serve; a bundled default would quietly target "
        "127.0.0.1 ('cdpr-gateway examples' shows the reference config)",
    )
    parser.add_argument("--cycles", type=int, default=None, help="stop after N cycles")
    parser.add_argument("--seconds", type=float, default=None, help="stop after N seconds")
    parser.add_argument(
        "--record",
        default=None,
        help="record what the gateway sees (.csv, .csv.gz or "
        ".parquet: the name chooses; with record.layout hive a folder); overrides record.path",
    )


def build_driver(cfg: Config, name: str | None = None, **kwargs: Any) -> Driver:
    """The configured driver; failures become :class:`ConfigError` naming file and key."""
    name = name or cfg.bus.driver
    from drivers.base import make_driver

    try:
        if kwargs:
            from drivers.base import driver_class

            return driver_class(name)(cfg, **kwargs)
        return make_driver(cfg, name)
    except DriverInitError as exc:
        key = "bus.driver" if "unknown driver" in str(exc) else f"bus.{name}"
        raise ConfigError(f"{cfg.source}: {key}: {exc}") from exc
    except ConfigError as exc:
        raise _with_source(cfg, name, exc) from exc
    except ImportError as exc:
        raise ConfigError(
            f"{cfg.source}: bus.driver: driver {name!r} is not available: {exc}"
        ) from exc


def _with_source(cfg: Config, bus: str, exc: ConfigError) -> ConfigError:
    """A driver's config error (register map, counts) with the file and full key."""
    text = str(exc)
    if cfg.source and text.startswith(cfg.source):
        return exc
    if text.startswith("registers"):
        text = f"bus.{bus}.{text}"
    return ConfigError(f"{cfg.source}: {text}" if cfg.source else text)


def describe_model(cfg: Config) -> str:
    f = cfg.friction
    wraps = "/".join(f"{p.wrap_deg:g}" for p in f.pulleys)
    return (
        f"{f.model}, {len(f.pulleys)} pulleys (wrap {wraps} deg), sigma {f.sigma_n_m:g} N/m, "
        f"{cfg.cables} cables"
    )


def banner(cfg: Config) -> list[str]:
    """The start-up lines: what runs, from which file, against which PLC, how fast."""
    from gateway.runtime.loop import describe_bus

    lp = cfg.loop
    return [
        f"cdpr-gateway {__version__} starting; config {cfg.source or '(built in)'}",
        f"bus: {describe_bus(cfg)} (bus.{cfg.bus.driver})",
        f"model: {describe_model(cfg)}",
        f"loop: period {lp.period_s * 1e3:g} ms, busy-wait {lp.busy_wait_s * 1e6:g} us, "
        f"PLC heartbeat timeout {lp.heartbeat_timeout_s:g} s; real-time: "
        + (
            "tried (loop.realtime; the real-time line says what was applied and refused)"
            if lp.realtime.enabled
            else "off (loop.realtime.enabled: false)"
        ),
    ]


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
    from gateway.recordings.reader import check_recording_name
    from gateway.runtime.loop import describe_bus
    from gateway.service.recorder import Recorder

    if rc.layout == "files":  # before the bus is connected; hive: a folder of .parquet
        check_recording_name(rc.path, "--record" if override else f"{cfg.source}: record.path")

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
    if cfg.source and Path(cfg.source).is_file():
        meta["config_sha256"] = hashlib.sha256(Path(cfg.source).read_bytes()).hexdigest()
    recorder = Recorder(
        rc, cfg.cables, with_mass=with_mass, metadata=meta, period_s=cfg.loop.period_s
    )
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
    setup_logging(args.log_level)
    if args.cycles is not None and args.cycles < 1:
        raise ConfigError("--cycles: must be >= 1")
    if args.seconds is not None and not args.seconds > 0:
        raise ConfigError("--seconds: must be > 0")
    from drivers.base import Lifecycle
    from gateway.runtime import realtime
    from gateway.runtime.loop import CyclicService
    from gateway.runtime.sdnotify import Notifier
    from gateway.service.exporter_proc import ExporterProcess
    from gateway.service.metrics_shm import MetricsBlock

    cfg = load_config(args.config)
    for line in banner(cfg):
        log.info("%s", line)
    for line in config_warnings(cfg):
        log.warning("%s", line)
    notifier = Notifier.from_env()
    service = CyclicService(cfg, build_driver(cfg), notifier=notifier)
    server: ExporterProcess | None = None
    block: MetricsBlock | None = None
    if cfg.metrics.enabled:  # served by a process of its own (gateway/service/exporter_proc.py)
        block = MetricsBlock(cfg.cables, len(service.driver.GATE_REASONS)).attach(service)
        block.publish()  # something to serve before the loop's first publication
        server = ExporterProcess(
            cfg.metrics,
            block,
            bus=cfg.bus.driver,
            gate_reasons=service.driver.GATE_REASONS,
            source=cfg.source,
            log_level=args.log_level or "INFO",
        )
        try:
            port = server.start()
        except BaseException:
            server.close()
            block.close()
            raise
        service.metrics = block
        log.info("metrics on http://%s:%d/metrics", cfg.metrics.host, port)
        exposed = exposure_warning("metrics.host", cfg.metrics.host, port, cfg.source)
        if exposed:
            log.warning("%s", exposed)
    previous = service.install_signal_handlers()
    if lost_signal() is not None:  # came before these handlers, its Interrupted swallowed
        service.stop()  # (raised in the import lock's weakref callback: seen under load)
    timer = None
    rt: RealtimeReport | None = None
    try:
        service.recorder = start_recorder(cfg, args.record)
        if args.seconds is not None:
            timer = threading.Timer(args.seconds, service.stop)
            timer.daemon = True
            timer.start()
        service.configure()
        rt = realtime.apply(cfg.loop.realtime)  # this thread runs the cycle
        (log.warning if rt.refused else log.info)("%s", rt.line())
        service.run(args.cycles)
    finally:
        if rt is not None:  # in-process callers (tests, tools) get their process back
            realtime.undo(rt)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if timer is not None:
            timer.cancel()
        if server is not None:
            server.close()
        if block is not None:
            service.metrics = None
            block.close()
        if notifier is not None:
            notifier.close()
        if service.recorder is not None:
            service.recorder.close()
    assert service.state is Lifecycle.STOPPED
    say(f"stopped: {summary(service)}")
    if service.recorder is not None:
        say(summary_record(service.recorder))
    return 0


def say(line: str) -> None:
    """A closing line in the log's format (with its time) whatever the log level."""
    record = log.makeRecord(log.name, logging.INFO, __file__, 0, line, (), None)
    print(logging.Formatter(LOG_FORMAT).format(record), file=sys.stderr, flush=True)
