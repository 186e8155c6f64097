"""What a residual depends on: named signals of a cable's recording, and the search for
structure beyond the catalogue.

:data:`SIGNALS` are the recorded quantities and the physically meaningful products a
residual is plotted against or explained by (an effect module names its plot signal from
this table): time, velocity, acceleration, the platform tension ``T``, the direction, the
direction times ``T`` (a load-dependent friction), ``T^2``, the cable position, the travel
since the last reversal (presliding), the reading's rate of change (a lag); a recording's
extra columns (a temperature) join them.

:func:`unexplained` asks, of the final model's residual, how much a smooth one-dimensional
function of each signal explains on held-out blocks: the function (means over quantile
bins, interpolated linearly between their centres) is fitted on the training blocks and
scored on the held-out ones with the held-out test of :mod:`.stats`; the p-values of every
signal go through Benjamini-Hochberg. Only a signal significant at the false-discovery
level is reported, with its share of the held-out residual variance, its curve with
standard errors, and the closest physical reading in words. An extra column that is a
cable's reading in disguise (:func:`disguised_readings`) is never searched.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from gateway.diagnose.stats import bh_qvalues, holdout_z, p_value

BINS = 16
TIE = 0.02
"""Signals whose shares lie within this fraction of the best one are ranked by linearity."""


def _travel_since_reversal(x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """|x - x at the last sign change of v| (m)."""
    s = np.sign(v)
    nz = np.flatnonzero(s)
    if nz.size == 0:
        return np.zeros_like(x)
    filled = s[np.maximum.accumulate(np.where(s != 0, np.arange(s.size), 0))]
    filled[: nz[0]] = s[nz[0]]  # the direction before the first move: that of the first
    change = np.concatenate(([True], filled[1:] != filled[:-1]))
    start = np.maximum.accumulate(np.where(change, np.arange(x.size), 0))
    return np.abs(x - x[start])


SIGNALS: dict[str, Callable[[object], np.ndarray]] = {
    "t": lambda d: d.t - d.t0,  # type: ignore[attr-defined]
    "v": lambda d: d.v,  # type: ignore[attr-defined]
    "a": lambda d: d.a,  # type: ignore[attr-defined]
    "T": lambda d: d.tp,  # type: ignore[attr-defined]
    "sgn(v)": lambda d: np.sign(d.v),  # type: ignore[attr-defined]
    "sgn(v)*T": lambda d: np.sign(d.v) * d.tp,  # type: ignore[attr-defined]
    "T^2": lambda d: d.tp**2,  # type: ignore[attr-defined]
    "sgn(v)*T^2": lambda d: np.sign(d.v) * d.tp**2,  # type: ignore[attr-defined]
    "x": lambda d: d.x,  # type: ignore[attr-defined]
    "travel since reversal": lambda d: _travel_since_reversal(d.x, d.v),  # type: ignore[attr-defined]
    "dT/dt": lambda d: np.gradient(d.ts, d.t) if d.t.size > 1 else np.zeros_like(d.ts),  # type: ignore[attr-defined]
}
UNITS = {
    "t": "s",
    "v": "m/s",
    "a": "m/s^2",
    "T": "N",
    "sgn(v)": "1",
    "sgn(v)*T": "N",
    "T^2": "N^2",
    "sgn(v)*T^2": "N^2",
    "x": "m",
    "travel since reversal": "m",
    "dT/dt": "N/s",
}
READINGS = {
    "t": "changes over time: a sensor drift or creep, a warming machine",
    "v": "a force that depends on speed beyond the fitted viscous term",
    "a": "a force that follows the acceleration: an inertia the model lacks",
    "T": "proportional to the tension whatever the direction: a sensor gain or creep",
    "sgn(v)": "flips with the direction at a constant level: a load-independent friction",
    "sgn(v)*T": "grows with tension and flips with direction: a load-dependent friction "
    "coefficient",
    "T^2": "grows with tension faster than linearly whatever the direction: a nonlinear "
    "sensor or a bending stiffness",
    "sgn(v)*T^2": "grows with tension faster than linearly and flips with direction: a "
    "friction coefficient that rises with the load",
    "x": "depends on the cable position: a spring, a cable stretch or a position-dependent "
    "friction",
    "travel since reversal": "concentrated just after each reversal: the transition of the "
    "presliding friction (a multi-state Maxwell-slip law, or backlash)",
    "dT/dt": "follows the rate of change of the reading: a lag the model lacks",
}


EDGE_SAMPLES = 50_000
"""Samples the bin edges are taken from (every k-th beyond that: the quantiles of a long
recording are as good from 50 000 samples, and a sort of 600 000 costs 10 x more)."""


def bin_fit(s: np.ndarray, r: np.ndarray, bins: int = BINS):
    """Quantile-bin centres, means, standard errors and counts of ``r`` against ``s``."""
    sample = s[:: max(1, s.size // EDGE_SAMPLES)]
    edges = np.unique(np.quantile(sample, np.linspace(0.0, 1.0, bins + 1)))
    edges[0], edges[-1] = min(edges[0], float(s.min())), max(edges[-1], float(s.max()))
    if edges.size < 2:
        return None
    which = np.clip(np.searchsorted(edges, s, side="right") - 1, 0, edges.size - 2)
    n = np.bincount(which, minlength=edges.size - 1).astype(float)
    keep = n > 1
    if not keep.any():  # too few samples for one bin of two: nothing to fit
        return None
    sx = np.bincount(which, s, minlength=edges.size - 1)
    sr = np.bincount(which, r, minlength=edges.size - 1)
    sr2 = np.bincount(which, r * r, minlength=edges.size - 1)
    centre = sx[keep] / n[keep]
    mean = sr[keep] / n[keep]
    var = np.maximum(sr2[keep] / n[keep] - mean**2, 0.0)
    se = np.sqrt(var / n[keep])
    return centre, mean, se, n[keep]


def smooth(centre: np.ndarray, mean: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The binned function at ``s`` (linear between bin centres, flat beyond)."""
    if centre.size == 1:
        return np.full(s.shape, float(mean[0]))
    return np.interp(s, centre, mean)


