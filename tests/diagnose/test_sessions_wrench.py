"""One machine, many recordings, without platform tensions (issue 29 item 1): ``diagnose
REC REC ...`` of recordings that carry pose and mass only joins them
(:func:`gateway.diagnose.sessions.join_wrench`) and diagnoses them as one against the wrench
balance -- the path ``calibrate --runs N`` takes."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.core.config import load_config
from gateway.diagnose import sessions as ss
from gateway.diagnose.fromfiles import diagnose_file
from gateway.diagnose.timebase import gap_starts
from gateway.diagnose.wrench import wrench_data
from gateway.errors import GatewayError
from gateway.recordings.reader import Recording
from tests.diagnose_helpers import check_report, wrench_recordings

ROOT = Path(__file__).resolve().parents[2]
MODEL = ROOT / "config" / "default.yaml"  # the gateway's side of config/calibrate/*.yaml
CFG = load_config(MODEL)


def _rec(n: int, rate: float, seed: int, t0: float) -> Recording:
    """A recording with pose and mass: a smooth platform motion, jittered time stamps."""
    rng = np.random.default_rng(seed)
    t = t0 + np.cumsum(rng.uniform(0.9, 1.1, n)) / rate
    pose = np.zeros((n, 6))
    for j in range(3):
        f = rng.uniform(0.1, 0.5)
        pose[:, j] = 0.1 * np.sin(2 * np.pi * f * t + rng.uniform(0, 6))
    pose[:, 2] += 1.5
    m = CFG.cables
    return Recording(
        t=t,
        velocity=rng.normal(0.0, 0.05, (n, m)),
        tension_sensor=rng.normal(200.0, 5.0, (n, m)),
        pose=pose,
        mass=np.full(n, 40.0),
        source=f"r{seed}.csv",
    )


@settings(max_examples=10, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(60, 300), st.sampled_from([30.0, 100.0, 1000.0])),
        min_size=2,
        max_size=3,
    ),
    st.floats(-1e3, 1e3),
)
def test_joined_wrench_rows_and_derivatives_are_each_recordings_own(parts, t0) -> None:
    """Rows kept in order behind a gap at each join; pose and mass kept; the platform's
    speed and acceleration of each recording are those it has alone (never differentiated
    across a join); the time blocks are drawn within each recording."""
    recs = [_rec(n, rate, k, t0 + 100.0 * k) for k, (n, rate) in enumerate(parts)]
    joined, sess = ss.join_wrench(recs, [r.source for r in recs])
    assert joined.tension_platform is None and sess.count == len(recs)
    assert np.array_equal(joined.pose, np.concatenate([r.pose for r in recs]))
    assert np.array_equal(joined.mass, np.concatenate([r.mass for r in recs]))
    joins = np.nonzero(np.diff(sess.index))[0] + 1
    assert set(joins) <= set(gap_starts(joined.t))
    data = wrench_data(joined, CFG, sess.index)
    for k, r in enumerate(recs):
        mine = sess.index == k
        alone = wrench_data(dataclasses.replace(r, t=joined.t[mine]), CFG)  # on its clock
        assert np.array_equal(data.acc[mine], alone.acc)
        assert np.array_equal(data.speed[mine], alone.speed)
    blocks, _ = ss.time_blocks(joined.t, sess)
    for k in range(sess.count):
        mine = blocks[sess.index == k]
        assert np.any(mine % 2 == 0) and np.any(mine % 2 == 1)


def test_rows_without_every_value_are_dropped_per_recording() -> None:
    a, b = _rec(100, 100.0, 1, 0.0), _rec(80, 100.0, 2, 0.0)
    b.pose[5, 0] = np.nan
    b.tension_sensor[7, 2] = np.nan
    joined, sess = ss.join_wrench([a, b], ["a.csv", "b.csv"])
    assert sess.samples == [100, 78] and joined.skipped_rows == 2
    assert np.isfinite(joined.pose).all() and np.isfinite(joined.tension_sensor).all()


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Two recordings of config/calibrate/viscous.yaml's plant (viscous 25 N s/m hidden),
    different motions and noise, 6 s each at 100 Hz, no platform tensions."""
    d = tmp_path_factory.mktemp("wrench-runs")
    return wrench_recordings(d, ROOT / "config" / "calibrate" / "viscous.yaml", 6.0, [1, 2])


def test_several_recordings_without_platform_tensions_are_diagnosed_jointly(runs) -> None:
    """One wrench report for both: ``recordings`` lists them, viscous found on every
    cable near the hidden 25 N s/m, the same findings in either order."""
    rep = diagnose_file(runs, MODEL).report
    check_report(rep)
    assert rep["reference"] == "wrench"
    assert [r["name"] for r in rep["recordings"]] == [p.name for p in runs]
    assert rep["recordings"][1]["start_s"] > rep["recordings"][0]["duration_s"]
    assert sum(r["samples"] for r in rep["recordings"]) == rep["samples"]
    assert [f["effect"] for f in rep["findings"]] == ["viscous"]
    (visc,) = rep["findings"]
    assert visc["cables"] == list(range(1, 9))
    assert np.allclose(visc["parameters"]["c_ns_m"], 25.0, rtol=0.1)
    back = diagnose_file(runs[::-1], MODEL).report
    assert [(f["effect"], f["cables"]) for f in back["findings"]] == [("viscous", visc["cables"])]


def test_mixing_platform_tensions_and_none_is_refused_in_one_line(runs, tmp_path) -> None:
    from gateway.recordings.reader import read_recording, write_recording

    rec = read_recording(runs[1])
    with_tp = dataclasses.replace(rec, tension_platform=rec.tension_sensor.copy())
    write_recording(tmp_path / "tp.csv", with_tp)
    with pytest.raises(GatewayError, match="platform tensions or none") as err:
        diagnose_file([runs[0], tmp_path / "tp.csv"], MODEL)
    assert "\n" not in str(err.value) and "tp.csv" in str(err.value)
