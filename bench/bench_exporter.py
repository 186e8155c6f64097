"""The metrics exporter under hostile scrapers: fds, threads, latency, overruns.

``python -m bench exporter``. The gateway daemon (``cdpr-gateway run``) runs as a child
process at 1 kHz against the soft PLC (``cdpr-gateway sim-plc``, another child) on
loopback, with the fd limit a systemd service gets by default (``RLIMIT_NOFILE`` 1024).
Then, against its metrics port:

1. **idle**: ``BENCH_IDLE`` (300) TCP clients connect and send nothing for
   ``BENCH_IDLE_HOLD_S`` (6 s); printed: the daemon's peak threads and open fds (from
   /proc) against the quiet figures, and one ordinary scrape's latency meanwhile;
2. **burst**: ``BENCH_SCRAPES`` (200) clients scrape at once (one request each, 30 s client
   timeout); printed: latency p50 / p99 / max, failures, and the overrun ratio of the
   cycle during the burst window against a quiet window of the same length.

``BENCH_EXPORTER_SRC`` runs the children from another source tree (e.g. an unpacked older
commit, for a before/after comparison). Figures only: nothing here asserts.
"""

from __future__ import annotations

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


def _child(src: Path, args: list[str]) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": str(src), "PYTHONUNBUFFERED": "1"}

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (FD_LIMIT, FD_LIMIT))

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


def _start(src: Path, tmp: Path) -> tuple[subprocess.Popen[str], subprocess.Popen[str], int]:
    base = src / "config" / "default.yaml"
    plc = _child(src, ["sim-plc", "--config", str(base), "--port", "0"])
    assert plc.stdout is not None
    line = plc.stdout.readline()
    host, port = line.rsplit(" on ", 1)[1].strip().rsplit(":", 1)
    data = yaml.safe_load(base.read_text())
    data["bus"]["modbus_tcp"].update(host=host, port=int(port))
    metrics_port = _free_port()
    data["metrics"] = {"host": "127.0.0.1", "port": metrics_port}
    cfg = tmp / "gateway.yaml"
    cfg.write_text(yaml.safe_dump(data))
    gw = _child(src, ["run", "--config", str(cfg)])
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


def run() -> None:
    src = Path(os.environ.get("BENCH_EXPORTER_SRC", ROOT)).resolve()
    idle = int(os.environ.get("BENCH_IDLE", "300"))
    hold = float(os.environ.get("BENCH_IDLE_HOLD_S", "6"))
    scrapes = int(os.environ.get("BENCH_SCRAPES", "200"))
    print(f"   source {src}; daemon RLIMIT_NOFILE {FD_LIMIT}")
    with tempfile.TemporaryDirectory() as tmp:
        plc, gw, port = _start(src, Path(tmp))
        try:
            _idle_phase(gw.pid, port, idle, hold)
            time.sleep(1.0)
            _burst_phase(port, scrapes)
            print(f"   after: threads, fds = {_proc_figures(gw.pid)}")
        finally:
            for proc in (gw, plc):
                stop_process(proc)


if __name__ == "__main__":
    run()