@dataclass
class Structure:
    """One signal's explanation of the residual: the test over held-out blocks (pooled over
    cables), the share of the held-out residual variance, the curve."""

    signal: str
    z: float
    p: float
    share: float
    centre: np.ndarray
    mean: np.ndarray
    se: np.ndarray
    q: float = 1.0
    line: float = 0.0
    """The held-out share a straight line in the signal explains."""


class Explainer:
    """Every signal's held-out explanation of a residual, gathered cable by cable
    (:meth:`add`; no (N, m) residual is held), then :meth:`result` (module docstring)."""

    def __init__(self, blocks: np.ndarray, n_blocks: int, extra: dict[str, np.ndarray]) -> None:
        self.blocks, self.n_blocks, self.extra = blocks, n_blocks, extra
        self.names = list(SIGNALS) + [f"column {k}" for k in extra]
        self.acc = {
            n: [np.zeros(n_blocks), np.zeros(n_blocks), np.zeros(n_blocks)] for n in self.names
        }
        self.bins: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]] = {
            n: [] for n in self.names
        }
        self.linear = dict.fromkeys(self.names, 0.0)

    def signal(self, name: str, d: object) -> np.ndarray:
        return self.extra[name[7:]] if name.startswith("column ") else SIGNALS[name](d)

    def add(self, d: object, r: np.ndarray, train: np.ndarray, test: np.ndarray) -> None:
        """One cable's series ``d``, residual ``r`` (N,) and training / held-out samples."""
        nb = self.n_blocks
        bt, rt, rtrain = self.blocks[test], r[test], r[train]
        sse_r = np.bincount(bt, weights=rt**2, minlength=nb)
        for name in self.names:
            s = self.signal(name, d)
            st = s[train]
            if not np.all(np.isfinite(st)) or np.ptp(st) == 0:
                continue
            fit = bin_fit(st, rtrain)
            if fit is None:
                continue
            f = smooth(fit[0], fit[1], s[test])
            rb = rt - f
            sse_a, sse_b, cross = self.acc[name]
            sse_a += sse_r
            sse_b += np.bincount(bt, weights=rb**2, minlength=nb)
            cross += np.bincount(bt, weights=rb * f, minlength=nb)
            self.bins[name].append(fit)
            line = np.polyfit(st, rtrain, 1)  # the simplest function of the signal
            self.linear[name] += float(np.sum((rt - np.polyval(line, s[test])) ** 2))

    def result(self) -> list[Structure]:
        """The signals, strongest first, with their q-values (BH over the signals).

        Strongest: the largest share of the held-out residual variance that a smooth
        function explains; among signals within ``TIE`` of that share (two signals that
        carry the same information, e.g. ``sgn(v)*T`` and ``sgn(v)*T^2`` for a positive
        tension, explain as much), the one in which the residual is closest to linear
        (the largest held-out share of a straight line): the most direct reading."""
        found = []
        for name in self.names:
            sse_a, sse_b, cross = self.acc[name]
            if not self.bins[name] or not np.any(sse_a):
                continue
            z = holdout_z(sse_a, sse_b, cross)
            total = float(sse_a.sum())
            share = max(0.0, float(sse_a.sum() - sse_b.sum()) / total) if total > 0 else 0.0
            line = max(0.0, (total - self.linear[name]) / total) if total > 0 else 0.0
            centre, mean, se = _pool(self.bins[name])
            held = int(np.count_nonzero(sse_a))
            found.append(
                Structure(name, float(z), p_value(z, held), share, centre, mean, se, line=line)
            )
        q = bh_qvalues([f.p for f in found])
        for f, qv in zip(found, q, strict=True):
            f.q = float(qv)
        best = max((f.share for f in found), default=0.0)
        found.sort(
            key=lambda f: (
                f.share < best - TIE * best,
                -f.line if f.share >= best - TIE * best else -f.share,
            )
        )
        return found


