"""``cdpr-gateway demo [--seconds N] [--config FILE] [--bus modbus_tcp|canopen] [--offline]``.

The whole product on one machine with no hardware: the soft PLC runs as a subprocess
(``python -m gateway.cli sim-plc --config FILE --port 0``; its line ``sim-plc: serving BUS
on HOST:PORT`` says where), the gateway connects to it on loopback and runs its 1 kHz
cycle; one progress line per second goes to stderr; at the end a table: cycles, overruns,
jitter and round-trip percentiles, and per cable the RMSE of the raw and of the corrected
tension against the plant's true platform tension.

The gateway never sees the truth: the demo observes the plant through its own channel and
scores what the gateway computed (an observer of the loop, :class:`TruthScorer`).

* Over Modbus the soft PLC serves a side channel that is in no gateway register map
  (:data:`sim_plc.modbus_server.TRUTH_ADDRESS`: the true tensions and the PLC heartbeat
  of the same plant step); the demo reads it on its own connection
  (:class:`TruthChannel`) every ``TRUTH_EVERY_CYCLES`` cycles and scores only when that
  heartbeat is the one of the gateway's reading, so truth and reading are of one step.
* With ``--bus canopen`` on python-can's ``virtual`` interface (the default), the soft PLC
  runs in this process (a virtual CAN channel does not cross processes) and the true
  tensions come from its process image; on a real interface (``socketcan``,
  ``udp_multicast``) it runs as the subprocess above and the table has no RMSE.
* ``--offline`` runs the soft PLC's plant in this process through the virtual driver (no
  sockets), stepped one period per gateway read, so truth and readings line up exactly.
  ``--offline --stand-in`` replaces the plant by :class:`StandInPlant`: sinusoidal
  platform tensions and cable velocities, the sensor reading made by the same friction
  chain run platform -> sensor, plus noise and the S7 ADC (no trajectory, no statics).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any, TextIO

import numpy as np

from drivers.base import Inputs
from drivers.s7 import S7Analog
from gateway.compensator import Compensator
from gateway.config import DEFAULT_CONFIG_PATH, Config, load_config
from gateway.daemon import build_driver
from gateway.errors import GatewayError
from gateway.loop import CyclicService
from gateway.model.chain import ChainParams, ChainStepper
from sim_plc.image import ProcessImage
from sim_plc.modbus_server import TRUTH_ADDRESS

STARTUP_TIMEOUT_S = 60.0  # the soft PLC imports numba and compiles on first start
SCORE_AFTER_S = 0.5  # scoring skips the model's warm-up
TRUTH_EVERY_CYCLES = 10  # the side channel costs a transaction: sample it this seldom
TruthSource = Callable[[np.ndarray], "int | None"]  # fills truth, returns its heartbeat


class TruthScore:
    """Sums of squared error of raw and corrected tensions against the plant's truth."""

    def __init__(self, cables: int) -> None:
        self.raw_sq = np.zeros(cables)
        self.corrected_sq = np.zeros(cables)
        self.samples = np.zeros(cables, dtype=np.int64)

    def add(self, truth: np.ndarray, raw: np.ndarray, corrected: np.ndarray,
            status: np.ndarray) -> None:  # fmt: skip
        """Add the squared errors of the good channels (status 0, finite) against ``truth``."""
        good = (status == 0) & np.isfinite(corrected) & np.isfinite(truth)
        self.raw_sq[good] += (raw[good] - truth[good]) ** 2
        self.corrected_sq[good] += (corrected[good] - truth[good]) ** 2
        self.samples[good] += 1

    def rmse(self) -> tuple[np.ndarray, np.ndarray]:
        n = np.maximum(self.samples, 1)
        return np.sqrt(self.raw_sq / n), np.sqrt(self.corrected_sq / n)


class TruthScorer:
    """A loop observer: every ``every`` cycles (after ``SCORE_AFTER_S``) it asks ``source``
    for the plant's truth and scores the gateway's raw and corrected tensions against it.

    ``source(truth)`` fills ``truth`` and returns the PLC heartbeat of that plant step
    (None: unknown, score anyway); a heartbeat other than the gateway's reading means
    the plant has stepped since: that sample is skipped (``mismatched``) and the next
    cycle tries again.
    """

    def __init__(self, cables: int, source: TruthSource, every: int = 1) -> None:
        self.score = TruthScore(cables)
        self.source = source
        self.every = every
        self.truth = np.zeros(cables)
        self.mismatched = 0
        self.failed = 0
        self._countdown = 1
        self._started: float | None = None

    def __call__(self, inputs: Inputs, comp: Compensator, now: float) -> None:
        if self._started is None:
            self._started = now
        if now - self._started < SCORE_AFTER_S:
            return
        self._countdown -= 1
        if self._countdown > 0:
            return
        self._countdown = self.every
        try:
            heartbeat = self.source(self.truth)
        except OSError:
            self.failed += 1
            return
        if heartbeat is not None and heartbeat != inputs.plc_heartbeat:
            self.mismatched += 1
            self._countdown = 1  # the plant stepped in between: try again next cycle
            return
        self.score.add(self.truth, comp.raw_n, comp.corrected_n, comp.status)


