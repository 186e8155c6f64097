"""The recorder writing Parquet: the gateway's process never loads pyarrow; a killed writer
leaves every batch it wrote; the Hive tree that ``run --record`` writes reads the same
in pyarrow, DuckDB and the diagnosis' reader."""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import duckdb
import numpy as np
import pyarrow.dataset as ds
import pyarrow.parquet as pq
import pytest
from numpy.testing import assert_array_equal

from gateway.core.config import DEFAULT_CONFIG_PATH
from gateway.recordings.reader import read_recording
from gateway.service.recorder import RecordConfig, Recorder
from tests.service.test_recorder import M, push_many, wait_for

ROOT = Path(__file__).resolve().parents[2]

NO_PYARROW = textwrap.dedent(
    """
    import sys
    import gateway.service.daemon, gateway.runtime.loop  # the gateway's own process
    from gateway.service.recorder import RecordConfig, Recorder
    from tests.service.test_recorder import M, push_many

    rec = Recorder(RecordConfig(path=sys.argv[1], batch_s=0.01), M, with_mass=True,
                   period_s=0.01)  # row groups of 500 rows
    rec.start()
    push_many(rec, 0, 1200)
    rec.close()
    print(rec.rows_written, rec.dropped, "pyarrow" in sys.modules, flush=True)
    """
)