def _pool(fits: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cables' binned curves pooled into :data:`BINS` bins (weighted by counts)."""
    c = np.concatenate([f[0] for f in fits])
    m = np.concatenate([f[1] for f in fits])
    se = np.concatenate([f[2] for f in fits])
    n = np.concatenate([f[3] for f in fits])
    order = np.argsort(c)
    c, m, se, n = c[order], m[order], se[order], n[order]
    cum = np.cumsum(n) / n.sum()
    which = np.minimum((cum * BINS).astype(int), BINS - 1)
    w = np.bincount(which, n, minlength=BINS)
    keep = w > 0
    cc = np.bincount(which, c * n, minlength=BINS)[keep] / w[keep]
    mm = np.bincount(which, m * n, minlength=BINS)[keep] / w[keep]
    ss = np.sqrt(np.bincount(which, (se * n) ** 2, minlength=BINS)[keep]) / w[keep]
    return cc, mm, ss


def reading(st: Structure) -> str:
    """The closest physical reading of a curve, in words: its shape, then what it is."""
    c, m = st.centre, st.mean
    if c.size >= 3:
        lin = np.polyfit(c, m, 1)
        resid_lin = float(np.sum((m - np.polyval(lin, c)) ** 2))
        total = float(np.sum((m - m.mean()) ** 2)) or 1.0
        curved = resid_lin > 0.2 * total
        rising = lin[0] > 0
        shape = f"{'rises' if rising else 'falls'} with {st.signal}" + (
            ", not in proportion" if curved else ", about linearly"
        )
    else:
        shape = f"depends on {st.signal}"
    what = READINGS.get(st.signal, f"depends on the recorded {st.signal[7:]}")
    return f"the residual {shape}: {what}"


def significant(found: list[Structure], fdr: float) -> Structure | None:
    """The strongest signal whose q-value passes, or None."""
    for st in found:
        if st.q <= fdr and st.z > 0 and math.isfinite(st.share):
            return st
    return None


DISGUISE_R = 0.95
"""|correlation| with a cable's reading at or above which an extra column is taken for the
reading itself (the raw motor torque or current logged beside the scaled tension: an affine
copy of it, bar friction and noise), explaining 90 % or more of its variance."""


def disguised_readings(
    extra: dict[str, np.ndarray], readings: list[np.ndarray], masks: list[np.ndarray]
) -> list[dict]:
    """The extra columns that are a cable's reading in disguise: for each, the cable
    (1-based) it follows most closely, their correlation over that cable's ``masks``
    samples, and why it may not explain the residual (the residual is the reading minus a
    prediction: a copy of the reading "explains" it by construction). Non-finite samples are
    left out of the correlation; a constant column or reading is no copy."""
    out = []
    for name, col in extra.items():
        best, best_r = 0, 0.0
        for i, (ts, m) in enumerate(zip(readings, masks, strict=True)):
            ok = m & np.isfinite(col) & np.isfinite(ts)
            if ok.sum() < 3:
                continue
            a, b = col[ok], ts[ok]
            sa, sb = float(np.std(a)), float(np.std(b))
            if sa == 0.0 or sb == 0.0:
                continue
            r = float(np.mean((a - a.mean()) * (b - b.mean())) / (sa * sb))
            if abs(r) > abs(best_r):
                best, best_r = i + 1, r
        if abs(best_r) >= DISGUISE_R:
            out.append(
                {
                    "column": name,
                    "cable": best,
                    "correlation": best_r,
                    "reason": f"collinear with cable {best}'s reading (correlation "
                    f"{best_r:.3f}): a scaled or offset copy of the reading explains the "
                    "residual by construction, not a cause of it",
                }
            )
    return out
