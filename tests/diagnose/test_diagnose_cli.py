"""``cdpr-gateway diagnose``: files in, JSON report and pictures out, clear errors."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

from evaluation.scenarios import Scenario
from gateway.cli import main
from tests.diagnose_helpers import check_report, write_scenario

SHORT = Scenario("cli", {"viscous": {"c_ns_m": 8.0}}, cables=1, seconds=20.0)


def test_cli_writes_schema_valid_report_and_pictures(tmp_path, capsys):
    rec, model = write_scenario(tmp_path, SHORT)
    val, _ = write_scenario(tmp_path, replace(SHORT, seed=7), "val.csv.gz")
    out = tmp_path / "r.json"
    rc = main(
        [
            "diagnose",
            str(rec),
            "--model",
            str(model),
            "--json",
            str(out),
            "--report",
            str(tmp_path / "rep"),
            "--validate",
            str(val),
        ]
    )
    assert rc == 0
    report = json.loads(out.read_text())
    check_report(report)
    assert [f["effect"] for f in report["findings"]] == ["viscous"]
    f = report["findings"][0]
    assert f["validation_rmse_after_n"] < f["validation_rmse_before_n"]
    assert "validation_rmse_after_n" in report["final"]
    names = {p.name for p in (tmp_path / "rep").iterdir()}
    assert {"residual.png", "overlay.png", "signature_viscous.png", "summary.md"} <= names
    assert "viscous" in (tmp_path / "rep" / "summary.md").read_text()
    assert "verdict: viscous" in capsys.readouterr().out


def test_cli_clean_recording_exits_zero_with_no_findings(tmp_path):
    rec, model = write_scenario(tmp_path, replace(SHORT, effects={}, seed=11))
    out = tmp_path / "r.json"
    assert (
        main(
            [
                "diagnose",
                str(rec),
                "--model",
                str(model),
                "--json",
                str(out),
                "--report",
                str(tmp_path / "rep"),
                "--quiet",
            ]
        )
        == 0
    )
    report = json.loads(out.read_text())
    check_report(report)
    assert report["findings"] == []
    assert "Verdict: none" in (tmp_path / "rep" / "summary.md").read_text()


def test_cli_refuses_malformed_recording_with_line_and_column(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text(
        "t,velocity_1,tension_sensor_1,tension_platform_1\n0.0,0.1,100,101\n0.001,0.1,abc,101\n"
    )
    _, model = write_scenario(tmp_path, replace(SHORT, seconds=1.0))
    rc = main(["diagnose", str(bad), "--model", str(model), "--json", str(tmp_path / "r.json")])
    err = capsys.readouterr().err
    assert rc != 0
    assert "bad.csv:3" in err and "tension_sensor_1" in err
    assert not (tmp_path / "r.json").exists()


def test_cli_refuses_unknown_model_key(tmp_path, capsys):
    rec, model = write_scenario(tmp_path, replace(SHORT, seconds=1.0))
    model.write_text(model.read_text() + "  colour: red\n")
    rc = main(["diagnose", str(rec), "--model", str(model), "--json", str(tmp_path / "r.json")])
    assert rc != 0
    assert "colour" in capsys.readouterr().err


def test_cli_needs_geometry_without_platform_tensions(tmp_path, capsys):
    csv = tmp_path / "pose.csv"
    csv.write_text(
        "t,velocity_1,tension_sensor_1,x,y,z,rx,ry,rz,mass\n"
        + "".join(f"{k}e-3,0.1,100,0,0,1.5,0,0,0,50\n" for k in range(12))  # >= 10 samples
    )
    _, model = write_scenario(tmp_path, replace(SHORT, seconds=1.0))
    rc = main(["diagnose", str(csv), "--model", str(model), "--json", str(tmp_path / "r.json")])
    assert rc != 0
    assert "geometry" in capsys.readouterr().err


def test_cli_requires_model(tmp_path):
    # --json is optional: the verdict is printed, --report may be all one wants
    with pytest.raises(SystemExit):
        main(["diagnose", "x.csv", "--json", "r.json"])


def test_cli_uses_wrench_balance_from_pose_with_full_config(tmp_path):
    """No tension_platform columns: the wrench balance from pose and mass with the config's
    geometry (no tension distribution assumed)."""
    from evaluation.scenarios import make_recording
    from gateway.core.config import DEFAULT_CONFIG_PATH
    from gateway.recordings.reader import write_recording

    sc = Scenario("pose", {}, plant=True, cables=8, seconds=2.0)
    rec = make_recording(sc)
    rec.tension_platform = None
    path = tmp_path / "pose.csv"
    write_recording(path, rec)
    out = tmp_path / "r.json"
    rc = main(
        ["diagnose", str(path), "--model", str(DEFAULT_CONFIG_PATH), "--json", str(out), "--quiet"]
    )
    assert rc == 0
    report = json.loads(out.read_text())
    check_report(report)
    assert report["cables"] == 8
    assert report["reference"] == "wrench"
    assert report["baseline"]["per_cable_rmse_n"] == []
    # force residual of white sensor noise through A: about noise * sqrt(m / 3) per component
    assert report["baseline"]["rmse_n"] < 1.3 * sc.noise_n * (8 / 3) ** 0.5
