"""``cdpr-gateway fleet``: each task's report is the bytes ``diagnose`` writes for that
recording alone, the table holds every finding of every report, a bad recording is listed
and never ends the job -- on a LocalCluster and against a real ``dask scheduler`` with two
``dask worker`` processes on 127.0.0.1."""

from __future__ import annotations

import json
import logging
import math
import subprocess
import sys
from pathlib import Path

import pytest

from gateway.cli import main
from gateway.errors import GatewayError
from gateway.fleet.cli import expand
from gateway.fleet.table import RECORDING, columns_of, table_rows
from gateway.fleet.task import TaskResult
from tests.dask_helpers import dask_cluster
from tests.fleet.fleet_helpers import (
    MODEL,
    ROOT,
    check_fleet_output,
    fleet_on_scheduler,
    single_reports,
)


@pytest.mark.long
def test_fleet_on_a_local_cluster_matches_diagnose_alone(
    recordings: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    singles = single_reports(recordings, tmp_path)
    out = tmp_path / "fleet"
    code = main(
        ["fleet", *map(str, recordings), "--model", str(MODEL), "--out", str(out), "--workers", "2"]
    )
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert captured.err.count("/4] ") == 4  # a line per finished recording
    assert "LocalCluster of 2 workers" in captured.out and "1 failed" in captured.out
    assert "distributed.scheduler: Remove client" in (out / "dask.log").read_text()
    check_fleet_output(out, recordings, singles)


@pytest.mark.long
def test_fleet_against_a_dask_scheduler_and_two_workers_on_loopback(
    recordings: list[Path], tmp_path: Path
) -> None:
    with dask_cluster(tmp_path, workers=2) as address:
        assert address.startswith("tcp://127.0.0.1:")
        out = tmp_path / "fleet"
        run = fleet_on_scheduler(recordings, out, address)
        lines = run.stderr.splitlines()  # a line per recording; Dask's own in dask.log
        assert len(lines) == 4 and all(line.startswith("[") for line in lines), run.stderr
        assert (out / "dask.log").is_file()
    check_fleet_output(out, recordings, single_reports(recordings, tmp_path))


def test_a_missing_fleet_extra_is_one_line_naming_it(tmp_path: Path) -> None:
    args = ["fleet", str(MODEL), "--model", str(MODEL), "--out", str(tmp_path)]
    code = (
        "import sys; sys.modules['distributed'] = None; from gateway.cli import main; "
        f"sys.exit(main({args!r}))"
    )
    res = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert res.returncode == 2
    assert res.stderr.count("\n") == 1 and "cdpr-gateway[fleet]" in res.stderr, res.stderr


def test_recordings_are_files_globs_or_trees(tmp_path: Path) -> None:
    tree = tmp_path / "tree" / "robot=a" / "date=2026-01-01"
    tree.mkdir(parents=True)
    for name in ("part-0000.parquet", "part-0001.parquet", "notes.txt"):
        (tree / name).write_bytes(b"")
    (tmp_path / "x.csv.gz").write_bytes(b"")
    got = expand([str(tmp_path / "tree"), str(tmp_path / "*.csv.gz"), str(tmp_path / "x.csv.gz")])
    assert [Path(p).name for p in got] == ["part-0000.parquet", "part-0001.parquet", "x.csv.gz"]
    with pytest.raises(GatewayError, match="no such recording"):
        expand([str(tmp_path / "missing.csv")])
    with pytest.raises(GatewayError, match="no recordings"):
        expand([str(tmp_path / "*.mcap")])


def test_the_table_has_a_row_per_finding_and_cable_and_keeps_the_rest() -> None:
    report = {
        "reference": "platform_tension",
        "samples": 100,
        "baseline": {"rmse_n": 2.0},
        "final": {"rmse_n": 1.0},
        "findings": [
            {
                "effect": "offset",
                "cables": [2, 5],
                "parameters": {"c_n": [1.5, -2.0]},
                "stderr": {"c_n": [0.1, 0.2]},
                "rmse_before_n": 2.0,
                "rmse_after_n": 1.2,
            },
            {
                "effect": "mass_change",
                "cables": [0],
                "parameters": {"q_kg_s": [0.02]},
                "stderr": {"q_kg_s": [0.001]},
                "rmse_before_n": 1.2,
                "rmse_after_n": 1.0,
            },
        ],
    }
    lsq = {"fits": {"coulomb_viscous": {"holdout_rmse_n": 1.7}, "dahl": {"holdout_rmse_n": 1.1}}}
    none = {**report, "findings": [], "baseline": {"rmse_n": 2.0, "least_squares": lsq}}
    res = [
        TaskResult("a", "r", "2026", json.dumps(report), None, 1.0, "w", 1.0),
        TaskResult("b", "r", "2026", json.dumps(none), None, 1.0, "w", 1.0),
        TaskResult("c", "r", "2026", None, "c: broken", 0.0, "w", 1.0),
    ]
    rows = table_rows([(r, r.recording + ".json") for r in res])
    assert [(r["recording"], r["effect"], r["cable"], r["rank"]) for r in rows] == [
        ("a", "offset", 2, 1),
        ("a", "offset", 5, 1),
        ("a", "mass_change", 0, 2),
        ("b", "none", 0, 0),
        ("c", "", 0, 0),
    ]
    assert rows[1]["c_n"] == -2.0 and rows[1]["c_n_stderr"] == 0.2
    assert rows[2]["q_kg_s"] == 0.02 and math.isnan(rows[2].get("c_n", math.nan))
    assert rows[4]["status"] == "failed" and rows[4]["error"] == "c: broken"
    # the better least-squares baseline's held-out RMSE, NaN without the block
    assert rows[3]["lsq_holdout_rmse_n"] == 1.1 and math.isnan(rows[0]["lsq_holdout_rmse_n"])
    assert columns_of(rows)[-4:] == RECORDING  # recording columns last, not parameters


def test_dask_log_lines_go_to_the_file_and_only_warnings_to_the_terminal_while_running(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from gateway.fleet.run import DaskLog

    logger = logging.getLogger("distributed")
    before = (logger.handlers[:], logger.level, logger.propagate)
    log = tmp_path / "dask.log"
    with DaskLog(log).installed() as dask_log:
        for h in logger.handlers:  # what LocalCluster(silence_logs=40) does to them
            h.setLevel(logging.ERROR)
        dask_log.running()
        logging.getLogger("distributed.scheduler").info("Register worker")
        logging.getLogger("distributed.nanny").warning("Worker exceeded 95% memory budget")
        dask_log.closing()
        try:
            raise ConnectionError("stream closed")
        except ConnectionError:
            logging.getLogger("distributed.batched").info("Batched Comm Closed", exc_info=True)
            logging.getLogger("distributed.batched").exception("Error in batched write")
    err = capsys.readouterr().err
    assert err == "dask: WARNING distributed.nanny: Worker exceeded 95% memory budget\n"
    text = log.read_text()
    for line in ("Register worker", "95% memory", "Batched Comm Closed", "Error in batched"):
        assert line in text
    assert text.count("Traceback") == 2
    assert (logger.handlers, logger.level, logger.propagate) == before


def test_two_fleets_on_one_machine_never_clash_on_a_port() -> None:
    """Each LocalCluster's scheduler serves its HTTP routes (``/metrics``) even without a
    dashboard, on 8787 unless told: a second fleet at once warned "Port 8787 is already in
    use" (an error under this suite's warning filter, seen when two fleet tests overlapped).
    Both now take a free loopback port."""
    import distributed

    from gateway.fleet.run import _client

    first = _client(distributed, None, 1)
    try:
        second = _client(distributed, None, 1)  # a warning here fails the test
        try:
            ports = [c.scheduler_info()["services"]["dashboard"] for c in (first[0], second[0])]
            assert 8787 not in ports and ports[0] != ports[1]
        finally:
            second[0].close()
            second[1].close()
    finally:
        first[0].close()
        first[1].close()
