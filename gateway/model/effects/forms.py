"""Signal helpers the effect modules share: cable displacement, acceleration (look-ahead
and causal), a delay by interpolation and the exact first-order filter.

Arrays are (N,) for one cable or (N, m) with one column per cable; parameters are scalars
or (m,). Sampling need not be uniform.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


def displacement(t: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    """Cable displacement ``x(t) = int v dt`` (m), trapezoidal, ``x(t_0) = 0``."""
    t = np.asarray(t, dtype=float)
    v = np.asarray(velocity, dtype=float)
    dt = np.diff(t).reshape((-1,) + (1,) * (v.ndim - 1))
    steps = 0.5 * (v[1:] + v[:-1]) * dt
    return np.concatenate([np.zeros_like(v[:1]), np.cumsum(steps, axis=0)])


def acceleration(t: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    """``a = dv/dt`` (m/s^2) by second-order finite differences on uneven samples."""
    return np.gradient(np.asarray(velocity, dtype=float), np.asarray(t, dtype=float), axis=0)


def delay(t: np.ndarray, y: np.ndarray, d_s: float | np.ndarray) -> np.ndarray:
    """``y(t - d)`` by linear interpolation; before the first sample the first value holds."""
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    if y.ndim == 1:
        return np.interp(t - float(d_s), t, y)
    d = np.broadcast_to(np.asarray(d_s, dtype=float), (y.shape[1],))
    return np.stack([np.interp(t - d[i], t, y[:, i]) for i in range(y.shape[1])], axis=1)


@njit(cache=True)
def lowpass_step_into(y_prev, y, out_prev, dt, tau, out):
    """One step of ``1 / (tau s + 1)`` for every column: exact for an input that moves
    linearly from ``y_prev`` to ``y`` over ``dt`` (first-order hold). ``tau <= 0`` or
    ``dt <= 0``: the input passes. Arrays (m,); ``out`` may be ``out_prev``."""
    for i in range(y.size):
        if tau[i] > 0.0 and dt > 0.0:
            keep = math.exp(-dt / tau[i])
            slope = (y[i] - y_prev[i]) / dt
            out[i] = y[i] - tau[i] * slope + (out_prev[i] - y_prev[i] + tau[i] * slope) * keep
        else:
            out[i] = y[i]


@njit(cache=True)
def _lowpass_kernel(t, y, tau, out):
    out[0] = y[0]
    for k in range(1, y.shape[0]):
        lowpass_step_into(y[k - 1], y[k], out[k - 1], t[k] - t[k - 1], tau, out[k])


def lowpass(t: np.ndarray, y: np.ndarray, tau_s: float | np.ndarray) -> np.ndarray:
    """First-order filter ``1 / (tau s + 1)`` started at rest on ``y[0]``; exact for an input
    linear between samples, so uneven sampling is handled."""
    y = np.asarray(y, dtype=float)
    y2 = y.reshape(len(y), -1)
    tau = np.broadcast_to(np.asarray(tau_s, dtype=float), (y2.shape[1],)).copy()
    out = np.empty_like(y2)
    _lowpass_kernel(np.asarray(t, dtype=float), np.ascontiguousarray(y2), tau, out)
    return out.reshape(y.shape)


class LowpassStepper:
    """The per-sample form of :func:`lowpass`: ``step(k, t, y)`` advances the filter by one
    sample (``k = 0`` starts it at rest on ``y``) and returns its state, the filtered value
    (owned by the stepper: copy it to keep it)."""

    def __init__(self, tau: np.ndarray) -> None:
        self.tau = tau
        self.y_in = np.zeros(tau.size)
        self.out = np.zeros(tau.size)
        self.t_prev = 0.0

    def step(self, k: int, t: float, y: np.ndarray) -> np.ndarray:
        if k == 0:
            self.out[:] = y
        else:
            lowpass_step_into(self.y_in, y, self.out, t - self.t_prev, self.tau, self.out)
        self.y_in[:] = y
        self.t_prev = t
        return self.out


def causal_acceleration(t: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    """``a_k = (v_k - v_{k-1}) / (t_k - t_{k-1})``, ``a_0 = 0`` (and 0 where dt <= 0): the
    acceleration a cycle can know (no look-ahead)."""
    t = np.asarray(t, dtype=float)
    v = np.asarray(velocity, dtype=float)
    dt = np.diff(t).reshape((-1,) + (1,) * (v.ndim - 1))
    dv = np.diff(v, axis=0)
    safe = np.where(dt > 0.0, dt, 1.0)
    acc = np.where(dt > 0.0, dv / safe, 0.0)
    return np.concatenate([np.zeros_like(v[:1]), acc])
