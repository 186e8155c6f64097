"""The gateway's 1 kHz cycle against the soft PLC over Modbus TCP on loopback: real-time
settings off and on, side by side in one run, and the floor.

``python -m bench loop`` (``BENCH_SECONDS`` shortens the default 60 s per run;
``BENCH_LOOP_CANOPEN=0`` leaves out the CANopen run; ``BENCH_LOOP_POLL=0`` the middle
run; ``BENCH_BUSY_WAIT_S`` overrides
``loop.busy_wait_s``). Three runs of the same length, each against a fresh soft PLC
subprocess (``cdpr-gateway sim-plc --port 0``, chunks prepared by its worker process):

* **RT off**: both processes as they start (SCHED_OTHER, no memory locking, GC on);
* **RT off + poll**: as RT off, but this process holds ``/dev/cpu_dma_latency`` at 0,
  so idle CPUs poll instead of halting (the one setting of ``loop.realtime`` that acts on
  the whole machine; on a VM with the ``haltpoll`` idle driver a halted vCPU's wake-up is
  the largest delay: docs/realtime.md);
* **RT on**: the config's ``loop.realtime`` forced on in this process (the gateway's
  cycle thread: SCHED_FIFO 50, mlockall, GC frozen and off, :mod:`gateway.runtime.realtime`)
  and ``sim-plc --realtime`` (the same for the soft PLC's threads).

Reported per run, as the ROS 2 real-time demos do: min / mean / p99 / p99.9 / max of the
cycle-start lateness (start - deadline) and of the cycle time (start - end of write);
overruns (a cycle ending after the next deadline) split by cause -- the one that took
the most of the period in that cycle: the **schedule** (lateness), the **bus** (the
wire part of the transaction: the Modbus driver's ``_transact``, send and wait for the
reply, timed by this bench around that one method) or the gateway's own **compute**
(everything else in the cycle: the driver's encode and decode and its bookkeeping,
plausibility, compensation with wrench, stats, write hand-over = cycle time - wire);
the compute's p50 / p99 / p99.9 and its parts (the driver's part of the read phase
outside the wire, i.e. encode + decode + bookkeeping; the compensate phase; the write
phase). The driver's own ``roundtrip_s`` (what the metrics export) covers encode + wire +
decode, so it is shown too but not used for the split. ``python -m bench cycle`` measures
the same compute on a fake in-process bus, without the machine's scheduling; minor and
major page faults of this process during the run (``getrusage``); CPU and peak RSS.
Then the floor (a bare socket doing the same function-23 transaction) and, unless
disabled, CANopen on python-can's virtual bus.

Goals (2-core machine): overruns <= 0.05 % with RT, <= 0.3 % without;
lateness p99.9 <= 150 us with RT; gateway compute p99 <= 20 us. Figures only: nothing
here asserts on time. The loop's per-phase timings are read from ``service.stats``
(rings ``jitter_ring``, ``cycle_ring``, ``read_ring``, ``compensate_ring``,
``write_ring``, ``roundtrip_ring``; counters ``cycles``, ``written``, ``overruns``,
``skipped``) and nothing else.
"""

from __future__ import annotations

import dataclasses
import os
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench import stop_process
from gateway.core.config import Config, load_config
from gateway.runtime import realtime
from gateway.runtime.loop import CyclicService
from gateway.runtime.loopstats import Ring
from gateway.service.daemon import build_driver
from sim_plc.demo import InProcessCanopenPlc, with_port

FLOOR_MAX = 20000  # floor transactions (back to back)
STARTUP_TIMEOUT_S = 60.0
ROOT = Path(__file__).resolve().parent.parent
STATS = ("min", "mean", "p99", "p99.9", "max")


def _us(ring: Ring | np.ndarray, *qs: float) -> str:
    data = ring.recent() if isinstance(ring, Ring) else ring
    if not data.size:
        return "n/a"
    return " / ".join(f"{v * 1e6:.0f}" for v in np.percentile(data, qs)) + " us"


