"""Pulley friction laws (paper eq. 7-15, physics.md sec. 3): pure functions, SI units.

Sign convention (eq. 8): ``T_j = T_{j-1} + sgn(v) F_Rj``, pulleys numbered from the sensor
(j = 0 side) towards the platform; ``v > 0`` pays the cable out, so the platform side
carries more tension than the sensor.

Scalar kernels are compiled with numba so that the chain (``chain_kernels.py``) can call them
inside its loops; they are ordinary Python-callable functions as well. :func:`dahl_step`,
the whole step the tests check, is plain Python over them.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

FR_FLOOR_N = 1e-9
"""Coulomb levels below this are treated as zero friction (no division by ~0)."""


def coulomb_ratio_exact(mu: float, wrap_rad: float, direction: float) -> float:
    """Exact ``n_j = T_{j-1} / T_j`` of a Coulomb bearing pulley (eq. 11, 12 with eq. 8).

    ``n = 1 - s lambda(n)`` squared gives ``n^2 - 2 B n + 1 = 0`` with
    ``B = (1 - mu^2 cos a) / (1 - mu^2)``; its roots are reciprocal. Paying out (s = +1)
    the sensor side is lower (n < 1), reeling in the root n > 1; at rest n = 1.
    """
    s = float(np.sign(direction))
    if s == 0.0 or mu == 0.0:
        return 1.0
    b_minus_1 = mu * mu * 2.0 * math.sin(wrap_rad / 2.0) ** 2 / (1.0 - mu * mu)  # no cancellation
    b = 1.0 + b_minus_1
    root = math.sqrt(b_minus_1 * (b + 1.0))
    low = 1.0 / (b + root)  # = b - root (< 1), written so that it loses no digits
    return low if s > 0 else 1.0 / low


@njit(cache=True, inline="always")
def dahl_step_slope(f: float, f_r: float, dx: float, sigma: float) -> tuple[float, float]:
    """The exact ``beta = 1`` Dahl step and its slope ``dF'/dF_R`` (``F_R > 0``, ``dx != 0``).

    ``F' = s F_R + (F - s F_R) exp(-k)``, ``k = sigma |dx| / F_R``, ``s = sgn(dx)``.
    The slope is what the compensation's Newton iteration needs (``F_R`` depends on the
    tension being solved for).
    """
    s = 1.0 if dx > 0.0 else -1.0
    k = sigma * abs(dx) / f_r
    e = math.exp(-k)
    rest = f - s * f_r
    return s * f_r + rest * e, s * (1.0 - e) + rest * e * k / f_r


def dahl_step(f: float, f_r: float, dx: float, sigma: float, beta: float) -> float:
    """One exact step of the Dahl model (eq. 14) over cable travel ``dx`` (m): the whole
    law, plain Python over the compiled steps the kernels inline (:func:`dahl_step_slope`,
    :func:`dahl_step_power`); no command calls it, so nothing compiles it.

    ``dF/dx = sigma (1 - F / F_R sgn(dx))^beta`` with ``F_R`` held over the step.
    With ``z = 1 - s F / F_R`` (s = sgn dx) it reads ``dz/d|x| = -(sigma/F_R) z^beta``,
    solved in closed form (so it is unconditionally stable at any step size):
    ``beta = 1``: ``F' = s F_R + (F - s F_R) exp(-sigma |dx| / F_R)`` (physics.md);
    ``beta != 1``: ``|z'|^(1-beta) = |z|^(1-beta) - (1-beta) sigma |dx| / F_R``, clamped
    at z = 0 for beta < 1 (reached in finite travel), with z's sign kept (z < 0 happens
    when F_R shrank below |F|: F then relaxes back to the level, never through it).
    """
    if dx == 0.0:
        return f
    if f_r <= FR_FLOOR_N:
        return 0.0
    if beta == 1.0:
        return dahl_step_slope(f, f_r, dx, sigma)[0]
    return dahl_step_power(f, f_r, dx, sigma, beta)


@njit(cache=True, inline="always")
def dahl_step_power(f: float, f_r: float, dx: float, sigma: float, beta: float) -> float:
    """:func:`dahl_step` for ``beta != 1``, ``dx != 0`` and ``F_R`` above the floor: the
    kernels call it where they have checked those, so that each inlined copy carries
    neither the checks nor the ``beta = 1`` step again (numba inlines at its IR level,
    and the copies cost compile time: see :func:`gateway.model.chain_kernels._elements`)."""
    s = 1.0 if dx > 0.0 else -1.0
    k = sigma * abs(dx) / f_r
    z = 1.0 - s * f / f_r
    a = abs(z)
    if a == 0.0:
        return f
    if beta < 1.0:
        p = a ** (1.0 - beta) - (1.0 - beta) * k
        a_new = p ** (1.0 / (1.0 - beta)) if p > 0.0 else 0.0
    else:
        a_new = (a ** (1.0 - beta) + (beta - 1.0) * k) ** (1.0 / (1.0 - beta))
    z_new = a_new if z > 0.0 else -a_new
    return s * f_r * (1.0 - z_new)
