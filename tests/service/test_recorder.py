"""The gateway's recorder: shared ring in the cycle, writer process, rotation, failures."""

from __future__ import annotations

import fcntl
import gzip
import logging
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from drivers.base import Inputs, Outputs
from gateway.recordings.reader import read_recording
from gateway.service.recorder import RecordConfig, Recorder
from tests.config_helpers import edited_config

ROOT = Path(__file__).resolve().parents[2]
M = 3


def frame(k: int) -> tuple[Inputs, Outputs]:
    """Inputs and outputs of cycle ``k``: every value derived from ``k``."""
    inp, out = Inputs.allocate(M), Outputs.allocate(M)
    inp.velocity_m_s[:] = 0.01 * k + np.arange(M)
    inp.tension_raw_n[:] = 100.0 + k
    inp.length_m[:] = 1.0 + 1e-3 * k
    inp.pose[:] = [0.1, 0.2, 1.5, 0.0, 0.01, 0.02]
    inp.platform_mass_kg = 40.0 - 1e-3 * k
    out.tension_corrected_n[:] = 101.0 + k
    out.channel_status[:] = k % 3
    return inp, out


def push_many(rec: Recorder, start: int, count: int) -> None:
    inp, out = frame(0)
    for k in range(start, start + count):
        inp.tension_raw_n[:] = 100.0 + k
        out.tension_corrected_n[:] = 101.0 + k
        rec.push(k * 1e-3, inp, out)


def wait_for(cond: Callable[[], bool], timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.005)
    return cond()


def data_rows(text: str) -> list[str]:
    return [x for x in text.splitlines() if not x.startswith("#")][1:]


def writer_children() -> list[int]:
    """Pids of this process's children that run the recorder's writer."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmd = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        if ppid == os.getpid() and b"gateway.service.recorder_proc" in cmd:
            pids.append(int(entry.name))
    return pids


def gone(pid: int) -> bool:
    """The process has exited (reaped, or a zombie nobody reaps in a container)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] in "ZX"
    except OSError:
        return True


def test_round_trip_through_the_reader(tmp_path: Path) -> None:
    cfg = RecordConfig(path=str(tmp_path / "r.csv.gz"), batch_s=0.01)
    rec = Recorder(cfg, M, with_mass=True, metadata={"config": "test.yaml"})
    rec.start()
    inp, out = frame(5)
    for k in range(50):
        rec.push(10.0 + k * 1e-3, inp, out)
    rec.close()
    back = read_recording(tmp_path / "r.csv.gz")
    assert back.samples == 50 and back.cables == M and rec.dropped == 0
    assert_allclose(back.t, np.arange(50) * 1e-3, atol=1e-9)  # t = 0 at the first sample
    assert_allclose(back.velocity[0], inp.velocity_m_s, rtol=1e-9)
    assert_allclose(back.tension_sensor[:, 1], 105.0, rtol=1e-12)
    assert_allclose(back.pose[7], inp.pose, rtol=1e-9)
    assert back.mass is not None
    assert_allclose(back.mass, 40.0 - 5e-3, rtol=1e-12)
    assert_allclose(back.extra["tension_corrected_2"], 106.0, rtol=1e-12)
    assert_allclose(back.extra["status_3"], 5 % 3, rtol=0)
    assert back.metadata["config"] == "test.yaml" and "started" in back.metadata


def test_column_selection(tmp_path: Path) -> None:
    cfg = RecordConfig(path=str(tmp_path / "r.csv"), columns=("velocity", "status"))
    rec = Recorder(cfg, M)
    rec.start()
    push_many(rec, 0, 3)
    rec.close()
    header = [x for x in (tmp_path / "r.csv").read_text().splitlines() if not x.startswith("#")]
    assert header[0] == "t,velocity_1,velocity_2,velocity_3,status_1,status_2,status_3"
    assert len(header) == 4


def test_slow_disk_never_blocks_the_cycle_and_drops_are_counted(tmp_path: Path) -> None:
    """The file is a FIFO nobody reads (a 4 KiB pipe): the writer blocks in write() like
    on a stalled disk; the ring fills, later samples are dropped and counted."""
    fifo = tmp_path / "slow.csv"
    os.mkfifo(fifo)
    rfd = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)
    try:
        fcntl.fcntl(rfd, 1031, 4096)  # F_SETPIPE_SZ
        cfg = RecordConfig(path=str(fifo), buffer_rows=64, batch_s=0.001)
        rec = Recorder(cfg, M)
        rec.start()
        stuck: list[int] = []
        for k in range(2000):  # the writer gets a chance every 10 samples
            push_many(rec, k, 1)
            if k % 10 == 0:
                time.sleep(0.001)
            if rec.dropped and not stuck:
                stuck.append(k)
        assert stuck, "the ring never filled"
        assert rec.dropped > 1000 and rec.failed is None
        os.set_blocking(rfd, True)
        chunks: list[bytes] = []
        reader = threading.Thread(
            target=lambda: chunks.extend(iter(lambda: os.read(rfd, 65536), b""))
        )
        reader.start()  # the disk comes back: the writer drains the ring
        rec.close()
        reader.join(10)
    finally:
        os.close(rfd)
    rows = data_rows(b"".join(chunks).decode())
    assert len(rows) == rec.rows_written and rec.rows_written + rec.dropped == 2000
    assert rec.rows_written >= 64  # the ring's rows were kept, not dropped
    t = np.array([float(r.split(",")[0]) for r in rows])
    assert_allclose(t, np.arange(t.size) * 1e-3, atol=1e-12)  # the oldest rows, whole


