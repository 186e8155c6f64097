"""A recording that starts in mid-motion (as ``run --record`` does) has a start-up transient
that is the diagnosis' own warm-up; the report says so and lists no mismatch region
inside it."""

from __future__ import annotations

import dataclasses
import json
import types

import numpy as np

from gateway.cli import main
from gateway.recordings.reader import read_recording, write_recording


def test_mid_motion_recording_reports_its_warm_up(tmp_path) -> None:
    from sim_plc.cli import run_command

    whole = tmp_path / "whole.csv"
    args = types.SimpleNamespace(
        config="config/default.yaml", seconds=8.0, out=str(whole), quiet=True, seed=None, robot=None
    )
    assert run_command("record", args) == 0
    rec = read_recording(whole)
    keep = rec.t >= rec.t[0] + 2.0  # join the machine 2 s in: friction state developed
    cut = dataclasses.replace(
        rec,
        t=rec.t[keep],
        velocity=rec.velocity[keep],
        tension_sensor=rec.tension_sensor[keep],
        tension_platform=rec.tension_platform[keep],
        length=None if rec.length is None else rec.length[keep],
        pose=None if rec.pose is None else rec.pose[keep],
        mass=None if rec.mass is None else rec.mass[keep],
        extra={},
    )
    mid = tmp_path / "mid.csv"
    write_recording(mid, cut)
    out = tmp_path / "r.json"
    assert (
        main(
            [
                "diagnose",
                str(mid),
                "--model",
                "config/default.yaml",
                "--json",
                str(out),
                "--report",
                str(tmp_path / "rep"),
                "--quiet",
            ]
        )
        == 0
    )
    rep = json.loads(out.read_text())
    warm = rep["warmup"]
    assert 0.0 < warm["seconds"] < 0.2 * (cut.t[-1] - cut.t[0]) and warm["samples"] > 0
    assert warm["until_s"] == float(cut.t[warm["samples"]])  # the recording's clock
    assert "left out of the selection, the fit and the held-out scores" in warm["treatment"]
    assert all(r["end_s"] > warm["until_s"] for r in rep["mismatch"])
    assert warm["regions"], rep["mismatch"]  # the start's transient was listed as mismatch
    assert all(r["end_s"] <= warm["until_s"] + 1e-9 for r in warm["regions"])
    summary = (tmp_path / "rep" / "summary.md").read_text()
    assert f"The first {warm['seconds']:.2f} s (to " in summary and "warm-up" in summary
    assert np.isfinite(warm["until_s"])
