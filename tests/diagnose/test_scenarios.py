"""The scenario suite: concealed effects are named, fitted and improve held-out data;
nothing is named on clean recordings (several seeds)."""

from __future__ import annotations

import pytest

from evaluation.scenarios import Scenario, evaluate, expected_cables, substitutes, suite
from tests.diagnose_helpers import check_report

FAST = {
    "viscous",
    "offset",
    "delay",
    "presliding",
    "coulomb",
    "rig_viscous",
    "clean_seed1",
    "clean_seed2",
    "clean_rig",
    "clean_uneven",
}


# `make test` runs one effect of each stage alone (chain, path, sensor), the clean
# recordings and the 1-cable rig; the other effects, the combinations, the per-cable
# variants and the 8-cable plant go to `make test-long` (CI runs both). The two sets are
# disjoint (checked below), so CI scores each case once and no case is listed as fast
# while it runs only in `make test-long`
LONG = {
    "plant_mass_change",
    "plant_viscous",
    "plant_clean",
    "gain+coulomb",
    "stribeck+inertia",
    "lowpass+inertia",
    "viscous+offset",
    "gain+eccentricity",
    "offset+drift",
    "delay+drift",
    "uneven_viscous",
    "offset_per_cable",
    "eccentricity_cable2",
    "rig_gain",
    "stribeck",
    "lowpass",
    "gain",
    "inertia",
    "drift",
    "eccentricity",
    "uneven_delay",
    # the effects of the last round alone (10-40 s each)
    "coulomb_directional",
    "maxwell_slip",
    "backlash",
    "cable_stretch",
    "sensor_creep",
    "plant_spring",
}


def test_each_case_is_fast_or_long_never_both():
    """A case in both lists ran only in `make test-long` while the list said otherwise."""
    names = {sc.name for sc in suite()}
    assert not FAST & LONG, FAST & LONG
    assert not (FAST | LONG) - names, (FAST | LONG) - names


def _cases():
    for sc in suite():
        marks = [] if sc.name in FAST and not sc.slow else [pytest.mark.slow]
        if sc.name in LONG:
            marks.append(pytest.mark.long)
        yield pytest.param(sc, id=sc.name, marks=marks)


@pytest.mark.parametrize("sc", list(_cases()))
def test_scenario(sc):
    res = evaluate(sc)
    report = res["report"]
    check_report(report)
    found = res["found"]
    if not sc.effects:
        assert found == [], f"false finding(s) on a clean recording: {found}"
        return
    # strictly named, or named as an alternative where the test cannot separate it
    # (:func:`evaluation.scenarios.substitutes`: the exact set, cables and tolerances still hold)
    assert res["passed"] or res["alternative"], (found, res["why"])
    swap = res["alternative"] or {}
    named = [swap.get(e, e) for e in found]
    assert set(named) == set(sc.effects), found
    assert named[0] in sc.effects
    for f in report["findings"]:
        assert f["cables"] == expected_cables(sc, swap.get(f["effect"], f["effect"]))
        assert f["holdout_rmse_after_n"] < f["holdout_rmse_before_n"]
        # cumulative with jointly fitted parameters: a finding alone may not help the other
        # recording by itself (e.g. stribeck before the inertia it was fitted with), so a
        # 1 % allowance per finding; the final model must improve it outright (below)
        assert f["validation_rmse_after_n"] < 1.01 * f["validation_rmse_before_n"]
    for name, err in res["errors"].items():
        assert err <= 1.0, f"{name}: error {err:.2f} x tolerance"
    assert report["final"]["holdout_rmse_n"] < report["baseline"]["rmse_n"]
    fin = report["final"]
    assert fin["validation_rmse_after_n"] < fin["validation_rmse_before_n"]
    assert report["final"]["holdout_rmse_n"] < 1.05 * sc.noise_n


def test_delay_without_fast_edges_is_reported_as_unseparable_from_lowpass():
    """Slow signals only: a delay and a first-order filter fit alike; the report says so."""
    sc = Scenario("delay_no_edges", {"delay": {"d_s": 0.004}}, cables=1, edges=False)
    report = evaluate(sc)["report"]
    check_report(report)
    found = [f["effect"] for f in report["findings"]]
    assert len(found) == 1 and found[0] in ("delay", "lowpass")
    assert "cannot tell it from" in report["findings"][0]["evidence"]


def _finding(effect, cables, alts=()):
    out = {"effect": effect, "cables": cables, "parameters": {}}
    if alts:
        out["alternatives"] = [{"effect": a, "cables": cables, "parameters": {}} for a in alts]
    return out


def test_a_true_effect_counts_as_an_alternative_only_where_everything_else_holds():
    """The outcome "named as an alternative": the finding lists the true effect among the
    rivals the test could not separate from it, on the same cables; the exact set holds."""
    fits = lambda a: True  # noqa: E731
    found = [_finding("presliding", [1, 2], ["backlash"])]
    assert substitutes({"backlash"}, found, fits) == {"presliding": found[0]["alternatives"][0]}
    # not listed as an alternative, or not fitting (cables, parameters): no
    assert substitutes({"backlash"}, [_finding("presliding", [1, 2])], fits) is None
    assert substitutes({"backlash"}, found, lambda a: False) is None
    # the alternative on other cables than the finding: no
    other = _finding("presliding", [1, 2], ["backlash"])
    other["alternatives"][0]["cables"] = [1]
    assert substitutes({"backlash"}, [other], fits) is None
    # an extra finding, a true effect missing, a true effect twice: no
    assert substitutes({"backlash"}, [*found, _finding("offset", [1, 2])], fits) is None
    assert substitutes({"backlash", "offset"}, found, fits) is None
    twice = [_finding("backlash", [1, 2]), *found]
    assert substitutes({"backlash"}, twice, fits) is None
    # a strict result is no substitution
    assert substitutes({"backlash"}, [_finding("backlash", [1, 2])], fits) is None
