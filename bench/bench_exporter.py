"""The metrics exporter under hostile scrapers: fds, threads, latency, overruns, gaps.

``python -m bench exporter``. The gateway daemon (``cdpr-gateway run --record``) runs as a
child process at 1 kHz against the soft PLC (``cdpr-gateway sim-plc``, another child) on
loopback, with the fd limit a systemd service gets by default (``RLIMIT_NOFILE`` 1024).
Then, against its metrics port:

0. **storm** (issue 30): ``BENCH_STORM_S`` (20) s quiet, then as long with
   ``BENCH_STORM_CLIENTS`` (32) keep-alive clients scraping ``/metrics`` flat out (each
   request with a 5 s timeout, every client ended at the window's end); side by side: the
   overruns of each window (from the gateway's counters), the longest gap between two
   writes and the gaps over 5 and 10 ms (from the recording's ``t``: one row per written
   cycle, on the loop's clock), scrapes served per second and the CPU seconds of the
   gateway's and the exporter's process (/proc) in each window;

1. **idle**: ``BENCH_IDLE`` (300) TCP clients connect and send nothing for
   ``BENCH_IDLE_HOLD_S`` (6 s); printed: the daemon's peak threads and open fds (from
   /proc) against the quiet figures, and one ordinary scrape's latency meanwhile;
2. **burst**: ``BENCH_SCRAPES`` (200) clients scrape at once (one request each, 30 s client
   timeout); printed: latency p50 / p99 / max, failures, and the overrun ratio of the
   cycle during the burst window against a quiet window of the same length.

The soft PLC runs SCHED_FIFO ``BENCH_PLC_FIFO`` (40, below the gateway's 50; 0: as
started) where permitted: it stands for a PLC of its own, which no scraper on the gateway's
host can slow; at SCHED_OTHER on a loaded host its replies are what the storm delays.
``BENCH_EXPORTER_SRC`` runs the children from another source tree (e.g. an unpacked older
commit, for a before/after comparison). ``BENCH_EXPORTER_SERVERS=1`` adds the server
comparison: the exporter process's registry (over a published metrics block) served by the
project's :class:`MetricsServer` and by prometheus_client's ``start_http_server``, each in a
process of its own under the same storm for ``BENCH_STORM_S`` s: scrapes/s and server CPU.
Figures only: nothing here asserts.
"""

from __future__ import annotations

import contextlib
import http.client
import os
import re
import resource
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import yaml

from bench import stop_process

ROOT = Path(__file__).resolve().parent.parent
FD_LIMIT = 1024  # systemd's default soft limit for a service


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _child(src: Path, args: list[str], fifo: int = 0) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": str(src), "PYTHONUNBUFFERED": "1"}

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (FD_LIMIT, FD_LIMIT))
        if fifo:  # where permitted; else the child runs as started
            with contextlib.suppress(OSError):
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(fifo))

    return subprocess.Popen(
        [sys.executable, "-m", "gateway.cli", *args],
        cwd=src,
        env=env,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        preexec_fn=limit,
    )


def _proc_figures(pid: int) -> tuple[int, int]:
    """(threads, open fds) of a process, from /proc."""
    return len(os.listdir(f"/proc/{pid}/task")), len(os.listdir(f"/proc/{pid}/fd"))


def _scrape(port: int, timeout: float = 30.0) -> tuple[float, str]:
    start = time.perf_counter()
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=timeout) as r:
        body = r.read().decode()
    return time.perf_counter() - start, body


def _counter(body: str, name: str) -> float:
    match = re.search(rf"^{name} (\S+)$", body, re.M)
    return float(match.group(1)) if match else float("nan")


def _cycles_overruns(port: int) -> tuple[float, float]:
    _, body = _scrape(port)
    return _counter(body, "cdpr_gateway_cycle_seconds_count"), _counter(
        body, "cdpr_gateway_overruns_total"
    )