@pytest.mark.parametrize("name", ["full.csv", "full.csv.gz"])
def test_dev_full_stops_the_recorder_and_counts_the_rest(
    tmp_path: Path, name: str, caplog: pytest.LogCaptureFixture
) -> None:
    """/dev/full: the kernel's ENOSPC on the first write that reaches it (a plain CSV at
    the first flush; a gzip when its compressed data is flushed, at the latest at close)."""
    path = tmp_path / name
    path.symlink_to("/dev/full")
    rec = Recorder(RecordConfig(path=str(path), batch_s=0.001), M, with_mass=True)
    rec.start()
    with caplog.at_level(logging.WARNING, logger="cdpr_gateway.recorder"):
        push_many(rec, 0, 200)
        if name.endswith(".csv"):
            assert wait_for(lambda: rec.failed is not None)  # the writer stopped by itself
            push_many(rec, 200, 5)  # the cycle goes on; nothing is recorded any more
            assert rec.dropped == 205 and rec.rows_written == 0
        rec.close()
    assert rec.failed is not None and "No space" in rec.failed
    pushed = 205 if name.endswith(".csv") else 200
    assert rec.rows_written + rec.dropped == pushed
    assert any("recording stopped" in r.message and "No space" in r.message for r in caplog.records)
    assert sum("recording stopped" in r.message for r in caplog.records) == 1  # logged once


SMALL_FILE = textwrap.dedent(
    """
    import resource, sys, time
    from tests.service.test_recorder import M, push_many
    from gateway.service.recorder import RecordConfig, Recorder

    rec = Recorder(RecordConfig(path=sys.argv[1], batch_s=0.001), M, with_mass=True)
    resource.setrlimit(resource.RLIMIT_FSIZE, (3000, resource.RLIM_INFINITY))  # inherited
    rec.start()
    push_many(rec, 0, 1)
    # the first row on disk before the rest: a writer started late on a loaded machine
    # would take all 200 rows in its first write, which the limit cuts, leaving none
    deadline = time.monotonic() + 30
    while rec.rows_written == 0 and not rec.failed and time.monotonic() < deadline:
        time.sleep(0.001)
    for k in range(1, 200):
        push_many(rec, k, 1)
        time.sleep(0.0002)
    rec.close()
    print(rec.rows_written, rec.dropped, rec.failed, flush=True)
    """
)


