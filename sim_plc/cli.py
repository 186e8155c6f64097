"""``cdpr-gateway record`` and ``cdpr-gateway sim-plc``.

* ``record --config FILE --seconds N --out FILE.csv[.gz]|FILE.parquet``: the plant
  simulated block by block, each block written as it comes (docs/recording-format.md);
  progress on stderr; SIGINT or SIGTERM closes the file with what was simulated, says how
  much in one line and exits 128 + the signal's number.
* ``sim-plc --config FILE [--host H] [--port P] [--bus modbus_tcp|canopen]``: the plant
  stepped in real time at the config's period and served on the bus until SIGINT or
  SIGTERM; prints ``sim-plc: serving modbus_tcp on HOST:PORT`` once listening. The plant's
  chunks are prepared by a worker process (``sim_plc.chunk_worker``) so the serving process
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

import numpy as np

from gateway.cli import Interrupted
from gateway.core.cliopts import add_config_option, lost_signal
from gateway.core.config import (
    DEFAULT_CONFIG_PATH,
    Config,
    TlsConfig,
    exposure_warning,
    load_config,
    output_path,
)
from gateway.errors import ConfigError
from gateway.recordings.reader import recording_columns
from gateway.recordings.writer import RowWriter, open_writer


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

    def end(self) -> None:
        """End a line left open on a terminal (before a closing line of another kind)."""
        if not self.quiet and 0 <= self.last < 100 and sys.stderr.isatty():
            print(file=sys.stderr, flush=True)


def _record(cfg: Config, args: argparse.Namespace) -> int:
    """The plant simulated block by block (:func:`sim_plc.plant.stream_recording`), each
    block written before the next is simulated. SIGINT or SIGTERM once the first block is
    written stops after the block being simulated: the file is closed properly (a valid
    recording of what was simulated), one line says how much, exit 128 + the signal's
    number. Before the first block (loading, compiling) nothing is on disk and nothing is
    left: one line says so."""
    from sim_plc.config import load_sim_config  # the effects registry: numba, when run
    from sim_plc.plant import stream_recording

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
    robot = args.robot or (Path(cfg.source).stem if cfg.source else "sim")
    writer: RowWriter | None = None
    stop = _StopSignals()
    try:
        bar(0.0)  # labelled from the start, before the first step
        blocks = stream_recording(cfg, sim, args.seconds, bar)
        for block in blocks:
            columns = recording_columns(block)
            if writer is None:  # the first block: kernels compiled; from now on a file
                stop.catch()  # a signal ends the loop below, never a write half done
                meta = {**block.metadata, "robot": robot, "started": started}
                writer = open_writer(out, [n for n, _ in columns], meta)
            writer.write_rows(np.column_stack([v for _, v in columns]))
            if stop.signum is not None:
                break
    except KeyboardInterrupt as exc:  # before the first block: the program's handler
        if writer is not None:  # not from a signal (ours notes them): not ours to end
            raise
        bar.end()
        nothing = f": before the first row: nothing recorded, no file written ({out})"
        raise Interrupted(int(getattr(exc, "signum", signal.SIGINT)), nothing) from None
    finally:
        try:
            if writer is not None:
                writer.close()  # our handler still in place: a signal cannot cut it
        finally:
            stop.restore()
    assert writer is not None
    took = time.perf_counter() - t0
    seconds = f"{writer.rows * sim.period_s:g} s"
    if stop.signum is not None:  # one line, by the program (gateway/cli.py), even if --quiet
        bar.end()
        raise Interrupted(
            stop.signum,
            f": {writer.rows} rows ({seconds} of {args.seconds:g} s) recorded in {out}, "
            f"the file closed ({took:.1f} s)",
        )
    if not args.quiet:
        print(
            f"record: {writer.rows} samples x {cfg.cables} cables -> {out} ({took:.1f} s)",
            file=sys.stderr,
        )
    return 0


class _StopSignals:
    """SIGINT and SIGTERM noted instead of raised once :meth:`catch` is called (main thread
    only), the previous handlers back at :meth:`restore`."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self._old: dict[int, Any] = {}

    def _note(self, signum: int, _frame: object) -> None:
        if self.signum is None:
            self.signum = signum

    def catch(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        for sig in (signal.SIGINT, signal.SIGTERM):
            if signal.getsignal(sig) is not signal.SIG_IGN:
                self._old[sig] = signal.signal(sig, self._note)
        lost = lost_signal()  # raised before, and swallowed where Python ignores exceptions
        if lost is not None and self.signum is None:
            self.signum = lost

    def restore(self) -> None:
        for sig, handler in self._old.items():
            signal.signal(sig, handler)
        self._old.clear()


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
    from sim_plc.chunk_worker import ChunkWorker
    from sim_plc.config import load_sim_config
    from sim_plc.image import ProcessImage
    from sim_plc.plant import Plant

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
