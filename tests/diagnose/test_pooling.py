"""Cables that share a design share evidence (:mod:`gateway.diagnose.pooling`): the pooled
statistic and the partial pooling as properties, and the diagnosis of 4-cable recordings
from the independent generator (:mod:`tests.diagnose_helpers`): a weak effect every cable
shares, the same effect on one cable only, and a clean machine."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.core.config import FrictionConfig, PulleyConfig
from gateway.diagnose.engine import diagnose
from gateway.diagnose.pooling import (
    departure,
    jointly,
    normal_score,
    on_cable,
    pooled_tests,
    richer,
    shrink,
    stouffer,
)
from gateway.diagnose.selection import Model, Outcome, Selector, Thresholds
from gateway.diagnose.significance import Tested as Scored
from gateway.diagnose.significance import candidate_tests
from tests.diagnose.linear_unit import LinearUnit
from tests.diagnose_helpers import Foreign, check_report, generate, recording_of

estimates = st.lists(
    st.tuples(
        st.floats(-1e3, 1e3, allow_nan=False),
        st.floats(1e-3, 1e2, allow_nan=False),
    ),
    min_size=2,
    max_size=8,
)


@given(rows=estimates, seed=st.integers(0, 2**16))
def test_shrinkage_moves_each_estimate_toward_the_common_value(rows, seed) -> None:
    """Each shrunk estimate lies between the cable's own and the common value, the common
    value within the estimates' range, the between-cable spread is not negative, and the
    result does not depend on the order of the cables."""
    y = np.array([r[0] for r in rows])
    s = np.array([r[1] for r in rows])
    mu, tau, out = shrink(y, s)
    tol = 1e-9 * (1.0 + np.abs(y).max())
    assert y.min() - tol <= mu <= y.max() + tol
    assert tau >= 0.0
    lo, hi = np.minimum(y, mu), np.maximum(y, mu)
    assert np.all(out >= lo - tol) and np.all(out <= hi + tol)
    perm = np.random.default_rng(seed).permutation(y.size)
    mu2, tau2, out2 = shrink(y[perm], s[perm])
    # summation order only: relative 1e-6 (weights 1/s^2 span up to 1e10)
    loose = 1e-6 * (1.0 + np.abs(y).max())
    assert mu2 == pytest.approx(mu, abs=loose) and tau2 == pytest.approx(tau, abs=loose)
    np.testing.assert_allclose(out2, out[perm], atol=loose)


@given(value=st.floats(-1e3, 1e3, allow_nan=False), s=estimates)
def test_equal_estimates_are_not_moved(value, s) -> None:
    y = np.full(len(s), value)
    mu, tau, out = shrink(y, np.array([r[1] for r in s]))
    assert tau == 0.0
    np.testing.assert_allclose(out, y, atol=1e-9 * (1 + abs(value)))
    assert mu == pytest.approx(value, abs=1e-9 * (1 + abs(value)))


def test_a_precise_estimate_far_from_the_others_keeps_its_value() -> None:
    """Cables that truly differ borrow little: tau is large against a precise cable's
    error."""
    _mu, tau, out = shrink(np.array([10.0, 10.5, 9.5, 40.0]), np.array([1.0, 1.0, 1.0, 0.1]))
    assert tau > 5.0
    assert out[3] == pytest.approx(40.0, abs=0.1)


@given(
    ps=st.lists(st.floats(1e-12, 1.0 - 1e-12), min_size=1, max_size=8),
    seed=st.integers(0, 2**16),
)
def test_stouffer_is_symmetric_and_grows_with_agreeing_evidence(ps, seed) -> None:
    z, p = stouffer(ps)
    perm = list(np.random.default_rng(seed).permutation(len(ps)))
    z2, _ = stouffer([ps[i] for i in perm])
    assert z2 == pytest.approx(z, abs=1e-9)
    assert 0.0 <= p <= 1.0
    same, _ = stouffer([ps[0]] * len(ps))
    assert same == pytest.approx(math.sqrt(len(ps)) * normal_score(ps[0]), rel=1e-9, abs=1e-9)


def _friction(fo: Foreign) -> FrictionConfig:
    return FrictionConfig(
        model=fo.model,  # type: ignore[arg-type]
        pulleys=tuple(PulleyConfig(w, m) for w, m in fo.pulleys),
        sigma_n_m=fo.sigma_n_m,
    )


FOUR = Foreign(cables=4, seconds=10.0, noise_n=1.5, seed=3)


def test_weak_effect_every_cable_shares_is_found_on_every_cable() -> None:
    """A viscous coefficient of 4 N s/m on four cables under 1.5 N of noise: alone, no
    cable's evidence survives the false-discovery control (main kept nothing); pooled, it
    is common to the four, each cable's value near the truth and the shrunk values closer
    together than the cables' own."""
    fo = replace(FOUR, effects={"viscous": {"c_ns_m": 4.0}})
    rep = diagnose(recording_of(generate(fo)), _friction(fo)).report
    check_report(rep)
    found = {f["effect"]: f for f in rep["findings"]}
    assert list(found) == ["viscous"]
    f = found["viscous"]
    assert f["cables"] == [1, 2, 3, 4]
    pool = f["pooling"]
    assert pool["scope"] == "common" and pool["differs"] == []
    assert pool["statistic"] >= 4.0
    own = np.array(f["parameters"]["c_ns_m"])
    shrunk = np.array(pool["parameters"]["c_ns_m"])
    np.testing.assert_allclose(own, 4.0, rtol=0.3)
    assert np.ptp(shrunk) <= np.ptp(own) + 1e-12
    assert pool["common_parameters"]["c_ns_m"] == pytest.approx(4.0, rel=0.15)


