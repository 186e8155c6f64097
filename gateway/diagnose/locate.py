"""Where the residual lives: motion regimes per sample and regions of concentrated energy.

Regimes (per sample and cable), from the setpoint velocity ``v`` and ``a = dv/dt``, with
``v_ref`` the 95th percentile of ``|v|`` and ``a_ref`` that of ``|a|``:

* ``reversal``: within a slow stretch (``|v| < 0.1 v_ref``) that contains a sign change;
* ``rest``: ``|v| < 0.005 v_ref`` without a sign change;
* ``low_speed``: the other slow samples;
* ``high_speed``: ``|v| > 0.8 v_ref``;
* ``acceleration``: ``|a| > 0.5 a_ref`` (and not one of the above);
* ``steady``: everything else.

Regions: the residual energy ``r^2`` smoothed over a window (0.5 % of the recording, at
least 25 samples) is compared with its mean; contiguous stretches above twice the mean
are regions, scored by their share of the total residual energy of all cables.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

REGIMES = ("rest", "reversal", "low_speed", "high_speed", "acceleration", "steady")


def runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and stop (exclusive) indices of the True runs of a boolean (N,) array."""
    d = np.diff(np.concatenate(([0], mask.view(np.int8), [0])))
    return np.nonzero(d == 1)[0], np.nonzero(d == -1)[0]


def regimes(v: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Regime index into :data:`REGIMES` per sample, (N,) int8, for one cable."""
    av = np.abs(v)
    v_ref = float(np.percentile(av, 95)) or 1.0
    a_ref = float(np.percentile(np.abs(a), 95)) or 1.0
    out = np.full(v.shape, REGIMES.index("steady"), dtype=np.int8)
    out[np.abs(a) > 0.5 * a_ref] = REGIMES.index("acceleration")
    out[av > 0.8 * v_ref] = REGIMES.index("high_speed")
    slow = av < 0.1 * v_ref
    sign = np.sign(v)
    starts, stops = runs(slow)
    for s, e in zip(starts, stops, strict=True):
        lo, hi = max(s - 1, 0), min(e + 1, v.size)
        seg = sign[lo:hi]
        nz = seg[seg != 0]
        if nz.size and nz.min() < 0 < nz.max():
            out[s:e] = REGIMES.index("reversal")
        else:
            still = av[s:e] < 0.005 * v_ref
            out[s:e] = np.where(still, REGIMES.index("rest"), REGIMES.index("low_speed"))
    return out


@dataclass(frozen=True)
class Region:
    """A stretch of concentrated residual energy on one cable (1-based cable number)."""

    cable: int
    start_s: float
    end_s: float
    regime: str
    share: float


def regions(t: np.ndarray, resid: np.ndarray, regime: np.ndarray, cap: int = 12) -> list[Region]:
    """The ``cap`` regions with the largest share; ``resid``, ``regime``: (N, m)."""
    n, m = resid.shape
    energy = resid**2
    total = float(energy.sum()) or 1.0
    w = max(25, n // 200)
    kernel = np.ones(w) / w
    found: list[Region] = []
    for i in range(m):
        e = energy[:, i]
        smooth = np.convolve(e, kernel, mode="same")
        hot = smooth > 2.0 * float(e.mean())
        starts, stops = runs(hot)
        csum = np.concatenate(([0.0], np.cumsum(e)))
        for s, stop in zip(starts, stops, strict=True):
            share = float(csum[stop] - csum[s]) / total
            counts = np.bincount(regime[s:stop, i], minlength=len(REGIMES))
            found.append(
                Region(i + 1, float(t[s]), float(t[stop - 1]), REGIMES[int(counts.argmax())], share)
            )
    found.sort(key=lambda r: r.share, reverse=True)
    return found[:cap]


def regime_shares(resid: np.ndarray, regime: np.ndarray) -> dict[str, tuple[float, float]]:
    """Per regime: (share of residual energy, share of samples), all cables together."""
    energy = resid**2
    total = float(energy.sum()) or 1.0
    out = {}
    for k, name in enumerate(REGIMES):
        sel = regime == k
        out[name] = (float(energy[sel].sum()) / total, float(sel.mean()))
    return out