def _start(
    src: Path, tmp: Path, record: Path | None = None
) -> tuple[subprocess.Popen[str], subprocess.Popen[str], int]:
    base = src / "config" / "default.yaml"
    fifo = int(os.environ.get("BENCH_PLC_FIFO", "40"))
    plc = _child(src, ["sim-plc", "--config", str(base), "--port", "0"], fifo)
    assert plc.stdout is not None
    line = plc.stdout.readline()
    host, port = line.rsplit(" on ", 1)[1].strip().rsplit(":", 1)
    data = yaml.safe_load(base.read_text())
    data["bus"]["modbus_tcp"].update(host=host, port=int(port))
    metrics_port = _free_port()
    data["metrics"] = {"host": "127.0.0.1", "port": metrics_port}
    cfg = tmp / "gateway.yaml"
    cfg.write_text(yaml.safe_dump(data))
    extra = ["--record", str(record)] if record is not None else []
    gw = _child(src, ["run", "--config", str(cfg), *extra])
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if _cycles_overruns(metrics_port)[0] > 2000:  # past numba warm-up
                return plc, gw, metrics_port
        except OSError:
            pass
        time.sleep(0.5)
    raise RuntimeError("the gateway's metrics never came up")


def _idle_phase(pid: int, port: int, count: int, hold_s: float) -> None:
    quiet = _proc_figures(pid)
    clients = []
    for _ in range(count):
        s = socket.socket()
        s.settimeout(2.0)
        try:
            s.connect(("127.0.0.1", port))
        except OSError:
            s.close()
            continue
        clients.append(s)
    peak_threads, peak_fds = quiet
    scrape = "failed"
    end = time.monotonic() + hold_s
    while time.monotonic() < end:
        threads, fds = _proc_figures(pid)
        peak_threads, peak_fds = max(peak_threads, threads), max(peak_fds, fds)
        if scrape == "failed" and time.monotonic() > end - hold_s / 2:
            try:
                scrape = f"{_scrape(port, 10.0)[0] * 1e3:.1f} ms"
            except OSError as exc:
                scrape = f"failed ({exc})"
        time.sleep(0.2)
    for s in clients:
        s.close()
    print(
        f"   idle x{len(clients)} for {hold_s:.0f} s: threads {quiet[0]} -> peak "
        f"{peak_threads}, fds {quiet[1]} -> peak {peak_fds}; a scrape meanwhile: "
        f"{scrape}"
    )


def _burst_phase(port: int, count: int) -> None:
    barrier = threading.Barrier(count)
    lat: list[float] = []
    failed: list[str] = []

    def one() -> None:
        barrier.wait()
        try:
            lat.append(_scrape(port)[0])
        except OSError as exc:
            failed.append(type(exc).__name__)

    time.sleep(0.5)  # past the exporter's payload cache (0.25 s): fresh counters
    c0, o0 = _cycles_overruns(port)
    start = time.monotonic()
    workers = [threading.Thread(target=one) for _ in range(count)]
    for w in workers:
        w.start()
    for w in workers:
        w.join(timeout=60)
    window = time.monotonic() - start
    time.sleep(0.5)
    c1, o1 = _cycles_overruns(port)
    time.sleep(1.0)
    c2, o2 = _cycles_overruns(port)
    time.sleep(window + 0.5)
    c3, o3 = _cycles_overruns(port)
    a = np.asarray(lat) * 1e3 if lat else np.asarray([np.nan])
    print(
        f"   burst x{count}: latency p50 {np.percentile(a, 50):.1f} ms, p99 "
        f"{np.percentile(a, 99):.1f} ms, max {a.max():.1f} ms; failed {len(failed)} "
        f"{sorted(set(failed))}; window {window:.2f} s"
    )
    print(
        f"   overruns during the burst {100 * (o1 - o0) / max(c1 - c0, 1):.2f} % "
        f"of {c1 - c0:.0f} cycles; quiet window {100 * (o3 - o2) / max(c3 - c2, 1):.2f} % "
        f"of {c3 - c2:.0f} cycles"
    )


