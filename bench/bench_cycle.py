"""The gateway's own compute per cycle, apart from the bus and the machine's scheduling.

``python -m bench cycle`` (``BENCH_CYCLES`` cycles per run, default 20000;
``BENCH_CYCLE_BASE`` a git revision to compare against, default ``main`` when this is a
git checkout, ``none`` to skip; ``BENCH_CYCLE_ROUNDS`` alternations, default 3).

The real :class:`drivers.modbus_tcp.ModbusTcpDriver` runs against an in-process fake bus:
``_transact`` copies a canned function-23 reply (prepared beforehand from a smooth
trajectory: tensions, setpoint velocities, lengths, pose, a counting heartbeat) into the
driver's receive buffer instead of using a socket. Everything else is the shipped code:
the driver's ``exchange`` (encode of the outputs into the request frame, the reply check,
decode of the inputs), the loop's ``_cycle`` (plausibility, compensation with wrench,
heartbeat watch, stats booking, write hand-over) and the pacing's booking and reporter
that follow each cycle. No sleep, no deadline.

Reported, each as p50 / p99 / p99.9 in microseconds over ``BENCH_CYCLES`` cycles:

* ``cycle``: one whole loop iteration without the wait (``_cycle`` + pacing
  ``finish`` + the reporter), back to back: the gateway's compute per cycle with warm
  caches (goal: p99 <= 20 us on the 2-core machine);
* ``cycle after sleep``: the same, each cycle after sleeping ``period - busy_wait_s``
  as the real loop does (at most 3000 cycles): on a shared machine whatever runs on the
  core meanwhile evicts the caches, and the same code takes several times longer;
* then each phase on its own, timed in a separate pass with the same data so that the
  timers do not disturb the cycle figure: ``decode`` (the driver's decode of the reply
  into :class:`drivers.base.Inputs`), ``encode`` (outputs into the request frame),
  ``exchange`` (the driver's whole fake transaction: encode + frame copy + reply check +
  decode + round-trip booking), ``plausibility``, ``compensate`` (the compensator's
  ``step``: validate, Dahl chain, wrench; a black box here) and ``booking`` (the stats
  the loop and its pacing book per cycle).

To quote before/after in one invocation, the same harness runs in a subprocess against a
``git archive`` of ``BENCH_CYCLE_BASE`` and against this tree, alternating ``rounds``
times; the medians of each figure over the rounds are printed side by side with their
ratio. GC is frozen and disabled during the timed passes (as ``loop.realtime`` does).
Figures only: nothing here asserts on time.
"""

from __future__ import annotations

import gc
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
PHASES = (
    "cycle",
    "cycle after sleep",
    "exchange",
    "decode",
    "encode",
    "plausibility",
    "compensate",
    "booking",
)
QS = (50.0, 99.0, 99.9)
# distinct canned replies, cycled through: the heartbeat register's whole range (uint16),
# so that the counter wraps as a PLC's does. With 1000 it jumped back every 1000 cycles,
# the sample clock refused the step (rightly), and the compensation ran its resynchronised
# (cold) path on every measured cycle: +4.6 us on the compensate p50 that no running
# gateway pays (14 resyncs in a 5000-cycle run, every cycle cold)
FRAMES = 1 << 16
COLD_CYCLES = 3000  # cycles each preceded by a sleep of most of a period


def _fake_driver(cfg: Any) -> Any:
    """A :class:`ModbusTcpDriver` whose transactions copy canned replies (no socket)."""
    import numpy as np

    from drivers.modbus_tcp import MBAP, ModbusTcpDriver
    from drivers.registers import FieldCodec

    class FakeBusDriver(ModbusTcpDriver):
        def __init__(self, config: Any) -> None:
            super().__init__(config)
            self.replies = _replies(config, self.layout, FieldCodec, np)
            self.k = 0

        def _open_begin(self) -> bool:
            return True

        def _transact(self, frame: bytearray, fc: int, address: int) -> int:
            reply = self.replies[self.k % len(self.replies)]
            self.k += 1
            size = len(reply)
            self._rx[:size] = reply
            self._rx[MBAP] = fc  # the reply answers the request's function (3 or 23)
            self._have = self._consumed = size
            self._check_reply(fc, address, size - MBAP)
            return size - MBAP

    return FakeBusDriver(cfg)


