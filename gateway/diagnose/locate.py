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

from dataclasses import dataclass, replace

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


def moving_mean(e: np.ndarray, w: int) -> np.ndarray:
    """``np.convolve(e, ones(w) / w, "same")`` (``e`` at least ``w`` long) by a running
    sum: O(N) whatever ``w`` (the window is 0.5 % of the recording: 3000 samples of a
    10-min one), with no index arrays (memory: one running sum beside the result)."""
    n = e.size
    h = w // 2  # the window of sample k: [k - h, k - h + w), clipped to the samples
    csum = np.empty(n + 1)
    csum[0] = 0.0
    np.cumsum(e, out=csum[1:])
    if n < w:  # short: every window clipped at both ends
        k = np.arange(n)
        return (csum[np.clip(k - h + w, 0, n)] - csum[np.clip(k - h, 0, n)]) / w
    out = np.empty(n)
    np.subtract(csum[w:], csum[: n - w + 1], out=out[h : n - w + h + 1])
    out[:h] = csum[w - h : w]
    out[n - w + h + 1 :] = csum[n] - csum[n - w + 1 : n - h]
    out /= w
    return out


def cable_regions(t: np.ndarray, e: np.ndarray, regime: np.ndarray, cable: int) -> list[Region]:
    """Regions of one cable (1-based ``cable``) from its residual energy ``e`` = r^2 (N,)
    and regimes (N,); ``share`` is the region's energy itself (divide by the total)."""
    w = max(25, e.size // 200)
    smooth = moving_mean(e, w)
    hot = smooth > 2.0 * float(e.mean())
    starts, stops = runs(hot)
    csum = np.concatenate(([0.0], np.cumsum(e)))
    found = []
    for s, stop in zip(starts, stops, strict=True):
        counts = np.bincount(regime[s:stop], minlength=len(REGIMES))
        share = float(csum[stop] - csum[s])
        found.append(
            Region(cable, float(t[s]), float(t[stop - 1]), REGIMES[int(counts.argmax())], share)
        )
    return found


def _top(found: list[Region], total: float, cap: int) -> list[Region]:
    total = total or 1.0
    out = [replace(r, share=r.share / total) for r in found]
    out.sort(key=lambda r: r.share, reverse=True)
    return out[:cap]


def regions(t: np.ndarray, resid: np.ndarray, regime: np.ndarray, cap: int = 12) -> list[Region]:
    """The ``cap`` regions with the largest share; ``resid``, ``regime``: (N, m)."""
    energy = resid**2
    found = [
        r
        for i in range(resid.shape[1])
        for r in cable_regions(t, energy[:, i], regime[:, i], i + 1)
    ]
    return _top(found, float(energy.sum()), cap)


class EnergyMap:
    """Regions and regime shares gathered cable by cable (:meth:`add`), so that no (N, m)
    residual is needed: what :func:`regions` and :func:`report_fields` give for the whole."""

    def __init__(self, t: np.ndarray) -> None:
        self.t = t
        self.total = 0.0
        self.energy = np.zeros(len(REGIMES))
        self.samples = np.zeros(len(REGIMES))
        self.found: list[Region] = []

    def add(self, cable: int, resid: np.ndarray, regime: np.ndarray) -> None:
        """One cable's residual (N,) and regimes (N,); ``cable`` 1-based."""
        e = resid**2
        self.total += float(e.sum())
        self.found += cable_regions(self.t, e, regime, cable)
        self.energy += np.bincount(regime, weights=e, minlength=len(REGIMES))
        self.samples += np.bincount(regime, minlength=len(REGIMES))

    def regions(self, cap: int = 12) -> list[Region]:
        return _top(self.found, self.total, cap)

    def report_fields(self, regions: list[Region]) -> dict:
        total, count = self.total or 1.0, float(self.samples.sum()) or 1.0
        return {
            "mismatch": [r.__dict__ for r in regions],
            "regime_shares": {
                k: {
                    "energy": float(self.energy[j]) / total,
                    "samples": float(self.samples[j] / count),
                }
                for j, k in enumerate(REGIMES)
            },
        }


def regime_shares(resid: np.ndarray, regime: np.ndarray) -> dict[str, tuple[float, float]]:
    """Per regime: (share of residual energy, share of samples), all cables together."""
    energy = resid**2
    total = float(energy.sum()) or 1.0
    out = {}
    for k, name in enumerate(REGIMES):
        sel = regime == k
        out[name] = (float(energy[sel].sum()) / total, float(sel.mean()))
    return out


def report_fields(regions: list[Region], resid: np.ndarray, regime: np.ndarray) -> dict:
    """The report's ``mismatch`` (the regions) and ``regime_shares`` entries."""
    return {
        "mismatch": [r.__dict__ for r in regions],
        "regime_shares": {
            k: {"energy": e, "samples": s} for k, (e, s) in regime_shares(resid, regime).items()
        },
    }
