"""The least-squares baseline for a real cable transmission: what a competent engineer fits
in an afternoon, to measure the diagnosis against.

One cable, sensor side from platform side::

    T_s = (1 + g) T_p - F - c v - k x + b
    dF/dx = sigma (1 - F / F_R sgn(dx)),   F_R = mu |T_p| + f0

a Dahl pre-sliding force ``F`` (:func:`gateway.diagnose.lsq.dahl_force`, the law of the
diagnosis' own least-squares baseline; stepped exactly over each sample's travel ``dx``,
the trapezoid of the velocities) whose level grows with the load, a gain ``g``, viscous ``c``,
a spring ``k`` linear in the position ``x`` (the recording's ``length``, e.g. the spindle
angle times the capstan radius) and a constant ``b`` (the spring's reference force and any
offset together). Seven parameters, fitted by plain :func:`scipy.optimize.least_squares`
(trust region, finite differences) on the scored samples (:func:`evaluation.realdata.scored`),
each trial from a relaxed ``F``; started from the linear least squares without ``F``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evaluation.realdata import scored, segments
from gateway.diagnose.lsq import dahl_force
from gateway.recordings.reader import Recording

NAMES = ("g", "mu", "f0_n", "log10_sigma_n_m", "c_ns_m", "k_n_m", "b_n")


@dataclass
class Baseline:
    """The fitted parameters (``NAMES``) and what the fit reports."""

    theta: np.ndarray
    cost: float
    nfev: int

    def as_dict(self) -> dict[str, float]:
        out = dict(zip(NAMES, (float(x) for x in self.theta), strict=True))
        out["sigma_n_m"] = 10.0 ** out.pop("log10_sigma_n_m")
        return out


def _columns(rec: Recording) -> tuple[np.ndarray, ...]:
    if rec.tension_platform is None or rec.length is None or rec.cables != 1:
        raise ValueError(f"{rec.source}: the baseline needs one cable, platform tensions, length")
    t = rec.t
    v = rec.velocity[:, 0]
    dx = np.zeros(t.size)
    for seg in segments(t):
        tt, vv = t[seg], v[seg]
        dx[seg][1:] = 0.5 * (vv[1:] + vv[:-1]) * np.diff(tt)
    return rec.tension_platform[:, 0], v, rec.length[:, 0], dx, rec.tension_sensor[:, 0]


def predict(theta: np.ndarray, rec: Recording) -> np.ndarray:
    """The baseline's sensor reading (N,) for ``rec``."""
    tp, v, x, dx, _ = _columns(rec)
    g, mu, f0, lsig, c, k, b = theta
    f = np.empty(tp.size)
    for seg in segments(rec.t):
        f[seg] = dahl_force(tp[seg], dx[seg], mu, f0, 10.0**lsig)
    return (1.0 + g) * tp - f - c * v - k * x + b


def fit(rec: Recording) -> Baseline:
    """Least squares on ``rec``'s scored samples (module docstring)."""
    from scipy.optimize import least_squares

    tp, v, x, _, ts = _columns(rec)
    keep = scored(rec.t)
    lin = np.column_stack([tp, -v, -x, np.ones_like(tp)])[keep]
    (g1, c0, k0, b0), *_ = np.linalg.lstsq(lin, (ts - tp)[keep], rcond=None)
    theta0 = np.array([g1, 0.05, 0.5, 4.0, max(c0, 0.0), k0, b0])
    lower = np.array([-0.5, 0.0, 0.0, 1.0, 0.0, -np.inf, -np.inf])
    upper = np.array([0.5, 1.0, np.inf, 7.0, np.inf, np.inf, np.inf])

    def resid(theta: np.ndarray) -> np.ndarray:
        return (predict(theta, rec) - ts)[keep]

    best = None
    for lsig in (3.0, 4.0, 5.0):  # the stiffness is the one non-convex direction
        start = theta0.copy()
        start[3] = lsig
        res = least_squares(
            resid, np.clip(start, lower, upper), bounds=(lower, upper), x_scale="jac", max_nfev=200
        )
        if best is None or res.cost < best.cost:
            best = res
    assert best is not None
    return Baseline(best.x, float(best.cost), int(best.nfev))
