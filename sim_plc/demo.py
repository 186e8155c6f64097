"""``cdpr-gateway demo [--seconds N] [--config FILE] [--bus modbus_tcp|canopen] [--offline]``.

The whole product on one machine with no hardware: the soft PLC runs as a subprocess
(``python -m gateway.cli sim-plc --config FILE --port 0``; its line ``sim-plc: serving BUS
on HOST:PORT`` says where), the gateway connects to it on loopback and runs its 1 kHz
cycle; one progress line per second goes to stderr; at the end a table: cycles, overruns,
jitter and round-trip percentiles, and per cable the RMSE of the raw and of the corrected
tension against the plant's true platform tension.

Real time: unless ``--no-realtime``, the gateway's loop thread applies ``loop.realtime``
(:mod:`gateway.runtime.realtime`, forced as if ``enabled``: SCHED_FIFO, mlockall, GC off) and the
soft PLC is started with ``--realtime``; what each applied and refused is in the output.

The gateway never sees the truth: the demo observes the plant through its own channel and
scores what the gateway computed, off the cycle (:mod:`sim_plc.truth`): the loop observer
(:class:`CycleRing`) only copies each cycle's heartbeat, raw and corrected tensions and
status into a preallocated ring; a thread of its own (:class:`TruthMatcher`, SCHED_FIFO 1
with real time: below the loop, but not preempted while it holds the GIL) reads the truth
and scores the cycle that read the same plant step.

* Over Modbus the soft PLC serves a side channel that is in no gateway register map
  (:data:`sim_plc.modbus_image.TRUTH_ADDRESS`: the true tensions and the PLC heartbeat
  of the same plant step); the matcher reads it on its own connection
  (:class:`TruthChannel`) every ``TRUTH_INTERVAL_S`` and scores only the cycle whose PLC
  heartbeat is that one, so truth and reading are of one step.
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
import collections
import contextlib
import dataclasses
import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO, Any, TextIO

import numpy as np

from drivers.s7 import S7Analog
from gateway.core.config import Config, RealtimeConfig, load_config
from gateway.errors import GatewayError
from gateway.model.chain_runs import ChainStepper
from gateway.model.chain_schema import ChainParams
from gateway.runtime import realtime
from gateway.runtime.loop import CyclicService
from gateway.runtime.realtime import RealtimeReport
from gateway.service.daemon import build_driver
from sim_plc.image import ProcessImage
from sim_plc.modbus_image import TRUTH_ADDRESS
from sim_plc.truth import (
    SCORE_AFTER_S,
    TRUTH_EVERY_CYCLES,
    ChainWarmup,
    CycleRing,
    TruthChannel,
    TruthMatcher,
    TruthScore,
    TruthScorer,
    TruthSource,
)

__all__ = [
    "SCORE_AFTER_S",
    "TRUTH_EVERY_CYCLES",
    "ChainWarmup",
    "CycleRing",
    "DemoRun",
    "InProcessCanopenPlc",
    "SoftPlc",
    "StandInPlant",
    "TruthChannel",
    "TruthMatcher",
    "TruthScore",
    "TruthScorer",
    "run_command",
    "table",
    "with_port",
]

NO_REALTIME = "real-time: off (--no-realtime): loop.realtime not applied"
STARTUP_TIMEOUT_S = 60.0  # the soft PLC imports numba and compiles on first start


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
    """The soft PLC as a subprocess; ``host``/``port`` parsed from its listening line.

    With ``realtime`` it is started with ``--realtime`` (it applies ``loop.realtime`` where
    it may); its stderr is drained on a thread (the last lines kept for errors) and its
    ``sim-plc: real-time: ...`` line is kept in :attr:`realtime_line`.
    """

    def __init__(self, config_path: str, bus: str, port: int = 0, realtime: bool = False) -> None:
        cmd = [
            sys.executable,
            "-m",
            "gateway.cli",
            "sim-plc",
            "--config",
            config_path,
            "--port",
            str(port),
        ]
        if bus != "modbus_tcp":
            cmd += ["--bus", bus]
        if realtime:
            cmd.append("--realtime")
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        root = str(Path(__file__).resolve().parent.parent)  # the project root
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
        self.proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
        )
        self.realtime_line = ""
        self._stderr: collections.deque[str] = collections.deque(maxlen=20)
        self._drain = threading.Thread(target=self._drain_stderr, daemon=True)
        self._drain.start()
        self.host, self.port = self._wait_listening(bus)

    def _drain_stderr(self) -> None:
        assert self.proc.stderr is not None
        with contextlib.suppress(ValueError, OSError):  # closed by close()
            for line in self.proc.stderr:
                if line.startswith("sim-plc: real-time"):
                    self.realtime_line = line.strip()
                self._stderr.append(line)

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
            self.proc.wait(timeout=10)
            self._drain.join(timeout=10)
            err = "".join(self._stderr)
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
        self._drain.join(timeout=10)
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


def run_timed(
    service: CyclicService,
    seconds: float,
    label: str,
    err: TextIO,
    rt: RealtimeConfig | None = None,
) -> RealtimeReport | None:
    """Run ``service`` in a thread for ``seconds``; one progress line per second.

    With ``rt`` the loop's thread applies it first (``force``: as ``loop.realtime`` would
    in the daemon, whatever ``enabled`` says), says on ``err`` what was applied and what
    was refused, and undoes it when the loop ends; the report is returned.
    """
    reports: list[RealtimeReport] = []

    def body() -> None:
        report = None
        if rt is not None:  # on this thread: the policy is per thread, the others keep theirs
            report = realtime.apply(rt, force=True)
            reports.append(report)
            print(report.line(f"{label}: gateway real-time"), file=err, flush=True)
        try:
            service.run()
        finally:
            if report is not None:
                realtime.undo(report)

    worker = threading.Thread(target=body, name="gateway-loop", daemon=True)
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
    return reports[0] if reports else None


def _us(x: float) -> str:
    return "n/a" if math.isnan(x) else f"{x * 1e6:.0f} us"


@dataclasses.dataclass
class DemoRun:
    """What the closing table reports: the loop, the truth samples, the real-time lines."""

    service: CyclicService
    score: TruthScore | None = None
    truth: str = ""  # how the truth samples were counted (one line)
    realtime: list[str] = dataclasses.field(default_factory=list)
    noise_n: float | None = None  # the plant's sensor noise (N): the best RMSE possible


def noise_floor(cfg: Config) -> float:
    """The soft PLC plant's sensor noise (``sim_plc.noise_std_n``), mean over cables."""
    from sim_plc.config import load_sim_config

    noise = np.asarray(load_sim_config(cfg).noise_std_n, dtype=float)
    return float(np.broadcast_to(noise, (cfg.cables,)).mean())