def test_effect_on_one_cable_stays_on_that_cable() -> None:
    """Viscous friction on cable 1 only (the other three clean, the same motions' seed):
    pooling does not spread it to the clean cables."""
    fo = replace(FOUR, noise_n=0.5)
    clean = generate(fo)
    hot = generate(replace(fo, effects={"viscous": {"c_ns_m": 30.0}}))
    cols = dict(clean)
    for k in ("velocity_1", "tension_sensor_1", "tension_platform_1"):
        cols[k] = hot[k]
    rep = diagnose(recording_of(cols), _friction(fo)).report
    check_report(rep)
    assert [(f["effect"], f["cables"]) for f in rep["findings"]] == [("viscous", [1])]
    assert rep["findings"][0]["pooling"]["scope"] == "cable_specific"


def test_clean_four_cables_give_no_finding() -> None:
    rep = diagnose(recording_of(generate(FOUR)), _friction(FOUR)).report
    check_report(rep)
    assert rep["findings"] == []


def _linear(y: np.ndarray, x: np.ndarray, tension: np.ndarray) -> LinearUnit:
    """A cable whose effects are linear columns: ``offset`` a constant, ``spring`` the
    length and a constant (it nests the offset), ``gain`` the tension."""
    one = np.ones(y.size)
    cols = {"offset": one[:, None], "spring": np.column_stack([x, -one]), "gain": tension[:, None]}
    return LinearUnit(y, cols)


def _cable(spring_k: float, seed: int, offset: float = 5.0) -> LinearUnit:
    """A cable with an ``offset`` and a 4 % gain (and a spring of ``spring_k`` N/m), its
    length and tension varying together (so a spring stands in for part of the offset and
    gain), 2 N of noise."""
    rng = np.random.default_rng(seed)
    n = 4000
    x = 2.0 + 0.5 * np.sin(np.linspace(0.0, 12.0, n))
    tension = 100.0 + 40.0 * (x - 2.0) + 5.0 * np.sin(np.linspace(0.0, 31.0, n))
    y = offset + 0.04 * tension + spring_k * (x - 2.0) + rng.normal(0.0, 2.0, n)
    return _linear(y, x, tension)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_stand_in_gives_way_to_the_common_effects(seed) -> None:
    """A cable that kept a spring (it holds the offset and part of the gain) gets the
    machine's common offset and gain in its place: the spring does not beat them on the
    cable's own held-out blocks by the strict test."""
    unit = _cable(0.0, seed)
    sel = Selector(unit, Thresholds())
    own = sel.fit({"spring": np.zeros(2)}, {"spring": None})
    values = {"offset": np.array([5.0]), "gain": np.array([0.04])}
    got = on_cable(sel, own, ["offset", "gain"], values, ["offset", "gain"], Thresholds())
    assert got is not None and set(got.kept) == {"offset", "gain"}
    assert got.kept["offset"][0] == pytest.approx(5.0, abs=1.5)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_cable_specific_effect_that_beats_the_common_ones_stays(seed) -> None:
    """A true spring of 30 N/m on the cable (beside the offset and gain): its own model
    beats the common effects on its held-out blocks, and the cable keeps it."""
    unit = _cable(30.0, seed)
    sel = Selector(unit, Thresholds())
    own = sel.fit({"spring": np.zeros(2), "gain": np.zeros(1)}, {"spring": None, "gain": None})
    values = {"offset": np.array([5.0])}
    got = on_cable(sel, own, ["offset"], values, ["offset", "gain"], Thresholds())
    assert got is own


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("common", [5.0, 9.0])
def test_a_common_value_an_other_effect_absorbed_is_not_refused(seed, common) -> None:
    """The cable kept a gain alone, which took part of its 5 N offset: the common offset
    on top of it, not refitted, counts that part twice (or is off: 9 N, fitted beside a
    stand-in on the other cables) and is worse on held-out blocks, but fitted with the
    gain it lowers the cable's held-out error: the cable gets it, at its own value."""
    unit = _cable(0.0, seed)
    sel = Selector(unit, Thresholds())
    own = sel.fit({"gain": np.zeros(1)}, {"gain": None})
    value = {"offset": np.array([common])}
    at = unit.evaluate({**own.kept, **value}, {})
    assert sel.z(own, at) <= -Thresholds().z_screen  # the un-refitted check refuses
    got = on_cable(sel, own, ["offset"], value, ["offset"], Thresholds())
    assert got is not None and set(got.kept) == {"offset", "gain"}
    assert got.kept["offset"][0] == pytest.approx(5.0, abs=1.5)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_clean_cable_refuses_the_common_value(seed) -> None:
    """No offset on this cable: the others' 5 N is refused on its data both ways (on top
    of its model, and fitted with it), and it stays without."""
    unit = _cable(0.0, seed, offset=0.0)
    sel = Selector(unit, Thresholds())
    own = sel.fit({"gain": np.zeros(1)}, {"gain": None})
    got = on_cable(sel, own, ["offset"], {"offset": np.array([5.0])}, ["offset"], Thresholds())
    assert got is None


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_common_effects_that_do_not_conflict_are_on_both_sides(seed) -> None:
    """A true spring of 30 N/m beside the offset and gain; the cable kept the spring alone.
    The common offset conflicts with the spring, the common gain does not: the cable's own
    model is compared with the gain in it too, wins, and keeps the spring with the gain
    (not the spring without the gain the machine shares)."""
    unit = _cable(30.0, seed)
    sel = Selector(unit, Thresholds())
    own = sel.fit({"spring": np.zeros(2)}, {"spring": None})
    values = {"offset": np.array([5.0]), "gain": np.array([0.04])}
    got = on_cable(sel, own, ["offset", "gain"], values, ["offset", "gain"], Thresholds())
    assert got is not None and set(got.kept) == {"spring", "gain"}
    assert abs(got.kept["gain"][0] - 0.04) <= 4.0 * got.stderr["gain"][0]  # 0.2 N under 2 N


