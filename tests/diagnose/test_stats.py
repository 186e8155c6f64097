"""The diagnosis' one robust noise estimator (gateway/diagnose/stats.white_noise) and its
standard errors across time blocks and trials (block_groups, jackknife_se)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.diagnose.stats import block_groups, jackknife_se, white_noise
from gateway.diagnose.timebase import gap_segments, time_blocks


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


def _trials(rng: np.random.Generator, trials: int, spread: float):
    """``trials`` 20 s trials joined 1 s apart, ``y = a_k x + noise`` with each trial's
    slope ``a_k`` drawn around 1 with std ``spread`` (a model-form error that each trial's
    conditions make different): t, x, y."""
    ts, xs, ys, start = [], [], [], 0.0
    for k in range(trials):
        t = np.arange(0.0, 20.0, 0.01)
        x = np.sin(2 * math.pi * (0.1 + 0.05 * k) * t)
        a = 1.0 + rng.normal(0.0, spread)
        ts.append(t + start)
        xs.append(x)
        ys.append(a * x + rng.normal(0.0, 0.3, t.size))
        start = ts[-1][-1] + 1.0
    return np.concatenate(ts), np.concatenate(xs), np.concatenate(ys)


@pytest.mark.parametrize("trials", [4, 9])
def test_block_errors_of_a_recording_of_trials_cover_the_spread_between_recordings(trials):
    """The truth's spread is known: the slope fitted on the training blocks of many
    recordings of ``trials`` trials, each trial with its own slope. The jackknife's error
    from one recording, leaving out whole trials, is that spread (rms over recordings
    within 25 %); leaving out interleaved blocks of every trial understates it."""
    rng = np.random.default_rng(7)
    fitted: list[float] = []
    by_trial: list[float] = []
    by_block: list[float] = []
    for _ in range(150):
        t, x, y = _trials(rng, trials, 0.1)
        blocks, _ = time_blocks(t)
        train = blocks % 2 == 0

        def slope(m: np.ndarray, x=x, y=y) -> np.ndarray:
            return np.array([x[m] @ y[m] / (x[m] @ x[m])])

        fitted.append(slope(train)[0])
        for segs, out in ((gap_segments(t), by_trial), (None, by_block)):
            masks = block_groups(blocks, train, 8, segs)
            out.append(jackknife_se(np.stack([slope(m) for m in masks]))[0])
    truth = float(np.std(fitted))
    assert math.sqrt(np.mean(np.square(by_trial))) == pytest.approx(truth, rel=0.25)
    assert math.sqrt(np.mean(np.square(by_block))) < 0.75 * truth


def test_trials_are_left_out_whole_and_too_few_fall_back_to_blocks() -> None:
    t = np.concatenate([np.arange(0.0, 5.0, 0.01), 6.0 + np.arange(0.0, 5.0, 0.01)])
    segs = gap_segments(t)
    assert segs.tolist() == [0] * 500 + [1] * 500
    blocks, nb = time_blocks(t)
    train = blocks % 2 == 0
    masks = block_groups(blocks, train, 8, segs)  # two trials: interleaved blocks
    assert len(masks) == min(8, nb // 2)
    three = np.repeat([0, 1, 2], [300, 300, 400])
    masks = block_groups(blocks, train, 8, three)
    assert len(masks) == 3
    for k, m in enumerate(masks):
        assert not np.any(m & (three == k)) and np.all(m[train & (three != k)])
