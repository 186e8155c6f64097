"""What the fleet tests share: three short recordings of robots hiding different effects
and one broken file (the ``recordings`` fixture, tests/fleet/conftest.py), each good one's
``diagnose`` report alone, and the check that a fleet run's outputs hold those reports."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from gateway.cli import main

ROOT = Path(__file__).resolve().parents[2]
MODEL = ROOT / "config" / "default.yaml"
HIDDEN = ("gain", "offset", "viscous")  # config/calibrate/*.yaml


def make_recordings(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Three short recordings of robots hiding different effects (Parquet and CSV.gz, one
    in a Hive tree) and one broken file."""
    d = tmp_path_factory.mktemp("fleet-recordings")
    out = []
    for i, effect in enumerate(HIDDEN):
        name = f"{effect}.parquet" if i != 1 else f"{effect}.csv.gz"
        path = d / ("robot=r-offset/date=2026-01-02" if i == 1 else "") / name
        path.parent.mkdir(parents=True, exist_ok=True)
        assert (
            main(
                [
                    "record",
                    "--config",
                    str(ROOT / "config" / "calibrate" / f"{effect}.yaml"),
                    "--seconds",
                    "6",
                    "--out",
                    str(path),
                    "--quiet",
                    "--robot",
                    f"r-{effect}",
                ]
            )
            == 0
        )
        out.append(path)
    (d / "broken.csv").write_text("t,velocity_1\n0,1\n")
    return [*out, d / "broken.csv"]


def single_reports(recs: list[Path], tmp: Path) -> dict[str, bytes]:
    """``diagnose REC --json`` of each good recording alone, the file's bytes."""
    out = {}
    for i, rec in enumerate(recs[:-1]):
        assert (
            main(
                [
                    "diagnose",
                    str(rec),
                    "--model",
                    str(MODEL),
                    "--json",
                    str(tmp / f"{i}.json"),
                    "--quiet",
                ]
            )
            == 0
        )
        out[str(rec.resolve())] = (tmp / f"{i}.json").read_bytes()
    return out


def check_fleet_output(out: Path, recs: list[Path], singles: dict[str, bytes]) -> None:
    table = pq.read_table(out / "fleet.parquet").to_pylist()
    by_rec: dict[str, list[dict]] = {}
    for row in table:
        by_rec.setdefault(row["recording"], []).append(row)
    assert set(by_rec) == {str(r.resolve()) for r in recs}
    broken = by_rec.pop(str(recs[-1].resolve()))
    assert broken[0]["status"] == "failed" and "has no column" in broken[0]["error"]
    for rec, rows in by_rec.items():
        report_bytes = (out / "reports" / rows[0]["report"]).read_bytes()
        assert report_bytes == singles[rec]  # the same bytes as diagnose alone
        report = json.loads(report_bytes)
        expect = [(f["effect"], c) for f in report["findings"] for c in f["cables"]]
        assert [(r["effect"], r["cable"]) for r in rows] == (expect or [("none", 0)])
        for r in rows:
            if r["effect"] == "none":
                continue
            f = next(f for f in report["findings"] if f["effect"] == r["effect"])
            k = f["cables"].index(r["cable"])
            for name, values in f["parameters"].items():
                assert r[name] == values[k] and r[f"{name}_stderr"] == f["stderr"][name][k]
            assert r["rmse_after_n"] == f["rmse_after_n"]
            assert r["baseline_rmse_n"] == report["baseline"]["rmse_n"]
            fits = report["baseline"]["least_squares"]["fits"].values()
            assert r["lsq_holdout_rmse_n"] == min(f["holdout_rmse_n"] for f in fits)
            assert r["final_holdout_rmse_n"] == report["final"]["holdout_rmse_n"]
    robots = {r["robot"] for rows in by_rec.values() for r in rows}
    assert robots == {f"r-{e}" for e in HIDDEN}
    hive = next(rows for rec, rows in by_rec.items() if "robot=r-offset" in rec)
    assert hive[0]["start"].startswith("20")  # the metadata's start, not the folder's date
    text = (out / "fleet.md").read_text()
    assert "1 failed" in text and "broken.csv" in text
    plots = sorted(p.name for p in (out / "plots").iterdir())  # the broken file's robot too
    broken_robot = f"robot-{recs[-1].parent.name}.png"  # the folder of the broken file
    assert plots == sorted([f"robot-r-{e}.png" for e in HIDDEN] + [broken_robot])
    csv_lines = (out / "fleet.csv").read_text().splitlines()
    assert len(csv_lines) == len(table) + 1


def fleet_on_scheduler(
    recordings: list[Path], out: Path, address: str, prefix: tuple[str, ...] = ()
) -> subprocess.CompletedProcess[str]:
    """``cdpr-gateway fleet RECORDINGS --scheduler ADDRESS`` in a process of its own (run
    through ``prefix``, e.g. ``ip netns exec NS``), bounded at 600 s; asserts it succeeded
    and named the scheduler with its two workers."""
    run = subprocess.run(
        [
            *prefix,
            sys.executable,
            "-m",
            "gateway.cli",
            "fleet",
            *map(str, recordings),
            "--model",
            str(MODEL),
            "--out",
            str(out),
            "--scheduler",
            address,
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert run.returncode == 0, run.stderr
    assert f"scheduler {address} with 2 workers" in run.stdout
    return run
