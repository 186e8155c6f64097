"""Building blocks of the diagnosis: forward models, blocks, statistics, regimes."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from gateway.core.config import FrictionConfig
from gateway.diagnose import locate
from gateway.diagnose.forward import CableData, Forward, report_stderr, to_report
from gateway.diagnose.prepare import nominal_from
from gateway.diagnose.stats import holdout_z
from gateway.diagnose.timebase import time_blocks
from gateway.model import effects as fx
from gateway.model.chain_runs import run
from gateway.model.chain_schema import ChainParams


def _data(n=4000, seed=0):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.5e-3, 1.5e-3, n))
    v = 0.08 * np.sin(2 * math.pi * 0.5 * t)
    tp = 200 + 30 * np.sin(2 * math.pi * 0.3 * t)
    return t, v, tp


def test_forward_matches_effects_module():
    """The diagnosis' forward model is the plant's physics (one implementation)."""
    t, v, tp = _data()
    fr = FrictionConfig()
    nom = nominal_from(fr)
    params = ChainParams.from_friction(fr, 1)
    ts = run(params, "simulate", tp[:, None], v[:, None], t)
    eff = fx.effect_values(
        {
            "inertia": {"m_eff_kg": 1.5},
            "eccentricity": {"a_n": 0.3, "r_m": 0.04, "phi_rad": 0.5},
            "gain": {"g": 0.01},
            "offset": {"c_n": 0.2},
            "drift": {"k_n_s": 0.05},
            "lowpass": {"tau_s": 0.003},
            "delay": {"d_s": 0.002},
        },
        1,
    )
    vv = v[:, None]
    s = fx.SeriesData(t, vv, fx.displacement(t, vv), fx.acceleration(t, vv), float(t[0]))
    truth = fx.forward(s, ts, eff)[:, 0]
    fw = Forward(CableData(t, v, tp, truth, float(t[0])), nom)
    ecc = np.array([0.3 * math.cos(0.5), 0.3 * math.sin(0.5), 1 / 0.04])
    theta = {
        "inertia": np.array([1.5]),
        "eccentricity": ecc,
        "gain": np.array([0.01]),
        "offset": np.array([0.2]),
        "drift": np.array([0.05]),
        "lowpass": np.array([0.003]),
        "delay": np.array([0.002]),
    }
    assert_allclose(fw.predict(theta), truth, atol=1e-9)


def test_forward_chain_effects_match_chainparams():
    t, v, tp = _data()
    nom = nominal_from(FrictionConfig())
    params = ChainParams.build(
        "dahl",
        1,
        nom.wrap_rad,
        0.02,
        sigma_n_m=300.0,
        f0_n=0.4,
        stribeck_k=0.5,
        stribeck_v_m_s=0.01,
        viscous_ns_m=5.0,
    )
    truth = run(params, "simulate", tp[:, None], v[:, None], t)[:, 0]
    fw = Forward(CableData(t, v, tp, truth, float(t[0])), nom)
    theta = {
        "coulomb": np.array([0.02, 0.4]),
        "presliding": np.array([math.log10(300.0)]),
        "stribeck": np.array([0.5, -2.0]),
        "viscous": np.array([5.0]),
    }
    assert_allclose(fw.predict(theta), truth, atol=1e-9)


def test_report_parameters_and_stderr_transforms():
    p = to_report("eccentricity", np.array([0.3, 0.4, 20.0]))
    assert p == pytest.approx({"a_n": 0.5, "r_m": 0.05, "phi_rad": math.atan2(0.4, 0.3)})
    se = report_stderr("presliding", np.array([2.0]), np.array([0.01]))
    assert se["sigma_n_m"] == pytest.approx(100 * math.log(10) * 0.01)
    assert to_report("stribeck", np.array([0.5, -2.0])) == pytest.approx(
        {"k": 0.5, "v_s_m_s": 0.01}
    )


def test_time_blocks_interleave_and_cover():
    t = np.linspace(0, 30, 30001)
    blocks, nb = time_blocks(t)
    assert nb % 2 == 0 and 10 <= nb <= 40
    assert blocks.min() == 0 and blocks.max() == nb - 1
    assert np.all(np.diff(blocks) >= 0)
    counts = np.bincount(blocks)
    assert counts.min() > 0.8 * counts.max()


def test_holdout_z_separates_signal_from_noise():
    rng = np.random.default_rng(3)
    n, nb = 20000, 10
    blocks = np.repeat(np.arange(nb), n // nb)
    y = rng.normal(0, 1, n)
    sig = 0.3 * np.sin(np.linspace(0, 60, n))
    for truth, expect_big in ((y + sig, True), (y, False)):
        a = np.zeros(n)
        b = sig
        sse_a = np.bincount(blocks, (truth - a) ** 2)
        sse_b = np.bincount(blocks, (truth - b) ** 2)
        cross = np.bincount(blocks, (truth - b) * (b - a))
        z = holdout_z(sse_a, sse_b, cross)
        assert (z > 10) if expect_big else (z < 0)


def test_regimes_find_reversals_rest_and_speed():
    t = np.linspace(0, 10, 10001)
    v = 0.1 * np.sin(2 * math.pi * 0.2 * t)
    v[(t > 6.0) & (t < 7.0)] = 0.0
    reg = locate.regimes(v, np.gradient(v, t))
    names = {locate.REGIMES[k] for k in np.unique(reg)}
    assert {"reversal", "high_speed", "rest"} <= names
    assert locate.REGIMES[reg[np.searchsorted(t, 2.5)]] == "reversal"  # v = 0 at t = 2.5


def test_regions_locate_a_burst():
    rng = np.random.default_rng(1)
    t = np.linspace(0, 20, 20001)
    r = rng.normal(0, 0.1, (t.size, 2))
    burst = (t > 12) & (t < 13)
    r[burst, 1] += 2.0
    regs = locate.regions(t, r, np.zeros(r.shape, dtype=np.int8))
    assert regs[0].cable == 2
    assert 11.8 < regs[0].start_s < 12.2 and 12.8 < regs[0].end_s < 13.2
    assert regs[0].share > 0.8


def test_selection_subset_uses_training_blocks_only():
    from gateway.diagnose.prepare import selection_subset

    t = np.arange(400_000) * 1e-3
    blocks, nb = time_blocks(t)
    sub = selection_subset(t, blocks, budget=100_000)
    assert sub is not None
    idx, sub_blocks, usable = sub
    assert np.all(np.diff(idx) > 0)
    assert np.all(blocks[idx[usable]] % 2 == 0)  # scored samples never from held-out blocks
    assert (~usable).sum() > 0  # warm-up simulated but not scored
    assert set(np.unique(sub_blocks[usable] % 2)) == {0, 1}  # it trains and tests itself
    assert usable.sum() <= 100_000 + nb
    assert selection_subset(t[:1000], blocks[:1000]) is None


def test_rows_with_missing_values_are_dropped_and_counted():
    from evaluation.scenarios import Scenario, make_recording
    from gateway.diagnose.engine import diagnose

    sc = Scenario("nan", {}, cables=1, seconds=10.0)
    rec = make_recording(sc)
    rec.tension_sensor[100:110, 0] = np.nan
    report = diagnose(rec, sc.nominal()).report
    assert report["samples"] == rec.samples - 10
    assert report["skipped_rows"] == 10
    assert math.isfinite(report["baseline"]["rmse_n"])


def test_standstill_recording_finds_offset_not_eccentricity():
    """No motion: only the sensor effects can be told; an offset stays an offset."""
    from gateway.diagnose.engine import diagnose
    from gateway.recordings.reader import Recording

    rng = np.random.default_rng(5)
    t = np.arange(10000) * 1e-3
    tp = 150 + 20 * np.sin(2 * math.pi * 0.3 * t)
    ts = tp + 0.3 + rng.normal(0, 0.4, t.size)
    rec = Recording(
        t=t,
        velocity=np.zeros((t.size, 1)),
        tension_sensor=ts[:, None],
        tension_platform=tp[:, None],
    )
    report = diagnose(rec, FrictionConfig()).report
    assert [f["effect"] for f in report["findings"]] == ["offset"]
    assert report["findings"][0]["parameters"]["c_n"][0] == pytest.approx(0.3, abs=0.03)


def test_recomputed_predictions_give_the_reported_rmse():
    """The plots' predictions are recomputed per cable (not held): they give the report's
    baseline and final RMSE."""
    from evaluation.scenarios import Scenario, make_recording
    from gateway.diagnose.engine import diagnose
    from gateway.diagnose.plots import overlay_series, residual_series, thin

    sc = Scenario("offset", {"offset": {"c_n": [2.0, 0.0]}}, cables=2, seconds=20.0)
    rec = make_recording(sc)
    diag = diagnose(rec, sc.nominal())
    assert [f["effect"] for f in diag.report["findings"]] == ["offset"]
    sse = np.zeros(2)
    for i in range(rec.cables):
        nominal, final = diag.predictions(i)
        assert (final is nominal) == (not diag.final_theta(i))
        r0, r1 = diag.measured[:, i] - nominal, diag.measured[:, i] - final
        assert_allclose(
            math.sqrt(np.mean(r0**2)), diag.report["baseline"]["per_cable_rmse_n"][i], rtol=1e-12
        )
        sse += [r0 @ r0, r1 @ r1]
    n = rec.samples * rec.cables
    assert_allclose(
        np.sqrt(sse / n),
        [diag.report["baseline"]["rmse_n"], diag.report["final"]["rmse_n"]],
        rtol=1e-12,
    )
    nom_thin, fin_thin = residual_series(diag)
    assert nom_thin.shape == fin_thin.shape == (diag.t[thin(diag.t.size)].size, rec.cables)
    assert_allclose(fin_thin[:, 0], diag.predictions(0)[1][thin(diag.t.size)], rtol=0)
    nom_win, fin_win = overlay_series(diag)
    assert nom_win.shape == fin_win.shape and nom_win.size > 0
