"""A real ``dask scheduler`` and ``dask worker`` processes on 127.0.0.1, for the fleet test
and ``python -m bench fleet``; and the same spread over network namespaces this module
creates, each worker on a "host" of its own (:func:`dask_hosts`)."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import textwrap
import time
import uuid
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


def _wait_for_workers(address: str, workers: int, env: dict[str, str], ns: list[str]) -> None:
    wait = textwrap.dedent(f"""
        from distributed import Client
        with Client("{address}", timeout="30s") as c:
            c.wait_for_workers({workers}, timeout=90)
            print(len(c.scheduler_info()["workers"]))
    """)
    ready = subprocess.run(
        [*ns, sys.executable, "-c", wait], capture_output=True, text=True, timeout=120, env=env
    )
    if ready.stdout.strip() != str(workers):
        raise RuntimeError(f"{workers} dask workers did not join: {ready.stderr}")


def _scheduler_address(sched_file: Path, scheduler: subprocess.Popen[bytes], log: Path) -> str:
    deadline = time.monotonic() + 60
    while not sched_file.exists() and time.monotonic() < deadline:
        if scheduler.poll() is not None:
            raise RuntimeError(log.read_text())
        time.sleep(0.1)
    return str(json.loads(sched_file.read_text())["address"])


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
        address = _scheduler_address(sched_file, procs[0], tmp / "scheduler.log")
        worker = [dask, "worker", address, "--host", "127.0.0.1", "--nthreads", "1"]
        limit = ["--memory-limit", f"{WORKER_MEMORY_BYTES >> 20}MiB", "--no-dashboard"]
        for i in range(workers):
            procs.append(_start([*worker, *limit], tmp / f"worker{i}.log", env))
        _wait_for_workers(address, workers, env, [])
        yield address
    finally:
        stop(procs)


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=10)


@contextlib.contextmanager
def dask_hosts(tmp: Path, hosts: int = 2) -> Iterator[tuple[list[str], str, list[str]]]:
    """A scheduler in a network namespace of its own and one single-threaded worker in
    each of ``hosts`` others, every worker joined to the scheduler's namespace by a veth
    pair on a private /24 (``10.213.K.0``): hosts as far as the network can tell, on this
    machine, touching nothing of its own network. Yields (the command prefix that runs a
    program in the scheduler's namespace, the scheduler's address, the workers' hosts);
    removes the namespaces, and with them the links, on exit. Needs root and ``ip``."""
    tag = uuid.uuid4().hex[:6]
    sched_ns, worker_ns = f"cdpr-fleet-{tag}-s", [f"cdpr-fleet-{tag}-w{k}" for k in range(hosts)]
    made: list[str] = []
    procs: list[subprocess.Popen[bytes]] = []
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    dask = str(Path(sys.executable).parent / "dask")
    try:
        for ns in (sched_ns, *worker_ns):
            _ip("netns", "add", ns)
            made.append(ns)
            _ip("-n", ns, "link", "set", "lo", "up")
        worker_hosts = []
        for k, ns in enumerate(worker_ns, start=1):
            here, there = f"cf{tag}s{k}", f"cf{tag}w{k}"  # <= 15 characters
            _ip(
                "-n",
                sched_ns,
                "link",
                "add",
                here,
                "type",
                "veth",
                "peer",
                "name",
                there,
                "netns",
                ns,
            )
            _ip("-n", sched_ns, "addr", "add", f"10.213.{k}.1/24", "dev", here)
            _ip("-n", sched_ns, "link", "set", here, "up")
            _ip("-n", ns, "addr", "add", f"10.213.{k}.2/24", "dev", there)
            _ip("-n", ns, "link", "set", there, "up")
            _ip("-n", ns, "route", "add", "default", "via", f"10.213.{k}.1")
            worker_hosts.append(f"10.213.{k}.2")
        in_sched = ["ip", "netns", "exec", sched_ns]
        sched_file = tmp / "scheduler.json"
        scheduler = [dask, "scheduler", "--host", "10.213.1.1", "--port", "0", "--no-dashboard"]
        log = tmp / "scheduler.log"
        procs.append(_start([*in_sched, *scheduler, "--scheduler-file", str(sched_file)], log, env))
        address = _scheduler_address(sched_file, procs[0], log)
        limit = ["--memory-limit", f"{WORKER_MEMORY_BYTES >> 20}MiB", "--no-dashboard"]
        for k, (ns, host) in enumerate(zip(worker_ns, worker_hosts, strict=True)):
            worker = ["ip", "netns", "exec", ns, dask, "worker", address, "--host", host]
            procs.append(_start([*worker, "--nthreads", "1", *limit], tmp / f"worker{k}.log", env))
        _wait_for_workers(address, hosts, env, in_sched)
        yield in_sched, address, worker_hosts
    finally:
        stop(procs)
        for ns in made:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)
