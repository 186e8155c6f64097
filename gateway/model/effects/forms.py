"""Signal helpers the effect modules share: cable displacement, acceleration (look-ahead
and causal), a delay by interpolation and the exact first-order filter.

Arrays are (N,) for one cable or (N, m) with one column per cable; parameters are scalars
or (m,). Sampling need not be uniform.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

CHUNK = 1 << 16
"""Rows per piece of :func:`displacement` and :func:`acceleration`: their temporaries are
a few of these, not a few copies of the whole series (a 10-min 1 kHz column: 4.8 MB each)."""


def displacement(t: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    """Cable displacement ``x(t) = int v dt`` (m), trapezoidal, ``x(t_0) = 0``.

    Computed :data:`CHUNK` rows at a time, the running sum carried into each piece's first
    step: the same additions in the same order as one ``cumsum`` over every step."""
    t = np.asarray(t, dtype=float)
    v = np.asarray(velocity, dtype=float)
    out = np.empty(v.shape, dtype=np.result_type(v, t))
    if v.shape[0] == 0:
        return out
    out[0] = 0.0
    for lo in range(1, v.shape[0], CHUNK):
        hi = min(lo + CHUNK, v.shape[0])
        dt = (t[lo:hi] - t[lo - 1 : hi - 1]).reshape((-1,) + (1,) * (v.ndim - 1))
        steps = 0.5 * (v[lo:hi] + v[lo - 1 : hi - 1]) * dt
        if lo > 1:
            steps[0] = out[lo - 1] + steps[0]
        np.cumsum(steps, axis=0, out=out[lo:hi])
    return out


def acceleration(t: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    """``a = dv/dt`` (m/s^2) by second-order finite differences on uneven samples:
    ``np.gradient(velocity, t, axis=0)`` (first-order at both ends), evaluated
    :data:`CHUNK` rows at a time with numpy's formulas (the uniform one when every step of
    ``t`` is equal), so the values are numpy's bit for bit."""
    f = np.asarray(velocity, dtype=float)
    x = np.asarray(t, dtype=float)
    n = f.shape[0]
    if n < 2:
        return np.gradient(f, x, axis=0)  # numpy's error for too few samples
    out = np.empty_like(f)
    step = x[1] - x[0]
    uniform = all(
        bool(np.all(x[lo + 1 : hi + 1] - x[lo:hi] == step))
        for lo, hi in ((lo, min(lo + CHUNK, n - 1)) for lo in range(0, n - 1, CHUNK))
    )
    shape = (-1,) + (1,) * (f.ndim - 1)
    for lo in range(1, n - 1, CHUNK):
        hi = min(lo + CHUNK, n - 1)  # rows lo..hi-1, each with both neighbours
        if uniform:
            out[lo:hi] = (f[lo + 1 : hi + 1] - f[lo - 1 : hi - 1]) / (2.0 * step)
            continue
        dx1 = (x[lo:hi] - x[lo - 1 : hi - 1]).reshape(shape)
        dx2 = (x[lo + 1 : hi + 1] - x[lo:hi]).reshape(shape)
        a = -(dx2) / (dx1 * (dx1 + dx2))
        b = (dx2 - dx1) / (dx1 * dx2)
        c = dx1 / (dx2 * (dx1 + dx2))
        out[lo:hi] = a * f[lo - 1 : hi - 1] + b * f[lo:hi] + c * f[lo + 1 : hi + 1]
    out[0] = (f[1] - f[0]) / step
    out[-1] = (f[-1] - f[-2]) / (step if uniform else x[-1] - x[-2])
    return out


def delay(t: np.ndarray, y: np.ndarray, d_s: float | np.ndarray) -> np.ndarray:
    """``y(t - d)`` by linear interpolation; before the first sample the first value holds."""
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    if y.ndim == 1:
        return np.interp(t - float(d_s), t, y)
    d = np.broadcast_to(np.asarray(d_s, dtype=float), (y.shape[1],))
    return np.stack([np.interp(t - d[i], t, y[:, i]) for i in range(y.shape[1])], axis=1)


@njit(cache=True)
def _hold_step(y_prev, y, out_prev, dt, tau, keep):
    """One column's step of ``1 / (tau s + 1)`` for a first-order-hold input, ``keep`` =
    ``exp(-dt / tau)``; ``tau > 0`` and ``dt > 0``. The one formula of both low-pass
    forms (:func:`lowpass_step_into`, :func:`_lowpass_kernel`)."""
    slope = (y - y_prev) / dt
    return y - tau * slope + (out_prev - y_prev + tau * slope) * keep


@njit(cache=True)
def lowpass_step_into(y_prev, y, out_prev, dt, tau, out):
    """One step of ``1 / (tau s + 1)`` for every column: exact for an input that moves
    linearly from ``y_prev`` to ``y`` over ``dt`` (first-order hold). ``tau <= 0`` or
    ``dt <= 0``: the input passes. Arrays (m,); ``out`` may be ``out_prev``."""
    for i in range(y.size):
        if tau[i] > 0.0 and dt > 0.0:
            keep = math.exp(-dt / tau[i])
            out[i] = _hold_step(y_prev[i], y[i], out_prev[i], dt, tau[i], keep)
        else:
            out[i] = y[i]


LOWPASS_MEMO = 32
"""Distinct time steps whose factors ``exp(-dt / tau)`` :func:`_lowpass_kernel` remembers."""


@njit(cache=True)
def _lowpass_kernel(t, y, tau, out):
    """:func:`lowpass_step_into` over the rows of ``y`` (N, m), bit for bit, with the
    factors ``exp(-dt / tau)`` of the last :data:`LOWPASS_MEMO` distinct steps remembered
    (the same value as computed again): a recording's steps take few distinct values
    (17 in 150 000 samples of a soft-PLC recording, whose times are decimal text), and the
    exponential was nine tenths of the filter's time (150 000 samples: 7.2 ms, 1.5 ms
    remembered; 4.4 ms with every step different, as the rows are no longer sliced)."""
    m = y.shape[1]
    out[0] = y[0]
    seen = np.full(LOWPASS_MEMO, np.nan)  # the step of each slot (NaN equals no step)
    keeps = np.empty((LOWPASS_MEMO, m))
    fill = 0
    slot = 0
    for k in range(1, y.shape[0]):
        dt = t[k] - t[k - 1]
        found = -1
        for j in range(LOWPASS_MEMO):  # from the slot the last step used
            s = slot + j if slot + j < LOWPASS_MEMO else slot + j - LOWPASS_MEMO
            if seen[s] == dt:
                found = s
                break
        if found < 0:
            found = fill
            fill = fill + 1 if fill + 1 < LOWPASS_MEMO else 0
            seen[found] = dt
            for i in range(m):
                keeps[found, i] = math.exp(-dt / tau[i]) if tau[i] > 0.0 and dt > 0.0 else 0.0
        slot = found
        for i in range(m):
            if tau[i] > 0.0 and dt > 0.0:
                out[k, i] = _hold_step(
                    y[k - 1, i], y[k, i], out[k - 1, i], dt, tau[i], keeps[found, i]
                )
            else:
                out[k, i] = y[k, i]


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