def _replies(cfg: Any, layout: Any, codec: Any, np: Any) -> list[bytes]:
    """``FRAMES`` function-23 replies of a smooth trajectory, encoded by the register codec."""
    import struct

    from drivers.modbus_tcp import FC_READ_WRITE, MBAP

    rs = layout.read_span
    image = bytearray(2 * rs.count)
    r = cfg.bus.modbus_tcp.registers
    sensor = cfg.sensor

    def enc(field: Any) -> Any:
        return codec(field, image, rs.start, 0, sensor)

    raw, vel, lng, pose, hb = (
        enc(r.raw_tensions),
        enc(r.setpoint_velocities),
        enc(r.setpoint_lengths),
        enc(r.pose),
        enc(r.plc_heartbeat),
    )
    m = cfg.cables
    home = np.asarray(cfg.geometry.home_pose, dtype=float)
    phase = np.arange(m) * 0.7
    out = []
    for k in range(FRAMES):
        t = k * cfg.loop.period_s
        raw.encode(120.0 + 40.0 * np.sin(2.0 * np.pi * 0.5 * t + phase))
        vel.encode(0.05 * np.cos(2.0 * np.pi * 0.5 * t + phase))
        lng.encode(1.5 + 0.02 * np.sin(2.0 * np.pi * 0.5 * t + phase))
        p = home.copy()
        p[:3] += 0.01 * np.sin(2.0 * np.pi * 0.5 * t)
        pose.encode(p)
        hb.encode(k & 0xFFFF)
        pdu = bytes((FC_READ_WRITE, len(image))) + bytes(image)
        header = struct.pack(">HHHB", 0, 0, len(pdu) + 1, cfg.bus.modbus_tcp.unit_id)
        assert len(header) == MBAP
        out.append(header + pdu)
    return out


def _pct(samples_ns: Any) -> list[float]:
    import numpy as np

    return [float(v) / 1e3 for v in np.percentile(samples_ns, QS)]


def measure(cycles: int) -> dict[str, list[float]]:
    """Run the harness in this process (this tree's code); p50/p99/p99.9 us per phase."""
    import numpy as np

    from drivers.base import Outputs
    from gateway.core.config import load_config
    from gateway.runtime.loop import CyclicService

    cfg = load_config()
    driver = _fake_driver(cfg)
    service = CyclicService(cfg, driver, history=cycles + 16)
    service.configure()
    if not service._open:
        raise RuntimeError("the fake bus did not open")
    clock = time.perf_counter
    ns = time.perf_counter_ns
    pacing, stats, report = service.pacing, service.stats, service._reporter.report
    pacing.begin()
    gc.collect()
    gc.freeze()
    gc.disable()
    try:
        for _ in range(2000):  # warm-up: caches, first-call paths, the heartbeat watch
            start = clock()
            service._cycle(start)
            pacing.finish(start, clock(), start, False)
            report(clock())
        whole = np.empty(cycles, dtype=np.int64)
        for i in range(cycles):
            t0 = ns()
            start = clock()
            service._got_data = False
            reanchor = service._cycle(start)
            end = clock()
            pacing.finish(start, end, start, reanchor)
            stats.cycles += 1
            report(end)
            whole[i] = ns() - t0
        res = {"cycle": _pct(whole)}
        # the same cycle after sleeping most of a period, as the real loop does: whatever
        # else runs on the core meanwhile (other processes on a shared machine) evicts the
        # caches, and the cycle runs cold
        cold = np.empty(min(cycles, COLD_CYCLES), dtype=np.int64)
        pause = service.period_s - service.cfg.loop.busy_wait_s
        for i in range(cold.size):
            time.sleep(pause)
            t0 = ns()
            start = clock()
            reanchor = service._cycle(start)
            end = clock()
            pacing.finish(start, end, start, reanchor)
            report(end)
            cold[i] = ns() - t0
        res["cycle after sleep"] = _pct(cold)
        res.update(_phases(service, driver, cycles, np, Outputs))
    finally:
        gc.enable()
        gc.unfreeze()
    if stats.written < cycles:
        raise RuntimeError(f"only {stats.written} of {cycles} cycles written")
    return res