def _summary(data: np.ndarray) -> dict[str, float]:
    """min / mean / p99 / p99.9 / max in us."""
    if not data.size:
        return dict.fromkeys(STATS, float("nan"))
    p99, p999 = np.percentile(data, [99, 99.9])
    values = (data.min(), data.mean(), p99, p999, data.max())
    return {k: float(v) * 1e6 for k, v in zip(STATS, values, strict=True)}


class BenchPlc:
    """``sim-plc --port 0 [--realtime]`` as a subprocess; its stderr kept for the report."""

    def __init__(self, config_path: str, rt: bool) -> None:
        cmd = [
            sys.executable,
            "-m",
            "gateway.cli",
            "sim-plc",
            "--config",
            config_path,
            "--port",
            "0",
        ] + (["--realtime"] if rt else [])
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
        self.proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
        )
        self.err: list[str] = []
        self._err_thread = threading.Thread(target=self._read_err, daemon=True)
        self._err_thread.start()
        found: list[str] = []
        reader = threading.Thread(target=self._read_out, args=(found,), daemon=True)
        reader.start()
        reader.join(STARTUP_TIMEOUT_S)
        if not found:
            self.close()
            raise RuntimeError(f"soft PLC did not start: {''.join(self.err)[-400:]}")
        self.host, _, port = found[0].rpartition(":")
        self.port = int(port)

    def _read_out(self, found: list[str]) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.startswith("sim-plc: serving"):
                found.append(line.rsplit(" on ", 1)[1].strip())
                return

    def _read_err(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.err.append(line)

    def lines(self, prefix: str) -> list[str]:
        return [line.strip() for line in self.err if line.startswith(prefix)]

    def close(self) -> None:
        stop_process(self.proc)
        self._err_thread.join(5.0)
        for pipe in (self.proc.stdout, self.proc.stderr):
            if pipe is not None:
                pipe.close()


class WireTimer:
    """Times the driver's wire part (``_transact``: send, wait for and frame the reply)
    into a preallocated array, one entry per transaction; bench-only instrumentation
    (two clock reads per cycle)."""

    def __init__(self, driver: Any, size: int) -> None:
        self.values = np.zeros(size)
        self.count = 0
        inner = driver._transact
        clock = time.perf_counter

        def timed(frame: bytearray, fc: int, address: int) -> int:
            start = clock()
            n = int(inner(frame, fc, address))
            if self.count < self.values.size:  # successful ones only, as the phase rings
                self.values[self.count] = clock() - start
            self.count += 1
            return n

        driver._transact = timed

    def recent(self) -> np.ndarray:
        return self.values[: min(self.count, self.values.size)]


def _causes(service: CyclicService, wire: WireTimer) -> dict[str, Any]:
    """Per-cycle attribution of the overruns, and the gateway's compute per cycle."""
    s, period = service.stats, service.period_s
    late, cycle = s.jitter_ring.recent(), s.cycle_ring.recent()
    read, comp, write = s.read_ring.recent(), s.compensate_ring.recent(), s.write_ring.recent()
    bus = wire.recent()[: read.size]  # (the STOPPED frame's write comes after the loop)
    n = late.size
    aligned = all(a.size == n for a in (cycle, read, comp, write, bus))
    out: dict[str, Any] = {"aligned": aligned, "compute": np.empty(0), "parts": None}
    if not aligned:  # a failed read skips the phase rings: no per-cycle split
        return out
    compute = cycle - bus
    out["parts"] = (read - bus, comp, write)
    over = late + cycle > period
    parts = np.stack([late, bus, compute])  # schedule, bus, compute
    cause = np.argmax(parts[:, over], axis=0)
    out["split"] = ", ".join(
        f"{name} {int(np.sum(cause == k))}" for k, name in enumerate(("schedule", "bus", "compute"))
    )
    out["compute"] = compute
    out["over"] = int(over.sum())
    return out


def run_modbus(cfg: Config, seconds: float, rt: bool, poll: bool = False) -> dict[str, Any]:
    """One run (RT off or on) against a fresh soft PLC; the figures as a dict. ``poll``
    (RT off only): this process holds ``/dev/cpu_dma_latency`` at 0 for the run, the one
    real-time setting that acts on the whole machine (idle CPUs poll instead of halting)."""
    cycles = max(1, round(seconds / cfg.loop.period_s))
    plc = BenchPlc(str(cfg.source), rt)
    report = None
    held: int | None = None  # the PM QoS file descriptor while ``poll`` holds it
    try:
        if poll:
            try:
                held = realtime.Ops().open_latency(0)
            except OSError as exc:
                print(f"  (RT off + poll: {realtime.CPU_DMA_LATENCY}: {exc.strerror})")
        live = with_port(cfg, "modbus_tcp", plc.host, plc.port)
        service = CyclicService(live, build_driver(live), history=cycles + 16)
        wire = WireTimer(service.driver, cycles + 16)
        service.configure()
        if rt:
            report = realtime.apply(cfg.loop.realtime, force=True)
        u0, wall0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        service.run(cycles=cycles)
        u1, wall1 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        floor = _floor(plc.host, plc.port, service, min(cycles, FLOOR_MAX))
    finally:
        if report is not None:
            realtime.undo(report)
        if held is not None:
            os.close(held)
        plc.close()
    wall = wall1 - wall0
    return {
        "rt": rt,
        "name": "RT on" if rt else ("RT off + poll" if poll else "RT off"),
        "service": service,
        "wall": wall,
        "rss": rss,
        "floor": floor,
        "cpu": (u1.ru_utime + u1.ru_stime - u0.ru_utime - u0.ru_stime) / wall,
        "minflt": u1.ru_minflt - u0.ru_minflt,
        "majflt": u1.ru_majflt - u0.ru_majflt,
        "gateway_rt": report.line("gateway real-time")
        if report
        else (
            "gateway real-time: off"
            + (f"; the bench holds {realtime.CPU_DMA_LATENCY} at 0" if held is not None else "")
        ),
        "plc_rt": "; ".join(plc.lines("sim-plc: real-time")) or "n/a",
        "plc_stop": "; ".join(plc.lines("sim-plc: stopped")) or "n/a",
        "causes": _causes(service, wire),
        "wire": wire.recent(),
    }


def _floor(host: str, port: int, service: CyclicService, n: int) -> np.ndarray:
    """The floor's fc23 transaction back to back on one socket (no decoding)."""
    from bench.modbus_floor import floor_roundtrips

    layout = getattr(service.driver, "layout", None)
    kwargs: dict[str, Any] = {}
    if layout is not None:
        kwargs = {"read_span": layout.read_span, "write_span": layout.write_span}
    unit = service.cfg.bus.modbus_tcp.unit_id
    try:
        floor_roundtrips(host, port, 200, unit, **kwargs)  # warm-up
        return floor_roundtrips(host, port, n, unit, **kwargs)
    except OSError as exc:
        print(f"  floor: failed ({exc})")
        return np.empty(0)


def _fmt(values: dict[str, float]) -> str:
    return " / ".join(f"{values[k]:.0f}" for k in STATS)


def _rows(r: dict[str, Any]) -> list[tuple[str, str]]:
    s = r["service"].stats
    c = r["causes"]
    pct = 100 * s.overruns / max(s.cycles, 1)
    split = c.get("split", "")
    rtt = s.roundtrip_ring.recent()
    floor = r["floor"]
    return [
        ("cycles (written)", f"{s.cycles} ({s.written})"),
        ("overruns", f"{s.overruns} ({pct:.3f} %), {s.skipped} skipped"),
        ("  by cause", split or "n/a (phase rings not aligned: bus errors)"),
        ("lateness min/mean/p99/p99.9/max", _fmt(_summary(s.jitter_ring.recent())) + " us"),
        ("cycle min/mean/p99/p99.9/max", _fmt(_summary(s.cycle_ring.recent())) + " us"),
        ("compute p50/p99/p99.9", _us(c["compute"], 50, 99, 99.9)),
        ("  p50: driver/compensate/write", _parts(c["parts"])),
        ("wire p50/p99", _us(r["wire"], 50, 99)),
        ("round trip (driver) p50/p99", _us(rtt, 50, 99)),
        ("floor round trip p50/p99", _us(floor, 50, 99)),
        ("page faults minor/major", f"{r['minflt']} / {r['majflt']}"),
        ("CPU (this process)", f"{100 * r['cpu']:.0f} % of one core"),
        ("peak RSS (this process)", f"{r['rss']:.0f} MB"),
        ("errors", f"{sum(s.errors.values())}"),
    ]


def _parts(parts: tuple[np.ndarray, ...] | None) -> str:
    """Medians of the compute's parts: the driver's (read phase - wire: encode, decode,
    bookkeeping), the compensate phase, the write phase."""
    if parts is None or not parts[0].size:
        return "n/a"
    return " / ".join(f"{np.median(p) * 1e6:.0f}" for p in parts) + " us"


def _print_side_by_side(*runs: dict[str, Any]) -> None:
    table = [_rows(r) for r in runs]
    print(f"  {'':<34}" + "".join(f"{r['name']:<40}" for r in runs).rstrip())
    for i, (name, _) in enumerate(table[0]):
        print(f"  {name:<34}" + "".join(f"{rows[i][1]:<40}" for rows in table).rstrip())
    for r in runs:
        for key in ("gateway_rt", "plc_rt", "plc_stop"):
            print(f"  {r['name']}: {r[key]}")


def run_canopen(cfg: Config, seconds: float) -> None:
    """The loop paced by the soft PLC's SYNC on python-can's virtual bus, all in process
    (RT off). Lateness here is the data's after its SYNC."""
    cycles = max(1, round(seconds / cfg.bus.canopen.sync_period_s))
    plc = InProcessCanopenPlc(cfg)
    try:
        service = CyclicService(plc.cfg, build_driver(plc.cfg), history=cycles + 16)
        service.run(cycles=cycles)
    finally:
        plc.close()
    s = service.stats
    print(
        f"  canopen (virtual bus, in process, RT off): {s.cycles} cycles, {s.overruns} "
        f"overruns ({100 * s.overruns / max(s.cycles, 1):.3f} %); lateness "
        f"{_fmt(_summary(s.jitter_ring.recent()))} us; cycle "
        f"{_fmt(_summary(s.cycle_ring.recent()))} us"
    )


def run() -> None:
    seconds = float(os.environ.get("BENCH_SECONDS", "60"))
    cfg = load_config()
    if "BENCH_BUSY_WAIT_S" in os.environ:  # spin before each deadline (config loop.busy_wait_s)
        loop = dataclasses.replace(cfg.loop, busy_wait_s=float(os.environ["BENCH_BUSY_WAIT_S"]))
        cfg = dataclasses.replace(cfg, loop=loop)
    print(
        f"  gateway vs soft PLC (subprocess) over modbus_tcp on loopback, {seconds:g} s each,"
        f" busy-wait {cfg.loop.busy_wait_s * 1e6:.0f} us"
    )
    runs = [run_modbus(cfg, seconds, rt=False)]
    if os.environ.get("BENCH_LOOP_POLL", "1") != "0":
        runs.append(run_modbus(cfg, seconds, rt=False, poll=True))
    runs.append(run_modbus(cfg, seconds, rt=True))
    _print_side_by_side(*runs)
    if os.environ.get("BENCH_LOOP_CANOPEN", "1") != "0":
        print()
        run_canopen(cfg, seconds)
    print(f"  load average        {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