def truth_line(matcher: TruthMatcher, source: str) -> str:
    """How the truth samples were counted, one line."""
    if matcher.by_heartbeat:
        how = "matched by the PLC heartbeat to the cycle that read that plant step"
    else:
        how = "paired with the latest cycle (no heartbeat to match)"
    return (
        f"{matcher.read} read {source}, {matcher.matched} {how} and scored, "
        f"{matcher.unmatched} unmatched (no cycle read that step), {matcher.failed} failed reads"
    )


def table(run: DemoRun, title: str) -> str:
    """The closing table: loop figures and what they count, then per-cable RMSE."""
    service, score = run.service, run.score
    s = service.stats
    pct = 100.0 * s.overruns / max(s.cycles, 1)
    failed = sum(s.errors[k] for k in ("connect", "io", "timeout", "write"))
    rows = [
        title,
        *(f"  {line}" for line in run.realtime),
        f"  cycles               {s.cycles}  (loop passes, one per deadline met or late: "
        "read -> compensate -> write, or a connection step)",
        f"  written              {s.written}  (frames sent: one per cycle with a good read, "
        "plus the STOPPED frame at exit)",
        f"  failed               {failed}  (cycles without a good read or write: "
        + ", ".join(f"{k} {s.errors[k]}" for k in ("connect", "io", "timeout", "write"))
        + ")",
        f"  overruns             {s.overruns} ({pct:.3f} % of cycles)  (cycles that ended "
        "after the next deadline)",
        f"  cycles skipped       {s.skipped}  (deadlines dropped after those overruns, phase "
        "kept: no cycle ran for them)",
        f"  reconnects           {service.reconnects}",
        f"  clock resyncs        {service.comp.clock.resyncs}  (PLC samples whose step the one "
        f"sample clock could not vouch for, heartbeat kind {service.comp.clock.kind}: each "
        "leaves the cables cold until re-warmed, docs/security.md)",
        f"  jitter p50 / p99     {_us(s.jitter_ring.percentile(50))} / "
        f"{_us(s.jitter_ring.percentile(99))}",
        f"  round trip p50 / p99 {_us(s.roundtrip_ring.percentile(50))} / "
        f"{_us(s.roundtrip_ring.percentile(99))}",
    ]
    if run.truth:
        rows.append(f"  truth samples        {run.truth}")
    if score is not None and score.samples.any():
        raw, corrected = score.rmse()
        rows += ["", "  cable  RMSE raw N  RMSE corrected N  samples"]
        scored = score.samples > 0  # a cable whose chain never warmed up has none
        for i in range(raw.size):
            rows.append(
                f"  {i + 1:>5}  {raw[i]:10.3f}  {corrected[i]:16.3f}  {score.samples[i]:7d}"
                if scored[i]
                else f"  {i + 1:>5}  not scored: its chain has not warmed up"
            )
        raw_mean, corrected_mean = raw[scored].mean(), corrected[scored].mean()
        rows.append(f"  {'mean':>5}  {raw_mean:10.3f}  {corrected_mean:16.3f}")
        if run.noise_n is not None:
            ratio = corrected_mean / run.noise_n if run.noise_n > 0 else math.nan
            rows.append(
                f"  noise floor {run.noise_n:.3f} N (sim_plc.noise_std_n, mean over cables): "
                f"corrected RMSE {ratio:.2f}x the floor"
            )
    else:
        rows.append("  (no true tensions received: no RMSE)")
    return "\n".join(rows)


