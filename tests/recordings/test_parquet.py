"""Parquet recordings: the same values as written, every batch on disk as it is written
(an Arrow IPC stream, converted at close, or when a killed writer's recording is next
opened), malformed files refused whole like a CSV."""

from __future__ import annotations

import io
import logging
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.testing import assert_array_equal

from gateway.errors import RecordingError
from gateway.recordings.parquet import ParquetRecordingWriter, stream_path
from gateway.recordings.reader import Recording, read_recording, write_recording

ROOT = Path(__file__).resolve().parents[2]
COLUMNS = ["t", "velocity_1", "tension_sensor_1", "tension_platform_1", "length_1", "status_1"]


def table(n: int, seed: int = 0, start: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rows = rng.normal(0, 100, (n, len(COLUMNS)))
    rows[:, 0] = (start + np.arange(n)) * 1e-3
    rows[:, -1] = rng.integers(0, 3, n)
    return rows


def on_disk(path: Path) -> np.ndarray:
    """What pyarrow reads of the file now, as a (rows, columns) array."""
    t = pq.read_table(path)
    return np.column_stack([t[c].to_numpy() for c in COLUMNS]) if t.num_rows else np.empty((0, 6))


def stream_rows(data: bytes) -> np.ndarray:
    """The complete record batches of an Arrow IPC stream (a cut last one left out)."""
    got = []
    with pa.ipc.open_stream(pa.BufferReader(data)) as reader:
        while True:
            try:
                got.append(reader.read_next_batch())
            except (StopIteration, pa.ArrowInvalid, OSError):  # the end, or cut short
                break
    t = pa.Table.from_batches(got, reader.schema)
    return np.column_stack([t[c].to_numpy() for c in COLUMNS]) if t.num_rows else np.empty((0, 6))


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    batches=st.lists(st.integers(1, 120), min_size=1, max_size=12),
    group=st.integers(1, 150),
    nan_at=st.integers(0, 50),
)
def test_every_batch_is_on_disk_when_written_and_the_file_has_the_values_written(
    tmp_path: Path, batches: list[int], group: int, nan_at: int
) -> None:
    path = tmp_path / "p.parquet"
    path.unlink(missing_ok=True)
    w = ParquetRecordingWriter(path, COLUMNS, {"robot": "r1"}, row_group_rows=group)
    stream = stream_path(path)
    assert stream_rows(stream.read_bytes()).shape == (0, 6)  # a valid stream from the start
    written, start = [], 0
    for k, n in enumerate(batches):
        block = table(n, k, start)
        block[min(nan_at, n - 1), 4] = np.nan  # a missing optional value stays missing
        start += n
        w.write_rows(block)
        written.append(block)
        # after each batch: every row so far on disk, each value as written
        assert_array_equal(stream_rows(stream.read_bytes()), np.concatenate(written))
        assert w.rows_on_disk == start and stream.stat().st_size == w.bytes
        assert not path.exists()  # the Parquet file appears whole, at close
    w.close()
    assert not stream.exists()
    assert_array_equal(on_disk(path), np.concatenate(written))
    pf = pq.ParquetFile(path)
    sizes = [pf.metadata.row_group(i).num_rows for i in range(pf.metadata.num_row_groups)]
    assert sizes == [group] * (start // group) + ([start % group] if start % group else [])
    assert pf.schema_arrow.metadata[b"robot"] == b"r1"
    assert pf.schema_arrow.field("tension_sensor_1").metadata == {b"unit": b"N"}
    assert pf.schema_arrow.field("t").metadata == {b"unit": b"s"}


def sample(n: int = 300, m: int = 2) -> Recording:
    rng = np.random.default_rng(1)
    return Recording(
        t=np.cumsum(rng.uniform(0.5e-3, 1.5e-3, n)),
        velocity=rng.normal(0, 0.05, (n, m)),
        tension_sensor=rng.uniform(-50, 400, (n, m)),
        tension_platform=rng.uniform(-50, 400, (n, m)),
        length=rng.uniform(1, 3, (n, m)),
        metadata={"source": "test", "robot": "r7"},
    )


def test_write_recording_round_trip_is_exact_and_reads_like_the_csv(tmp_path: Path) -> None:
    rec = sample()
    rec.tension_platform[3, 1] = np.nan  # a missing required value: the row is skipped
    write_recording(tmp_path / "r.parquet", rec)
    write_recording(tmp_path / "r.csv", rec)
    back, csv = read_recording(tmp_path / "r.parquet"), read_recording(tmp_path / "r.csv")
    assert back.samples == csv.samples == 299 and back.skipped_rows == csv.skipped_rows == 1
    keep = np.ones(300, bool)
    keep[3] = False
    for name in ("t", "velocity", "tension_sensor", "tension_platform", "length"):
        assert_array_equal(getattr(back, name), getattr(rec, name)[keep])  # bit for bit
        np.testing.assert_allclose(getattr(back, name), getattr(csv, name), rtol=1e-9)
    assert back.metadata == csv.metadata == {"source": "test", "robot": "r7"}


def _write_table(path: Path, columns: dict[str, object], meta: dict | None = None) -> None:
    pq.write_table(pa.table(columns).replace_schema_metadata(meta), path)


T = np.arange(20) * 1e-3
GOOD = {
    "t": T,
    "velocity_1": np.zeros(20),
    "tension_sensor_1": np.ones(20),
    "tension_platform_1": np.ones(20),
}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"t": np.r_[T[:5], T[3], T[6:]]}, r"r\.parquet: row 6: column 't': 0\.003 does not"),
        (
            {"tension_sensor_1": np.r_[np.ones(9), np.inf, np.ones(10)]},
            r"row 10: column "
            r"'tension_sensor_1': value is not finite",
        ),
        ({"velocity_1": np.full(20, 2e9)}, r"row 1: column 'velocity_1': 2000000000\.0 exceeds"),
        ({"tension_sensor_1": None}, r"schema: cable 1 has no column 'tension_sensor_1'"),
        ({"velocity_3": np.zeros(20)}, r"schema: cable 2 has no column 'velocity_2'"),
        ({"note": ["x"] * 20}, r"schema: column 'note': type string is not a number"),
        ({"t": None}, r"schema: no 't' column"),
    ],
)
def test_malformed_parquet_is_refused_naming_file_row_and_column(
    tmp_path: Path, change: dict, message: str
) -> None:
    columns = {**GOOD, **change}
    _write_table(tmp_path / "r.parquet", {k: v for k, v in columns.items() if v is not None})
    with pytest.raises(RecordingError, match=message):
        read_recording(tmp_path / "r.parquet")


