"""Fitting candidate effects to one cable: starting values, joint least squares, scores.

Each candidate has a neutral parameter vector (the nominal model), bounds, the indices of
its (nearly) linear parameters, and a few starting points for its nonlinear ones (grids,
or a periodogram for the eccentricity radius). At each start the linear parameters are
solved by one Gauss-Newton step from finite-difference signatures; the best start is
refined together with every effect already kept by bounded nonlinear least squares
(:func:`scipy.optimize.least_squares`, trust region reflective) on the training samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from gateway.diagnose.forward import CableData, Forward, Nominal

INF = np.inf


@dataclass(frozen=True)
class Spec:
    """How to fit one effect: neutral vector, bounds, linear indices, FD steps."""

    neutral: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    linear: tuple[int, ...]
    step: np.ndarray
    starts: tuple[np.ndarray, ...]


def _speeds(d: CableData) -> tuple[float, float]:
    """95th percentile of |v| (m/s) and the median sample period (s)."""
    v95 = float(np.percentile(np.abs(d.v), 95)) or 1e-3
    dt = float(np.median(np.diff(d.t))) if d.t.size > 1 else 1e-3
    return v95, dt


KAPPA_BATCH = 16
"""Wave numbers per batch of the periodogram: six (20000, 16) float64 temporaries, 15 MB."""


def eccentricity_kappas(
    d: CableData, resid: np.ndarray, mask: np.ndarray, r_nom: float, top: int = 3
) -> list[float]:
    """Wave numbers ``1/r`` (rad/m) where the residual is most periodic in cable travel.

    A least-squares periodogram of ``resid`` against the displacement ``x`` on a grid of
    wave numbers from 2 turns over the travelled span up to 1/(2 mm), on at most 20000
    training samples; ``1/r_nom`` (the model's pulley radius) is always among them.
    """
    idx = np.nonzero(mask)[0]
    if idx.size > 20000:
        idx = idx[:: math.ceil(idx.size / 20000)]
    x, r = d.x[idx], resid[idx] - resid[idx].mean()
    span = float(np.ptp(d.x)) if d.x.size else 0.0
    if span <= 0:
        return [1.0 / r_nom]
    k_lo, k_hi = 4 * math.pi / span, 500.0
    if k_lo >= k_hi:
        return [1.0 / r_nom]
    n_grid = int(min(3000, max(200, (k_hi - k_lo) * span / (0.5 * math.pi))))
    kappas = np.linspace(k_lo, k_hi, n_grid)
    power = np.empty(n_grid)
    for lo in range(0, n_grid, KAPPA_BATCH):
        kk = kappas[lo : lo + KAPPA_BATCH]
        ph = np.outer(x, kk)
        s, c = np.sin(ph), np.cos(ph)
        ss, cc, sc = (s * s).sum(0), (c * c).sum(0), (s * c).sum(0)
        rs, rc = r @ s, r @ c
        det = np.maximum(ss * cc - sc**2, 1e-300)
        power[lo : lo + KAPPA_BATCH] = (cc * rs**2 - 2 * sc * rs * rc + ss * rc**2) / det
    order = np.argsort(power)[::-1]
    chosen: list[float] = []
    for j in order:
        if all(abs(kappas[j] - c) > 2 * (kappas[1] - kappas[0]) for c in chosen):
            chosen.append(float(kappas[j]))
        if len(chosen) >= top:
            break
    return [*chosen, 1.0 / r_nom]


def spec_for(effect: str, d: CableData, nom: Nominal, resid: np.ndarray, mask: np.ndarray) -> Spec:
    """The fitting recipe of ``effect`` for this cable (``resid``: current residual)."""
    v95, dt = _speeds(d)
    a = np.asarray

    def lin(neutral: float, step: float, lo: float = -INF, hi: float = INF) -> Spec:
        return Spec(a([neutral]), a([lo]), a([hi]), (0,), a([step]), (a([neutral]),))

    if effect == "coulomb":
        mu0 = nom.mu_mean if nom.model != "none" else 0.0
        # no wrap anywhere (a rig without pulleys): only f0 acts, mu is held at 0
        mu_hi = 0.5 if np.any(nom.wrap_rad > 0) else 1e-6
        lin_idx = (0, 1) if mu_hi > 1e-3 else (1,)
        # f0 >= 0: seals, brushes and preload only ever add friction (nominal f0 is 0)
        return Spec(
            a([mu0, 0.0]), a([0.0, 0.0]), a([mu_hi, INF]), lin_idx, a([1e-3, 0.1]), (a([mu0, 0.0]),)
        )
    if effect == "presliding":
        s0 = math.log10(nom.sigma_n_m) if nom.model == "dahl" else 7.0
        starts = tuple(a([s]) for s in (1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 5.0))
        return Spec(a([s0]), a([0.5]), a([7.5]), (), a([0.05]), starts)
    if effect == "viscous":  # physical bound: the total viscous coefficient is >= 0
        return lin(0.0, 1.0, lo=-nom.viscous_ns_m)
    if effect == "stribeck":
        lv = math.log10(v95)
        starts = tuple(a([0.0, lv + o]) for o in (-2.5, -2.0, -1.5, -1.0))
        # v_s at most 1/8 of the typical speed: above that it would mimic a Coulomb change
        return Spec(
            a([0.0, lv - 1.5]),
            a([0.0, lv - 4.0]),
            a([20.0, lv - 0.9]),
            (0,),
            a([0.05, 0.05]),
            starts,
        )
    if effect == "inertia":  # a rotating mass is >= 0 (a negative one is a model-form error)
        return lin(0.0, 1.0, lo=0.0)
    if effect in ("delay", "lowpass"):
        grid = (1, 2, 3, 5, 8, 13, 20, 35, 60, 100, 200)
        return Spec(
            a([0.0]),
            a([0.0]),
            a([max(1.0, 300 * dt)]),
            (),
            a([dt / 4]),
            tuple(a([g * dt]) for g in grid),
        )
    if effect == "gain":  # the reading keeps its sign: 1 + g > 0
        return lin(0.0, 1e-3, lo=-0.9)
    if effect == "offset":
        return lin(0.0, 1.0)
    if effect == "drift":
        return lin(0.0, 1e-3)
    if effect == "eccentricity":
        kap = eccentricity_kappas(d, resid, mask, nom.pulley_radius_m)
        span = max(float(np.ptp(d.x)), 1e-6)
        return Spec(
            a([0.0, 0.0, kap[-1]]),
            a([-INF, -INF, 2 * math.pi / span]),
            a([INF, INF, 1e3]),
            (0, 1),
            a([0.1, 0.1, 0.01]),
            tuple(a([0.0, 0.0, k]) for k in kap),
        )
    if effect == "mass_change":
        return lin(0.0, 1e-3)
    raise ValueError(f"unknown effect {effect!r}")


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
    return np.clip(out, spec.lower, spec.upper)


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
    return {e: np.clip(v, specs[e].lower, specs[e].upper) for e, v in out.items()}


def best_start(
    fw: Forward, base: dict[str, np.ndarray], effect: str, spec: Spec, mask: np.ndarray
) -> np.ndarray:
    """The starting point (linear parts solved) with the lowest training SSE."""
    best, best_sse = spec.neutral, math.inf
    for start in spec.starts:
        th = _linear_step(fw, base, effect, spec, start.astype(float), mask)
        sse = float(np.sum((fw.data.ts - fw.predict({**base, effect: th}))[mask] ** 2))
        if sse < best_sse:
            best, best_sse = th, sse
    return best


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
