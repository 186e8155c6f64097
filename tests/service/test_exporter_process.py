"""The metrics exporter in a process of its own (gateway/service/exporter_proc.py), fed by
the seqlock block (gateway/service/metrics_shm.py).

* the block gives back exactly what was published (a property over generated figures), and
  a reader in another process never sees a half-written publication;
* ``cdpr-gateway run`` (a real subprocess, against the soft PLC, another one) holds
  no listening socket itself: its exporter child does, serves the gateway's figures and
  the gateway's ``process_*``; a killed exporter is restarted on the same port; a killed
  daemon takes its exporter with it.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.base import ChannelStatus
from gateway.runtime.loopstats import ERROR_KINDS, LoopStats
from gateway.service import metrics
from gateway.service.metrics_shm import MetricsBlock, TornSnapshot
from tests.service.test_daemon_operator import write_config
from tests.service.test_recorder_parquet import _soft_plc

ROOT = Path(__file__).resolve().parents[2]
CABLES, REASONS = 3, 4


def fake_service(k: float, cables: int = CABLES) -> SimpleNamespace:
    """A stand-in for CyclicService whose every figure is ``k`` (ages too)."""
    stats = LoopStats(history=4)
    for hist in (stats.cycle, stats.jitter, stats.roundtrip):
        hist.counts = [int(k)] * len(hist.counts)
        hist.sum = k
    stats.overruns = int(k)
    stats.errors = dict.fromkeys(ERROR_KINDS, int(k))
    full = np.full(cables, k)
    return SimpleNamespace(
        stats=stats,
        state=int(k),
        bus_up=bool(k),
        heartbeat_fault=False,
        reconnects=int(k),
        recorder=SimpleNamespace(dropped=int(k)),
        plc_heartbeat_age_s=lambda: k,
        sample_age_s=lambda: k,
        driver=SimpleNamespace(gated=np.full(REASONS, k)),
        comp=SimpleNamespace(raw_n=full, corrected_n=full, friction_n=full, status=full),
    )


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
count = st.integers(0, 2**53)


@settings(max_examples=100, deadline=None)
@given(
    cables=st.integers(1, 12),
    counts=st.lists(count, min_size=3 * 11, max_size=3 * 11),
    sums=st.lists(finite, min_size=3, max_size=3),
    scalars=st.lists(count, min_size=5, max_size=5),
    ages=st.lists(st.floats(0, 1e6) | st.just(float("nan")), min_size=2, max_size=2),
    errors=st.lists(count, min_size=len(ERROR_KINDS), max_size=len(ERROR_KINDS)),
    data=st.data(),
)
def test_a_snapshot_is_exactly_what_was_published(
    cables, counts, sums, scalars, ages, errors, data
):
    svc = fake_service(0.0, cables)
    stats = svc.stats
    for i, hist in enumerate((stats.cycle, stats.jitter, stats.roundtrip)):
        hist.counts = counts[11 * i : 11 * i + len(hist.counts)]
        hist.count = sum(hist.counts)
        hist.sum = sums[i]
    stats.overruns, svc.reconnects, svc.recorder.dropped, state, fault = scalars
    svc.state, svc.heartbeat_fault, svc.bus_up = state % 4, bool(fault % 2), bool(state % 2)
    stats.errors = dict(zip(ERROR_KINDS, errors, strict=True))
    svc.plc_heartbeat_age_s = lambda: ages[0]
    svc.sample_age_s = lambda: ages[1]
    per_cable = [
        np.array(data.draw(st.lists(finite, min_size=cables, max_size=cables))) for _ in range(3)
    ]
    status = np.array(data.draw(st.lists(st.integers(0, 2), min_size=cables, max_size=cables)))
    svc.comp = SimpleNamespace(
        raw_n=per_cable[0], corrected_n=per_cable[1], friction_n=per_cable[2], status=status
    )
    svc.driver.gated = np.array(data.draw(st.lists(count, min_size=REASONS, max_size=REASONS)))

    block = MetricsBlock(cables, REASONS, fd=-1).attach(svc)
    assert block.snapshot() is None  # nothing published yet: nothing to serve
    block.publish()
    snap = block.snapshot()
    block.close()
    assert snap is not None
    for name in ("cycle", "jitter", "roundtrip"):
        hist, got = getattr(stats, name), getattr(snap, name)
        assert got.counts == hist.counts and got.count == hist.count and got.sum == hist.sum
    assert (snap.overruns, snap.reconnects, snap.record_dropped) == tuple(scalars[:3])
    assert (snap.state, snap.heartbeat_fault, snap.bus_up) == (
        svc.state,
        svc.heartbeat_fault,
        svc.bus_up,
    )
    assert snap.errors == stats.errors
    np.testing.assert_array_equal(snap.gated, svc.driver.gated)
    for got, want in zip((snap.raw_n, snap.corrected_n, snap.friction_n), per_cable, strict=True):
        np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(snap.status, status)
    # an age goes on growing after its publication, never shrinks (NaN stays NaN)
    for got, want in ((snap.plc_heartbeat_age_s, ages[0]), (snap.sample_age_s, ages[1])):
        assert (np.isnan(got) and np.isnan(want)) or want <= got < want + 5.0


def test_the_collector_marks_invalid_as_the_driver_does():
    assert int(ChannelStatus.INVALID) == metrics.INVALID


def test_a_block_left_mid_write_is_refused_not_half_read():
    block = MetricsBlock(CABLES, REASONS, fd=-1).attach(fake_service(1.0))
    block.publish()
    block._seq[0] += 1  # odd: a writer that died in the middle of a publication
    with pytest.raises(TornSnapshot):
        block.snapshot()  # bounded (READ_TIMEOUT_S): the exporter answers 500, never hangs
    block.close()


WRITER = """
import sys, numpy as np
from tests.service.test_exporter_process import fake_service, CABLES, REASONS
from gateway.service.metrics_shm import MetricsBlock
block = MetricsBlock(CABLES, REASONS, fd=int(sys.argv[1]))
for k in range(1, int(sys.argv[2]) + 1):
    block.attach(fake_service(float(k))).publish()