CATCH_UP_MAX = 100  # plant periods stepped in one read at most (a longer stall is skipped)


def real_time(step: Any, period_s: float, clock: Any = time.monotonic) -> Any:
    """``step`` (one plant period, the PLC heartbeat +1) called as often as the periods
    elapsed since the first call, at least once a read: the in-process plant keeps time
    as a real PLC does. One step a read made the plant's time run slower than the
    gateway's clock whenever cycles were skipped, and the gateway, which times the PLC's
    samples by its own clock (docs/security.md), integrated 2-3 periods of travel for each
    (a loaded machine: corrected 5.44 N against raw 4.32 N). A stall over
    :data:`CATCH_UP_MAX` periods is skipped, not replayed."""
    t0 = [-1.0]  # the first call's time (moved on by skipped stalls)
    done = [0]  # periods stepped

    def stepped() -> None:
        now = clock()
        if t0[0] < 0:
            t0[0] = now
        due = int((now - t0[0]) / period_s) + 1 - done[0]
        n = min(max(due, 1), CATCH_UP_MAX)
        if due > CATCH_UP_MAX:
            t0[0] += (due - n) * period_s
        for _ in range(n):
            step()
        done[0] += n

    return stepped


def run_offline(cfg: Config, seconds: float, stand_in: bool = False) -> DemoRun:
    """In process, one thread: the truth is read in the cycle (same plant step, exact)."""
    from drivers.virtual import VirtualDriver

    image = ProcessImage(cfg.cables)
    if stand_in:
        step = real_time(StandInPlant(cfg, image).step, cfg.loop.period_s)
    else:
        from sim_plc.config import load_sim_config
        from sim_plc.plant import Plant

        plant = Plant(cfg, load_sim_config(cfg))
        step = real_time(lambda: plant.step(image), plant.period_s)

    def truth(out: np.ndarray) -> None:  # same thread, same plant step as the reading
        out[:] = image.true_tension_n

    driver = VirtualDriver(cfg, image=image, step=step)
    service = CyclicService(cfg, driver)
    scorer = TruthScorer(cfg.cables, truth)  # plant and gateway start together: no warm-up
    service.add_observer(scorer)
    run_timed(service, seconds, "demo (offline)", sys.stderr)
    n = int(scorer.score.samples.max()) if scorer.score.samples.size else 0
    noise = None if stand_in else noise_floor(cfg)
    how = f"{n} read in the cycle from the plant it steps (same step, exact)"
    return DemoRun(service, scorer.score, how, noise_n=noise)