def test_a_write_cut_by_the_kernel_leaves_whole_rows(tmp_path: Path) -> None:
    """A file size limit (RLIMIT_FSIZE, inherited by the writer) fails a write halfway,
    as a disk filling up does: the plain CSV is cut back to its last whole row."""
    path = tmp_path / "cut.csv"
    proc = subprocess.run(
        [sys.executable, "-c", SMALL_FILE, str(path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    written, dropped, failed = proc.stdout.split(maxsplit=2)
    assert "File too large" in failed and "recording stopped" in proc.stderr
    assert int(written) > 0 and int(written) + int(dropped) == 200
    back = read_recording(path, min_samples=1)  # cut back to the last whole row: readable
    assert back.samples == int(written)
    assert path.stat().st_size <= 3000


def test_a_killed_writer_stops_the_recorder_and_the_cycle_goes_on(tmp_path: Path) -> None:
    rec = Recorder(RecordConfig(path=str(tmp_path / "k.csv"), batch_s=0.001), M)
    rec.start()
    push_many(rec, 0, 10)
    assert wait_for(lambda: rec.rows_written == 10)
    assert rec.pid is not None
    os.kill(rec.pid, signal.SIGKILL)
    assert wait_for(lambda: rec.failed is not None)
    assert "exit status -9" in str(rec.failed)
    push_many(rec, 10, 5)
    assert rec.dropped == 5 and rec.rows_written == 10
    rec.close()
    assert rec.rows_written + rec.dropped == 15


def test_close_leaves_no_process_descriptor_or_shared_memory(tmp_path: Path) -> None:
    fds = sorted(os.listdir("/proc/self/fd"))
    shm = sorted(os.listdir("/dev/shm"))
    rec = Recorder(RecordConfig(path=str(tmp_path / "n.csv.gz"), batch_s=0.01), M, with_mass=True)
    rec.start()
    assert writer_children() == [rec.pid]
    assert sorted(os.listdir("/dev/shm")) == shm  # the ring has no name
    push_many(rec, 0, 20)
    rec.close()
    rec.close()  # twice is fine
    assert writer_children() == []
    assert rec._events is not None and not rec._events.is_alive()
    assert sorted(os.listdir("/proc/self/fd")) == fds  # the ring is unmapped, pipes closed
    assert sorted(os.listdir("/dev/shm")) == shm
    assert read_recording(tmp_path / "n.csv.gz", min_samples=1).samples == 20
    push_many(rec, 20, 3)  # a push after close is counted, never written
    assert rec.dropped == 3


def test_an_unwritable_path_fails_at_start(tmp_path: Path) -> None:
    rec = Recorder(RecordConfig(path=str(tmp_path / "no" / "dir.csv")), M)
    with pytest.raises(OSError, match="No such file"):
        rec.start()
    assert writer_children() == []


def test_rotation_by_size_gives_complete_numbered_files(tmp_path: Path) -> None:
    cfg = RecordConfig(path=str(tmp_path / "rot.csv.gz"), rotate_bytes=4096, batch_s=0.001)
    rec = Recorder(cfg, M, with_mass=True)
    rec.start()
    for k in range(300):
        push_many(rec, k, 1)
        if k % 20 == 0:
            time.sleep(0.005)  # let the writer write batches between pushes
    rec.close()
    assert len(rec.files) > 2 and rec.files[0].name == "rot-0000.csv.gz"
    parts = [read_recording(p, min_samples=1) for p in rec.files]
    t = np.concatenate([p.t for p in parts])
    assert_allclose(t, np.arange(300) * 1e-3, atol=1e-9)
    assert [p.metadata["part"] for p in parts] == [str(i) for i in range(len(parts))]


def test_config_values_are_checked() -> None:
    with pytest.raises(ValueError, match="columns: unknown"):
        RecordConfig(columns=("velocity", "torque"))
    with pytest.raises(ValueError, match="rotate_s"):
        RecordConfig(rotate_s=0.0)


SCRIPT = textwrap.dedent(
    """
    import signal, sys, time, threading
    import numpy as np
    from drivers.base import Inputs, Outputs
    from gateway.service.recorder import RecordConfig, Recorder

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *a: stop.set())
    rec = Recorder(RecordConfig(path=sys.argv[1], batch_s=0.05), 2, with_mass=True)
    rec.start()
    inp, out = Inputs.allocate(2), Outputs.allocate(2)
    inp.platform_mass_kg = 40.0
    k = 0
    print("ready", rec.pid, flush=True)
    while not stop.is_set() and k < 200000:
        inp.tension_raw_n[:] = k
        rec.push(k * 1e-3, inp, out)
        k += 1
        time.sleep(0.0005)
    rec.close()
    print(k, rec.rows_written, rec.dropped, flush=True)
    """
)


def test_sigterm_leaves_a_valid_gzip(tmp_path: Path) -> None:
    out = tmp_path / "term.csv.gz"
    proc = subprocess.Popen(
        [sys.executable, "-c", SCRIPT, str(out)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    assert proc.stdout.readline().split()[0] == "ready"
    time.sleep(0.5)
    proc.send_signal(signal.SIGTERM)
    stdout, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0
    pushed, written, dropped = map(int, stdout.split())
    assert pushed > 10 and written == pushed and dropped == 0
    gzip.decompress(out.read_bytes())  # the trailer is there (raises on a cut stream)
    back = read_recording(out)
    assert back.samples == pushed
    assert_allclose(back.tension_sensor[:, 0], np.arange(pushed), rtol=0)


def test_a_killed_gateway_leaves_no_orphan_writer(tmp_path: Path) -> None:
    """SIGKILL on the gateway: the writer sees its pipe close, finishes the file (the
    gzip trailer) and exits."""
    out = tmp_path / "orphan.csv.gz"
    proc = subprocess.Popen(
        [sys.executable, "-c", SCRIPT, str(out)], cwd=ROOT, stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None
    ready, pid = proc.stdout.readline().split()
    assert ready == "ready"
    writer = int(pid)
    time.sleep(0.3)
    proc.kill()
    proc.wait(10)
    proc.stdout.close()
    assert wait_for(lambda: gone(writer)), "the writer outlived the gateway"
    back = read_recording(out)  # complete: a cut gzip is refused
    assert back.samples > 10
    assert_allclose(back.tension_sensor[:, 0], np.arange(back.samples), rtol=0)


def _virtual_config(tmp_path: Path) -> Path:
    def virtual(data):
        data["bus"]["driver"] = "virtual"
        data["metrics"]["enabled"] = False

    return edited_config(tmp_path, virtual, "virtual.yaml")


def _rows_of(path: Path) -> tuple[list[str], np.ndarray]:
    text = gzip.decompress(path.read_bytes()).decode()  # raises on a missing trailer
    lines = [x for x in text.splitlines() if not x.startswith("#")]
    header = lines[0].split(",")
    assert all(len(x.split(",")) == len(header) for x in lines[1:])  # whole rows only
    return header, np.array([float(x.split(",")[0]) for x in lines[1:]])


def test_run_records_for_n_seconds(tmp_path: Path) -> None:
    out = tmp_path / "run.csv.gz"
    cfg = _virtual_config(tmp_path)
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "gateway.cli",
            "run",
            "--config",
            str(cfg),
            "--seconds",
            "1",
            "--record",
            str(out),
            "--log-level",
            "WARNING",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    header, t = _rows_of(out)
    assert header[:2] == ["t", "velocity_1"] and "tension_corrected_8" in header
    assert "mass" not in header  # the virtual driver has no platform_mass register
    assert t.size > 100 and np.all(np.diff(t) > 0) and t[-1] < 5.0
    assert f"recorded {t.size} rows" in proc.stderr


def test_run_sigterm_closes_the_recording(tmp_path: Path) -> None:
    out = tmp_path / "term.csv.gz"
    cfg = _virtual_config(tmp_path)
    proc = subprocess.Popen(
        [sys.executable, "-m", "gateway.cli", "run", "--config", str(cfg), "--record", str(out)],
        cwd=ROOT,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stderr is not None
        seen: list[str] = []
        for _ in range(20):  # banner lines, "recording to ...", then "connected to the PLC ..."
            seen.append(proc.stderr.readline())
            if "connected to the PLC" in seen[-1]:
                break
        assert "connected to the PLC" in seen[-1], seen
        assert any("recording to" in line for line in seen), seen
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    finally:  # a failed assertion must not leave a gateway running for ever
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    _, t = _rows_of(out)
    assert f"recorded {t.size} rows" in err and "dropped 0" in err


def test_soft_plc_serves_the_platform_mass_and_the_driver_reads_it() -> None:
    from drivers.modbus_tcp import ModbusTcpDriver
    from gateway.core.config import load_config
    from tests.modbus_helpers import plc_server

    cfg = load_config()
    assert cfg.bus.modbus_tcp.registers.platform_mass is not None  # mapped by default.yaml
    with plc_server(cfg=cfg) as (_, image, live):
        image.platform_mass_kg = 37.25
        inputs = Inputs.allocate(cfg.cables)
        with ModbusTcpDriver(live) as drv:
            drv.read_into(inputs)
            assert inputs.platform_mass_kg == 37.25
            image.platform_mass_kg = 36.5  # falling while it prints
            drv.read_into(inputs)
            assert inputs.platform_mass_kg == 36.5


def test_the_plant_writes_a_falling_platform_mass() -> None:
    from gateway.core.config import load_config
    from sim_plc.image import ProcessImage
    from sim_plc.plant import Plant

    cfg = load_config()
    plant, image = Plant(cfg), ProcessImage(cfg.cables)
    masses = []
    for _ in range(400):
        plant.step(image)
        masses.append(image.platform_mass_kg)
    assert masses[0] > 0 and np.all(np.diff(masses) <= 0) and masses[-1] < masses[0]


def test_the_writer_process_runs_below_a_real_time_cycle(tmp_path: Path) -> None:
    """A process inherits the policy and nice of the thread that forks it: a recorder
    started by a SCHED_FIFO cycle thread must still write at SCHED_OTHER, nice >= 10."""

    def fifo_then_start(out: list[tuple[int, int]]) -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        except (AttributeError, OSError):
            return  # not permitted here: nothing to check
        rec = Recorder(RecordConfig(path=str(tmp_path / "rt.csv"), batch_s=0.01), M)
        rec.start()
        try:
            assert rec.pid is not None
            out.append((os.sched_getscheduler(rec.pid), os.getpriority(os.PRIO_PROCESS, rec.pid)))
        finally:
            rec.close()

    result: list[tuple[int, int]] = []
    starter = threading.Thread(target=fifo_then_start, args=(result,))
    starter.start()
    starter.join(30.0)
    if not result:
        pytest.skip("SCHED_FIFO is not permitted for this process")
    policy, nice = result[0]
    assert policy == os.SCHED_OTHER and nice >= 10
