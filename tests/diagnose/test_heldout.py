"""A fitted model is written only if it lowers the error on data it was not fitted on: the
rule as a property over reports, then ``diagnose --write-model`` and ``calibrate`` refusing
such a model in one line, with the motion the recording had."""

from __future__ import annotations

import dataclasses
import math
import types

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.cli import main
from gateway.diagnose import heldout

rmse = st.floats(0.01, 10.0, allow_nan=False)


def report(before: float, after: float, validation: bool) -> dict:
    finding = {
        "effect": "inertia",
        "cables": [1],
        "parameters": {"m_eff_kg": [27.45]},
        "holdout_rmse_before_n": before,
        "holdout_rmse_after_n": after,
    }
    final = {"rmse_n": after, "holdout_rmse_n": after}
    if validation:  # the in-recording blocks say better; the unseen recording decides
        finding["holdout_rmse_after_n"] = final["holdout_rmse_n"] = before / 2
        final.update(validation_rmse_before_n=before, validation_rmse_after_n=after)
    return {"cables": 8, "findings": [finding], "final": final}


MOVED = heldout.Motion(seconds=0.7, reversals=1, speed_min_m_s=0.0, speed_max_m_s=0.04)


@given(before=rmse, after=rmse, validation=st.booleans())
def test_refused_exactly_when_unseen_data_is_not_better(before, after, validation) -> None:
    why = heldout.refusal(report(before, after, validation), MOVED)
    assert (why is None) == (after < before)
    if why is not None:
        assert "\n" not in why and "0.7 s" in why and "1 velocity reversals" in why
        assert "record about 30 s (43x more" in why
        assert ("--validate recording" if validation else "held-out time blocks") in why


def test_no_findings_nothing_to_refuse() -> None:
    assert heldout.refusal({"findings": [], "final": {}}, MOVED) is None


def test_motion_counts_reversals_and_the_speed_range() -> None:
    t = np.linspace(0.0, 10.0, 1001)
    sine = 0.1 * np.sin(2 * np.pi * 0.5 * t + 0.3)  # 5 periods in 10 s: 10 sign changes
    v = np.stack([sine, sine, np.full(t.size, 0.02)], axis=1)  # and a constant: none
    m = heldout.motion(t, v)
    assert m.seconds == 10.0 and m.speed_max_m_s == pytest.approx(0.1, rel=1e-3)
    assert m.reversals == 10  # median of 10, 10, 0


@pytest.fixture
def recording(tmp_path):
    from sim_plc.cli import run_command

    out = tmp_path / "rec.csv"
    args = types.SimpleNamespace(
        config="config/default.yaml", seconds=2.0, out=str(out), quiet=True, seed=None, robot=None
    )
    assert run_command("record", args) == 0
    return out


def test_diagnose_refuses_to_write_a_model_worse_on_unseen_data(
    recording, tmp_path, capsys, monkeypatch
):
    from gateway.diagnose import fromfiles  # the CLI diagnoses files through it

    real = fromfiles.diagnose

    def worse(*args, **kwargs):
        diag = real(*args, **kwargs)
        rep = {**diag.report, **report(0.7, 0.9, False)}
        return dataclasses.replace(diag, report=rep)

    monkeypatch.setattr(fromfiles, "diagnose", worse)
    fitted = tmp_path / "fitted.yaml"
    rc = main(
        [
            "diagnose",
            str(recording),
            "--model",
            "config/default.yaml",
            "--write-model",
            str(fitted),
            "--quiet",
        ]
    )
    assert rc == 2 and not fitted.exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--write-model {fitted}: not written" in err[0], err
    assert "0.700 N before, 0.900 N after" in err[0] and "velocity reversals" in err[0]


def test_calibrate_refuses_and_runs_no_after(tmp_path, capsys, monkeypatch):
    from gateway.diagnose import fromfiles
    from sim_plc import calibrate

    runs: list[str] = []

    def fake_run(plant, cfg, seconds, label, record=None):
        runs.append(label)
        if record is not None:
            t = np.arange(0, 1.0, 0.001)
            rec = make_recording(t)
            from gateway.recordings.reader import write_recording

            write_recording(record, rec)
        return calibrate.RunScore(0.5, 1.0, [0.5] * 8, 100, 100, 0)

    def fake_wrench(rec, friction, reference, validation=None, progress=None):
        assert reference.name == "wrench"
        assert validation is not None and validation.samples < rec.samples
        return types.SimpleNamespace(report=report(0.707, 0.907, True) | {"reference": "wrench"})

    def make_recording(t):
        from gateway.recordings.reader import Recording

        m = 8
        rng = np.random.default_rng(0)
        ts = 200 + rng.normal(0, 0.5, (t.size, m))
        pose = np.tile([0.0, 0.0, 1.5, 0.0, 0.0, 0.0], (t.size, 1))
        return Recording(
            t=t,
            velocity=np.full((t.size, m), 0.01),
            tension_sensor=ts,
            tension_platform=None,
            pose=pose,
            mass=np.full(t.size, 40.0),
            extra={f"status_{i + 1}": np.zeros(t.size) for i in range(m)},
            source="fake",
        )

    monkeypatch.setattr(calibrate, "run_scored", fake_run)
    monkeypatch.setattr(fromfiles, "diagnose", fake_wrench)
    out = tmp_path / "cal"
    rc = main(
        [
            "calibrate",
            "--config",
            "config/default.yaml",
            "--seconds",
            "1",
            "--out",
            str(out),
            "--quiet",
        ]
    )
    err = capsys.readouterr().err
    assert rc == 2, err
    assert not (out / "fitted.yaml").exists() and "calibrate after" not in runs
    assert "not written" in err and "the recording's last quarter, not fitted" in err
    assert "0.707 N before, 0.907 N after" in err and math.isfinite(0.0)