def _tested(kept: dict[str, float], screened: dict[str, float]) -> Scored:
    """A scored cable: its kept effects' and its screened candidates' one-sided p-values."""
    theta = {e: np.zeros(1) for e in kept}
    tests = {e: {"z": normal_score(p), "p": p} for e, p in {**kept, **screened}.items()}
    out = Outcome(list(kept), theta, {}, {}, tests=tests)
    return Scored(None, Model(theta, {}, {}, np.zeros(0)), out)


@given(
    springs=st.integers(2, 4),
    offsets=st.integers(2, 6),
    p=st.floats(1e-12, 1e-6),
)
def test_of_two_common_effects_that_nest_the_simpler_is_common(springs, offsets, p) -> None:
    """A spring kept on some cables (tested there against nothing, its offset part
    included) and the offset it nests on the others, both strongly: the offset is the
    machine's common effect, the spring is not (its extra freedom was never tested across
    the cables), so the spring cannot keep the common offset off the cables that kept it."""
    units = [_tested({"spring": p}, {}) for _ in range(springs)]
    units += [_tested({"offset": p}, {}) for _ in range(offsets)]
    pooled = pooled_tests(units, Thresholds())
    assert pooled["offset"].common
    assert not pooled["spring"].common


def _spread(seed: int, offset: float) -> LinearUnit:
    """A cable of :func:`_cable`'s kind with its length and tension apart (a gain and an
    offset told apart) and ``offset`` N on it, 2 N of noise."""
    rng = np.random.default_rng(seed)
    n = 4000
    x = 2.0 + 0.5 * np.sin(np.linspace(0.0, 12.0, n) + seed)
    tension = 100.0 + 60.0 * np.sin(np.linspace(0.0, 31.0, n) + 2.0 * seed)
    return _linear(offset + 0.04 * tension + rng.normal(0.0, 2.0, n), x, tension)