def _phases(service: Any, driver: Any, cycles: int, np: Any, outputs_cls: Any) -> dict:
    """Each phase on its own, ``cycles`` times, on the same data."""
    ns = time.perf_counter_ns
    inputs, outputs, comp, plaus = (
        service.inputs,
        service.outputs,
        service.comp,
        service.plausibility,
    )
    stats, pacing = service.stats, service.pacing
    t = np.empty((6, cycles), dtype=np.int64)
    clock = time.perf_counter
    for i in range(cycles):
        a = ns()
        driver.exchange(outputs, inputs)
        b = ns()
        driver._decode(inputs)
        c = ns()
        driver._encode(outputs)
        d = ns()
        plaus.check(inputs)
        e = ns()
        comp.step(inputs, clock(), outputs)
        f = ns()
        stats.add_roundtrip_from(driver.roundtrip_s)
        stats.read_ring.add(1e-5)
        stats.compensate_ring.add(1e-5)
        stats.write_ring.add(1e-5)
        stats.add_jitter(1e-6)
        pacing.finish(0.0, 1e-5, 0.0, True)
        g = ns()
        t[:, i] = (b - a, c - b, d - c, e - d, f - e, g - f)
    names = ("exchange", "decode", "encode", "plausibility", "compensate", "booking")
    return {name: _pct(t[k]) for k, name in enumerate(names)}


def _worker() -> None:
    """One measurement in this process; under ``loop.realtime`` settings unless
    ``BENCH_CYCLE_RT=0`` (SCHED_FIFO 50, memory locked: what the gateway runs with)."""
    cycles = int(sys.argv[2])
    report = None
    if os.environ.get("BENCH_CYCLE_RT", "1") != "0":
        from gateway.core.config import RealtimeConfig
        from gateway.runtime import realtime

        report = realtime.apply(RealtimeConfig(enabled=True), force=True)
    try:
        res: dict[str, Any] = dict(measure(cycles))
    finally:
        if report is not None:
            realtime.undo(report)
    res["rt"] = report.line("rt") if report is not None else "rt: off"
    print(json.dumps(res))


def _run_in(tree: Path, cycles: int) -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": str(tree), "PYTHONDONTWRITEBYTECODE": "1"}
    env.pop("NUMBA_CACHE_DIR", None)
    script = ROOT / "bench" / "bench_cycle.py"
    out = subprocess.run(
        [sys.executable, str(script), "--worker", str(cycles)],
        capture_output=True,
        text=True,
        env=env,
        cwd=str(tree),
        timeout=900,
    )
    if out.returncode != 0:
        raise RuntimeError(f"harness in {tree} failed: {out.stderr[-800:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _median(runs: list[dict[str, Any]]) -> dict[str, list[float]]:
    import numpy as np

    return {p: [float(np.median([r[p][k] for r in runs])) for k in range(3)] for p in PHASES}


def run() -> None:
    cycles = int(os.environ.get("BENCH_CYCLES", "20000"))
    rounds = int(os.environ.get("BENCH_CYCLE_ROUNDS", "3"))
    base_rev = os.environ.get("BENCH_CYCLE_BASE", "main")
    print(
        f"  compute per cycle, fake in-process bus (modbus_tcp driver, no socket), "
        f"{cycles} cycles x {rounds} rounds, p50 / p99 / p99.9 us"
    )
    with tempfile.TemporaryDirectory(prefix="bench-cycle-") as tmp:
        # imported here: the worker runs this file against an older tree on its path
        from bench.trees import tree_of

        base = tree_of(base_rev, tmp) if base_rev != "none" else None
        trees = (
            {"this tree": ROOT} if base is None else {f"base {base_rev}": base, "this tree": ROOT}
        )
        runs: dict[str, list[dict[str, Any]]] = {name: [] for name in trees}
        for tree in trees.values():  # numba compiles (and caches) before the timed rounds
            _run_in(tree, 100)
        for _ in range(rounds):
            for name, tree in trees.items():
                runs[name].append(_run_in(tree, cycles))
    med = {name: _median(r) for name, r in runs.items()}
    names = list(med)
    head = "".join(f"{n:<26}" for n in names) + ("ratio p50 / p99" if len(names) == 2 else "")
    print(f"  {'phase':<18}{head}")
    for p in PHASES:
        cells = "".join(f"{' / '.join(f'{v:.1f}' for v in med[n][p]):<26}" for n in names)
        if len(names) == 2:
            a, b = med[names[0]][p], med[names[1]][p]
            cells += f"{b[0] / a[0]:.2f} / {b[1] / a[1]:.2f}"
        print(f"  {p:<18}{cells}")
    print(f"  {runs[names[-1]][-1]['rt']}")
    print(
        f"  (medians over {rounds} alternating rounds; load average "
        f"{' '.join(f'{x:.2f}' for x in os.getloadavg())})"
    )


if __name__ == "__main__" and len(sys.argv) > 2 and sys.argv[1] == "--worker":
    _worker()
