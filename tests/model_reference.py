"""Reference forms of the friction laws that only the tests use (physics.md sec. 3).

Closed forms and shortcuts the production model does not need but the tests check the
model against: the capstan law (eq. 7), the bearing normal force (eq. 10), ``lambda_j``
(eq. 12), the ``n_j ~ 1`` shortcut, the chain's Coulomb gain and Dahl from rest (eq. 15).
"""

from __future__ import annotations

import math

import numpy as np

from gateway.model.friction import coulomb_ratio_exact


def capstan_ratio(mu_p: float, wrap_rad: float, direction: float) -> float:
    """Euler-Eytelwein (eq. 7): ``T_j / T_{j-1} = exp(sgn(v) mu_p alpha)``."""
    return math.exp(float(np.sign(direction)) * mu_p * wrap_rad)


def normal_force(
    t_prev: np.ndarray | float, t_next: np.ndarray | float, wrap_rad: np.ndarray | float
) -> np.ndarray:
    """Bearing normal force (eq. 10), N: resultant of the two cable tensions at a pulley.

    Broadcasts: tensions and wrap angles (rad) may be scalars or arrays.
    """
    t_prev = np.asarray(t_prev, dtype=float)
    t_next = np.asarray(t_next, dtype=float)
    sq = t_prev**2 - 2.0 * t_prev * t_next * np.cos(wrap_rad) + t_next**2
    return np.sqrt(np.maximum(sq, 0.0))


def coulomb_lambda(n: float, mu: float, wrap_rad: float) -> float:
    """``lambda_j(n_j) = mu sqrt(n^2 - 2 n cos(alpha) + 1)`` with ``n = T_{j-1}/T_j``."""
    return mu * math.sqrt(max(n * n - 2.0 * n * math.cos(wrap_rad) + 1.0, 0.0))


def coulomb_ratio_small_angle(mu: float, wrap_rad: float, direction: float) -> float:
    """The ``n_j ~ 1`` shortcut: ``lambda ~ 2 mu sin(a/2)``, ``n = 1 - s 2 mu sin(a/2)``."""
    s = float(np.sign(direction))
    return 1.0 - s * 2.0 * mu * math.sin(wrap_rad / 2.0)


def coulomb_gain(
    mu: np.ndarray, wrap_rad: np.ndarray, direction: float, exact: bool = True
) -> float:
    """Platform over sensor tension ``T_p / T_s = prod_j 1 / n_j`` for one direction.

    ``mu``, ``wrap_rad``: (n,) per pulley. Returns a float.
    """
    ratio = coulomb_ratio_exact if exact else coulomb_ratio_small_angle
    gain = 1.0
    for m_j, a_j in zip(np.atleast_1d(mu), np.atleast_1d(wrap_rad), strict=True):
        gain /= ratio(float(m_j), float(a_j), direction)
    return gain


def dahl_from_rest(x: np.ndarray, f_r: float, sigma: float) -> np.ndarray:
    """Eq. 15: ``F(x) = sgn(x) F_R (1 - exp(-sigma |x| / F_R))`` from F = 0 at x = 0."""
    x = np.asarray(x, dtype=float)
    return np.sign(x) * f_r * (1.0 - np.exp(-sigma * np.abs(x) / f_r))