def test_cut_short_or_foreign_files_and_too_many_rows_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "r.parquet"
    _write_table(path, GOOD)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(RecordingError, match=r"r\.parquet: not a Parquet file \(no footer"):
        read_recording(path)
    path.write_bytes(data[:-8] + (10**9).to_bytes(4, "little") + b"PAR1")
    with pytest.raises(RecordingError, match="Parquet footer of 1000000000 bytes"):
        read_recording(path)
    path.write_bytes(b"PAR1" + b"\x00" * 40 + (20).to_bytes(4, "little") + b"PAR1")
    with pytest.raises(RecordingError, match="not a readable Parquet file"):
        read_recording(path)
    _write_table(path, GOOD)
    with pytest.raises(RecordingError, match="20 rows of 4 columns exceed the reader's limit"):
        read_recording(path, max_samples=19)
    schema = pa.schema([pa.field("t", pa.float64())] * 2)
    pq.write_table(pa.Table.from_arrays([pa.array(T), pa.array(T)], schema=schema), path)
    with pytest.raises(RecordingError, match="schema: column 't' appears twice"):
        read_recording(path)


class FullDisk(io.BytesIO):
    """A file that refuses to grow past ``limit`` bytes (ENOSPC), as a full disk does."""

    def __init__(self, limit: int) -> None:
        super().__init__()
        self.limit = limit

    def write(self, data) -> int:  # type: ignore[override]
        if self.tell() + len(data) > self.limit:
            room = max(0, self.limit - self.tell())
            super().write(bytes(data)[:room])  # part of it lands, as on a real disk
            raise OSError(28, "No space left on device")
        return super().write(data)

    def close(self) -> None:  # keep the bytes readable after the writer closes
        pass


def test_a_full_disk_keeps_every_complete_batch(tmp_path: Path) -> None:
    disk = FullDisk(limit=14_000)
    w = ParquetRecordingWriter(tmp_path / "x.parquet", COLUMNS, {}, fileobj=disk)
    rows = []
    with pytest.raises(OSError, match="No space"):
        for k in range(100):
            rows.append(table(100, k, 100 * k))
            w.write_rows(rows[-1])
    assert 0 < w.rows_on_disk < 100 * len(rows)
    got = stream_rows(disk.getvalue())  # the batches before the cut one, whole
    assert_array_equal(got, np.concatenate(rows)[: w.rows_on_disk])


