"""Regression cases of the diagnosis on recordings it has never seen, each made by
the independent generator (:mod:`tests.diagnose_helpers`), short recordings."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from gateway.core.config import FrictionConfig, PulleyConfig
from gateway.diagnose.engine import diagnose
from gateway.diagnose.fit import spec_for
from gateway.diagnose.forward import CableData, Forward
from gateway.diagnose.prepare import cable_data, clipped_mask, nominal_from
from gateway.diagnose.reference import CableUnit, validation_scores
from gateway.diagnose.selection import Selector, Thresholds
from gateway.diagnose.stats import white_noise
from gateway.diagnose.timebase import time_blocks
from tests.diagnose_helpers import Foreign, generate, recording_of, run_foreign
from tests.foreign_cases import P5_MIXED, RIG_AXIS


def _found(diag) -> dict[str, dict]:
    return {f["effect"]: f for f in diag.report["findings"]}


def test_rig_without_pulleys_fits_f0_instead_of_crashing():
    """Nominal `none` with no pulleys: the coulomb candidate used to divide by zero."""
    fo = Foreign(
        rig=True,
        tension=150.0,
        pulleys=(),
        model="coulomb",
        seconds=15.0,
        effects={"coulomb": {"f0_n": 5.0}},
    )
    found = _found(run_foreign(fo, "none", ()))
    assert list(found) == ["coulomb"]
    assert found["coulomb"]["parameters"]["f0_n"][0] == pytest.approx(5.0, rel=0.05)


@pytest.mark.long  # ~5 s
def test_positioning_axis_recovers_all_four_terms():
    """Inertia, viscous, load-independent Coulomb and offset on a rig moving at a few
    constant speeds with many reversals: the joint optimum, not a stand-in."""
    fo = Foreign(
        rig=True,
        tension=150.0,
        pulleys=(),
        model="coulomb",
        motion="positioning",
        vmax=0.13,
        seconds=16.0,
        rate_hz=250.0,
        effects=RIG_AXIS,
    )
    diag = run_foreign(fo, "none", ())
    found = _found(diag)
    assert set(found) == {"inertia", "viscous", "coulomb", "offset"}
    assert found["inertia"]["parameters"]["m_eff_kg"][0] == pytest.approx(95.0, rel=0.05)
    assert found["viscous"]["parameters"]["c_ns_m"][0] == pytest.approx(200.0, rel=0.05)
    assert found["coulomb"]["parameters"]["f0_n"][0] == pytest.approx(20.0, rel=0.05)
    assert found["offset"]["parameters"]["c_n"][0] == pytest.approx(-3.0, abs=0.3)
    fin = diag.report["final"]
    assert fin["holdout_rmse_n"] < 3 * fin["noise_n"]


def test_pair_found_where_no_single_passes():
    """Offset and drift that cancel in the mean: with the single-effect screen made
    impassable, the pair screen still finds both (and fits them)."""
    fo = Foreign(
        model="coulomb", seconds=20.0, effects={"offset": {"c_n": 0.6}, "drift": {"k_n_s": -0.06}}
    )
    rec = recording_of(generate(fo))
    fr = FrictionConfig(model="coulomb", pulleys=tuple(PulleyConfig(w, m) for w, m in fo.pulleys))
    from gateway.diagnose.engine import diagnose

    diag = diagnose(rec, fr, thresholds=Thresholds(z_screen=1e6))
    found = _found(diag)
    assert set(found) == {"offset", "drift"}
    assert found["drift"]["parameters"]["k_n_s"][0] == pytest.approx(-0.06, rel=0.2)
    assert found["offset"]["parameters"]["c_n"][0] == pytest.approx(0.6, rel=0.2)


@pytest.mark.parametrize("rate, jitter", [(100.0, 2e-3), (250.0, 8e-4)])
def test_noise_free_jittered_recording_gives_no_finding(rate, jitter):
    """No finding, and the nominal model's residual after warm-up is at the floor of
    generator vs model (0.014 and 0.010 N; 1 kHz without jitter: 0.012-0.014 N): the chain
    steps the Dahl state over the trapezoid travel of the actual time stamps. Stepped with
    ``v_k dt_k`` the residual was 0.13 and 0.030 N."""
    fo = Foreign(rate_hz=rate, jitter_s=jitter, noise_n=0.0, seconds=15.0)
    cols = generate(fo)
    rec = recording_of(cols)
    fr = FrictionConfig(
        model="dahl",
        pulleys=tuple(PulleyConfig(w, m) for w, m in fo.pulleys),
        sigma_n_m=fo.sigma_n_m,
    )
    assert _found(diagnose(rec, fr)) == {}
    t, v = cols["t"], cols["velocity_1"]
    data = CableData(t, v, cols["tension_platform_1"], cols["tension_sensor_1"], float(t[0]))
    residual = data.ts - Forward(data, nominal_from(fr)).predict({})
    after = t - t[0] > 2.0  # the generator starts 0.5 s into its motion, the model relaxed
    assert np.sqrt(np.mean(residual[after] ** 2)) < 0.025  # ~2x the 1 kHz floor


def test_jittered_200hz_logger_finds_viscous_only():
    fo = Foreign(rate_hz=200.0, jitter_s=8e-4, seconds=15.0, effects={"viscous": {"c_ns_m": 300.0}})
    found = _found(run_foreign(fo))
    assert list(found) == ["viscous"]
    assert found["viscous"]["parameters"]["c_ns_m"][0] == pytest.approx(300.0, rel=0.05)


def test_validation_scores_every_kept_effect_and_drops_none():
    """The validation recording scores each kept effect (its z there with the parameters
    fitted here) and decides nothing: the real effect scores high, an offset fitted on
    noise does not, and both are scored."""
    fo = Foreign(pulleys=P5_MIXED, seconds=15.0, effects={"viscous": {"c_ns_m": 80.0}})
    fr = FrictionConfig(pulleys=tuple(PulleyConfig(w, m) for w, m in fo.pulleys))
    nom = nominal_from(fr)
    vrec = recording_of(generate(replace(fo, seed=fo.seed + 100)))
    vd = cable_data(vrec, vrec.tension_platform, None)[0]
    theta = {"viscous": np.array([80.0]), "offset": np.array([-0.02])}
    out = validation_scores(theta, Forward(vd, nom), np.ones(vd.t.size, bool))
    assert set(out) == {"viscous", "offset"}
    assert out["viscous"]["validation_z"] > Thresholds().z_holdout
    assert out["viscous"]["validation_gain"] > 0.1
    assert out["offset"]["validation_z"] < Thresholds().z_holdout


def test_same_findings_whichever_validation_recording():
    """The same fitted recording with two different --validate recordings (and none)
    gives the same findings, cables and parameters: the validation only scores."""
    fo = Foreign(cables=2, pulleys=P5_MIXED, seconds=15.0, effects={"viscous": {"c_ns_m": 80.0}})
    fr = FrictionConfig(pulleys=tuple(PulleyConfig(w, m) for w, m in fo.pulleys))
    rec = recording_of(generate(fo))
    reports = []
    for seed in (None, fo.seed + 100, fo.seed + 200):
        validation = None
        if seed is not None:
            vrec = recording_of(generate(replace(fo, seed=seed, seconds=8.0)), "validation")
            validation = (vrec, vrec.tension_platform, None)
        reports.append(diagnose(rec, fr, validation=validation).report)

    def answer(rep):
        return [(f["effect"], f["cables"], f["parameters"]) for f in rep["findings"]]

    assert answer(reports[0]) and reports[0]["findings"][0]["effect"] == "viscous"
    assert answer(reports[1]) == answer(reports[0]) == answer(reports[2])
    for rep in reports[1:]:
        for f in rep["findings"]:
            assert len(f["validation_statistic"]) == len(f["cables"])
    assert reports[1]["final"]["validation_rmse_before_n"] != pytest.approx(
        reports[2]["final"]["validation_rmse_before_n"]
    )


def test_physical_bounds_on_inertia_viscous_and_gain():
    fo = Foreign(seconds=5.0)
    cols = generate(fo)
    rec = recording_of(cols)
    d = cable_data(rec, rec.tension_platform, None)[0]
    nom = nominal_from(FrictionConfig(viscous_ns_m=12.0))
    mask = np.ones(d.t.size, bool)
    assert spec_for("inertia", d, nom, d.ts, mask).lower[0] == 0.0
    assert spec_for("viscous", d, nom, d.ts, mask).lower[0] == -12.0
    assert spec_for("gain", d, nom, d.ts, mask).lower[0] > -1.0


def test_negative_inertia_is_never_reported_as_physics():
    """A reading that leads the model like a negative mass: whatever is reported, no
    inertia below zero and no total viscous coefficient below zero."""
    fo = Foreign(seconds=15.0, effects={"inertia": {"m_eff_kg": -40.0}})
    for f in run_foreign(fo).report["findings"]:
        assert min(f["parameters"].get("m_eff_kg", [0.0])) >= 0.0
        assert min(f["parameters"].get("c_ns_m", [0.0])) >= 0.0


def test_clipped_readings_are_detected_excluded_counted_and_named():
    from gateway.diagnose.plots import summary

    fo = Foreign(
        cables=2,
        seconds=15.0,
        clip_n=400.0,
        clip_cables=(2,),
        effects={"viscous": {"c_ns_m": 300.0}},
    )
    diag = run_foreign(fo)
    clip = diag.report["clipped"]
    assert clip["per_cable"][0] == 0
    assert clip["per_cable"][1] > 0.1 * diag.report["samples"]
    assert clip["levels_n"][1] == [400.0]
    assert list(_found(diag)) == ["viscous"]
    assert "Cable 2:" in summary(diag, "x.csv") and "clipped" in summary(diag, "x.csv")


def test_clipped_mask_leaves_a_quantised_extreme_alone():
    rng = np.random.default_rng(1)
    ts = np.round((300 + 5 * rng.normal(size=20000)) / 0.1) * 0.1
    assert not clipped_mask(ts)[0].any()
    ts[5000:5200] = ts.max() + 1.0
    mask, levels = clipped_mask(ts)
    assert mask.sum() == 200 and len(levels) == 1


def test_f0_under_dahl_adds_to_the_coulomb_level():
    """Forward model: under Dahl the state tends to lambda T + f0, so at steady sliding the
    Dahl chain with f0 reads the same as the Coulomb chain with f0 (docs/physics.md)."""
    t = np.arange(0.0, 4.0, 1e-3)
    v = np.full(t.size, 0.1)
    tp = np.full(t.size, 300.0)
    eff = {"coulomb": np.array([0.015, 4.0])}
    pulleys = (PulleyConfig(90.0, 0.015), PulleyConfig(60.0, 0.015))
    data = CableData(t, v, tp, tp, 0.0)
    dahl = Forward(data, nominal_from(FrictionConfig(model="dahl", pulleys=pulleys)))
    coul = Forward(data, nominal_from(FrictionConfig(model="coulomb", pulleys=pulleys)))
    y_d, y_c = dahl.predict(eff), coul.predict(eff)
    np.testing.assert_allclose(y_d[-100:], y_c[-100:], atol=1e-6)
    without = coul.predict({"coulomb": np.array([0.015, 0.0])})
    np.testing.assert_allclose(without[-1] - y_c[-1], 4.0, rtol=0.02)  # f0 lowers the reading


def test_dahl_recording_with_f0_finds_coulomb_f0():
    fo = Foreign(seconds=20.0, effects={"coulomb": {"f0_n": 3.0}})
    found = _found(run_foreign(fo))
    assert list(found) == ["coulomb"]
    assert found["coulomb"]["parameters"]["f0_n"][0] == pytest.approx(3.0, rel=0.1)


def test_summary_explains_when_no_region_concentrates_the_residual():
    from gateway.diagnose.plots import summary

    rep = {
        "cables": 1,
        "samples": 10,
        "baseline": {"rmse_n": 1.0},
        "final": {"rmse_n": 1.0, "holdout_rmse_n": 1.0, "noise_n": 1.0, "unexplained_n": 0.0},
        "findings": [],
        "regime_shares": {},
        "mismatch": [],
    }
    text = summary(SimpleNamespace(report=rep), "x.csv")  # type: ignore[arg-type]
    assert "Largest regions" not in text
    assert "No region concentrates the residual" in text
    rep["mismatch"] = [
        {"cable": 1, "start_s": 1.0, "end_s": 2.0, "regime": "reversal", "share": 0.5}
    ]
    text = summary(SimpleNamespace(report=rep), "x.csv")  # type: ignore[arg-type]
    assert "Largest regions" in text and "cable 1, 1.00-2.00 s, reversal" in text


@pytest.mark.long  # ~5 s
def test_subset_search_undoes_a_stand_in():
    """Started from the greedy dead end of the issue (inertia and a Coulomb level that
    holds the viscous force at the typical speed), the best-subset search reaches the
    joint optimum of the four terms."""
    from gateway.diagnose.prepare import cable_candidates, candidates_for

    fo = Foreign(
        rig=True,
        tension=150.0,
        pulleys=(),
        model="coulomb",
        motion="positioning",
        vmax=0.13,
        seconds=16.0,
        rate_hz=250.0,
        effects=RIG_AXIS,
    )
    rec = recording_of(generate(fo))
    nom = nominal_from(FrictionConfig(model="none", pulleys=()))
    d = cable_data(rec, rec.tension_platform, None)[0]
    fw = Forward(d, nom)
    blocks, nb = time_blocks(rec.t)
    unit = CableUnit(fw, blocks, nb, cable_candidates(candidates_for(False), d, nom))
    sel = Selector(unit, Thresholds())
    specs = {e: spec_for(e, d, nom, d.ts, unit.train) for e in ("inertia", "coulomb")}
    stand_in = sel.fit({"inertia": np.array([95.0]), "coulomb": np.array([0.0, 36.0])}, specs)
    assert sel.left(stand_in)
    out, _ = sel._look_further(stand_in, ["inertia", "coulomb"])
    assert set(out.kept) == {"inertia", "viscous", "coulomb", "offset"}
    assert out.kept["viscous"][0] == pytest.approx(200.0, rel=0.05)
    assert out.kept["coulomb"][1] == pytest.approx(20.0, rel=0.05)
    held = out.resid[unit.test]
    # no longer far above the noise (the stand-in left 3x it; no warm-up mask here)
    assert np.sqrt(np.mean(held**2)) < 3.0 * white_noise(out.resid[unit.train])
