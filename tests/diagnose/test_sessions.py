"""One machine, many recordings (issue 29 item 1; gateway/diagnose/sessions.py):
``diagnose REC REC ...`` gives one set of findings for the machine, the same whichever
recording is left out for ``--validate`` and in whatever order the others are given."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.cli import main
from gateway.core.config import load_friction
from gateway.diagnose import sessions as ss
from gateway.diagnose.forward import CableData, Forward, report_stderr, to_report
from gateway.diagnose.fromfiles import diagnose_file
from gateway.diagnose.prepare import nominal_from
from gateway.diagnose.timebase import GAP_SPACINGS, gap_starts
from gateway.diagnose.timebase import time_blocks as one_blocks
from gateway.model import effects as fx
from gateway.recordings.reader import Recording
from tests import reallike as rl
from tests import reallike_cases as rc
from tests.diagnose_helpers import check_report


def _rec(n: int, rate: float, cables: int, t0: float, seed: int) -> Recording:
    rng = np.random.default_rng(seed)
    t = t0 + np.cumsum(rng.uniform(0.9, 1.1, n)) / rate
    return Recording(
        t=t,
        velocity=rng.normal(0.0, 0.1, (n, cables)),
        tension_sensor=rng.normal(100.0, 5.0, (n, cables)),
        source=f"r{seed}.csv",
    )


@settings(max_examples=25, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(40, 400), st.sampled_from([10.0, 30.0, 100.0])),
        min_size=2,
        max_size=4,
    ),
    st.floats(-1e4, 1e4),
)
def test_joined_recordings_keep_their_rows_and_each_trains_and_is_held_out(parts, t0) -> None:
    """Rows kept in order, each recording shifted by a constant, a gap at every join; time
    blocks drawn within each recording (the single-recording blocks, renumbered), so
    every recording has training and held-out blocks and no block spans two."""
    recs = [_rec(n, rate, 3, t0 + 50.0 * k, k) for k, (n, rate) in enumerate(parts)]
    names = [f"r{k}.csv" for k in range(len(recs))]
    joined, tp, dm, sess = ss.join([(r, r.tension_sensor, None) for r in recs], names)
    assert dm is None and sess.count == len(recs)
    assert np.array_equal(joined.tension_sensor, np.concatenate([r.tension_sensor for r in recs]))
    assert np.array_equal(tp, joined.tension_sensor)
    assert np.all(np.diff(joined.t) > 0)
    for k, r in enumerate(recs):
        t = joined.t[sess.index == k]
        assert np.allclose(t - t[0], r.t - r.t[0], rtol=0, atol=1e-9)
        assert t[0] == sess.starts[k]
    joins = np.nonzero(np.diff(sess.index))[0] + 1
    assert set(joins) <= set(gap_starts(joined.t))
    assert GAP_SPACINGS < ss.JOIN_SPACINGS
    blocks, nb = ss.time_blocks(joined.t, sess)
    assert nb % 2 == 0 and blocks.max() < nb
    for k, r in enumerate(recs):
        mine = blocks[sess.index == k]
        assert np.any(mine % 2 == 0) and np.any(mine % 2 == 1)
        alone, _ = one_blocks(r.t)
        assert np.array_equal(mine - mine.min(), alone)
    assert not set(blocks[sess.index == 0]) & set(blocks[sess.index != 0])


def test_recordings_of_different_machines_are_refused_in_one_line(tmp_path: Path, capsys) -> None:
    run = rl.Run(seed=1, seconds=30.0)
    a = rl.write(tmp_path / "a.csv", rl.generate(rl.Machine(cables=4), run))
    b = rl.write(tmp_path / "b.csv", rl.generate(rl.Machine(cables=6), run))
    model = tmp_path / "model.yaml"
    model.write_text(rl.model_yaml(), encoding="utf-8")
    code = main(["diagnose", str(a), str(b), "--model", str(model), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and str(b) in err and "cables" in err


def test_an_offset_per_recording_acts_on_its_own_recording_only(tmp_path: Path) -> None:
    """``Effect.per_recording`` (declared in the offset's and the drift's modules): one
    parameter vector per recording on a joined series, each sample its recording's; the
    report's value is their mean; a series of one recording (the validation) gets the
    mean; a shared effect is left alone."""
    assert {n for n, e in fx.REGISTRY.items() if e.per_recording} == {"offset", "drift"}
    n = 300
    t = np.arange(n) * 0.1
    session = np.repeat([0, 1, 2], n // 3)
    t0 = np.array([0.0, 10.0, 20.0])[session]
    tp = np.full(n, 100.0)
    d = CableData(t, np.zeros(n), tp, tp, t0, session=session)
    model = tmp_path / "model.yaml"
    model.write_text(rl.model_yaml(), encoding="utf-8")
    nom = nominal_from(load_friction(model))
    fw = Forward(d, nom)
    base = fw.predict({})
    theta = {"offset": np.array([1.0, -2.0, 4.0]), "drift": np.array([0.1, 0.0, -0.2])}
    got = fw.predict(theta) - base
    want = np.array([1.0, -2.0, 4.0])[session] + np.array([0.1, 0.0, -0.2])[session] * (t - t0)
    assert np.allclose(got, want, atol=1e-12)
    assert to_report("offset", theta["offset"]) == {"c_n": 1.0}
    se = report_stderr("offset", theta["offset"], np.array([0.3, 0.4, 1.2]))
    assert se["c_n"] == pytest.approx(np.sqrt(0.09 + 0.16 + 1.44) / 3)
    one = Forward(CableData(t, np.zeros(n), tp, tp, 0.0), nom)
    assert np.allclose(one.predict({"offset": theta["offset"]}) - one.predict({}), 1.0)
    spec = fx.REGISTRY["offset"].linear_spec(nom)
    tiled = ss.tile_spec(spec, 1, 3)
    assert tiled.linear == (0, 1, 2) and tiled.neutral.size == 3
    assert ss.per_recording("viscous", 3) == 1 and ss.per_recording("offset", 3) == 3


def _three(tmp_path: Path, machine: rl.Machine, seconds: float) -> tuple[list[Path], Path]:
    paths = [
        rl.write(
            tmp_path / f"r{k}.csv",
            rl.generate(machine, rl.Run(seed=2 + 101 * k, rate_hz=10.0, seconds=seconds)),
        )
        for k in range(3)
    ]
    model = tmp_path / "model.yaml"
    model.write_text(rl.model_yaml(), encoding="utf-8")
    return paths, model


@pytest.mark.long
def test_one_recording_in_a_list_is_the_one_recording_report(tmp_path: Path) -> None:
    """A single recording takes the path it always took: the same report given alone or as
    a list of one, without ``recordings`` or ``per_recording``."""
    paths, model = _three(tmp_path, rl.Machine(cables=4, offset_n=-8.0), 60.0)
    alone = diagnose_file(paths[0], model, paths[1]).report
    listed = diagnose_file([paths[0]], model, paths[1]).report
    assert json.dumps(alone) == json.dumps(listed)
    assert "recordings" not in alone
    assert all("per_recording" not in f for f in alone["findings"])


def _found(report: dict) -> dict[str, list[int]]:
    return {f["effect"]: f["cables"] for f in report["findings"]}


ROBOT = rl.Machine(cables=4, c_ns_m=200.0, offset_n=-8.0, noise_frac=0.18)
"""Issue 29's 4-cable robot: shared viscous 200 N s/m, offset -8 N, noise 18 %."""
ALL_CABLES = {e: [1, 2, 3, 4] for e in rl.truth_effects(ROBOT)}


