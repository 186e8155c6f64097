"""Recording throughput: the 1 kHz loop with and without ``--record``, side by side.

``python -m bench record`` (``BENCH_SECONDS`` shortens the default 600 s per kind;
``BENCH_RT=1`` runs the gateway's thread and the soft PLC under the real-time settings of
``loop.realtime``, where the process may, so that a loaded machine's scheduling does not
drown the comparison). One
soft PLC subprocess (``cdpr-gateway sim-plc``, Modbus TCP on loopback, the default config
with ``platform_mass`` mapped, stderr to a file) serves every run; the gateway runs in
this process, without a recorder and with one (writing ``.csv.gz`` to a temporary
directory, default ``record:`` settings) in alternating halves, so that a drifting load on
a shared machine hits both kinds alike. Printed per kind: cycles, overruns, jitter
p50/p99/p99.9, cycle p50/p99, CPU; for the recording: rows written, samples dropped, file
size, the extra CPU (in the gateway's process, and in the recorder's writer process), and
the file read back with ``gateway.recordings.reader.read_recording``
(samples, time to read, the reader's peak RSS growth). Figures only: nothing asserts on
time.
"""

from __future__ import annotations

import dataclasses
import os
import queue
import resource
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import numpy as np

from bench import stop_process
from gateway.core.config import Config, RealtimeConfig, load_config
from gateway.recordings.reader import read_recording
from gateway.runtime import realtime
from gateway.runtime.loop import CyclicService
from gateway.service.daemon import build_driver, start_recorder
from gateway.service.recorder import Recorder
from sim_plc.demo import with_port

HALVES = 2  # each kind runs in this many parts, alternating, against drifting load


@dataclass
class _Runs:
    """The figures of the runs of one kind (without or with recording), summed."""

    cycles: int = 0
    overruns: int = 0
    errors: int = 0
    wall: float = 0.0
    cpu: float = 0.0
    writer_cpu: float = 0.0  # the recorder's writer process
    jitter: list[np.ndarray] = field(default_factory=list)
    cycle: list[np.ndarray] = field(default_factory=list)

    def add(self, cfg: Config, cycles: int, recorder: Recorder | None) -> None:
        service = CyclicService(cfg, build_driver(cfg), history=cycles + 16)
        service.recorder = recorder
        pid = recorder.pid if recorder is not None else None
        c0 = _process_cpu(pid)
        u0, w0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        service.run(cycles=cycles)
        u1, w1 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        self.cpu += u1.ru_utime + u1.ru_stime - u0.ru_utime - u0.ru_stime
        self.writer_cpu += _process_cpu(pid) - c0
        self.wall += w1 - w0
        s = service.stats
        self.cycles += s.cycles
        self.overruns += s.overruns
        self.errors += sum(s.errors.values())
        self.jitter.append(s.jitter_ring.recent().copy())
        self.cycle.append(s.cycle_ring.recent().copy())

    def report(self, title: str) -> None:
        def us(parts: list[np.ndarray], *qs: float) -> str:
            data = np.concatenate(parts)
            return " / ".join(f"{v * 1e6:.0f}" for v in np.percentile(data, qs)) + " us"

        print(f"  {title}: {self.wall:.1f} s, CPU {100 * self.cpu / self.wall:.0f} % of one core")
        share = 100 * self.overruns / max(self.cycles, 1)
        print(f"    cycles {self.cycles}, overruns {self.overruns} ({share:.3f} %), "
              f"errors {self.errors}")  # fmt: skip
        print(f"    jitter p50/p99/p99.9 {us(self.jitter, 50, 99, 99.9)}; "
              f"cycle p50/p99 {us(self.cycle, 50, 99)}")  # fmt: skip


def _process_cpu(pid: int | None) -> float:
    """User + system CPU seconds of process ``pid`` so far (/proc; 0 without one)."""
    if pid is None:
        return 0.0
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class _Plc:
    """``cdpr-gateway sim-plc --port 0`` with stderr to a file (an unread stderr pipe fills
    up in a long run and stalls the soft PLC) and stdout drained by a thread."""

    def __init__(self, config_path: str, log: IO[str], rt: bool = False) -> None:
        cmd = [sys.executable, "-m", "gateway.cli", "sim-plc", "--config", config_path,
               "--port", "0", *(["--realtime"] if rt else [])]  # fmt: skip
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
        stop_process(self.proc, timeout_s=10)


def run() -> None:
    seconds = float(os.environ.get("BENCH_SECONDS", "600"))
    rt = os.environ.get("BENCH_RT", "0") == "1"
    cfg = load_config()
    if rt:
        cfg = dataclasses.replace(
            cfg, loop=dataclasses.replace(cfg.loop, realtime=RealtimeConfig(enabled=True))
        )
        print(f"  {realtime.apply(cfg.loop.realtime).line()}")
    cycles = max(1, round(seconds / cfg.loop.period_s))
    print(f"  {seconds:.0f} s per kind at {1 / cfg.loop.period_s:.0f} Hz, {cfg.cables} cables, "
          f"in {2 * HALVES} alternating runs (without, with, without, ...)")  # fmt: skip
    plain, recorded = _Runs(), _Runs()
    plc_log = tempfile.TemporaryFile("w+")  # noqa: SIM115 (closed in the finally below)
    plc = _Plc(str(cfg.source), plc_log, rt)
    try:
        live = with_port(cfg, "modbus_tcp", plc.host, plc.port)
        with tempfile.TemporaryDirectory(prefix="bench-record-") as tmp:
            out = Path(tmp) / "bench.csv.gz"
            rec = start_recorder(live, str(out))
            assert rec is not None
            try:
                for _ in range(HALVES):
                    plain.add(live, cycles // HALVES, None)
                    recorded.add(live, cycles // HALVES, rec)
            finally:
                rec.close()
            size = out.stat().st_size
            rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
            t0 = time.perf_counter()
            back = read_recording(out)
            took = time.perf_counter() - t0
            rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    finally:
        plc.close()
        plc_log.close()
    plain.report("without recording")
    recorded.report("with recording   ")
    print(f"    recorded {rec.rows_written} rows x {len(rec.columns)} columns, dropped "
          f"{rec.dropped}, {size / 1e6:.1f} MB gzip ({size / max(rec.rows_written, 1):.0f} "
          f"B/row){', FAILED: ' + rec.failed if rec.failed else ''}")  # fmt: skip
    extra = recorded.cpu / recorded.wall - plain.cpu / plain.wall
    print(f"    recording costs {100 * extra:+.1f} % of one core in the gateway's process, "
          f"{100 * recorded.writer_cpu / recorded.wall:.1f} % in the writer process")  # fmt: skip
    print(f"  overruns with/without recording: {recorded.overruns} / {plain.overruns}")
    print(f"  read back: {back.samples} samples, {back.cables} cables, mass "
          f"{'yes' if back.mass is not None else 'no'}, {took:.1f} s, peak RSS growth "
          f"{max(0, rss1 - rss0) / 1024:.0f} MB (process peak {rss1 / 1024:.0f} MB)")  # fmt: skip
    print(f"  load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