def _off_cycle(service: CyclicService, cfg: Config, source: TruthSource, rt: bool) -> TruthMatcher:
    """The ring observer on ``service`` and the matcher's thread, started (with ``rt`` at
    SCHED_FIFO 1, below the loop: measured, a normal-priority thread that holds the GIL
    when other processes preempt it makes the loop overrun -- 1.9 % vs 0.03-0.05 %)."""
    ring = CycleRing(cfg.cables, warmup=ChainWarmup(cfg))
    service.add_observer(ring)
    matcher = TruthMatcher(ring, source, cfg.cables)
    if rt:
        matcher.set_realtime()
    matcher.start()
    return matcher


def _matcher_line(matcher: TruthMatcher | None) -> list[str]:
    if matcher is None or matcher.priority is None:
        return []
    got = "applied" if matcher.priority_applied else "refused (not permitted)"
    return [f"real-time truth reader: SCHED_FIFO priority 1 {got}"]


def run_canopen_in_process(cfg: Config, seconds: float, rt: bool = True) -> DemoRun:
    plc = InProcessCanopenPlc(cfg)
    matcher = None
    try:
        print(
            f"demo: soft PLC on canopen virtual:{plc.cfg.bus.canopen.channel} (in process)",
            file=sys.stderr,
        )
        service = CyclicService(plc.cfg, build_driver(plc.cfg))
        matcher = _off_cycle(service, cfg, plc.truth, rt)
        report = run_timed(service, seconds, "demo", sys.stderr, cfg.loop.realtime if rt else None)
    finally:
        if matcher is not None:
            matcher.stop()
        plc.close()
    lines = [report.line("real-time gateway") if report is not None else NO_REALTIME]
    lines += _matcher_line(matcher)
    how = "from the process image (the analog PDOs follow SYNC, not the plant step)"
    return DemoRun(service, matcher.score, truth_line(matcher, how), lines, noise_floor(cfg))


def run_online(cfg: Config, config_path: str, bus: str, seconds: float, rt: bool = True) -> DemoRun:
    if bus == "canopen" and cfg.bus.canopen.interface == "virtual":
        return run_canopen_in_process(cfg, seconds, rt)
    plc = SoftPlc(config_path, bus, realtime=rt)
    channel = matcher = None
    try:
        print(f"demo: soft PLC serving {bus} on {plc.host}:{plc.port}", file=sys.stderr)
        live = with_port(cfg, bus, plc.host, plc.port)
        service = CyclicService(live, build_driver(live))
        if bus == "modbus_tcp":
            mb = live.bus.modbus_tcp
            channel = TruthChannel(mb.host, mb.port, mb.unit_id, cfg.cables)
            matcher = _off_cycle(service, cfg, channel, rt)
        report = run_timed(service, seconds, "demo", sys.stderr, cfg.loop.realtime if rt else None)
    finally:
        if matcher is not None:
            matcher.stop()
        if channel is not None:
            channel.close()
        plc.close()
    lines = [report.line("real-time gateway") if report is not None else NO_REALTIME]
    lines += _matcher_line(matcher)
    soft = plc.realtime_line.removeprefix("sim-plc: real-time: ")
    if rt:
        lines.append(f"real-time soft PLC: {soft or 'no report'}")
    if matcher is None:
        return DemoRun(service, None, "", lines)
    how = f"from the side channel (register {TRUTH_ADDRESS}, own connection, off the cycle)"
    return DemoRun(service, matcher.score, truth_line(matcher, how), lines, noise_floor(cfg))


def run_command(command: str, args: argparse.Namespace) -> int:
    if not args.seconds > 0:
        raise GatewayError("--seconds: must be > 0")
    cfg = load_config(args.config)
    bus = args.bus or cfg.bus.driver
    if args.offline or bus == "virtual":
        run = run_offline(cfg, args.seconds, args.stand_in)
        plant = "stand-in plant" if args.stand_in else "plant"
        title = f"demo: {plant} in process, virtual driver, {args.seconds:g} s"
    else:
        run = run_online(cfg, args.config, bus, args.seconds, not args.no_realtime)
        where = "on loopback"
        if bus == "canopen" and cfg.bus.canopen.interface == "virtual":
            where = "(virtual CAN, in process)"
        title = f"demo: soft PLC over {bus} {where}, {args.seconds:g} s"
    print(table(run, title))
    return 0