def _storm(port: int, clients: int, seconds: float) -> tuple[int, int]:
    """``clients`` keep-alive clients scraping flat out for ``seconds``: (served, failed)."""
    served, failed = [0] * clients, [0] * clients
    end = time.monotonic() + seconds

    def client(i: int) -> None:
        conn: http.client.HTTPConnection | None = None
        while time.monotonic() < end:
            try:
                if conn is None:
                    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5.0)
                conn.request("GET", "/metrics")
                response = conn.getresponse()
                response.read()
                served[i] += response.status == 200
                if response.will_close:
                    conn.close()
                    conn = None
            except (OSError, http.client.HTTPException):
                failed[i] += 1
                if conn is not None:
                    conn.close()
                conn = None
        if conn is not None:
            conn.close()

    workers = [threading.Thread(target=client, args=(i,)) for i in range(clients)]
    for w in workers:
        w.start()
    for w in workers:
        w.join(timeout=seconds + 30)
    return sum(served), sum(failed)


def _cpu_s(pid: int | None) -> float:
    """utime + stime of a process (and its reaped children: none here), in s."""
    if pid is None:
        return float("nan")
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return float("nan")
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _exporter_pid(pid: int) -> int | None:
    """The gateway's exporter process, if it has one (before issue 30 it had none)."""
    for task in Path(f"/proc/{pid}/task").iterdir():
        for child in (task / "children").read_text().split():
            if b"exporter_proc" in Path(f"/proc/{child}/cmdline").read_bytes():
                return int(child)
    return None


def _gaps(t: np.ndarray, lo: float, hi: float) -> tuple[float, int, int]:
    """(longest gap in ms, gaps over 5 ms, over 10 ms) between rows with lo <= t <= hi."""
    d = np.diff(t[(t >= lo) & (t <= hi)]) * 1e3
    if d.size == 0:
        return float("nan"), 0, 0
    return float(d.max()), int((d > 5).sum()), int((d > 10).sum())


def _storm_phase(gw: subprocess.Popen[str], port: int, clients: int, seconds: float) -> list[float]:
    """Quiet window, then the storm; prints overruns, scrapes and CPU; returns the window
    bounds (time.monotonic()) for the recording's gaps."""
    exporter = _exporter_pid(gw.pid)
    marks = [time.monotonic()]
    c0, o0 = _cycles_overruns(port)
    cpu0 = (_cpu_s(gw.pid), _cpu_s(exporter))
    time.sleep(seconds)
    marks.append(time.monotonic())
    c1, o1 = _cycles_overruns(port)
    cpu1 = (_cpu_s(gw.pid), _cpu_s(exporter))
    served, failed = _storm(port, clients, seconds)
    marks.append(time.monotonic())
    c2, o2 = _cycles_overruns(port)
    cpu2 = (_cpu_s(gw.pid), _cpu_s(exporter))
    quiet = 100 * (o1 - o0) / max(c1 - c0, 1)
    storm = 100 * (o2 - o1) / max(c2 - c1, 1)
    print(
        f"   storm x{clients} for {seconds:.0f} s: {served} scrapes served "
        f"({served / (marks[2] - marks[1]):.0f}/s), {failed} failed"
    )
    print(
        f"   overruns: quiet {quiet:.3f} % of {c1 - c0:.0f} cycles, storm {storm:.3f} % of "
        f"{c2 - c1:.0f} cycles: {storm - quiet:+.3f} percentage points"
    )
    print(
        f"   CPU s (gateway / exporter process): quiet {cpu1[0] - cpu0[0]:.2f} / "
        f"{cpu1[1] - cpu0[1]:.2f}, storm {cpu2[0] - cpu1[0]:.2f} / {cpu2[1] - cpu1[1]:.2f}"
        + ("" if exporter else " (no exporter process: it serves from the gateway's)")
    )
    return marks


def _storm_gaps(record: Path, stopped_at: float, marks: list[float]) -> None:
    """The recording's ``t`` on the bench's clock: the last row was written just before
    the stop (both clocks are CLOCK_MONOTONIC; the loop ends within a cycle of SIGTERM)."""
    with record.open() as fh:
        rows = [line for line in fh if not line.startswith("#")][1:]  # the header first
    t = np.array([float(line.split(",", 1)[0]) for line in rows])
    t0 = stopped_at - t[-1]
    windows = {"quiet": (marks[0], marks[1]), "storm": (marks[1], marks[2])}
    parts = []
    for name, (lo, hi) in windows.items():
        longest, over5, over10 = _gaps(t, lo - t0 + 0.1, hi - t0 - 0.1)
        parts.append(f"{name} {longest:.2f} ms ({over5} over 5 ms, {over10} over 10 ms)")
    print("   longest gap between writes: " + "; ".join(parts))


