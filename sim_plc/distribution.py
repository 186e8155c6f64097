"""The plant controller's tension distribution, when it is not the gateway's statics.

A real robot's controller need not share tension among its cables the way the gateway's
statics does (eq. 18, 19 with the config's ``tension:`` limits, aiming at their midpoint).
``sim_plc.distribution`` makes the soft PLC's plant use another one, so that a recording
shows what a diagnosis must cope with when it cannot assume the controller's choice:

```yaml
sim_plc:
  distribution:
    method: closed_form   # statics (default) | qp | closed_form
    tau_min_n: 40.0       # limits of this distribution (N)
    tau_max_n: 260.0
    target_n: 120.0       # qp only: the tension aimed at (default: the limits' midpoint)
```

* ``statics``: :func:`gateway.model.statics.distribute_tensions` (eq. 18, 19 aiming at the
  limits' midpoint) with ``tau_min_n``/``tau_max_n``, by default the plant's
  ``sim_plc.tension`` limits (what the plant always did).
* ``qp``: eq. 18, 19 with other limits and another target: among ``A tau + w = 0``,
  ``tau_min <= tau <= tau_max`` the ``tau`` closest to ``target_n`` (Euclidean), solved
  exactly as a least-distance program in the null-space coordinates (Lawson & Hanson,
  one NNLS).
* ``closed_form``: Pott's closed-form method ``tau = tau_m - A^+ (w + A tau_m)``,
  ``tau_m = (tau_min + tau_max) / 2``; when the result leaves the limits the pose is
  outside what this method can handle and ``InfeasiblePoseError`` is raised (a clipped
  vector is never returned).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from gateway.core.configtypes import require
from gateway.errors import InfeasiblePoseError
from gateway.model import statics

TOL_REL = 1e-9


@dataclass(frozen=True)
class DistributionConfig:
    """``sim_plc.distribution`` (see the module docstring). Limits None: ``sim_plc.tension``."""

    method: Literal["statics", "qp", "closed_form"] = "statics"
    tau_min_n: float | None = None
    tau_max_n: float | None = None
    target_n: float | None = None

    def __post_init__(self) -> None:
        lo, hi = self.tau_min_n, self.tau_max_n
        if lo is not None and hi is not None:
            require(lo < hi, "tau_max_n must be > tau_min_n")
        if self.target_n is not None:
            require(self.method == "qp", "target_n is for method qp only")
            if lo is not None and hi is not None:
                require(lo <= self.target_n <= hi, "target_n must lie within the limits")


def qp(a: np.ndarray, w: np.ndarray, lo: float, hi: float, target: float) -> np.ndarray:
    """``tau`` (m,) closest to ``target`` with ``A tau + w = 0`` and ``lo <= tau <= hi``."""
    m = a.shape[1]
    part, basis = statics.null_space_split(a, w)
    t_star = part + basis @ (basis.T @ np.full(m, target))
    tol = TOL_REL * max(1.0, abs(lo), abs(hi), float(np.max(np.abs(w))))
    if np.all(t_star >= lo - tol) and np.all(t_star <= hi + tol):
        return np.clip(t_star, lo, hi)
    if basis.shape[1] == 0:
        raise InfeasiblePoseError("no tension distribution within the limits")
    tau = t_star + basis @ statics.least_distance(basis, lo - t_star, hi - t_star)
    if np.any(tau < lo - 1e-6 * max(1.0, hi)) or np.any(tau > hi + 1e-6 * max(1.0, hi)):
        raise InfeasiblePoseError("no tension distribution within the limits")
    return np.clip(tau, lo, hi)


def closed_form(a: np.ndarray, w: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Pott's closed-form distribution ``tau_m - A^+ (w + A tau_m)`` within ``[lo, hi]``."""
    tau_m = np.full(a.shape[1], 0.5 * (lo + hi))
    part, _ = statics.null_space_split(a, w + a @ tau_m)
    tau = tau_m + part
    tol = TOL_REL * max(1.0, abs(lo), abs(hi))
    if np.any(tau < lo - tol) or np.any(tau > hi + tol):
        k = int(np.argmax(np.maximum(lo - tau, tau - hi)))
        raise InfeasiblePoseError(
            f"closed-form distribution leaves [{lo:g}, {hi:g}] N (cable {k + 1} at {tau[k]:.6g} N)"
        )
    return tau


class Distributor:
    """``distributor(A, w) -> tau`` for one plant; ``lo``/``hi`` default to ``tension``."""

    def __init__(self, cfg: DistributionConfig, min_n: float, max_n: float) -> None:
        self.method = cfg.method
        self.lo = min_n if cfg.tau_min_n is None else cfg.tau_min_n
        self.hi = max_n if cfg.tau_max_n is None else cfg.tau_max_n
        self.target = 0.5 * (self.lo + self.hi) if cfg.target_n is None else cfg.target_n
        require(self.lo < self.hi, f"distribution limits {self.lo} .. {self.hi}: need min < max")

    def __call__(self, a: np.ndarray, w: np.ndarray) -> np.ndarray:
        if self.method == "closed_form":
            return closed_form(a, w, self.lo, self.hi)
        if self.method == "qp":
            return qp(a, w, self.lo, self.hi, self.target)
        return statics.distribute_tensions(a, w, self.lo, self.hi)
