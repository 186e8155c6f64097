"""A real ``dask scheduler`` and ``dask worker`` processes on 127.0.0.1, for the fleet test
and ``python -m bench fleet``."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

from gateway.fleet.run import WORKER_MEMORY_BYTES

ROOT = Path(__file__).resolve().parents[1]


def _start(cmd: list[str], log: Path, env: dict[str, str]) -> subprocess.Popen[bytes]:
    with open(log, "wb") as fh:
        return subprocess.Popen(cmd, cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT, env=env)


def stop(procs: list[subprocess.Popen[bytes]]) -> None:
    """Terminate, then kill what is still running after 20 s."""
    for p in procs:
        if p.poll() is None:
            p.terminate()
    for p in procs:
        try:
            p.wait(20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(10)


@contextlib.contextmanager
def dask_cluster(tmp: Path, workers: int = 2) -> Iterator[str]:
    """Start a scheduler (any free port) and ``workers`` single-threaded workers with the
    fleet's memory limit, all on 127.0.0.1, logs in ``tmp``; yield the scheduler's address
    once every worker has joined; stop them all on exit."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    dask = str(Path(sys.executable).parent / "dask")
    sched_file = tmp / "scheduler.json"
    scheduler = [dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard"]
    procs = [_start([*scheduler, "--scheduler-file", str(sched_file)], tmp / "scheduler.log", env)]
    try:
        deadline = time.monotonic() + 60
        while not sched_file.exists() and time.monotonic() < deadline:
            if procs[0].poll() is not None:
                raise RuntimeError((tmp / "scheduler.log").read_text())
            time.sleep(0.1)
        address = json.loads(sched_file.read_text())["address"]
        worker = [dask, "worker", address, "--host", "127.0.0.1", "--nthreads", "1"]
        limit = ["--memory-limit", f"{WORKER_MEMORY_BYTES >> 20}MiB", "--no-dashboard"]
        for i in range(workers):
            procs.append(_start([*worker, *limit], tmp / f"worker{i}.log", env))
        wait = textwrap.dedent(f"""
            from distributed import Client
            with Client("{address}", timeout="30s") as c:
                c.wait_for_workers({workers}, timeout=90)
                print(len(c.scheduler_info()["workers"]))
        """)
        ready = subprocess.run(
            [sys.executable, "-c", wait], capture_output=True, text=True, timeout=120, env=env
        )
        if ready.stdout.strip() != str(workers):
            raise RuntimeError(f"{workers} dask workers did not join: {ready.stderr}")
        yield address
    finally:
        stop(procs)