def _machine(offset: float, seed: int, cables: int = 8) -> tuple[list[Scored], dict]:
    """Each cable selected on its own and scored (its candidates' held-out tests), then
    the pooled tests and the joint test over them."""
    th = Thresholds()
    units = []
    for k in range(cables):
        sel = Selector(_spread(seed * cables + k, offset), th)
        out = sel.run()
        m = sel.final
        tests = candidate_tests(sel, m)
        units.append(Scored(sel, m, Outcome(out.kept, m.kept, m.stderr, m.specs, tests=tests)))
    pooled = pooled_tests(units, th)
    values = jointly(units, pooled, th, lambda u: (u.selector, u.model))
    return units, {e: (r, values.get(e)) for e, r in pooled.items()}


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_an_effect_no_cable_kept_alone_is_common_by_the_joint_test(seed) -> None:
    """0.5 N of offset on eight cables under 2 N of noise: no cable keeps it on its own
    evidence (its share of the held-out error is below the forward step's), the cables'
    joint fits pool to a common offset near the truth; the spring that nests it is not
    common (its extra freedom over the offset is nothing)."""
    units, pooled = _machine(0.5, seed)
    assert not any("offset" in u.model.kept for u in units)
    offset, value = pooled["offset"]
    assert offset.common and offset.statistic >= Thresholds().z_holdout
    assert value is not None and value[0] == pytest.approx(0.5, abs=0.25)
    assert "spring" not in pooled or not pooled["spring"][0].common


@pytest.mark.parametrize("seed", range(8))
def test_the_joint_test_finds_nothing_on_clean_cables(seed) -> None:
    """No offset: nothing the cables did not keep becomes common."""
    _, pooled = _machine(0.0, seed)
    assert {e for e, (r, _) in pooled.items() if r.common} == {"gain"}
    assert all(v is None for _, v in pooled.values())


def _stiff(seed: int, k: float, cables: int = 8) -> list[Scored]:
    """Cables of :func:`_spread`'s kind with a 3 N offset and a spring of ``k`` N/m on
    top, each selected on its own and scored."""
    th = Thresholds()
    units = []
    for j in range(cables):
        cab = _spread(seed * cables + j, 3.0)
        x = cab.cols["spring"][:, 0]
        cab.y = cab.y + k * (x - 2.0)
        sel = Selector(cab, th)
        out = sel.run()
        m = sel.final
        tests = candidate_tests(sel, m)
        units.append(Scored(sel, m, Outcome(out.kept, m.kept, m.stderr, m.specs, tests=tests)))
    return units


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_richer_effect_every_cable_shares_is_common_by_its_joint_test(seed) -> None:
    """A stiffness of 0.7 N/m (0.35 N over the cable's length swing) on top of a 3 N
    offset, eight cables under 2 N of noise: too small for most cables to keep the spring
    over the offset on their own (it must beat the offset by z_holdout there), the offset
    is common at first; tested on the cables jointly against the offset, the spring is
    common in its place, its common stiffness near the truth, and every cable then
    carries it."""
    th = Thresholds()
    units = _stiff(seed, 0.7)
    alone = sum("spring" in u.model.kept for u in units)
    assert alone < len(units) / 2
    first = pooled_tests(units, th)
    assert first["offset"].common and not ("spring" in first and first["spring"].common)
    values = richer(units, first, th, lambda u: (u.selector, u.model))
    assert first["spring"].common and not first["offset"].common
    assert first["spring"].statistic >= th.z_holdout and first["spring"].loo >= th.z_screen
    assert values["spring"][0] == pytest.approx(0.7, abs=0.2)
    common = [e for e, r in first.items() if r.common]
    for u in units:  # what extend does on each cable that lacks the common spring
        if "spring" in u.model.kept:
            continue
        got = on_cable(u.selector, u.model, ["spring"], values, common, th)
        assert got is not None and "spring" in got.kept and "offset" not in got.kept


@pytest.mark.parametrize("seed", range(6))
def test_the_richer_effect_is_not_common_where_the_cables_show_none(seed) -> None:
    """The same cables without a spring: the offset stays common and the spring is not,
    on every cable."""
    th = Thresholds()
    units = _stiff(seed, 0.0)
    pooled = pooled_tests(units, th)
    assert richer(units, pooled, th, lambda u: (u.selector, u.model)) == {}
    assert pooled["offset"].common
    assert "spring" not in pooled or not pooled["spring"].common


@given(
    d=st.floats(-1e3, 1e3, allow_nan=False),
    s=st.floats(1e-3, 1e2, allow_nan=False),
    k=st.integers(2, 8),
)
def test_equal_departures_lie_their_pooled_standard_errors_from_none(d, s, k) -> None:
    """k cables that agree on a departure d, each with standard error s: no spread
    between them, so the pooled error is s / sqrt(k) and the departure |d| sqrt(k) / s
    of them from none, whatever its sign."""
    got = departure([d] * k, [s] * k)
    assert got == pytest.approx(abs(d) * math.sqrt(k) / s, rel=1e-9, abs=1e-9)
    assert departure([-d] * k, [s] * k) == pytest.approx(got, rel=1e-12, abs=1e-12)


@given(rows=estimates)
def test_a_departure_without_two_usable_errors_is_none(rows) -> None:
    d = [y for y, _ in rows]
    assert departure(d[:1], [1.0]) == 0.0
    assert departure(d, [float("nan")] * len(d)) == 0.0
