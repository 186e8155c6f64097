"""The diagnosis' one robust noise estimator (gateway/diagnose/stats.white_noise)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.diagnose.stats import white_noise


@given(
    sigma=st.floats(0.01, 10.0),
    slope=st.floats(-1e-2, 1e-2),
    seed=st.integers(0, 2**32 - 1),
)
def test_white_noise_reads_the_noise_under_a_slow_drift(sigma, slope, seed) -> None:
    rng = np.random.default_rng(seed)
    r = rng.normal(0.0, sigma, 20_000) + slope * sigma * np.arange(20_000)
    for order in (1, 2):
        assert white_noise(r, order) == pytest.approx(sigma, rel=0.05)


def test_the_second_difference_ignores_ramps_and_steps_of_a_setpoint() -> None:
    """A piecewise-linear setpoint has no noise: order 2 says 0, order 1 does not."""
    v = np.concatenate([np.linspace(0, 0.5, 500), np.full(500, 0.5), np.linspace(0.5, -0.5, 500)])
    assert white_noise(v, order=2) == pytest.approx(0.0, abs=1e-12)
    assert white_noise(v, order=1) > 1e-4


def test_too_short_a_series_has_no_estimate() -> None:
    assert white_noise(np.array([1.0, 2.0]), order=1) == 0.0
    assert white_noise(np.array([1.0, 2.0, 3.0]), order=2) == 0.0
