"""Findings by significance, uncertainty from the data, ambiguity said, and what lies
beyond the catalogue (gateway/diagnose/stats.py, significance.py, signals.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evaluation.scenarios import Scenario, _truth_chain, make_recording, motion
from gateway.diagnose.engine import diagnose
from gateway.diagnose.stats import bh_qvalues, jackknife_se, p_value, sign_test_p
from gateway.model.chain_runs import run
from gateway.recordings.reader import Recording
from tests.diagnose_helpers import check_report


@given(st.lists(st.floats(0.0, 1.0), min_size=1, max_size=60))
@settings(max_examples=200)
def test_bh_qvalues_are_monotone_and_at_least_p(ps: list[float]) -> None:
    q = bh_qvalues(ps)
    p = np.asarray(ps)
    assert np.all(q >= p - 1e-15) and np.all(q <= 1.0)
    order = np.argsort(p)
    assert np.all(np.diff(q[order]) >= -1e-15)  # the same order as the p-values


def test_bh_matches_the_step_up_rule() -> None:
    p = np.array([0.001, 0.008, 0.039, 0.041, 0.042, 0.06, 0.074, 0.205, 0.212, 0.216])
    q = bh_qvalues(p)
    rejected = set(np.flatnonzero(q <= 0.05))
    k = max(i for i in range(1, 11) if sorted(p)[i - 1] <= 0.05 * i / 10)  # the rule itself
    assert rejected == set(np.argsort(p)[:k])


def test_p_value_takes_the_blocks_degrees_of_freedom() -> None:
    assert p_value(3.0, 5) > p_value(3.0, 20) > 1 - 0.99865  # fewer blocks: less evidence
    assert p_value(-1.0, 10) > 0.5
    assert p_value(math.inf, 10) == 0.0 and p_value(math.nan, 10) == 1.0
    assert sign_test_p(10, 10) == pytest.approx(0.5**10)
    assert sign_test_p(0, 10) == 1.0


def test_jackknife_of_a_mean_is_its_standard_error() -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(size=(400,))
    groups = np.array([np.mean(np.delete(x, np.s_[k::8])) for k in range(8)])[:, None]
    assert jackknife_se(groups)[0] == pytest.approx(np.std(x) / math.sqrt(400), rel=0.6)


def _diag(sc: Scenario):
    rec = make_recording(sc)
    return diagnose(rec, sc.nominal()).report


def test_every_finding_carries_its_test_and_both_errors() -> None:
    rep = _diag(Scenario("v", {"viscous": {"c_ns_m": 6.0}}, seconds=20.0))
    check_report(rep)
    (f,) = rep["findings"]
    assert f["effect"] == "viscous"
    for key in ("statistic", "p", "q"):
        assert len(f[key]) == len(f["cables"])
    assert all(q <= rep["significance"]["fdr"] for q in f["q"])
    assert all(z > 4 for z in f["statistic"])
    se, jac, blk = (f[k]["c_ns_m"] for k in ("stderr", "stderr_jacobian", "stderr_blocks"))
    assert np.all(np.asarray(se) >= np.asarray(jac)) and np.all(np.asarray(se) >= np.asarray(blk))
    assert rep["significance"]["tests"] >= 2 * 10  # every candidate on both cables


def test_a_coefficient_at_its_nominal_value_is_not_a_finding() -> None:
    """The issue's case: a Coulomb mu equal to the nominal's (0.015) with f0 ~ 0 fitted on
    a clean recording must not be reported as missing physics."""
    for seed in (11, 12, 13):
        rep = _diag(Scenario("clean", {}, seed=seed, seconds=20.0))
        assert rep["findings"] == [], [f["effect"] for f in rep["findings"]]
        assert "unexplained" not in rep


def test_delay_and_lowpass_without_fast_edges_are_said_to_be_alternatives() -> None:
    """Without fast load steps a delay and a low-pass fit about as well: the report says so
    (one finding, the other as an alternative, and the motion that would separate them)."""
    rep = _diag(Scenario("lag", {"delay": {"d_s": 0.004}}, edges=False, seconds=20.0))
    named = [f["effect"] for f in rep["findings"]]
    assert len(named) == 1 and named[0] in ("delay", "lowpass"), named
    f = rep["findings"][0]
    alts = {a["effect"] for a in f.get("alternatives", [])}
    assert alts & ({"delay", "lowpass"} - {f["effect"]}), f.get("alternatives")
    assert f["separate_by"] and "faster" in f["separate_by"]
    assert "cannot tell it from" in f["evidence"]


def test_unexplained_names_a_temperature_column_outside_the_catalogue() -> None:
    """A sensor zero that follows the temperature (a strain gauge's thermal drift, which
    the catalogue has no effect for): the report names the temperature column first."""
    sc = Scenario("thermal", {}, seed=4, seconds=30.0)
    t, v, tp = motion(sc)
    temp = 25.0 + 4.0 * np.sin(2 * np.pi * t / 17.0) + 2.0 * np.sin(2 * np.pi * t / 5.3)
    ts = run(_truth_chain(sc, 2), "simulate", tp, v, t) + 0.3 * (temp - 25.0)[:, None]
    ts = ts + np.random.default_rng(5).normal(0.0, 0.4, ts.shape)
    rec = Recording(
        t=t,
        velocity=v,
        tension_sensor=ts,
        tension_platform=tp,
        extra={"temperature_c": temp},
        metadata={},
    )
    rep = diagnose(rec, sc.nominal()).report
    check_report(rep)
    un = rep["unexplained"]
    assert un["signal"] == "column temperature_c", un["ranking"]
    assert un["share"] > 0.3
    assert "temperature_c" in un["reading"]
    clean = diagnose(
        Recording(
            t=t,
            velocity=v,
            tension_sensor=ts - 0.3 * (temp - 25.0)[:, None],
            tension_platform=tp,
            extra={"temperature_c": temp},
            metadata={},
        ),
        sc.nominal(),
    ).report
    assert "unexplained" not in clean


def _dahl_with_load_level(t, v, tp, c0: float, k: float, sigma: float) -> np.ndarray:
    """Friction outside the catalogue, written here and not with the project's model: a Dahl
    state (exact exponential step over the trapezoid travel) whose level grows with the
    square of the tension, ``F_R = c0 + k T^2``; positive while the cable moves out."""
    f = np.zeros_like(tp)
    for j in range(v.shape[1]):
        state = 0.0
        for i in range(1, t.size):
            dx = 0.5 * (v[i - 1, j] + v[i, j]) * (t[i] - t[i - 1])
            level = c0 + k * tp[i, j] ** 2
            if dx != 0.0:
                s = math.copysign(1.0, dx)
                state = s * level + (state - s * level) * math.exp(-sigma * abs(dx) / level)
            f[i, j] = state
    return f


# Since coulomb_load (mu = mu0 + mu1 |T|, a Coulomb level growing with T^2) is in the
# catalogue, this friction is no longer beyond it: the catalogue takes part of it as
# coulomb_load and what it leaves is ranked with sgn(v)*T^2 no longer first (2026-11-29,
# measured: seed 1, 30 s: coulomb_load on cable 2 only, mu1 5.3e-6 1/N, unexplained 'v'
# 44 % then sgn(v)*T^2 40 %; 0.3 N + 3e-5 T^2, 120 s: coulomb_load on both cables beside
# maxwell_slip / presliding, unexplained sgn(v)*T 6.1 % then sgn(v)*T^2 5.9 %). Open: the
# test becomes a catalogue test (coulomb_load on every cable, in tolerance, nothing left).
# The 120-s case (seed 1, 0.3 N + 3e-5 T^2, share 0.1) was a third strict xfail of the same
# reason: 400 s of one test worker in `make test-long` (2026-11-29, load 5) to show again
# what the 30-s seed-1 case shows; it is gone, its figures are the ones above.
IN_CATALOGUE = (
    "coulomb_load is in the catalogue since 2026-11-29: the T^2 friction is partly found as "
    "coulomb_load (not on every cable) and the rest is not ranked sgn(v)*T^2 first"
)


@pytest.mark.long
@pytest.mark.parametrize(
    ("seed", "c0", "k", "seconds", "share"),
    [
        pytest.param(
            1,
            0.0,
            2e-5,
            30.0,
            0.3,
            marks=pytest.mark.xfail(strict=True, reason=IN_CATALOGUE),
        ),
        pytest.param(
            3,
            0.0,
            2e-5,
            30.0,
            0.3,
            marks=pytest.mark.xfail(
                strict=True,
                reason="open since the cables pool their evidence (issue 29, "
                "gateway/diagnose/pooling.py): on seed 3 the report no longer carries "
                "'unexplained' (KeyError); the T^2 friction is absorbed, not named",
            ),
        ),
    ],
)
def test_unexplained_names_a_friction_growing_with_the_square_of_the_tension(
    seed: int, c0: float, k: float, seconds: float, share: float
) -> None:
    """The issue's example beyond the catalogue: a pulley friction whose level grows with
    T^2 (0.15-1.5 N over this motion's 85-275 N). The catalogue's Coulomb level is linear
    in T, so what it leaves is named: ``sgn(v)*T^2`` first, read as a coefficient rising
    with the load. With a load-independent part beside it (0.3 N + 3e-5 T^2) the catalogue
    takes a Coulomb and a presliding stiffness first and leaves less (13-18 %); 30 s of
    seed 1 then name ``v`` first (59 % against 50 %; after ``v``, ``sgn(v)*T^2`` explains
    9 % more at q 0.65: 30 s cannot tell them apart), 120 s name ``sgn(v)*T^2`` (seeds 1
    and 3 by hand: 13 % and 18 %)."""
    sc = Scenario("t2", {}, seed=seed, seconds=seconds)
    t, v, tp = motion(sc)
    ts = run(_truth_chain(sc, 2), "simulate", tp, v, t) - _dahl_with_load_level(
        t, v, tp, c0, k, 2e3
    )
    ts = ts + np.random.default_rng(seed + 100).normal(0.0, 0.4, ts.shape)
    rec = Recording(t=t, velocity=v, tension_sensor=ts, tension_platform=tp, metadata={})
    rep = diagnose(rec, sc.nominal()).report
    check_report(rep)
    un = rep["unexplained"]
    assert un["signal"] == "sgn(v)*T^2", un["ranking"]
    assert un["q"] <= rep["significance"]["fdr"] and un["share"] > share
    assert "rises with the load" in un["reading"]


@pytest.mark.long
def test_clean_recordings_of_random_foreign_machines_give_no_finding() -> None:
    """The significance promise as a rate, on physics not written for it: 30 clean
    recordings of the independent generator, each machine drawn as the sealed suite draws
    them (1-4 pulleys, Coulomb or Dahl chain, 200-1000 Hz, jitter, five noise kinds at
    0.15-0.5 N, moves or positioning, 1-3 cables) but from another seed. Each recording's
    tests are held at a false-discovery rate of 1 %, so a finding or an ``unexplained``
    entry should come on about 1 in 100 recordings at most; more than 1 of 30 fails (that is
    below 0.4 % likely at the promised rate). Measured on 2026-11-28: 0 of 30."""
    from tests import foreign_sealed
    from tests.diagnose_helpers import Foreign, run_foreign

    rng = np.random.default_rng(20261128)
    false = []
    for k in range(30):
        machine = foreign_sealed._machine(rng, 7000 + k)
        rep = run_foreign(Foreign(seconds=20.0, **machine)).report
        named = [f["effect"] for f in rep["findings"]]
        if named or "unexplained" in rep:
            false.append((k, machine, named, rep.get("unexplained", {}).get("signal")))
    assert len(false) <= 1, false