SERVE = """
import sys, time
from prometheus_client import start_http_server
from gateway.core.config import load_config
from gateway.runtime.loop import CyclicService
from gateway.service.daemon import build_driver
from gateway.service.metrics import exporter_registry
from gateway.service.metrics_shm import MetricsBlock
from gateway.service.exporter import MetricsServer
from gateway.core.config import MetricsConfig
cfg = load_config(sys.argv[2])
svc = CyclicService(cfg, build_driver(cfg))
block = MetricsBlock(cfg.cables, len(svc.driver.GATE_REASONS), fd=-1).attach(svc)
block.publish()
registry = exporter_registry(block, "modbus_tcp", svc.driver.GATE_REASONS, 1)
port = int(sys.argv[3])
if sys.argv[1] == "prometheus_client":
    start_http_server(port, "127.0.0.1", registry=registry)
else:
    MetricsServer(MetricsConfig(host="127.0.0.1", port=port), registry)
print("ready", flush=True)
sys.stdin.read()
"""


def _servers_phase(src: Path, clients: int, seconds: float) -> None:
    """Decision input: the same registry, two servers, each in its own process, one storm."""
    cfg = src / "config" / "default.yaml"
    for server in ("MetricsServer", "prometheus_client"):
        port = _free_port()
        env = {**os.environ, "PYTHONPATH": str(src)}
        proc = subprocess.Popen(
            [sys.executable, "-c", SERVE, server, str(cfg), str(port)],
            cwd=src,
            env=env,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            assert proc.stdout is not None
            proc.stdout.readline()
            cpu0, start = _cpu_s(proc.pid), time.monotonic()
            served, failed = _storm(port, clients, seconds)
            cpu, wall = _cpu_s(proc.pid) - cpu0, time.monotonic() - start
            threads = len(os.listdir(f"/proc/{proc.pid}/task"))
            print(
                f"   server {server}: {served / wall:.0f} scrapes/s ({failed} failed), "
                f"CPU {cpu:.2f} s in {wall:.1f} s ({1e3 * cpu / max(served, 1):.3f} ms a "
                f"scrape), {threads} threads after"
            )
        finally:
            assert proc.stdin is not None and proc.stdout is not None
            proc.stdin.close()
            stop_process(proc)
            proc.stdout.close()


def run() -> None:
    src = Path(os.environ.get("BENCH_EXPORTER_SRC", ROOT)).resolve()
    idle = int(os.environ.get("BENCH_IDLE", "300"))
    hold = float(os.environ.get("BENCH_IDLE_HOLD_S", "6"))
    scrapes = int(os.environ.get("BENCH_SCRAPES", "200"))
    clients = int(os.environ.get("BENCH_STORM_CLIENTS", "32"))
    storm_s = float(os.environ.get("BENCH_STORM_S", "20"))
    print(f"   source {src}; daemon RLIMIT_NOFILE {FD_LIMIT}")
    with tempfile.TemporaryDirectory() as tmp:
        record = Path(tmp) / "run.csv"
        plc, gw, port = _start(src, Path(tmp), record)
        try:
            time.sleep(1.0)
            marks = _storm_phase(gw, port, clients, storm_s)
            stopped_at = time.monotonic()
            gw.terminate()
            gw.wait(timeout=30)
            _storm_gaps(record, stopped_at, marks)
        finally:
            for proc in (gw, plc):
                stop_process(proc)
        plc, gw, port = _start(src, Path(tmp))
        try:
            _idle_phase(gw.pid, port, idle, hold)
            time.sleep(1.0)
            _burst_phase(port, scrapes)
            print(f"   after: threads, fds = {_proc_figures(gw.pid)}")
        finally:
            for proc in (gw, plc):
                stop_process(proc)
    if os.environ.get("BENCH_EXPORTER_SERVERS") == "1":
        _servers_phase(src, clients, storm_s)


if __name__ == "__main__":
    run()
