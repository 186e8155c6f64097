"""The gateway's recorder: ring buffer in the cycle, writer thread, rotation, failures."""

from __future__ import annotations

import errno
import gzip
import io
import logging
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from drivers.base import Inputs, Outputs
from gateway.recorder import RecordConfig, Recorder
from gateway.recording import read_recording

ROOT = Path(__file__).resolve().parent.parent
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


class BlockingFile(io.BytesIO):
    """A file whose writes after the first (the header) wait until released."""

    def __init__(self) -> None:
        super().__init__()
        self.release = threading.Event()
        self.writes = 0

    def write(self, data: bytes) -> int:  # type: ignore[override]
        self.writes += 1
        if self.writes > 1:
            self.release.wait(30)
        return super().write(data)

    def close(self) -> None:
        self.final = self.getvalue()
        super().close()


class FullDisk(io.FileIO):
    """A real file that fails with ENOSPC once it would exceed ``limit`` bytes."""

    limit = 3000

    def write(self, data: bytes) -> int:  # type: ignore[override]
        if self.tell() + len(data) > self.limit:
            half = max(0, self.limit - self.tell())
            super().write(bytes(data)[:half])  # a partial write, as a full disk does
            raise OSError(errno.ENOSPC, "No space left on device")
        return super().write(data)


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
    slow = BlockingFile()
    cfg = RecordConfig(path=str(tmp_path / "slow.csv"), buffer_rows=64, batch_s=0.001)
    rec = Recorder(cfg, M, opener=lambda p: slow)
    rec.start()
    push_many(rec, 0, 10)
    deadline = time.monotonic() + 10
    while slow.writes < 2 and time.monotonic() < deadline:  # the writer is stuck in write
        time.sleep(0.001)
    assert slow.writes == 2
    pusher = threading.Thread(target=push_many, args=(rec, 10, 500))
    pusher.start()
    pusher.join(10)
    assert not pusher.is_alive()  # 500 cycles pushed while the disk was stuck
    assert not slow.release.is_set()
    assert rec.dropped == 510 - 64  # the ring held 64 rows; every other sample counted
    slow.release.set()
    rec.close()
    rows = [x for x in slow.final.decode().splitlines() if not x.startswith("#")][1:]
    assert len(rows) == 64 == rec.rows_written
    t = np.array([float(r.split(",")[0]) for r in rows])
    assert_allclose(t, np.arange(64) * 1e-3, atol=1e-12)  # the oldest rows, whole


def test_full_disk_stops_the_recorder_cleanly(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "full.csv"
    cfg = RecordConfig(path=str(path), batch_s=0.001)
    rec = Recorder(cfg, M, with_mass=True, opener=lambda p: FullDisk(p, "wb"))
    rec.start()
    with caplog.at_level(logging.WARNING, logger="cdpr_gateway.recorder"):
        for k in range(200):
            push_many(rec, k, 1)
            time.sleep(0.0002)
        assert rec._thread is not None
        rec._thread.join(10)
        assert not rec._thread.is_alive()  # the writer ended by itself
        assert rec.failed is not None and "No space" in rec.failed
        before = rec.dropped
        push_many(rec, 1000, 5)  # the cycle goes on; nothing is recorded any more
        assert rec.dropped == before + 5
        rec.close()
    assert rec.rows_written + rec.dropped == 205
    assert any("recording stopped" in r.message and "No space" in r.message for r in caplog.records)
    back = read_recording(path)  # cut back to the last whole row: readable
    assert back.samples == rec.rows_written
    assert path.stat().st_size <= FullDisk.limit


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
    from gateway.recorder import RecordConfig, Recorder

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *a: stop.set())
    rec = Recorder(RecordConfig(path=sys.argv[1], batch_s=0.05), 2, with_mass=True)
    rec.start()
    inp, out = Inputs.allocate(2), Outputs.allocate(2)
    inp.platform_mass_kg = 40.0
    k = 0
    print("ready", flush=True)
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
    assert proc.stdout.readline().strip() == "ready"
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


def _virtual_config(tmp_path: Path) -> Path:
    from gateway.config import DEFAULT_CONFIG_PATH

    text = DEFAULT_CONFIG_PATH.read_text().replace("driver: modbus_tcp", "driver: virtual", 1)
    text = text.replace("\nmetrics:\n", "\nmetrics:\n  enabled: false\n", 1)
    path = tmp_path / "virtual.yaml"
    path.write_text(text)
    return path


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
    assert proc.returncode == 0, err
    _, t = _rows_of(out)
    assert f"recorded {t.size} rows" in err and "dropped 0" in err


def test_soft_plc_serves_the_platform_mass_and_the_driver_reads_it() -> None:
    from drivers.modbus_tcp import ModbusTcpDriver
    from gateway.config import load_config
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
    from gateway.config import load_config
    from sim_plc.image import ProcessImage
    from sim_plc.plant import Plant

    cfg = load_config()
    plant, image = Plant(cfg), ProcessImage(cfg.cables)
    masses = []
    for _ in range(400):
        plant.step(image)
        masses.append(image.platform_mass_kg)
    assert masses[0] > 0 and np.all(np.diff(masses) <= 0) and masses[-1] < masses[0]
