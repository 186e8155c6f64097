"""Recording throughput: the 1 kHz loop without recording, recording CSV.gz and recording
Parquet, side by side; then the two files read as ``diagnose`` reads them, and
``diagnose`` of a soft-PLC recording written both ways.

``python -m bench record`` (``BENCH_SECONDS`` shortens the default 600 s per kind;
``BENCH_RT=1`` runs the gateway's thread and the soft PLC under the real-time settings of
``loop.realtime``, where the process may, so that a loaded machine's scheduling does not
drown the comparison). One soft PLC subprocess (``cdpr-gateway sim-plc``, Modbus TCP on
loopback, the default config with ``platform_mass`` mapped, stderr to a file) serves every
run; the gateway runs in this process without a recorder, with a ``.csv.gz`` recorder and
with a ``.parquet`` recorder (default ``record:`` settings, a temporary directory) in
alternating parts, so that a drifting load on a shared machine hits every kind alike.
Printed per kind: cycles, overruns, jitter p50/p99/p99.9, cycle p50/p99, CPU; for each
recording: rows written, samples dropped, file size, the extra CPU (in the gateway's
process, and in the recorder's writer process). Then each file read in a fresh process
as ``diagnose`` reads it (time, peak RSS from ``wait4``), and a ``record`` of the same
length (config/calibrate/viscous.yaml) written as CSV.gz and as Parquet and diagnosed:
time, peak RSS (the process's own VmHWM), verdict (``BENCH_RECORD_ONLY=diagnose``: this
part alone). Figures only: nothing asserts on time.
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
from gateway.core.config import DEFAULT_CONFIG_PATH, Config, RealtimeConfig, load_config
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
        print(
            f"    cycles {self.cycles}, overruns {self.overruns} ({share:.3f} %), "
            f"errors {self.errors}"
        )
        print(
            f"    jitter p50/p99/p99.9 {us(self.jitter, 50, 99, 99.9)}; "
            f"cycle p50/p99 {us(self.cycle, 50, 99)}"
        )


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
        cmd = [
            sys.executable,
            "-m",
            "gateway.cli",
            "sim-plc",
            "--config",
            config_path,
            "--port",
            "0",
            *(["--realtime"] if rt else []),
        ]
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


_PEAK = (
    "import atexit, sys\n"
    "def _peak():\n"
    "    with open('/proc/self/status') as f:\n"
    "        hwm = next(x for x in f if x.startswith('VmHWM:')).split()[1]\n"
    "    print(f'PEAK_KB {hwm}', file=sys.stderr)\n"
    "atexit.register(_peak)\n"
)  # the peak of this process's own memory (ru_maxrss would carry the forking parent's)


def _child(code: str, *args: str) -> tuple[str, float, float]:
    """Run Python ``code`` with ``args`` in a fresh process: (its stdout, wall s, its own
    peak RSS in MB, VmHWM)."""
    t0 = time.perf_counter()
    res = subprocess.run(
        [sys.executable, "-c", _PEAK + code, *args], capture_output=True, text=True, env=_env()
    )
    if res.returncode != 0:
        raise RuntimeError(f"{args}: exit status {res.returncode}: {res.stderr[-500:]}")
    peak = next(x for x in res.stderr.splitlines() if x.startswith("PEAK_KB"))
    return res.stdout, time.perf_counter() - t0, int(peak.split()[1]) / 1024


def _child_read(path: Path) -> tuple[float, float, float, int]:
    """Read ``path`` as ``diagnose`` does (lengths: first row only) in a fresh process:
    (seconds to read, peak RSS MB, RSS MB after the imports, samples)."""
    code = (
        "import sys, time\n"
        "from gateway.recordings.reader import read_recording\n"
        "import gateway.recordings.parquet\n"
        "before = int(next(x for x in open('/proc/self/status') if x.startswith('VmRSS:'))"
        ".split()[1])\n"
        "t0 = time.perf_counter()\n"
        "rec = read_recording(sys.argv[1], first_row_only=('length',))\n"
        "print(time.perf_counter() - t0, before, rec.samples)\n"
    )
    out, _, peak = _child(code, str(path))
    took, before, samples = out.split()
    return float(took), peak, float(before) / 1024, int(samples)


def _child_diagnose(path: Path) -> tuple[float, float, str]:
    """``cdpr-gateway diagnose PATH --model config/default.yaml --json`` in a fresh
    process: (wall s, peak RSS MB, verdict line)."""
    code = "import sys\nfrom gateway.cli import main\nsys.exit(main(sys.argv[1:]))\n"
    args = [
        "diagnose",
        str(path),
        "--model",
        str(DEFAULT_CONFIG_PATH),
        "--json",
        str(path) + ".json",
        "--quiet",
    ]
    out, wall, peak = _child(code, *args)
    return wall, peak, out.strip()


def _env() -> dict[str, str]:
    root = str(Path(__file__).resolve().parent.parent)
    env = {**os.environ, "PYTHONPATH": root}
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    return env


def _read_figures(files: dict[str, Path]) -> None:
    print("  read as diagnose reads it (a fresh process each; lengths: first row only):")
    for kind, path in files.items():
        took, peak, before, samples = _child_read(path)
        print(
            f"    {kind:8s} {path.stat().st_size / 1e6:6.1f} MB: {samples} samples in "
            f"{took:5.1f} s, peak RSS {peak:.0f} MB (imports {before:.0f} MB)"
        )


def _diagnose_figures(tmp: Path, seconds: float) -> None:
    """The soft PLC's 10-min recording (pose, mass and platform tensions) written both
    ways by ``record`` from one seed, then ``diagnose`` of each."""
    cfg = Path(__file__).resolve().parent.parent / "config" / "calibrate" / "viscous.yaml"
    print(f"  diagnose of a {seconds:.0f}-s `record` recording ({cfg.name}), each format:")
    for suffix in (".csv.gz", ".parquet"):
        path = tmp / f"sim{suffix}"
        t0 = time.perf_counter()
        subprocess.run(
            [
                sys.executable,
                "-m",
                "gateway.cli",
                "record",
                "--config",
                str(cfg),
                "--seconds",
                f"{seconds:g}",
                "--out",
                str(path),
                "--quiet",
            ],
            check=True,
            env=_env(),
        )
        made = time.perf_counter() - t0
        took, read_peak, before, _ = _child_read(path)
        wall, rss, verdict = _child_diagnose(path)
        print(
            f"    {suffix:8s} {path.stat().st_size / 1e6:6.1f} MB (record {made:.0f} s): "
            f"read {took:.1f} s, peak RSS {read_peak:.0f} MB (imports {before:.0f} MB); "
            f"diagnose {wall:.1f} s, peak RSS {rss:.0f} MB; {verdict}"
        )


KINDS = (("csv.gz", "bench.csv.gz"), ("parquet", "bench.parquet"))


def run() -> None:
    seconds = float(os.environ.get("BENCH_SECONDS", "600"))
    if os.environ.get("BENCH_RECORD_ONLY") == "diagnose":  # the files and diagnose alone
        with tempfile.TemporaryDirectory(prefix="bench-record-") as name:
            _diagnose_figures(Path(name), seconds)
        print(f"  load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
        return
    rt = os.environ.get("BENCH_RT", "0") == "1"
    cfg = load_config()
    if rt:
        cfg = dataclasses.replace(
            cfg, loop=dataclasses.replace(cfg.loop, realtime=RealtimeConfig(enabled=True))
        )
        print(f"  {realtime.apply(cfg.loop.realtime).line()}")
    cycles = max(1, round(seconds / cfg.loop.period_s))
    print(
        f"  {seconds:.0f} s per kind at {1 / cfg.loop.period_s:.0f} Hz, {cfg.cables} cables, "
        f"in {3 * HALVES} alternating runs (without, csv.gz, parquet, without, ...)"
    )
    plain = _Runs()
    runs = {kind: _Runs() for kind, _ in KINDS}
    plc_log = tempfile.TemporaryFile("w+")  # noqa: SIM115 (closed in the finally below)
    plc = _Plc(str(cfg.source), plc_log, rt)
    with tempfile.TemporaryDirectory(prefix="bench-record-") as name:
        tmp = Path(name)
        files = {kind: tmp / file for kind, file in KINDS}
        recs: dict[str, Recorder] = {}
        try:
            live = with_port(cfg, "modbus_tcp", plc.host, plc.port)
            for kind, path in files.items():
                rec = start_recorder(live, str(path))
                assert rec is not None
                recs[kind] = rec
            for _ in range(HALVES):
                plain.add(live, cycles // HALVES, None)
                for kind, rec in recs.items():
                    runs[kind].add(live, cycles // HALVES, rec)
        finally:
            for rec in recs.values():
                rec.close()
            plc.close()
            plc_log.close()
        plain.report("without recording")
        for kind, rec in recs.items():
            r, size = runs[kind], files[kind].stat().st_size
            r.report(f"with {kind:8s}   ")
            print(
                f"    recorded {rec.rows_written} rows x {len(rec.columns)} columns, dropped "
                f"{rec.dropped}, {size / 1e6:.1f} MB ({size / max(rec.rows_written, 1):.0f} "
                f"B/row){', FAILED: ' + rec.failed if rec.failed else ''}"
            )
            extra = r.cpu / r.wall - plain.cpu / plain.wall
            print(
                f"    recording costs {100 * extra:+.1f} % of one core in the gateway's "
                f"process, {100 * r.writer_cpu / r.wall:.1f} % in the writer "
                "process"
            )
        print(
            "  overruns without / "
            + " / ".join(f"with {k}" for k in recs)
            + ": "
            + " / ".join(str(x.overruns) for x in (plain, *runs.values()))
        )
        print(f"  load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
        _read_figures(files)
        _diagnose_figures(tmp, seconds)
    print(f"  load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