KILLED = textwrap.dedent(
    """
    import sys
    from gateway.recordings.parquet import ParquetRecordingWriter, stream_path
    from tests.recordings.test_parquet import COLUMNS, table

    w = ParquetRecordingWriter(sys.argv[1], COLUMNS, {"robot": "k"}, row_group_rows=50)
    for k in range(33):  # 33 batches of 10 rows
        w.write_rows(table(10, k, 10 * k))
    print(w.rows_on_disk, w.rows, flush=True)
    sys.stdin.readline()  # killed here, close() never called
    """
)


def test_a_killed_writer_leaves_a_stream_that_the_reader_recovers(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """SIGKILL: no Parquet file, the stream holds every batch; opening the recording
    converts it (one warning) and reads every row; the stream is gone after. A kill inside
    a write is tests/recordings/test_kill_recordings.py's."""
    path = tmp_path / "killed.parquet"
    proc = subprocess.Popen(
        [sys.executable, "-c", KILLED, str(path)],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline() == "330 330\n"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        proc.stdout.close()  # type: ignore[union-attr]
        proc.stdin.close()  # type: ignore[union-attr]
    assert not path.exists() and stream_path(path).exists()
    with caplog.at_level(logging.WARNING):
        back = read_recording(path)
    assert back.samples == 330
    expected = np.concatenate([table(10, k, 10 * k) for k in range(33)])
    assert_array_equal(back.t, expected[:, 0])
    assert_array_equal(back.tension_sensor[:, 0], expected[:, 2])
    assert back.metadata == {"robot": "k"}
    said = [r.getMessage() for r in caplog.records if "unclean stop" in r.getMessage()]
    assert said == [
        f"{path}: ends after an unclean stop: 330 rows to t = 0.329 s recovered "
        f"from {path.name}.arrows"
    ]
    assert not stream_path(path).exists()


def test_a_cut_stream_keeps_its_complete_batches(tmp_path: Path, caplog) -> None:
    path = tmp_path / "cut.parquet"
    w = ParquetRecordingWriter(path, COLUMNS, {"robot": "c"})
    for k in range(5):
        w.write_rows(table(100, k, 100 * k))
    data = stream_path(path).read_bytes()
    w._raw.close()  # as a kill would: no end of stream, no conversion
    # a batch: 100 rows x 6 float64 (4800 bytes) and its message header
    for cut, whole in ((1, 400), (3000, 400), (9000, 300)):
        stream_path(path).write_bytes(data[: len(data) - cut])
        path.unlink(missing_ok=True)
        with caplog.at_level(logging.WARNING):
            back = read_recording(path)
        assert back.samples == whole  # the batches before the cut one, whole
        assert "the last partial batch dropped" in caplog.records[-1].getMessage()


@pytest.mark.long  # two diagnoses: ~5-9 s
def test_diagnose_reads_parquet_as_it_reads_the_csv_and_refuses_a_bad_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The same values as CSV.gz and as Parquet (the CSV's values written to Parquet):
    the two reports are byte for byte the same; a malformed Parquet is one line, status 2."""
    from gateway.cli import main

    cfg = ROOT / "config" / "calibrate" / "offset.yaml"
    csv = tmp_path / "r.csv.gz"
    assert (
        main(["record", "--config", str(cfg), "--seconds", "4", "--out", str(csv), "--quiet"]) == 0
    )
    write_recording(tmp_path / "r.parquet", read_recording(csv))
    model = ROOT / "config" / "default.yaml"
    for name in ("r.csv.gz", "r.parquet"):
        assert (
            main(
                [
                    "diagnose",
                    str(tmp_path / name),
                    "--model",
                    str(model),
                    "--json",
                    str(tmp_path / f"{name}.json"),
                    "--quiet",
                ]
            )
            == 0
        )
    assert (tmp_path / "r.csv.gz.json").read_bytes() == (tmp_path / "r.parquet.json").read_bytes()
    capsys.readouterr()
    _write_table(tmp_path / "bad.parquet", {**GOOD, "t": np.r_[T[:5], T[3], T[6:]]})
    code = main(
        [
            "diagnose",
            str(tmp_path / "bad.parquet"),
            "--model",
            str(model),
            "--json",
            str(tmp_path / "bad.json"),
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1, err
    assert "bad.parquet: row 6: column 't'" in err and not (tmp_path / "bad.json").exists()
