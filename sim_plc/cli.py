"""``cdpr-gateway record`` and ``cdpr-gateway sim-plc``.

* ``record --config FILE --seconds N --out FILE.csv[.gz]``: the plant in batch mode,
  written as a recording (docs/recording-format.md); progress on stderr.
* ``sim-plc --config FILE [--host H] [--port P] [--bus modbus_tcp|canopen]``: the plant
  stepped in real time at the config's period and served on the bus until SIGINT or
  SIGTERM; prints ``sim-plc: serving modbus_tcp on HOST:PORT`` once listening. The plant's
  chunks are prepared by a worker process (``sim_plc.prepare``) so the serving process
  never stalls on them; ``--realtime`` applies the config's real-time settings
  (``loop.realtime``, which ``run`` applies by default) to the PLC's threads, reported in
  one line on stderr.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

from gateway.core.cliopts import add_config_option
from gateway.core.config import (
    DEFAULT_CONFIG_PATH,
    Config,
    TlsConfig,
    exposure_warning,
    load_config,
    output_path,
)
from gateway.errors import ConfigError
from gateway.recordings.reader import write_recording


def configure_parser(command: str, parser: argparse.ArgumentParser) -> None:
    add_config_option(parser, DEFAULT_CONFIG_PATH)
    if command == "record":
        parser.add_argument("--seconds", type=float, required=True, help="duration (s)")
        parser.add_argument(
            "--out", required=True, help="recording to write (.csv, .csv.gz or .parquet)"
        )
        parser.add_argument(
            "--robot", help="the robot's name in the metadata (default: the config's name)"
        )
        parser.add_argument(
            "--seed",
            type=int,
            default=None,
            help="noise (and random-motion) seed instead of the config's: a second "
            "recording of the same machine for diagnose --validate",
        )
    else:
        parser.add_argument("--host", default=None, help="address to listen on")
        parser.add_argument("--port", type=int, default=None, help="TCP port (0: any free)")
        parser.add_argument(
            "--bus",
            choices=("modbus_tcp", "canopen"),
            default=None,
            help="the bus to serve (default: the config's bus.driver if canopen, else modbus_tcp)",
        )
        parser.add_argument("--seconds", type=float, default=None, help="stop after (s)")
        parser.add_argument("--tls-cert", help="Modbus/TCP Security: server certificate (PEM)")
        parser.add_argument("--tls-key", help="Modbus/TCP Security: server private key (PEM)")
        parser.add_argument("--tls-ca", help="CA (PEM) that client certificates must chain to")
        parser.add_argument(
            "--realtime",
            action="store_true",
            help="apply the config's loop.realtime settings (SCHED_FIFO, mlockall, ...) to "
            "the soft PLC (default: not applied; the demo passes it)",
        )
        parser.add_argument(
            "--chunks-in-process",
            action="store_true",
            help="prepare the plant's chunks in this process instead of a worker process "
            "(stalls the server ~2 ms every 250 cycles; for comparison)",
        )


RECORDING_SUFFIXES = (".csv", ".csv.gz", ".parquet")


def run_command(command: str, args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    if command == "record":
        return _record(cfg, args)
    return _serve(cfg, args)


class _ProgressBar:
    """``LABEL: WHAT: NN % (X of Y s), ~Z s left``: a line rewritten on a terminal, a line
    every 10 % in a log; the first at 0 %, before any work."""

    def __init__(self, label: str, quiet: bool = False, what: str = "", total_s: float = 0.0):
        self.label, self.quiet, self.last = label, quiet, -1
        self.what, self.total_s = what, total_s
        self.t0 = time.monotonic()

    def __call__(self, fraction: float) -> None:
        pct = int(fraction * 100)
        if not self.quiet and pct != self.last:
            self.last = pct
            text = f"{self.label}: " + (f"{self.what}: " if self.what else "") + f"{pct:3d} %"
            if self.total_s:
                text += f" ({fraction * self.total_s:.0f} of {self.total_s:g} s)"
            took = time.monotonic() - self.t0
            if 0 < fraction < 1:
                text += f", ~{took * (1 - fraction) / fraction:.0f} s left"
            if sys.stderr.isatty():  # one line, rewritten
                end = "\n" if pct >= 100 else ""
                print(f"\r{text}\033[K", end=end, file=sys.stderr, flush=True)
            elif pct % 10 == 0:  # a log file gets a line every 10 %
                print(text, file=sys.stderr, flush=True)


def _record(cfg: Config, args: argparse.Namespace) -> int:
    from sim_plc.config import load_sim_config  # the effects registry: numba, when run
    from sim_plc.plant import make_recording

    if not args.seconds > 0:
        raise ConfigError("--seconds must be > 0")
    out = output_path(args.out, "--out")  # before the simulation, not after it
    if not out.name.endswith(RECORDING_SUFFIXES):
        raise ConfigError(
            f"--out {out}: not a recording format (the name must end in "
            + ", ".join(RECORDING_SUFFIXES)
            + ")"
        )
    sim = load_sim_config(cfg)
    if getattr(args, "seed", None) is not None:
        traj = sim.trajectory
        motion = dataclasses.replace(traj.random, seed=args.seed + 1000)
        sim = dataclasses.replace(
            sim, seed=args.seed, trajectory=dataclasses.replace(traj, random=motion)
        )
    t0 = time.perf_counter()
    started = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    bar = _ProgressBar("record", args.quiet, "simulating the plant", args.seconds)
    bar(0.0)  # labelled from the start, before the first step
    rec = make_recording(cfg, sim, args.seconds, bar)
    robot = args.robot or (Path(cfg.source).stem if cfg.source else "sim")
    write_recording(out, rec, {"robot": robot, "started": started})
    if not args.quiet:
        took = time.perf_counter() - t0
        print(
            f"record: {rec.samples} samples x {rec.cables} cables -> {out} ({took:.1f} s)",
            file=sys.stderr,
        )
    return 0


def _server(
    cfg: Config,
    image: Any,
    bus: str,
    host: str | None,
    port: int | None,
    tls: TlsConfig | None = None,
):
    """Start the bus server; returns (server, description of where it serves)."""
    if bus == "canopen":
        from sim_plc.canopen_nodes import CanopenPlc  # lazy: needs python-can

        plc = CanopenPlc(cfg, image)
        plc.start(realtime=True)
        return plc, f"canopen on {cfg.bus.canopen.interface}:{cfg.bus.canopen.channel}"
    from sim_plc.modbus_server import ModbusPlcServer

    mb = cfg.bus.modbus_tcp
    host = mb.host if host is None else host
    srv = ModbusPlcServer(cfg, image, host, mb.port if port is None else port, tls=tls)
    srv.start()
    return srv, f"modbus_tcp{'+tls' if tls else ''} on {host}:{srv.port}"


def _tls_from_args(args: argparse.Namespace) -> TlsConfig | None:
    given = [getattr(args, k, None) for k in ("tls_cert", "tls_key", "tls_ca")]
    if not any(given):
        return None
    if not all(given):
        raise ConfigError("--tls-cert, --tls-key and --tls-ca go together")
    return TlsConfig(*given)  # type: ignore[arg-type]


def _plant(cfg: Config, in_process: bool) -> tuple[Any, Any, Any]:
    """(plant, chunk worker or None, image holding a valid first sample)."""
    from sim_plc.config import load_sim_config
    from sim_plc.image import ProcessImage
    from sim_plc.plant import Plant
    from sim_plc.prepare import ChunkWorker

    sim = load_sim_config(cfg)
    plant = Plant(cfg, sim)
    chunks = None
    if not in_process:  # chunks prepared off the serving process
        chunks = ChunkWorker(cfg, sim, plant.chunk).start()
        try:
            plant.use_chunks(chunks)
        except BaseException:
            chunks.close()
            raise
    image = ProcessImage(cfg.cables)
    plant.step(image)  # the image holds a valid first sample before anyone can read it
    return plant, chunks, image


def _serve(cfg: Config, args: argparse.Namespace) -> int:
    from gateway.runtime import realtime
    from sim_plc.runtime import PlcRuntime

    plant, chunks, image = _plant(cfg, bool(getattr(args, "chunks_in_process", False)))
    runtime = PlcRuntime(plant, image, plant.period_s)
    done = threading.Event()
    # before the runtime and server threads start: they inherit the policy and affinity
    # the config's loop.realtime is the gateway's (on by default): the soft PLC applies
    # those settings only when asked to
    wanted = bool(getattr(args, "realtime", False))
    rt = realtime.apply(dataclasses.replace(cfg.loop.realtime, enabled=wanted))
    if chunks is not None and rt.old_policy is not None and cfg.loop.realtime.policy != "other":
        ok, what = chunks.lowest_realtime()  # background, above normal tasks
        (rt.applied if ok else rt.refused).append(what)
    line = rt.line("sim-plc: real-time") if wanted else "sim-plc: real-time: off (no --realtime)"
    print(line, file=sys.stderr, flush=True)

    def on_signal(signum: int, frame: object) -> None:
        done.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    server = None
    try:
        runtime.start()
        bus = args.bus or (cfg.bus.driver if cfg.bus.driver == "canopen" else "modbus_tcp")
        server, where = _server(cfg, image, bus, args.host, args.port, _tls_from_args(args))
        print(f"sim-plc: serving {where}", flush=True)
        listen = getattr(server, "host", None)
        exposed = listen and exposure_warning("--host", listen, getattr(server, "port", 0))
        if exposed:
            print(f"sim-plc: warning: {exposed}", file=sys.stderr, flush=True)
        deadline = None if args.seconds is None else time.monotonic() + args.seconds
        while not done.wait(0.2):
            if runtime.error is not None:
                raise runtime.error
            if deadline is not None and time.monotonic() >= deadline:
                break
    finally:
        if server is not None:
            server.stop()
        runtime.stop()
        if chunks is not None:
            chunks.close()
        realtime.undo(rt)
        for s, handler in old.items():
            signal.signal(s, handler)
    st = runtime.stats
    waits = f", waited {chunks.waits}x for a chunk" if chunks is not None else ""
    print(
        f"sim-plc: stopped after {st.cycles} cycles, {st.late} late, {st.missed} skipped, "
        f"longest step {st.max_step_s * 1e3:.2f} ms{waits}",
        file=sys.stderr,
    )
    return 0
