"""Pulley friction laws against closed forms (physics.md sec. 3)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from gateway.model.friction import coulomb_ratio_exact, dahl_step
from tests.model_reference import (
    capstan_ratio,
    coulomb_gain,
    coulomb_lambda,
    coulomb_ratio_small_angle,
    dahl_from_rest,
    normal_force,
)

WRAPS = np.radians([90.0, 60.0, 30.0])


@given(mu=st.floats(0.001, 0.3), wrap=st.floats(0.01, math.pi), s=st.sampled_from([-1.0, 1.0]))
def test_exact_coulomb_ratio_solves_eq_8_and_12(mu: float, wrap: float, s: float) -> None:
    n = coulomb_ratio_exact(mu, wrap, s)
    # n = 1 - s lambda(n), with the sign of the direction (paying out: sensor side lower)
    assert n == pytest.approx(1.0 - s * coulomb_lambda(n, mu, wrap), abs=1e-12)
    assert (n < 1.0) if s > 0 else (n > 1.0)


def test_exact_ratio_roots_are_reciprocal() -> None:
    for mu, wrap in [(0.015, WRAPS[0]), (0.1, WRAPS[2]), (0.2, math.pi)]:
        assert coulomb_ratio_exact(mu, wrap, 1) * coulomb_ratio_exact(mu, wrap, -1) == (
            pytest.approx(1.0, abs=1e-14)
        )


@pytest.mark.parametrize("mu", [0.005, 0.015, 0.05])
def test_small_angle_shortcut_agrees_to_second_order(mu: float) -> None:
    for wrap in WRAPS:
        for s in (-1.0, 1.0):
            exact = coulomb_ratio_exact(mu, wrap, s)
            approx = coulomb_ratio_small_angle(mu, wrap, s)
            # they differ by O(mu^2): (2 mu sin(a/2))^2 / 2 plus the 1/sqrt(1-mu^2) factor
            assert abs(exact - approx) <= 4.0 * mu**2
            assert abs(exact - approx) > 0.0


def test_coulomb_gain_of_the_three_pulleys() -> None:
    mu = np.full(3, 0.015)
    gain_out = coulomb_gain(mu, WRAPS, 1.0)
    gain_in = coulomb_gain(mu, WRAPS, -1.0)
    expected_out = 1.0
    for a in WRAPS:
        expected_out /= coulomb_ratio_exact(0.015, a, 1.0)
    assert gain_out == pytest.approx(expected_out, rel=1e-14)
    assert gain_out * gain_in == pytest.approx(1.0, rel=1e-12)  # reciprocal directions
    assert coulomb_gain(mu, WRAPS, 0.0) == 1.0
    # first order: sum over pulleys of 2 mu sin(a/2); the rest is ~(sum)^2 / 2, ~2 %
    assert gain_out - 1.0 == pytest.approx(sum(2 * 0.015 * np.sin(WRAPS / 2)), rel=0.05)


def test_normal_force_equal_tensions() -> None:
    assert_allclose(normal_force(100.0, 100.0, WRAPS), 2 * 100.0 * np.sin(WRAPS / 2), rtol=1e-14)


def test_capstan_direction() -> None:
    assert capstan_ratio(0.1, math.pi, 1.0) == pytest.approx(math.exp(0.1 * math.pi))
    assert capstan_ratio(0.1, math.pi, -1.0) == pytest.approx(math.exp(-0.1 * math.pi))


@pytest.mark.parametrize("step_m", [1e-5, 4e-5, 1e-3])
def test_dahl_steps_from_rest_equal_eq_15(step_m: float) -> None:
    f_r, sigma = 4.0, 500.0
    f = 0.0
    x = np.arange(1, 400) * step_m
    got = np.empty_like(x)
    for k in range(x.size):
        f = dahl_step(f, f_r, step_m, sigma, 1.0)
        got[k] = f
    assert_allclose(got, dahl_from_rest(x, f_r, sigma), rtol=1e-12, atol=1e-12)
    # and backwards from rest: odd symmetry
    assert dahl_step(0.0, f_r, -step_m, sigma, 1.0) == pytest.approx(
        -dahl_step(0.0, f_r, step_m, sigma, 1.0), rel=1e-14
    )


def test_dahl_tends_to_coulomb_level_and_never_overshoots() -> None:
    f_r, sigma = 3.0, 500.0
    f = -f_r
    for _ in range(2000):
        f = dahl_step(f, f_r, 1e-3, sigma, 1.0)
        assert -f_r <= f <= f_r
    assert f == pytest.approx(f_r, rel=1e-12)
    assert dahl_step(0.5, f_r, 0.0, sigma, 1.0) == 0.5  # no travel, no change


@pytest.mark.parametrize("beta", [0.5, 1.0, 2.0, 3.0])
def test_general_beta_matches_fine_integration(beta: float) -> None:
    f_r, sigma, travel = 4.0, 500.0, 0.01
    coarse = dahl_step(-1.0, f_r, travel, sigma, beta)  # one exact step
    fine = -1.0
    h = travel / 200_000
    for _ in range(200_000):  # explicit Euler with a tiny step as the reference
        z = 1.0 - fine / f_r
        fine += h * sigma * math.copysign(abs(z) ** beta, z)
    assert coarse == pytest.approx(fine, abs=2e-4)


@pytest.mark.parametrize("beta", [0.5, 1.0, 2.0])
def test_dahl_unconditionally_stable_for_huge_steps(beta: float) -> None:
    # sigma |dx| / F_R = 1e4: explicit Euler would explode; the closed form lands on F_R
    assert dahl_step(-2.0, 2.0, 40.0, 500.0, beta) == pytest.approx(2.0, abs=1e-3)
    assert dahl_step(2.0, 2.0, -40.0, 500.0, beta) == pytest.approx(-2.0, abs=1e-3)


def test_beta_one_is_the_limit_of_general_beta() -> None:
    a = dahl_step(0.3, 4.0, 2e-3, 500.0, 1.0)
    b = dahl_step(0.3, 4.0, 2e-3, 500.0, 1.0 + 1e-7)
    assert a == pytest.approx(b, abs=1e-6)
