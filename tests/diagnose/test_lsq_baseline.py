"""The engineer's least-squares baselines in every report (gateway/diagnose/lsq.py,
``baseline.least_squares``) and the reading in disguise left out of ``unexplained``
(:func:`gateway.diagnose.signals.disguised_readings`)."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evaluation.scenarios import Scenario, _truth_chain, motion
from gateway.diagnose import lsq
from gateway.diagnose.engine import diagnose
from gateway.diagnose.fromfiles import diagnose_file
from gateway.diagnose.plots import summary
from gateway.diagnose.signals import DISGUISE_R, disguised_readings
from gateway.model.chain_runs import run
from gateway.recordings.reader import Recording
from tests.diagnose_helpers import check_report, write_scenario


def _series(n: int = 4000, seed: int = 0) -> SimpleNamespace:
    """A slow stroke under a varying load at 100 Hz (platform side), without a reading."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 100.0
    v = 0.2 * np.sin(2 * np.pi * t / 7.0) + 0.05 * np.sin(
        2 * np.pi * t / 2.3 + rng.uniform(0.0, 6.0)
    )
    x = np.concatenate(([0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) / 100.0)))
    a = np.gradient(v, t)
    tp = 100.0 + 40.0 * np.sin(2 * np.pi * t / 11.0)
    return SimpleNamespace(t=t, v=v, a=a, x=x, tp=tp, ts=tp.copy())


def _halves(n: int) -> tuple[np.ndarray, np.ndarray]:
    blocks = np.arange(n) * 20 // n
    return blocks % 2 == 0, blocks % 2 == 1


@given(
    fc=st.floats(0.0, 20.0),
    c=st.floats(-50.0, 300.0),
    b=st.floats(-30.0, 30.0),
    seed=st.integers(0, 2**16),
)
@settings(max_examples=30, deadline=None)
def test_coulomb_viscous_recovers_its_own_law(fc: float, c: float, b: float, seed: int) -> None:
    """Readings made by the linear baseline's own law (plus small noise) give back its
    parameters, whatever they are."""
    d = _series(seed=seed)
    noise = np.random.default_rng(seed).normal(0.0, 0.01, d.t.size)
    d.ts = d.tp - fc * np.sign(d.v) - c * d.v + b + noise
    train, _ = _halves(d.t.size)
    got = lsq.fit_coulomb_viscous(lsq.cable_series(d), train).params
    assert abs(got["coulomb_n"] - fc) < 0.01 and abs(got["viscous_ns_m"] - c) < 0.1
    assert abs(got["offset_n"] - b) < 0.01


@given(
    mu=st.floats(0.01, 0.1),
    f0=st.floats(0.5, 5.0),
    c=st.floats(0.0, 200.0),
    k=st.floats(-50.0, 50.0),
    seed=st.integers(0, 2**16),
)
@settings(max_examples=8, deadline=None)
def test_dahl_baseline_predicts_its_own_law_to_the_noise(
    mu: float, f0: float, c: float, k: float, seed: int
) -> None:
    """Readings made by the Dahl baseline's own law: its held-out error falls to the noise,
    and well below the linear baseline's when the load-dependent friction is large."""
    d = _series(seed=seed)
    f = lsq.dahl_force(d.tp, lsq.travel(d.x), mu, f0, 2e4)
    noise = np.random.default_rng(seed).normal(0.0, 0.2, d.t.size)
    d.ts = 1.01 * d.tp - f - c * d.v - 0.5 * d.a - k * d.x + 2.0 + noise
    train, test = _halves(d.t.size)
    cab = lsq.cable_series(d)
    dahl = lsq.fit_dahl(cab, train)
    err = float(np.sqrt(np.mean((d.ts - dahl.predict(cab))[test] ** 2)))
    assert err < 0.2 * 1.15, dahl.params
    lin = lsq.fit_coulomb_viscous(cab, train)
    assert err <= float(np.sqrt(np.mean((d.ts - lin.predict(cab))[test] ** 2)))


def test_dahl_fit_on_windows_of_a_long_recording(monkeypatch) -> None:
    """A recording longer than the fit's budget is fitted on windows (the state from rest
    in each): the prediction over every sample still falls to the noise."""
    monkeypatch.setattr(lsq, "FIT_SAMPLES", 1000)
    d = _series(n=8000, seed=3)
    d.ts = d.tp - lsq.dahl_force(d.tp, lsq.travel(d.x), 0.05, 2.0, 2e4) - 80.0 * d.v
    d.ts = d.ts + np.random.default_rng(3).normal(0.0, 0.2, d.t.size)
    train, test = _halves(d.t.size)
    design = lsq.Design(train, d.x)
    assert len(design.windows) == lsq.WINDOWS and design.idx.size < 1000
    assert np.all(train[design.idx])
    cab = lsq.cable_series(d)
    fit = lsq.fit_dahl(cab, train)
    err = float(np.sqrt(np.mean((d.ts - fit.predict(cab))[test] ** 2)))
    assert err < 0.2 * 1.15, fit.params


