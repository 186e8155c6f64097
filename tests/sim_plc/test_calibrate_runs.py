"""``cdpr-gateway calibrate --runs N`` (issue 29 item 1): several 'before' runs of the
plant, each another motion and noise draw, diagnosed jointly for one fitted model, through
the joined path of ``diagnose REC REC ...`` (gateway/diagnose/sessions.py, join_wrench)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gateway.cli import main
from gateway.core.configtypes import read_yaml
from sim_plc.calibrate import diagnose_runs, prepare_dir, run_plants
from tests.diagnose_helpers import check_report, wrench_recordings

ROOT = Path(__file__).resolve().parents[2]
VISCOUS = ROOT / "config" / "calibrate" / "viscous.yaml"


def test_each_run_is_the_plant_with_its_seeds_raised(tmp_path: Path) -> None:
    assert run_plants(str(VISCOUS), 1, tmp_path) == [str(VISCOUS)]
    assert not list(tmp_path.iterdir())  # one run: nothing written
    plants = run_plants(str(VISCOUS), 3, tmp_path)
    assert plants[0] == str(VISCOUS)
    base = read_yaml(VISCOUS)
    for k, plant in enumerate(plants[1:], start=1):
        assert Path(plant) == tmp_path / f"plant-run-{k + 1}.yaml"
        data = read_yaml(plant)
        sim, want = data.pop("sim_plc"), dict(base["sim_plc"])
        assert data == {key: v for key, v in base.items() if key != "sim_plc"}
        assert sim["seed"] == want["seed"] + k
        assert sim["trajectory"]["random"]["seed"] == want["trajectory"]["random"]["seed"] + k
        assert sim["trajectory"]["kind"] == want["trajectory"]["kind"]
        assert sim["effects"] == want["effects"]  # the same machine


def test_bad_runs_is_refused_in_one_line(tmp_path: Path, capsys) -> None:
    argv = ["calibrate", "--config", str(VISCOUS), "--runs", "0", "--out", str(tmp_path / "o")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "--runs" in err and err.count("\n") == 1
    assert not (tmp_path / "o").exists()


def test_several_runs_give_one_joined_report_and_one_fitted_model(tmp_path: Path) -> None:
    """Step 3 on two runs (small: 6 s each at 100 Hz): one wrench report listing both runs,
    the hidden viscous term found on every cable near its 25 N s/m, validated on the runs'
    last quarters; the fitted model carries it."""
    runs = wrench_recordings(tmp_path, VISCOUS, 6.0, [1, 2])
    nominal, _ = prepare_dir(str(VISCOUS), tmp_path / "cal")
    said: list[str] = []
    rep = diagnose_runs(
        runs, nominal, tmp_path / "diagnosis.json", tmp_path / "fitted.yaml", said.append
    )
    check_report(rep)
    assert json.loads((tmp_path / "diagnosis.json").read_text()) == rep
    assert rep["reference"] == "wrench"
    assert [r["name"] for r in rep["recordings"]] == [p.name for p in runs]
    fit_rows = sum(r["samples"] for r in rep["recordings"])
    assert fit_rows == rep["samples"] and fit_rows < 0.8 * 2 * 600  # 75 % of each fitted
    (visc,) = rep["findings"]
    assert visc["effect"] == "viscous" and visc["cables"] == list(range(1, 9))
    assert np.allclose(visc["parameters"]["c_ns_m"], 25.0, rtol=0.1)
    fin = rep["final"]
    assert fin["validation_rmse_after_n"] < fin["validation_rmse_before_n"]
    fitted = read_yaml(tmp_path / "fitted.yaml")
    assert fitted["friction"]["effects"]["viscous"]["c_ns_m"]
    assert any("2 runs" in line for line in said)


@pytest.mark.loopback
@pytest.mark.slow
@pytest.mark.long
def test_calibrate_with_two_runs_closes_the_loop(tmp_path, capsys) -> None:
    """Two runs recorded and diagnosed jointly, the fitted model run: the hidden viscous
    term found on every cable near its 25 N s/m, the after run better than the before run
    of the same motion. (Within 1.15x the noise floor is the single-run test's
    contract, tests/sim_plc/test_calibrate.py; it needs an unloaded machine: on the
    shared one at a load of 4 the after run overran 2312 of 2699 cycles, 1.24x.)"""
    out = tmp_path / "cal"
    argv = ["calibrate", "--config", str(VISCOUS), "--seconds", "12", "--runs", "2"]
    assert main([*argv, "--out", str(out)]) == 0
    result = json.loads((out / "calibration.json").read_text())
    assert result["runs"] == 2 and len(result["before_runs"]) == 2
    assert result["before"] == result["before_runs"][0]
    assert "viscous" in result["findings"]
    report = json.loads((out / "diagnosis.json").read_text())
    assert [r["name"] for r in report["recordings"]] == ["before-1.csv.gz", "before-2.csv.gz"]
    (visc,) = [f for f in report["findings"] if f["effect"] == "viscous"]
    assert visc["cables"] == list(range(1, 9))
    assert abs(float(np.median(visc["parameters"]["c_ns_m"])) - 25.0) <= 2.5
    assert result["after"]["rmse_n"] < result["before"]["rmse_n"]
    stdout = capsys.readouterr().out
    assert "before run 2 (nominal)" in stdout and "after (fitted model)" in stdout