@pytest.mark.long
@pytest.mark.timeout(1200)  # six diagnoses of 2 x 200 s: minutes on a loaded 2-core machine
def test_one_answer_whichever_recording_is_validated_and_in_either_order(tmp_path: Path) -> None:
    """Three recordings of different motions of :data:`ROBOT`: every choice of the
    ``--validate`` recording and both orders of the two fitted give the same findings, the
    truth (viscous and offset on every cable, parameters within the real-like scorer's
    tolerances), per-recording offsets for the fitted recordings, a lower validation
    error, and a schema-valid report."""
    paths, model = _three(tmp_path, ROBOT, 200.0)
    truth = rl.truth_effects(ROBOT)
    for val in range(3):
        fit = [paths[k] for k in range(3) if k != val]
        for order in (fit, fit[::-1]):
            rep = diagnose_file(order, model, paths[val]).report
            check_report(rep)
            assert _found(rep) == ALL_CABLES, (val, [p.name for p in order], _found(rep))
            assert [r["name"] for r in rep["recordings"]] == [p.name for p in order]
            (off,) = [f for f in rep["findings"] if f["effect"] == "offset"]
            assert len(off["per_recording"]) == 2
            fin = rep["final"]
            assert fin["validation_rmse_after_n"] < fin["validation_rmse_before_n"]
            # the offset's parameters: the mean over the fitted recordings
            assert max(rc._param_errors(truth, f) for f in rep["findings"]) <= 1.0


@pytest.mark.long
@pytest.mark.timeout(1200)  # six diagnoses of 3 x 150 s
def test_one_answer_in_every_order_of_three_recordings(tmp_path: Path) -> None:
    """All three recordings fitted together, in each of the six orders: the same findings,
    the truth on every cable."""
    paths, model = _three(tmp_path, ROBOT, 150.0)
    answers = [_found(diagnose_file(list(o), model).report) for o in itertools.permutations(paths)]
    assert all(a == ALL_CABLES for a in answers), answers
