"""The statistics every stage of the diagnosis shares (on scipy.special, not scipy.stats:
the distributions needed are two lines each, and scipy.stats costs 20 MiB more to import):
one robust noise estimator, the held-out test of a finding, its p-value, the false-discovery
control over every candidate tried, and standard errors from refits across time blocks.

**The held-out test.** The recording is cut into interleaved time blocks; even blocks train,
odd blocks are held out. Model B (with a finding) against model A (without): the decrease
of the held-out sum of squares ``sum_b (sse_a - sse_b)`` equals ``sum (2 r_b d + d^2)`` with
``r_b`` B's residual and ``d = p_b - p_a``. If B adds nothing real its noise lies in
``2 sum r_b d``, whose variance is estimated from the per-block sums (robust to residuals
correlated in time within a block): ``z = gain / (2 sqrt(sum_b c_b^2))``
(:func:`holdout_z`). With ``k`` held-out blocks the variance comes from ``k`` sums, so the
one-sided p-value takes Student's t with ``k - 1`` degrees of freedom (:func:`p_value`): a
test of a mean over blocks, which stays honest with 5-20 blocks where the normal would
overstate the evidence. A finding fitted on the training blocks and evaluated held out is
biased *against* itself under the null (fitted noise does not generalise), so the test is
conservative.

**False discoveries.** Every candidate effect is tested on every cable (a kept one
against the model without it, one not kept against the model with it): the p-values of all
candidate x cable tests go through Benjamini-Hochberg (:func:`bh_qvalues`); a finding is
kept only with ``q <= alpha``.

**Standard errors from the data's own spread.** The Jacobian's errors assume white noise
and a correct model; refitting with one group of training blocks left out at a time
(delete-a-group jackknife, :func:`jackknife_se`) gives errors that also carry what varies
between stretches of the recording (a model-form error, a drifting machine), the spread a
second recording of the same machine would show. A recording of several trials leaves out
whole trials (:func:`block_groups`): what a trial's conditions make of a model-form error
is shared by all its blocks.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import special

MAD_SIGMA = 0.6745
"""Median absolute deviation of a standard normal."""


def white_noise(r: np.ndarray, order: int = 1) -> float:
    """White-noise std of a residual series (N,): the median absolute difference of
    ``order`` over ``0.6745 sqrt(C(2 order, order))`` (the std of white noise's differences:
    ``sqrt 2`` for the first, ``sqrt 6`` for the second); robust to the slow part of the
    series (the second difference also to ramps) and to outliers. The one estimator of the
    diagnosis (per cable, per wrench component, of a final model, of a velocity column)."""
    r = np.asarray(r, dtype=float)
    if r.size < order + 2:
        return 0.0
    spread = math.sqrt(math.comb(2 * order, order))
    return float(np.median(np.abs(np.diff(r, order)))) / (MAD_SIGMA * spread)


def white_noise_columns(r: np.ndarray) -> np.ndarray:
    """:func:`white_noise` of each column of (N, k)."""
    r = np.asarray(r, dtype=float)
    if r.shape[0] < 3:
        return np.zeros(r.shape[1])
    return np.median(np.abs(np.diff(r, axis=0)), axis=0) / (MAD_SIGMA * math.sqrt(2.0))


def holdout_z(sse_a: np.ndarray, sse_b: np.ndarray, cross: np.ndarray) -> float:
    """How many standard errors model B's held-out SSE lies below model A's (module
    docstring). ``sse_a``, ``sse_b``: per held-out block; ``cross``: per block
    ``sum r_b (p_b - p_a)``."""
    gain = float(sse_a.sum() - sse_b.sum())
    noise = 2.0 * math.sqrt(float(np.sum(cross**2)))
    if noise == 0.0:
        return math.inf if gain > 0 else 0.0
    return gain / noise


def p_value(z: float, blocks: int) -> float:
    """One-sided p-value of a held-out ``z`` from ``blocks`` held-out blocks (Student's t
    with ``blocks - 1`` degrees of freedom)."""
    if math.isinf(z):
        return 0.0 if z > 0 else 1.0
    if math.isnan(z):
        return 1.0
    df = max(blocks - 1, 1)
    tail = 0.5 * float(special.betainc(0.5 * df, 0.5, df / (df + z * z)))  # P(T > |z|)
    return tail if z >= 0 else 1.0 - tail


def sign_test_p(above: int, n: int) -> float:
    """One-sided sign test: the probability of at least ``above`` of ``n`` fair coin flips
    coming up heads."""
    if n <= 0 or above <= 0:
        return 1.0
    return float(special.bdtrc(above - 1, n, 0.5))


def bh_qvalues(p: Sequence[float]) -> np.ndarray:
    """Benjamini-Hochberg q-values of the p-values ``p`` (the smallest false-discovery rate
    at which each would be rejected)."""
    arr = np.asarray(p, dtype=float)
    n = arr.size
    if n == 0:
        return arr
    order = np.argsort(arr)
    ranked = arr[order] * n / np.arange(1, n + 1)
    q = np.minimum.accumulate(ranked[::-1])[::-1]
    out = np.empty(n)
    out[order] = np.minimum(q, 1.0)
    return out


MIN_SEGMENT_GROUPS = 3
"""Fewest segments (trials) whose leave-one-out refits give the errors (fewer: blocks)."""


def block_groups(
    blocks: np.ndarray, train: np.ndarray, groups: int, segments: np.ndarray | None = None
) -> list[np.ndarray]:
    """Masks leaving one group of training samples out each.

    A recording joined from ``MIN_SEGMENT_GROUPS`` or more segments (trials, pieces
    between gaps: ``segments`` (N,), their index per sample) leaves out whole segments:
    the segments split into ``groups`` runs of consecutive ones (each segment its own
    group where there are fewer). Blocks of one trial share what that trial's conditions
    make of a model-form error (a speed, a load level), so refits that leave out
    interleaved blocks and keep the rest of every trial see the same error each time
    and understate the spread between trials, the spread a second recording shows.
    Otherwise the training blocks split into ``groups`` interleaved groups (every
    ``groups``-th block), so each refit still sees every part of the recording."""
    if segments is not None:
        ids = np.unique(segments[train])
        if ids.size >= MIN_SEGMENT_GROUPS:
            parts = np.array_split(ids, min(groups, ids.size))
            return [train & ~np.isin(segments, part) for part in parts]
    ids = np.unique(blocks[train])
    g = min(groups, ids.size)
    out = []
    for k in range(g):
        left_out = ids[k::g]
        out.append(train & ~np.isin(blocks, left_out))
    return out


def jackknife_se(estimates: np.ndarray) -> np.ndarray:
    """Delete-a-group jackknife standard errors from ``estimates`` (G, p): one row per
    refit with one group left out."""
    est = np.asarray(estimates, dtype=float)
    g = est.shape[0]
    if g < 2:
        return np.full(est.shape[1:], np.nan)
    mean = est.mean(axis=0)
    return np.sqrt((g - 1) / g * np.sum((est - mean) ** 2, axis=0))
