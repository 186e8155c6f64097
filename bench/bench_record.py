"""Recording throughput: the 1 kHz loop with and without ``--record``, side by side.

``python -m bench record`` (``BENCH_SECONDS`` shortens the default 600 s per run). One
soft PLC subprocess (``cdpr-gateway sim-plc``, Modbus TCP on loopback, the default config
with ``platform_mass`` mapped) serves both runs; the gateway runs in this process, first
without a recorder, then with one writing ``.csv.gz`` to a temporary directory (the
default ``record:`` settings). Printed per run: cycles, overruns, jitter p50/p99/p99.9,
cycle p50/p99; for the recorded run: rows written, samples dropped, file size, the
recorder's CPU share, and the file read back with ``gateway.recording.read_recording``
(samples, time to read, the reader's peak RSS growth). Figures only: nothing asserts on
time.
"""

from __future__ import annotations

import os
import queue
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import IO

import numpy as np

from gateway.config import Config, load_config
from gateway.daemon import build_driver, start_recorder
from gateway.demo import with_port
from gateway.loop import CyclicService, Ring
from gateway.recording import read_recording


def _us(ring: Ring, *qs: float) -> str:
    data = ring.recent()
    return " / ".join(f"{v * 1e6:.0f}" for v in np.percentile(data, qs)) + " us"


def _one(cfg: Config, cycles: int, record: str | None) -> tuple[CyclicService, float, float]:
    """One run of ``cycles``; returns the service, wall s and CPU s of this process."""
    service = CyclicService(cfg, build_driver(cfg), history=cycles + 16)
    service.recorder = start_recorder(cfg, record) if record else None
    u0, w0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    try:
        service.run(cycles=cycles)
    finally:
        if service.recorder is not None:
            service.recorder.close()
    u1, w1 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    cpu = u1.ru_utime + u1.ru_stime - u0.ru_utime - u0.ru_stime
    return service, w1 - w0, cpu


def _report(title: str, service: CyclicService, wall: float, cpu: float) -> None:
    s = service.stats
    print(f"  {title}: {wall:.1f} s, CPU {100 * cpu / wall:.0f} % of one core")
    print(f"    cycles {s.cycles} (written {s.written}), overruns {s.overruns} "
          f"({100 * s.overruns / max(s.cycles, 1):.3f} %), skipped {s.skipped}, "
          f"errors {sum(s.errors.values())}")  # fmt: skip
    print(f"    jitter p50/p99/p99.9 {_us(s.jitter_ring, 50, 99, 99.9)}; "
          f"cycle p50/p99 {_us(s.cycle_ring, 50, 99)}")  # fmt: skip


class _Plc:
    """``cdpr-gateway sim-plc --port 0`` with stderr to a file (an unread stderr pipe fills
    up in a long run and stalls the soft PLC) and stdout drained by a thread."""

    def __init__(self, config_path: str, log: IO[str]) -> None:
        cmd = [sys.executable, "-m", "gateway.cli", "sim-plc", "--config", config_path,
               "--port", "0"]  # fmt: skip
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        root = str(Path(__file__).resolve().parent.parent)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log, text=True, env=env)
        assert self.proc.stdout is not None
        out = self.proc.stdout
        ready: queue.Queue[str] = queue.Queue()

        def drain() -> None:
            for line in out:
                if line.startswith("sim-plc: serving"):
                    ready.put(line.rsplit(" on ", 1)[1].strip())

        threading.Thread(target=drain, daemon=True).start()
        try:
            address = ready.get(timeout=60)
        except queue.Empty:
            self.close()
            raise RuntimeError("the soft PLC did not start") from None
        host, _, port = address.rpartition(":")
        self.host, self.port = host, int(port)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)


def run() -> None:
    seconds = float(os.environ.get("BENCH_SECONDS", "600"))
    cfg = load_config()
    cycles = max(1, round(seconds / cfg.loop.period_s))
    print(f"  {seconds:.0f} s per run at {1 / cfg.loop.period_s:.0f} Hz, {cfg.cables} cables")
    plc_log = tempfile.TemporaryFile("w+")  # noqa: SIM115 (closed in the finally below)
    plc = _Plc(str(cfg.source), plc_log)
    try:
        live = with_port(cfg, "modbus_tcp", plc.host, plc.port)
        plain = _one(live, cycles, None)
        with tempfile.TemporaryDirectory(prefix="bench-record-") as tmp:
            out = Path(tmp) / "bench.csv.gz"
            recorded = _one(live, cycles, str(out))
            size = out.stat().st_size
            rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
            t0 = time.perf_counter()
            back = read_recording(out)
            took = time.perf_counter() - t0
            rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    finally:
        plc.close()
        plc_log.close()
    _report("without recording", *plain)
    _report("with recording   ", *recorded)
    rec = recorded[0].recorder
    assert rec is not None
    print(f"    recorded {rec.rows_written} rows x {len(rec.columns)} columns, dropped "
          f"{rec.dropped}, {size / 1e6:.1f} MB gzip ({size / max(rec.rows_written, 1):.0f} "
          f"B/row){', FAILED: ' + rec.failed if rec.failed else ''}")  # fmt: skip
    extra_cpu = recorded[2] / recorded[1] - plain[2] / plain[1]
    print(f"    recording costs {100 * extra_cpu:+.1f} % of one core")
    o0, o1 = plain[0].stats.overruns, recorded[0].stats.overruns
    print(f"  overruns with/without recording: {o1} / {o0}")
    print(f"  read back: {back.samples} samples, {back.cables} cables, mass "
          f"{'yes' if back.mass is not None else 'no'}, {took:.1f} s, peak RSS growth "
          f"{max(0, rss1 - rss0) / 1024:.0f} MB (process peak {rss1 / 1024:.0f} MB)")  # fmt: skip
    print(f"  load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