class TruthChannel:
    """The demo's own Modbus connection to the soft PLC's side channel (function 3).

    Reads the true tensions and the PLC heartbeat of one plant step in one transaction;
    a failed connection is retried at most once per second.
    """

    def __init__(self, host: str, port: int, unit_id: int, cables: int) -> None:
        self.address = (host, port)
        self.unit_id = unit_id
        self.words = 2 * cables + 1
        self.reply_len = 9 + 2 * self.words
        self._sock: socket.socket | None = None
        self._tid = 0
        self._retry_at = 0.0

    def __call__(self, truth: np.ndarray) -> int:
        sock = self._connect()
        self._tid = (self._tid + 1) & 0xFFFF
        request = struct.pack(">HHHBBHH", self._tid, 0, 6, self.unit_id, 3, TRUTH_ADDRESS,
                              self.words)  # fmt: skip
        try:
            sock.sendall(request)
            reply = b""
            while len(reply) < self.reply_len:
                chunk = sock.recv(self.reply_len - len(reply))
                if not chunk:
                    raise OSError("side channel closed")
                reply += chunk
                if len(reply) >= 9 and reply[7] & 0x80:
                    raise OSError(f"side channel: exception {reply[8]}")
        except OSError:
            self.close()
            raise
        if struct.unpack_from(">H", reply)[0] != self._tid:
            self.close()
            raise OSError("side channel: wrong transaction id")
        truth[:] = np.frombuffer(reply, ">f4", count=truth.size, offset=9)
        return int(struct.unpack_from(">H", reply, 9 + 4 * truth.size)[0])

    def _connect(self) -> socket.socket:
        if self._sock is not None:
            return self._sock
        if time.monotonic() < self._retry_at:
            raise OSError("side channel: waiting to reconnect")
        self._retry_at = time.monotonic() + 1.0
        sock = socket.create_connection(self.address, timeout=0.05)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = sock
        return sock

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def configure_parser(command: str, parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seconds", type=float, default=10.0, help="how long to run")
    parser.add_argument("--config", default=str(DEFAULT_CONFIG_PATH), help="YAML config file")
    parser.add_argument("--bus", choices=("modbus_tcp", "canopen"), default=None,
                        help="fieldbus (default: bus.driver of the config)")  # fmt: skip
    parser.add_argument("--offline", action="store_true",
                        help="plant in process, virtual driver, no sockets")  # fmt: skip
    parser.add_argument("--stand-in", action="store_true",
                        help="with --offline: sinusoidal stand-in, not the plant")  # fmt: skip


class StandInPlant:
    """Stepped stand-in for the soft PLC's plant, writing a :class:`ProcessImage`.

    Platform tension ``T_p = 200 + 80 sin(2 pi 0.5 t + phi_i)`` N and cable velocity
    ``v = 0.15 sin(2 pi 0.3 t + psi_i)`` m/s; the sensor reads the friction chain run
    platform -> sensor (same parameters as the gateway's model), plus 0.2 N noise, in
    S7 counts. One :meth:`step` per period; the PLC heartbeat +1 per step.
    """

    def __init__(self, cfg: Config, image: ProcessImage, seed: int = 7) -> None:
        m = cfg.cables
        self.cfg, self.image, self.dt = cfg, image, cfg.loop.period_s
        self.chain = ChainStepper(ChainParams.from_friction(cfg.friction, m), self.dt, False)
        self.phase = np.linspace(0, 2 * math.pi, m, endpoint=False)
        self.rng = np.random.default_rng(seed)
        self.t = 0.0
        self.length = np.full(m, 2.0)
        self.sensor = np.zeros(m)
        self.adc = S7Analog.from_sensor(cfg.sensor)
        image.pose[:] = cfg.geometry.home_pose

    def step(self) -> None:
        self.t += self.dt
        tp = 200.0 + 80.0 * np.sin(2 * math.pi * 0.5 * self.t + self.phase)
        v = 0.15 * np.sin(2 * math.pi * 0.3 * self.t + 1.3 * self.phase)
        self.length += v * self.dt
        self.chain.step(tp, v, self.sensor)
        noisy = self.sensor + self.rng.normal(0.0, 0.2, self.sensor.size)
        counts = self.adc.encode(noisy)
        img = self.image
        with img.lock:
            img.raw_counts[:] = counts
            img.velocity_m_s[:] = v
            img.length_m[:] = self.length
            img.true_tension_n[:] = tp
            img.plc_heartbeat = (img.plc_heartbeat + 1) & 0xFFFF
            img.time_s = self.t


class SoftPlc:
    """The soft PLC as a subprocess; ``host``/``port`` parsed from its listening line."""

    def __init__(self, config_path: str, bus: str, port: int = 0) -> None:
        cmd = [sys.executable, "-m", "gateway.cli", "sim-plc", "--config", config_path,
               "--port", str(port)]  # fmt: skip
        if bus != "modbus_tcp":
            cmd += ["--bus", bus]
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        root = str(Path(__file__).resolve().parent.parent)  # the project root
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
        self.proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
        )
        self.host, self.port = self._wait_listening(bus)

    def _wait_listening(self, bus: str) -> tuple[str, int]:
        found: dict[str, Any] = {}
        assert self.proc.stdout is not None
        stdout: IO[str] = self.proc.stdout

        def reader() -> None:
            for line in stdout:
                if line.startswith("sim-plc: serving") and "address" not in found:
                    found["address"] = line.rsplit(" on ", 1)[1].strip()
                    break

        thread = threading.Thread(target=reader, daemon=True)
        thread.start()
        thread.join(STARTUP_TIMEOUT_S)
        if "address" not in found:
            if self.proc.poll() is None:
                self.proc.kill()
            err = self.proc.communicate(timeout=10)[1] or ""
            self.close()
            raise GatewayError(f"soft PLC ({bus}) did not start: {err.strip()[-400:]}")
        host, _, port = found["address"].rpartition(":")
        return host, int(port) if port.isdigit() else 0

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        for pipe in (self.proc.stdout, self.proc.stderr):
            if pipe is not None:
                pipe.close()