def test_block_says_when_the_catalogue_loses_and_which_term_carries_it() -> None:
    """A catalogue model that lacks the viscous friction the readings carry: the block says
    it does not beat the baselines and names the viscous term as what it lacks."""
    datas = []
    for seed in (1, 2):
        d = _series(seed=seed)
        d.ts = d.tp - 150.0 * d.v + np.random.default_rng(seed).normal(0.0, 0.3, d.t.size)
        datas.append(d)
    n = datas[0].t.size
    train, test = _halves(n)
    train2, test2 = np.column_stack([train, train]), np.column_stack([test, test])
    out = lsq.block(datas, train2, test2, lambda i: datas[i].tp)
    assert out["compared_on"] == "holdout" and not out["beaten"]
    assert out["terms"][0]["term"] == "c_ns_m"
    assert "does not beat" in out["sentence"] and "viscous" in out["sentence"]
    assert out["terms"][0]["rise_n"] > 3.0  # the viscous term carries tens of N
    assert all(t["rise_n"] < 1.0 for t in out["terms"][1:])
    # the same catalogue with the viscous term: it beats them, and no term is named
    good = lsq.block(datas, train2, test2, lambda i: datas[i].tp - 150.0 * datas[i].v)
    assert good["beaten"] and "terms" not in good and "beats" in good["sentence"]


@pytest.mark.long
def test_every_report_carries_the_least_squares_baseline(tmp_path) -> None:
    """The block is in the report, schema-valid, and scores the catalogue exactly as the
    report's own ``final`` does (same held-out blocks, same validation recording)."""
    sc = Scenario("lsq", {"viscous": {"c_ns_m": 8.0}}, cables=2, seconds=20.0)
    rec, model = write_scenario(tmp_path, sc)
    val, _ = write_scenario(tmp_path, replace(sc, seed=7), "val.csv.gz")
    rep = diagnose_file(rec, model, val).report
    check_report(rep)
    ls = rep["baseline"]["least_squares"]
    assert "rmse_n" in rep["baseline"]  # the nominal model's RMSE is kept
    assert np.isclose(ls["catalogue"]["holdout_rmse_n"], rep["final"]["holdout_rmse_n"])
    assert np.isclose(ls["catalogue"]["validation_rmse_n"], rep["final"]["validation_rmse_after_n"])
    assert ls["compared_on"] == "validation"
    for fit in ls["fits"].values():
        assert len(fit["per_cable_holdout_rmse_n"]) == 2
        assert all(len(v) == 2 for v in fit["parameters"].values())
    best = ls["fits"][ls["best"]]["validation_rmse_n"]
    assert ls["beaten"] == (ls["catalogue"]["validation_rmse_n"] <= best)
    assert ("beats" if ls["beaten"] else "does not beat") in ls["sentence"]


@given(
    scale=st.floats(0.01, 100.0) | st.floats(-100.0, -0.01),
    offset=st.floats(-1e3, 1e3),
    seed=st.integers(0, 2**16),
)
@settings(max_examples=50, deadline=None)
def test_an_affine_copy_of_a_reading_is_a_reading_in_disguise(
    scale: float, offset: float, seed: int
) -> None:
    """Any scaled, offset copy of a cable's reading (with noise well below the reading's
    spread) is flagged with that cable; an independent column is not."""
    rng = np.random.default_rng(seed)
    n = 2000
    readings = [100.0 + 30.0 * rng.standard_normal(n) for _ in range(3)]
    which = int(rng.integers(3))
    copy = scale * (readings[which] + rng.normal(0.0, 2.0, n)) + offset
    other = rng.standard_normal(n)
    masks = [np.ones(n, bool)] * 3
    got = disguised_readings({"torque": copy, "temp": other}, readings, masks)
    assert [g["column"] for g in got] == ["torque"]
    assert got[0]["cable"] == which + 1 and abs(got[0]["correlation"]) >= DISGUISE_R
    assert "torque" not in str(got[0]["reason"]) and "cable" in got[0]["reason"]


@pytest.mark.long
def test_unexplained_ignores_the_motor_torque_beside_the_tension() -> None:
    """A recording whose residual follows the temperature, with the drive's torque (the
    reading divided by an undocumented torque constant, plus a small friction, plus an
    offset) logged beside it: the torque is excluded and named with its reason, and the
    temperature is still what explains the residual."""
    sc = Scenario("thermal", {}, seed=4, seconds=30.0)
    t, v, tp = motion(sc)
    temp = 25.0 + 4.0 * np.sin(2 * np.pi * t / 17.0) + 2.0 * np.sin(2 * np.pi * t / 5.3)
    ts = run(_truth_chain(sc, 2), "simulate", tp, v, t) + 0.3 * (temp - 25.0)[:, None]
    ts = ts + np.random.default_rng(5).normal(0.0, 0.4, ts.shape)
    torque = (ts[:, 0] + 0.5 * np.sign(v[:, 0])) / 12.5 + 0.3
    rec = Recording(
        t=t,
        velocity=v,
        tension_sensor=ts,
        tension_platform=tp,
        extra={"temperature_c": temp, "motor_torque_nm": torque},
        metadata={},
    )
    diag = diagnose(rec, sc.nominal())
    rep = diag.report
    check_report(rep)
    text = summary(diag, "thermal.csv")
    assert "`motor_torque_nm` is not searched" in text
    assert rep["baseline"]["least_squares"]["sentence"] in text
    (ex,) = rep["unexplained_excluded"]
    assert ex["column"] == "motor_torque_nm" and ex["cable"] == 1
    assert "collinear" in ex["reason"]
    un = rep["unexplained"]
    assert un["signal"] == "column temperature_c", un["ranking"]
    assert all(r["signal"] != "column motor_torque_nm" for r in un["ranking"])
