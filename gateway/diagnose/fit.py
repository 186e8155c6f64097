"""Fitting candidate effects to one cable: starting values, joint least squares, scores.

Each candidate's module gives its :class:`~gateway.model.effects.Spec`: a neutral parameter
vector (the nominal model), bounds, the indices of its (nearly) linear parameters, and a
few starting points for its nonlinear ones (grids, or a periodogram). At each start the
linear parameters are
solved by one Gauss-Newton step from finite-difference signatures; the best start is
refined together with every effect already kept by bounded nonlinear least squares
(:func:`scipy.optimize.least_squares`, trust region reflective) on the training samples.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from gateway.diagnose.forward import CableData, Forward, Nominal
from gateway.diagnose.sessions import tile_spec
from gateway.model import effects as fx
from gateway.model.effects import Spec


def spec_for(effect: str, d: CableData, nom: Nominal, resid: np.ndarray, mask: np.ndarray) -> Spec:
    """The fitting recipe of ``effect`` for this cable (``resid``: current residual;
    ``mask``: the training samples): the effect module's :meth:`~Effect.spec`, repeated
    per recording for an effect fitted per recording on several (:mod:`.sessions`)."""
    e = fx.REGISTRY[effect]
    spec = e.spec(d, nom, resid, mask)
    count = 0 if d.session is None else int(d.session.max()) + 1
    if e.per_recording and count > 1:
        return tile_spec(spec, len(e.params), count)
    return spec


@dataclass
class FitResult:
    """Joint fit of several effects on one cable."""

    theta: dict[str, np.ndarray]
    stderr: dict[str, np.ndarray]
    pred: np.ndarray
    ok: bool


def _linear_step(
    fw: Forward,
    base: dict[str, np.ndarray],
    effect: str,
    spec: Spec,
    theta: np.ndarray,
    mask: np.ndarray,
) -> np.ndarray:
    """Solve the linear parameters of ``effect`` at fixed nonlinear ones (one GN step)."""
    if not spec.linear:
        return theta
    y0 = fw.predict({**base, effect: theta})
    r = (fw.data.ts - y0)[mask]
    cols = []
    for j in spec.linear:
        th = theta.copy()
        th[j] += spec.step[j]
        cols.append(((fw.predict({**base, effect: th}) - y0) / spec.step[j])[mask])
    jac = np.column_stack(cols)
    sol, *_ = np.linalg.lstsq(jac, r, rcond=None)
    out = theta.copy()
    out[list(spec.linear)] += sol
    return spec.clip(out)


def linear_refit(
    fw: Forward, theta: dict[str, np.ndarray], specs: dict[str, Spec], mask: np.ndarray
) -> dict[str, np.ndarray]:
    """One joint Gauss-Newton step on the linear parameters of every effect in ``theta``
    (nonlinear ones held), so that a new effect is judged with the kept ones' linear parts
    free: a drift screened on top of an offset fixed at the mean would otherwise look
    weaker than it is (the offset holds the drift's mean)."""
    y0 = fw.predict(theta)
    r = (fw.data.ts - y0)[mask]
    cols, where = [], []
    for e, th in theta.items():
        for j in specs[e].linear:
            trial = {**theta, e: th.copy()}
            trial[e][j] += specs[e].step[j]
            cols.append(((fw.predict(trial) - y0) / specs[e].step[j])[mask])
            where.append((e, j))
    if not cols:
        return theta
    sol, *_ = np.linalg.lstsq(np.column_stack(cols), r, rcond=None)
    out = {e: v.astype(float).copy() for e, v in theta.items()}
    for (e, j), step in zip(where, sol, strict=True):
        out[e][j] += step
    return {e: specs[e].clip(v) for e, v in out.items()}


def best_start(
    fw: Forward, base: dict[str, np.ndarray], effect: str, spec: Spec, mask: np.ndarray
) -> np.ndarray:
    """The starting point (linear parts solved) with the lowest training SSE (the first
    such in ``spec.starts``).

    Cheaper, with the same result: remembered on ``fw`` (:attr:`Forward.starts`) by
    everything it depends on (the selector screens on an unchanged model again in the next
    round, and a single kept effect's swaps screen on the empty model); the start that won
    the effect's last screen is tried first, and a start's simulation stops once its error
    exceeds the best so far (:meth:`Forward.predict_bounded`). The best start's chain
    output is left as the cache's newest entry, for the screen's residual."""
    key = _start_key(base, effect, spec, mask)
    known = fw.starts.get(key)
    if known is not None:
        return known.copy()
    first = fw.start_hint.get(effect, 0)
    order = list(range(len(spec.starts)))
    if 0 < first < len(order):
        order = [first, *order[:first], *order[first + 1 :]]
    best, best_sse, best_i = spec.neutral, math.inf, -1
    best_chain: np.ndarray | None = None
    for i in order:
        th = _linear_step(fw, base, effect, spec, spec.starts[i].astype(float), mask)
        trial = {**base, effect: th}
        pred = fw.predict_bounded(trial, mask, best_sse)
        if pred is None:
            continue
        sse = float(np.sum((fw.data.ts - pred)[mask] ** 2))
        if sse < best_sse or (sse == best_sse and i < best_i):
            best, best_sse, best_i, best_chain = th, sse, i, fw.chain(trial)
    if best_chain is not None:
        fw.keep({**base, effect: best}, best_chain)
        fw.start_hint[effect] = best_i
    fw.starts[key] = np.array(best, dtype=float)
    return best


def _start_key(base: dict[str, np.ndarray], effect: str, spec: Spec, mask: np.ndarray) -> bytes:
    """A digest of what :func:`best_start` depends on besides the forward model."""
    h = hashlib.blake2b(digest_size=20)
    h.update(effect.encode())
    for name in sorted(base):
        h.update(b"|" + name.encode() + b"=")
        h.update(np.ascontiguousarray(base[name], dtype=float).tobytes())
    for arr in (spec.neutral, spec.lower, spec.upper, spec.step, *spec.starts):
        h.update(b"|")
        h.update(np.ascontiguousarray(arr, dtype=float).tobytes())
    h.update(b"|" + repr(tuple(spec.linear)).encode() + b"|")
    h.update(np.packbits(np.ascontiguousarray(mask, dtype=bool)).tobytes())
    return h.digest()


def joint_fit(
    fw: Forward,
    theta0: dict[str, np.ndarray],
    specs: dict[str, Spec],
    mask: np.ndarray,
    max_nfev: int = 60,
    stride: int = 1,
    fixed: dict[str, np.ndarray] | None = None,
) -> FitResult:
    """Refine every effect in ``theta0`` together on the samples in ``mask``.

    ``stride`` > 1 scores only every stride-th training sample (the forward model still
    runs on every sample), to keep the Jacobian small on long recordings. ``fixed``:
    effects held at their values while ``theta0`` is fitted.
    """
    fixed = fixed or {}
    names = list(theta0)
    sizes = [theta0[n].size for n in names]
    x0 = np.concatenate([theta0[n] for n in names]).astype(float)
    lo = np.concatenate([specs[n].lower for n in names])
    hi = np.concatenate([specs[n].upper for n in names])
    step = np.concatenate([specs[n].step for n in names])
    pad = 1e-9 * (np.abs(x0) + 1.0)
    x0 = np.minimum(
        np.maximum(x0, np.where(np.isfinite(lo), lo + pad, lo)),
        np.where(np.isfinite(hi), hi - pad, hi),
    )
    idx = np.nonzero(mask)[0][::stride]
    ts = fw.data.ts[idx]

    def unpack(x: np.ndarray) -> dict[str, np.ndarray]:
        return dict(zip(names, np.split(x, np.cumsum(sizes)[:-1]), strict=True))

    def fun(x: np.ndarray) -> np.ndarray:
        return ts - fw.predict({**fixed, **unpack(x)})[idx]

    scale = np.where(np.isfinite(step), step, 1.0)
    try:
        res = least_squares(
            fun,
            x0,
            bounds=(lo, hi),
            x_scale=scale,
            diff_step=None,
            method="trf",
            max_nfev=max_nfev,
            xtol=1e-10,
            ftol=1e-10,
        )
        x, jac, resid, ok = res.x, res.jac, res.fun, True
    except (ValueError, np.linalg.LinAlgError):
        x, jac, resid, ok = x0, None, fun(x0), False
    se = _stderr(jac, resid, x.size, stride)
    return FitResult(unpack(x), unpack(se), fw.predict({**fixed, **unpack(x)}), ok)


def _stderr(jac: np.ndarray | None, resid: np.ndarray, p: int, stride: int) -> np.ndarray:
    """Standard errors from the Jacobian at the optimum (those of the thinned sample)."""
    if jac is None:
        return np.full(p, np.nan)
    n = resid.size
    s2 = float(resid @ resid) / max(n - p, 1)
    try:
        cov = np.linalg.pinv(jac.T @ jac) * s2
    except np.linalg.LinAlgError:
        return np.full(p, np.nan)
    return np.sqrt(np.maximum(np.diag(cov), 0.0))


def block_sse(resid: np.ndarray, blocks: np.ndarray, n_blocks: int, mask: np.ndarray) -> np.ndarray:
    """Sum of squared residuals per block (n_blocks,), counting only samples in ``mask``."""
    return np.bincount(blocks[mask], weights=resid[mask] ** 2, minlength=n_blocks)