class InProcessCanopenPlc:
    """The soft PLC on python-can's in-process ``virtual`` bus: plant, runtime, CANopen nodes.

    A virtual CAN channel does not cross processes, so with ``bus.canopen.interface:
    virtual`` the soft PLC runs in this process, on a private channel. ``truth`` copies the
    plant's true tensions and heartbeat from the process image (the demo's own channel).
    """

    def __init__(self, cfg: Config) -> None:
        from sim_plc.canopen_nodes import CanopenPlc
        from sim_plc.config import load_sim_config
        from sim_plc.plant import Plant
        from sim_plc.runtime import PlcRuntime

        channel = f"cdpr-demo-{os.getpid()}-{id(self)}"
        can_cfg = dataclasses.replace(cfg.bus.canopen, interface="virtual", channel=channel)
        self.cfg = dataclasses.replace(
            cfg, bus=dataclasses.replace(cfg.bus, driver="canopen", canopen=can_cfg)
        )
        sim = load_sim_config(cfg)
        plant = Plant(cfg, sim)
        self.image = ProcessImage(cfg.cables)
        plant.step(self.image)
        self.runtime = PlcRuntime(plant, self.image, sim.period_s)
        self.plc = CanopenPlc(self.cfg, self.image)
        self.runtime.start()
        self.plc.start(realtime=True)

    def truth(self, truth: np.ndarray) -> int | None:
        with self.image.lock:
            truth[:] = self.image.true_tension_n
        return None  # the analog PDOs follow SYNC, not the plant step: no heartbeat match

    def close(self) -> None:
        self.plc.stop()
        self.runtime.stop()


def with_port(cfg: Config, bus: str, host: str, port: int) -> Config:
    """``cfg`` with the bus chosen and the Modbus server's host/port replaced."""
    mb = dataclasses.replace(cfg.bus.modbus_tcp, host=host or "127.0.0.1", port=port)
    if bus != "modbus_tcp":
        mb = cfg.bus.modbus_tcp
    bus_cfg = dataclasses.replace(cfg.bus, driver=bus, modbus_tcp=mb)
    return dataclasses.replace(cfg, bus=bus_cfg)


def run_timed(service: CyclicService, seconds: float, label: str, err: TextIO) -> None:
    """Run ``service`` in a thread for ``seconds``; one progress line per second."""
    worker = threading.Thread(target=service.run, name="gateway-loop", daemon=True)
    worker.start()
    start = time.monotonic()
    try:
        while worker.is_alive() and time.monotonic() - start < seconds:
            time.sleep(min(1.0, max(0.0, seconds - (time.monotonic() - start))))
            s = service.stats
            print(
                f"{label}: {time.monotonic() - start:4.0f} s  cycles {s.cycles}  "
                f"written {s.written}  overruns {s.overruns}  state {service.state.name.lower()}  "
                f"T1 corrected {service.comp.corrected_n[0]:7.2f} N",
                file=err,
                flush=True,
            )
    except KeyboardInterrupt:
        print(f"{label}: interrupted", file=err, flush=True)
    finally:
        service.stop()
        worker.join(timeout=30)


def _us(x: float) -> str:
    return "n/a" if math.isnan(x) else f"{x * 1e6:.0f} us"