def test_the_gateways_process_records_parquet_without_importing_pyarrow(tmp_path: Path) -> None:
    path = tmp_path / "r.parquet"
    proc = subprocess.run(
        [sys.executable, "-c", NO_PYARROW, str(path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    written, dropped, imported = proc.stdout.split()
    assert imported == "False"  # the writer process imported it, not this one
    assert int(written) + int(dropped) == 1200 and int(written) > 0
    assert pq.ParquetFile(path).metadata.num_row_groups == 3  # 500, 500, the last 200
    back = read_recording(path)
    assert back.samples == int(written)
    assert_array_equal(back.tension_sensor[:, 0], 100.0 + np.arange(back.samples))
    assert back.metadata["source"] == "cdpr-gateway run --record" and back.metadata["robot"]


def test_a_killed_writer_process_leaves_every_batch_it_wrote(tmp_path: Path) -> None:
    path = tmp_path / "k.parquet"
    rec = Recorder(RecordConfig(path=str(path), batch_s=0.001), M, with_mass=True, period_s=0.01)
    rec.start()
    push_many(rec, 0, 1700)
    assert wait_for(lambda: rec.rows_written == 1700)  # each drain a batch on disk
    assert rec.pid is not None
    os.kill(rec.pid, signal.SIGKILL)
    assert wait_for(lambda: rec.failed is not None)
    rec.close()
    assert rec.rows_written == 1700 and rec.dropped == 0
    back = read_recording(path)  # converted from the stream the killed writer left
    assert back.samples == 1700
    assert_array_equal(back.tension_sensor[:, 2], 100.0 + np.arange(1700))


def test_the_hive_layout_rotates_into_a_tree_duckdb_reads_as_one_table(tmp_path: Path) -> None:
    cfg = RecordConfig(
        path=str(tmp_path / "tree"), layout="hive", robot="cell-3", rotate_bytes=4096, batch_s=0.001
    )
    rec = Recorder(cfg, M, with_mass=True, period_s=0.01)
    rec.start()
    for k in range(0, 3000, 250):
        push_many(rec, k, 250)
        time.sleep(0.05)  # the writer drains each batch on its own: files rotate between
    rec.close()
    assert rec.dropped == 0 and len(rec.files) >= 3
    parts = sorted((tmp_path / "tree").glob("robot=cell-3/date=*/part-*.parquet"))
    assert [p.name for p in parts] == [f"part-{i:04d}.parquet" for i in range(len(parts))]
    assert parts == sorted(rec.files)
    sensor = np.concatenate([read_recording(p, min_samples=1).tension_sensor[:, 0] for p in parts])
    assert_array_equal(sensor, 100.0 + np.arange(3000))
    rows = duckdb.sql(
        f"SELECT robot, count(*), min(tension_sensor_1), max(tension_sensor_1) FROM "
        f"read_parquet('{tmp_path}/tree/**/*.parquet', hive_partitioning = true) GROUP BY robot"
    ).fetchall()
    assert rows == [("cell-3", 3000, 100.0, 3099.0)]
    # a restart adds parts to the same folder, never overwrites one
    rec2 = Recorder(cfg, M, period_s=0.01)
    rec2.start()
    push_many(rec2, 0, 10)
    rec2.close()
    assert rec2.files[0].name == f"part-{len(parts):04d}.parquet"


@pytest.mark.parametrize(("key", "value"), [("layout", "tree"), ("robot", "../x"), ("robot", "")])
def test_layout_and_robot_are_checked(key: str, value: str) -> None:
    from gateway.errors import ConfigError

    with pytest.raises((ConfigError, ValueError), match=key):
        RecordConfig(path="x", **{key: value})


def _soft_plc() -> tuple[subprocess.Popen[str], int, threading.Thread]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "gateway.cli", "sim-plc", "--port", "0", "--host", "127.0.0.1"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    lines: queue.Queue[str] = queue.Queue()
    reader = threading.Thread(target=lambda: [lines.put(x) for x in proc.stdout], daemon=True)  # type: ignore[union-attr]
    reader.start()
    while True:
        line = lines.get(timeout=60)
        if line.startswith("sim-plc: serving"):
            return proc, int(line.rsplit(":", 1)[1]), reader


@pytest.mark.long  # the soft PLC and the gateway as processes: ~8 s
def test_run_record_writes_a_tree_pyarrow_duckdb_and_the_reader_agree_on(tmp_path: Path) -> None:
    plc, port, reader = _soft_plc()
    try:
        text = DEFAULT_CONFIG_PATH.read_text().replace("port: 5020", f"port: {port}", 1)
        text = text.replace("\nmetrics:\n", "\nmetrics:\n  enabled: false\n", 1)
        text += "\nrecord:\n  layout: hive\n  robot: r2\n  rotate_s: 1\n"
        (tmp_path / "gw.yaml").write_text(text)
        tree = tmp_path / "tree"
        run = subprocess.run(
            [
                sys.executable,
                "-m",
                "gateway.cli",
                "run",
                "--config",
                str(tmp_path / "gw.yaml"),
                "--seconds",
                "2.5",
                "--record",
                str(tree),
                "--log-level",
                "WARNING",
            ],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=120,
        )
    finally:
        plc.terminate()
        plc.wait(20)
        reader.join(10)  # the pipe's end ends the reader
        plc.stdout.close()  # type: ignore[union-attr]
    assert run.returncode == 0, run.stderr
    parts = sorted(tree.glob("robot=r2/date=*/part-*.parquet"))
    assert len(parts) >= 2, run.stderr
    recs = [read_recording(p, min_samples=1) for p in parts]
    assert all(r.mass is not None and r.pose is not None for r in recs)  # the wrench columns
    t = np.concatenate([r.t for r in recs])
    assert np.all(np.diff(t) > 0) and f"recorded {t.size} rows" in run.stderr
    sensor = np.concatenate([r.tension_sensor for r in recs])
    mass = np.concatenate([r.mass for r in recs])  # type: ignore[misc]
    table = ds.dataset(tree, format="parquet", partitioning="hive").to_table()
    table = table.sort_by("t")
    assert_array_equal(table["t"].to_numpy(), t)
    assert_array_equal(table["tension_sensor_5"].to_numpy(), sensor[:, 4])
    assert_array_equal(table["mass"].to_numpy(), mass)
    got = duckdb.sql(
        f"SELECT t, tension_sensor_5, mass, robot FROM read_parquet('{tree}/**/*.parquet', "
        "hive_partitioning = true) ORDER BY t"
    ).fetchnumpy()
    assert_array_equal(got["t"], t)
    assert_array_equal(got["tension_sensor_5"], sensor[:, 4])
    assert_array_equal(got["mass"], mass)
    assert set(got["robot"]) == {"r2"}
    assert recs[0].metadata["robot"] == "r2" and len(recs[0].metadata["config_sha256"]) == 64