"""


def test_a_reader_in_another_process_never_sees_a_torn_publication():
    block = MetricsBlock(CABLES, REASONS)  # shared: a memfd
    publications = 20_000
    writer = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(block.fd), str(publications)],
        pass_fds=(block.fd,),
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        cwd=ROOT,
    )
    seen: set[float] = set()
    try:
        deadline = time.monotonic() + 120
        while writer.poll() is None and time.monotonic() < deadline and len(seen) < 50_000:
            snap = block.snapshot()
            if snap is None:
                continue
            k = snap.overruns
            figures = [
                snap.reconnects,
                snap.record_dropped,
                float(snap.state),
                snap.cycle.sum,
                snap.roundtrip.sum,
                *snap.jitter.counts,
                *snap.errors.values(),
                *snap.gated,
                *snap.raw_n,
                *snap.corrected_n,
                *snap.friction_n,
                *snap.status,
            ]
            assert all(f == k for f in figures), (k, figures)  # one publication, whole
            seen.add(k)
        assert writer.wait(timeout=120) == 0
    finally:
        if writer.poll() is None:
            writer.kill()
            writer.wait()
        block.close()
    assert len(seen) > 10  # read while it wrote, not only before or after


# --- the daemon ----------------------------------------------------------------------------


def children(pid: int) -> list[int]:
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        out += [int(c) for c in (task / "children").read_text().split()]
    return out


def listening_inodes(port: int | None = None) -> set[str]:
    """Socket inodes of every TCP listener (on ``port``), from /proc/net/tcp{,6}."""
    inodes = set()
    for name in ("tcp", "tcp6"):
        for line in Path(f"/proc/net/{name}").read_text().splitlines()[1:]:
            fields = line.split()
            local_port = int(fields[1].rsplit(":", 1)[1], 16)
            if fields[3] == "0A" and (port is None or local_port == port):
                inodes.add(fields[9])
    return inodes


def socket_inodes(pid: int) -> set[str]:
    out = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            out.add(target[8:-1])
    return out


def serves(pid: int, port: int) -> bool:
    """``pid`` holds the (every) socket listening on ``port``."""
    listener = listening_inodes(port)
    return bool(listener) and listener <= socket_inodes(pid)


def wait_for(predicate, seconds: float):
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.1)
    return predicate()


def metrics_port(err_path: Path) -> int | None:
    match = re.search(r"metrics on http://127\.0\.0\.1:(\d+)/metrics", err_path.read_text())
    return int(match.group(1)) if match else None


def scrape(port: int) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as r:
        return r.read().decode()


def value(body: str, name: str) -> float:
    match = re.search(rf"^{name} (\S+)$", body, re.M)
    assert match, name
    return float(match.group(1))


def start_time(pid: int) -> float:
    """process_start_time_seconds as prometheus_client computes it from /proc."""
    stat = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    btime = next(
        float(line.split()[1])
        for line in Path("/proc/stat").read_text().splitlines()
        if line.startswith("btime ")
    )
    return float(stat[19]) / os.sysconf("SC_CLK_TCK") + btime


def exporter_of(pid: int) -> int | None:
    kids = [c for c in children(pid) if b"exporter_proc" in Path(f"/proc/{c}/cmdline").read_bytes()]
    return kids[0] if len(kids) == 1 else None


@pytest.mark.loopback
@pytest.mark.slow
def test_the_daemon_serves_no_http_its_exporter_process_does_and_is_restarted(tmp_path):
    log = tmp_path / "err.log"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("NOTIFY_SOCKET", None)
    plc, plc_port, reader = _soft_plc()
    config = write_config(tmp_path, bus__modbus_tcp__port=plc_port)
    with log.open("w") as sink:  # the daemon's stderr into a file: never a full pipe
        proc = subprocess.Popen(
            [sys.executable, "-m", "gateway", "run", "--config", str(config)],
            stdout=subprocess.DEVNULL,
            stderr=sink,
            env=env,
        )
    again = None
    try:
        port = wait_for(lambda: metrics_port(log), 60)
        assert port, log.read_text()
        exporter = exporter_of(proc.pid)
        assert exporter, log.read_text()
        assert serves(exporter, port)
        assert not socket_inodes(proc.pid) & listening_inodes()  # the loop listens nowhere

        body = wait_for(lambda: scrape(port) if "cycle_seconds_count" in scrape(port) else "", 10)
        cycles = value(body, "cdpr_gateway_cycle_seconds_count")
        # process_* are the gateway's, read by the exporter from /proc/PID
        assert value(body, "process_start_time_seconds") == pytest.approx(
            start_time(proc.pid), abs=0.02
        )
        assert wait_for(lambda: value(scrape(port), "cdpr_gateway_state") == 2.0, 20)  # active
        assert wait_for(
            lambda: value(scrape(port), "cdpr_gateway_cycle_seconds_count") > cycles, 10
        )

        os.kill(exporter, signal.SIGKILL)  # the exporter dies: the daemon starts another
        again = wait_for(lambda: (exporter_of(proc.pid) or exporter) != exporter, 30) and (
            exporter_of(proc.pid)
        )
        assert again, log.read_text()
        assert wait_for(lambda: serves(again, port), 30), log.read_text()
        assert value(scrape(port), "cdpr_gateway_cycle_seconds_count") > cycles
        assert "the exporter process ended (exit status -9)" in log.read_text()
        assert proc.poll() is None  # the loop never stopped

        os.kill(proc.pid, signal.SIGKILL)  # the daemon dies: its exporter with it
        proc.wait(timeout=10)
        assert wait_for(lambda: not Path(f"/proc/{again}").exists() or _zombie(again), 15)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=10)
        for pid in (exporter_of(proc.pid) if proc.poll() is None else None, again):
            if pid and Path(f"/proc/{pid}").exists() and not _zombie(pid):
                os.kill(pid, signal.SIGKILL)  # only on failure: the test asserts it ended
        plc.kill()
        plc.wait(timeout=10)
        reader.join(timeout=10)
        assert plc.stdout is not None
        plc.stdout.close()
    assert "Traceback" not in log.read_text()


def _zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True
