"""Soft PLC plant: per-cycle step cost, the longest GIL stall it causes, batch throughput.

``python -m bench plant``:

1. ``Plant.step`` cost paced at 1 kHz, as the thread's CPU time (the time it holds the
   GIL, not counting the OS preempting it, but counting system calls, which release it):
   median, p99, p99.9, max, steps > 100 us; all steps, the steps within a chunk, and the
   first step of each chunk (which takes the next chunk);
2. the stall a server thread sees: the plant stepped in real time by :class:`PlcRuntime`
   (1 kHz, ``BENCH_PLANT_SECONDS`` s, default 5) while a probe thread in the same process
   sleeps 50 us again and again and records how late each wake-up is -- a wake-up is late
   by as long as something else held the GIL (or the CPU), exactly what the soft PLC's
   Modbus server thread waits through. Once with chunks prepared in process (the old
   way: statics of 250 samples every 250th step) and once with them prepared by the
   worker process (:mod:`sim_plc.chunk_worker`), side by side; all of that with real-time
   settings off and on (SCHED_FIFO 50 for this process: the other load of the machine
   drops out and the GIL is what is left);
3. ``make_recording`` throughput.
"""

from __future__ import annotations

import os
import threading
import time
from typing import Any

import numpy as np

from gateway.core.config import load_config
from sim_plc.image import ProcessImage
from sim_plc.plant import Plant, make_recording
from sim_plc.runtime import PlcRuntime

PROBE_SLEEP_S = 50e-6


def _probe(stop: threading.Event, out: list[float]) -> None:
    """Record how late each 50 us sleep wakes up (s); bounded by ``stop``."""
    clock = time.perf_counter
    for _ in range(10_000_000):
        if stop.is_set():
            return
        t0 = clock()
        time.sleep(PROBE_SLEEP_S)
        out.append(clock() - t0 - PROBE_SLEEP_S)


def stalls(plant: Plant, seconds: float) -> tuple[np.ndarray, PlcRuntime]:
    """Wake-up lateness (s) of a probe thread while ``plant`` runs in real time."""
    image = ProcessImage(plant.model.cables)
    for _ in range(200):  # compile (numba) and warm up
        plant.step(image)
    runtime = PlcRuntime(plant, image, plant.period_s)
    late: list[float] = []
    stop = threading.Event()
    probe = threading.Thread(target=_probe, args=(stop, late), daemon=True)
    runtime.start()
    time.sleep(0.3)  # past the first chunks
    probe.start()
    time.sleep(seconds)
    stop.set()
    probe.join(5.0)
    runtime.stop()
    return np.asarray(late), runtime


def _stall_line(name: str, late: np.ndarray, runtime: PlcRuntime) -> str:
    p50, p99, p999 = np.percentile(late, [50, 99, 99.9]) * 1e6
    over = int(np.sum(late > 100e-6))
    st = runtime.stats
    return (
        f"   {name:<32} probe wake-up late p50 {p50:5.0f} / p99 {p99:5.0f} / p99.9 "
        f"{p999:5.0f} / max {late.max() * 1e6:6.0f} us, {over} stalls > 100 us in "
        f"{late.size} wake-ups; runtime: longest step {st.max_step_s * 1e6:.0f} us, "
        f"{st.late} late cycles of {st.cycles}"
    )


def _stall_run(cfg: Any, seconds: float, worker: bool, rt: bool) -> None:
    """One stall measurement; with ``rt`` this process (runtime and probe threads) runs
    SCHED_FIFO 50 + mlockall and the worker SCHED_FIFO 1, so the machine's other load
    drops out and what is left is the GIL."""
    from gateway.core.config import RealtimeConfig
    from gateway.runtime import realtime
    from sim_plc.chunk_worker import ChunkWorker

    plant = Plant(cfg)
    chunks = None
    if worker:
        chunks = ChunkWorker(plant.model.cfg, plant.model.sim, plant.chunk).start()
        plant.use_chunks(chunks)
    report = realtime.apply(RealtimeConfig(enabled=rt, gc_off=False))
    if rt and report.refused:
        print(f"   ({report.line()})")
    if chunks is not None and report.old_policy is not None:
        chunks.lowest_realtime()
    try:
        late, runtime = stalls(plant, seconds)
    finally:
        realtime.undo(report)
        if chunks is not None:
            chunks.close()
    name = f"RT {'on ' if rt else 'off'}, chunks {'in a worker' if worker else 'in process'}"
    waits = f", waited {chunks.waits}x for a chunk" if chunks is not None else ""
    print(_stall_line(name, late, runtime) + waits)


def _step_cost(cfg, worker: bool) -> tuple[np.ndarray, np.ndarray]:
    """CPU time of 5000 steps paced at the plant's period (as the runtime steps them), and
    which of them began a chunk."""
    plant = Plant(cfg)
    chunks = None
    if worker:
        from sim_plc.chunk_worker import ChunkWorker

        chunks = ChunkWorker(plant.model.cfg, plant.model.sim, plant.chunk).start()
        plant.use_chunks(chunks)
    image = ProcessImage(cfg.cables)
    try:
        for _ in range(200):  # compile and warm up
            plant.step(image)
        took = np.empty(5000)  # the step's own CPU time: how long it holds the GIL
        first = np.zeros(took.size, dtype=bool)
        for k in range(took.size):
            first[k] = plant.k % plant.chunk == 0
            t0 = time.thread_time()
            plant.step(image)
            took[k] = time.thread_time() - t0
            time.sleep(plant.period_s)
    finally:
        if chunks is not None:
            chunks.close()
    return took, first


def run() -> None:
    cfg = load_config()
    seconds = float(os.environ.get("BENCH_PLANT_SECONDS", "5"))
    for worker in (False, True):
        took, first = _step_cost(cfg, worker)
        where = "the plant in a worker (replayed)" if worker else "the plant in process"
        for name, sel in (("all steps", slice(None)), ("  within a chunk", ~first)):
            t = took[sel]
            med, p99, p999 = np.percentile(t, [50, 99, 99.9]) * 1e6
            print(
                f"   Plant.step CPU, {where}, {name}: median {med:.0f} us, p99 {p99:.0f} "
                f"us, p99.9 {p999:.0f} us, max {t.max() * 1e6:.0f} us, "
                f"{int(np.sum(t > 100e-6))} of {t.size} steps > 100 us"
            )
        t = took[first]
        print(
            f"     first step of a chunk ({t.size}): median {np.median(t) * 1e6:.0f} us, max "
            f"{t.max() * 1e6:.0f} us"
            + (
                " (a write and a read on the worker's socket; "
                "the GIL is released in both system calls)"
                if worker
                else ""
            )
        )
    for rt in (False, True):
        for worker in (False, True):
            _stall_run(cfg, seconds, worker, rt)
    seconds = 10.0
    t0 = time.perf_counter()
    rec = make_recording(cfg, None, seconds)
    dt = time.perf_counter() - t0
    print(
        f"   make_recording: {rec.samples} samples in {dt:.2f} s "
        f"({rec.samples / dt:,.0f} samples/s, {seconds / dt:.1f}x real time)"
    )