def table(service: CyclicService, title: str, score: TruthScore | None = None) -> str:
    """The closing table: loop figures, then per-cable RMSE raw vs corrected."""
    s = service.stats
    pct = 100.0 * s.overruns / max(s.cycles, 1)
    rows = [
        title,
        f"  cycles               {s.cycles}",
        f"  written              {s.written}",
        f"  overruns             {s.overruns} ({pct:.3f} %), {s.skipped} cycles skipped",
        f"  reconnects           {service.reconnects}",
        f"  jitter p50 / p99     {_us(s.jitter_ring.percentile(50))} / "
        f"{_us(s.jitter_ring.percentile(99))}",
        f"  round trip p50 / p99 {_us(s.roundtrip_ring.percentile(50))} / "
        f"{_us(s.roundtrip_ring.percentile(99))}",
    ]
    if score is not None and score.samples.any():
        raw, corrected = score.rmse()
        rows += ["", "  cable  RMSE raw N  RMSE corrected N  samples"]
        for i in range(raw.size):
            rows.append(
                f"  {i + 1:>5}  {raw[i]:10.3f}  {corrected[i]:16.3f}  {score.samples[i]:7d}"
            )
        rows.append(f"  {'mean':>5}  {raw.mean():10.3f}  {corrected.mean():16.3f}")
    else:
        rows.append("  (no true tensions received: no RMSE)")
    return "\n".join(rows)


Demo = tuple[CyclicService, "TruthScorer | None"]


def run_offline(cfg: Config, seconds: float, stand_in: bool = False) -> Demo:
    from drivers.virtual import VirtualDriver

    image = ProcessImage(cfg.cables)
    if stand_in:
        step = StandInPlant(cfg, image).step
    else:
        from sim_plc.config import load_sim_config
        from sim_plc.plant import Plant

        plant = Plant(cfg, load_sim_config(cfg))

        def step() -> None:
            plant.step(image)

    def truth(out: np.ndarray) -> None:  # same thread, same plant step as the reading
        out[:] = image.true_tension_n

    driver = VirtualDriver(cfg, image=image, step=step)
    service = CyclicService(cfg, driver)
    scorer = TruthScorer(cfg.cables, truth)
    service.add_observer(scorer)
    run_timed(service, seconds, "demo (offline)", sys.stderr)
    return service, scorer


def run_canopen_in_process(cfg: Config, seconds: float) -> Demo:
    plc = InProcessCanopenPlc(cfg)
    try:
        print(f"demo: soft PLC on canopen virtual:{plc.cfg.bus.canopen.channel} (in process)",
              file=sys.stderr)  # fmt: skip
        service = CyclicService(plc.cfg, build_driver(plc.cfg))
        scorer = TruthScorer(cfg.cables, plc.truth)
        service.add_observer(scorer)
        run_timed(service, seconds, "demo", sys.stderr)
    finally:
        plc.close()
    return service, scorer


def run_online(cfg: Config, config_path: str, bus: str, seconds: float) -> Demo:
    if bus == "canopen" and cfg.bus.canopen.interface == "virtual":
        return run_canopen_in_process(cfg, seconds)
    plc = SoftPlc(config_path, bus)
    channel = None
    try:
        print(f"demo: soft PLC serving {bus} on {plc.host}:{plc.port}", file=sys.stderr)
        live = with_port(cfg, bus, plc.host, plc.port)
        service = CyclicService(live, build_driver(live))
        scorer = None
        if bus == "modbus_tcp":
            mb = live.bus.modbus_tcp
            channel = TruthChannel(mb.host, mb.port, mb.unit_id, cfg.cables)
            scorer = TruthScorer(cfg.cables, channel, TRUTH_EVERY_CYCLES)
            service.add_observer(scorer)
        run_timed(service, seconds, "demo", sys.stderr)
    finally:
        if channel is not None:
            channel.close()
        plc.close()
    return service, scorer


def run_command(command: str, args: argparse.Namespace) -> int:
    if not args.seconds > 0:
        raise GatewayError("--seconds: must be > 0")
    cfg = load_config(args.config)
    bus = args.bus or cfg.bus.driver
    if args.offline or bus == "virtual":
        service, scorer = run_offline(cfg, args.seconds, args.stand_in)
        plant = "stand-in plant" if args.stand_in else "plant"
        title = f"demo: {plant} in process, virtual driver, {args.seconds:g} s"
    else:
        service, scorer = run_online(cfg, args.config, bus, args.seconds)
        where = "on loopback"
        if bus == "canopen" and cfg.bus.canopen.interface == "virtual":
            where = "(virtual CAN, in process)"
        title = f"demo: soft PLC over {bus} {where}, {args.seconds:g} s"
    print(table(service, title, scorer.score if scorer is not None else None))
    return 0
