"""Forms of the effects outside the friction chain (physics.md sec. 5).

The friction-side effects (``coulomb`` f0, ``presliding``, ``viscous``, ``stribeck``) are
parameters of :class:`gateway.model.chain.ChainParams` (see ``registry.chain_params``);
``mass_change`` belongs to the statics. What remains acts between the chain and the number
the sensor reports:

* path effects, between platform and sensor: ``inertia`` (``- m_eff a``) and
  ``eccentricity`` (``+ A sin(x / r + phi)``, ``x`` the cable displacement);
* sensor effects: ``gain`` (``(1 + g) T``), ``offset`` (``+ c``), ``drift`` (``+ k t``),
  ``lowpass`` (``1 / (tau s + 1)``), ``delay`` (``T(t - d)``).

Arrays are (N,) for one cable or (N, m) with one column per cable; parameters are scalars
or (m,). Sampling need not be uniform.

Forward (what the plant and the diagnosis do: truth -> reading) in batch form:
:func:`apply_path_effects`, :func:`apply_sensor_effects`. Inverse (what the gateway does:
reading -> the model's sensor-side tension) in batch form :func:`remove_sensor_effects`,
:func:`remove_path_effects` with :func:`causal_acceleration`, and in the causal,
allocation-free per-cycle form :func:`online_inputs_into` (tested against the batch form).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

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


@dataclass(frozen=True)
class PathSensorEffects:
    """Per-cable parameters (scalar or (m,)); zero means the effect is off."""

    inertia_kg: float | np.ndarray = 0.0
    eccentricity_a_n: float | np.ndarray = 0.0
    eccentricity_r_m: float | np.ndarray = 0.05
    eccentricity_phi_rad: float | np.ndarray = 0.0
    gain: float | np.ndarray = 0.0
    offset_n: float | np.ndarray = 0.0
    drift_n_s: float | np.ndarray = 0.0
    lowpass_tau_s: float | np.ndarray = 0.0
    delay_s: float | np.ndarray = 0.0


def apply_path_effects(
    t: np.ndarray,
    velocity: np.ndarray,
    tension_sensor: np.ndarray,
    eff: PathSensorEffects,
    x: np.ndarray | None = None,
) -> np.ndarray:
    """Tension at the sensor with pulley inertia and eccentricity added (N).

    ``x``: the cable length (m), same shape as ``velocity``; None: the travel since the
    first sample (:func:`displacement`). The acceleration is :func:`acceleration`.
    """
    out = np.array(tension_sensor, dtype=float)
    if np.any(np.asarray(eff.inertia_kg) != 0):
        out -= np.asarray(eff.inertia_kg) * acceleration(t, velocity)
    if np.any(np.asarray(eff.eccentricity_a_n) != 0):
        x = displacement(t, velocity) if x is None else np.asarray(x, dtype=float)
        phase = x / np.asarray(eff.eccentricity_r_m) + np.asarray(eff.eccentricity_phi_rad)
        out += np.asarray(eff.eccentricity_a_n) * np.sin(phase)
    return out


def apply_sensor_effects(
    t: np.ndarray, tension_sensor: np.ndarray, eff: PathSensorEffects
) -> np.ndarray:
    """What the sensor reports for the tension it carries: gain, offset, drift, filter, delay."""
    t = np.asarray(t, dtype=float)
    tt = t.reshape((-1,) + (1,) * (np.ndim(tension_sensor) - 1))
    out = (1.0 + np.asarray(eff.gain)) * np.asarray(tension_sensor, dtype=float)
    out = out + np.asarray(eff.offset_n) + np.asarray(eff.drift_n_s) * (tt - t[0])
    if np.any(np.asarray(eff.lowpass_tau_s) > 0):
        out = lowpass(t, out, eff.lowpass_tau_s)
    if np.any(np.asarray(eff.delay_s) != 0):
        out = delay(t, out, eff.delay_s)
    return out


class ForwardStepper:
    """Per-sample forms of :func:`apply_path_effects` and :func:`apply_sensor_effects`
    (the soft PLC's plant runs them cycle by cycle).

    They reproduce the batch functions sample by sample (same formulas: ``np.gradient``'s
    second-order differences with one sample of look-ahead, eccentricity on the cable
    length, the first-order-hold low-pass, linear interpolation for the delay). Not causal
    (the truth may look ahead one sample); the gateway's causal forms are
    :func:`online_inputs_into`.
    """

    def __init__(self, eff: PathSensorEffects, cables: int, period_s: float):
        def arr(x: object) -> np.ndarray:
            return np.broadcast_to(np.asarray(x, dtype=float), (cables,)).copy()

        self.m_eff, self.ecc_a = arr(eff.inertia_kg), arr(eff.eccentricity_a_n)
        self.ecc_r, self.ecc_phi = arr(eff.eccentricity_r_m), arr(eff.eccentricity_phi_rad)
        self.gain, self.offset = arr(eff.gain), arr(eff.offset_n)
        self.drift, self.tau = arr(eff.drift_n_s), arr(eff.lowpass_tau_s)
        self.delay = arr(eff.delay_s)
        self.has_inertia, self.has_ecc = bool(np.any(self.m_eff)), bool(np.any(self.ecc_a))
        self.has_lowpass, self.has_delay = bool(np.any(self.tau > 0)), bool(np.any(self.delay))
        size = math.ceil(float(self.delay.max(initial=0.0)) / period_s) + 3
        self.hist_t, self.hist_y = np.zeros(size), np.zeros((size, cables))
        self.t0 = 0.0
        self.lp_in, self.lp_out = np.zeros(cables), np.zeros(cables)

    def path(
        self, k: int, t3: np.ndarray, v3: np.ndarray, length: np.ndarray, ts: np.ndarray
    ) -> np.ndarray:
        """``t3`` (3,), ``v3`` (3, m): previous, current, next sample; ``length``, ``ts``
        (m,): the current cable length (eccentricity's ``x``) and sensor tension."""
        if self.has_inertia:
            if k == 0:
                acc = (v3[2] - v3[1]) / (t3[2] - t3[1])
            else:
                dx1, dx2 = t3[1] - t3[0], t3[2] - t3[1]
                a = -(dx2) / (dx1 * (dx1 + dx2))
                b = (dx2 - dx1) / (dx1 * dx2)
                c = dx1 / (dx2 * (dx1 + dx2))
                acc = a * v3[0] + b * v3[1] + c * v3[2]
            ts = ts - self.m_eff * acc
        if self.has_ecc:
            ts = ts + self.ecc_a * np.sin(length / self.ecc_r + self.ecc_phi)
        return ts

    def sensor(self, k: int, t: float, ts: np.ndarray) -> np.ndarray:
        if k == 0:
            self.t0 = t
        out = (1.0 + self.gain) * ts
        out = out + self.offset + self.drift * (t - self.t0)
        if self.has_lowpass:
            if k == 0:
                self.lp_out[:] = out
            else:
                dt = t - self.hist_t[-1]
                lowpass_step_into(self.lp_in, out, self.lp_out, dt, self.tau, self.lp_out)
            self.lp_in[:] = out
            out = self.lp_out.copy()
        if k == 0:
            self.hist_t[:] = t - np.arange(self.hist_t.size)[::-1] * 1.0
            self.hist_y[:] = out
        else:
            self.hist_t[:-1], self.hist_y[:-1] = self.hist_t[1:], self.hist_y[1:]
            self.hist_t[-1], self.hist_y[-1] = t, out
        if self.has_delay:
            out = np.array(
                [np.interp(t - d, self.hist_t, self.hist_y[:, i]) for i, d in enumerate(self.delay)]
            )
        return out


class OnlineEffects(NamedTuple):
    """Per-cable (m,) parameters of the effects the gateway removes each cycle."""

    gain: np.ndarray
    offset_n: np.ndarray
    inertia_kg: np.ndarray
    eccentricity_a_n: np.ndarray
    eccentricity_r_m: np.ndarray
    eccentricity_phi_rad: np.ndarray

    @staticmethod
    def from_path_sensor(eff: PathSensorEffects, cables: int) -> OnlineEffects:
        def arr(x: object) -> np.ndarray:
            return np.ascontiguousarray(np.broadcast_to(np.asarray(x, dtype=float), (cables,)))

        return OnlineEffects(
            arr(eff.gain), arr(eff.offset_n), arr(eff.inertia_kg), arr(eff.eccentricity_a_n),
            arr(eff.eccentricity_r_m), arr(eff.eccentricity_phi_rad),
        )  # fmt: skip


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


def remove_sensor_effects(reading: np.ndarray, eff: OnlineEffects) -> np.ndarray:
    """Inverse of gain and offset: ``T_s = (reading - c) / (1 + g)`` (N)."""
    return (np.asarray(reading, dtype=float) - eff.offset_n) / (1.0 + eff.gain)


def remove_path_effects(
    tension_sensor: np.ndarray, acc: np.ndarray, x: np.ndarray, eff: OnlineEffects
) -> np.ndarray:
    """Inverse of inertia and eccentricity: the chain's sensor-side tension (N),
    ``T_s + m_eff a - a_n sin(x / r + phi)``."""
    phase = np.asarray(x, dtype=float) / eff.eccentricity_r_m + eff.eccentricity_phi_rad
    out = np.asarray(tension_sensor, dtype=float) + eff.inertia_kg * np.asarray(acc, dtype=float)
    return out - eff.eccentricity_a_n * np.sin(phase)


@njit(cache=True)
def online_inputs_into(eff, reading, velocity, velocity_prev, dt, length, out):
    """Per-cycle form of ``remove_path_effects(remove_sensor_effects(...))``.

    ``eff``: :class:`OnlineEffects`; ``reading``, ``velocity``, ``velocity_prev`` (the
    previous cycle's setpoint velocity), ``length`` (setpoint cable length), ``out``: (m,);
    ``dt``: the time since the previous cycle (s; <= 0: first cycle, no acceleration).
    Allocates nothing.
    """
    for i in range(reading.size):
        ts = (reading[i] - eff.offset_n[i]) / (1.0 + eff.gain[i])
        if eff.inertia_kg[i] != 0.0 and dt > 0.0:
            ts += eff.inertia_kg[i] * (velocity[i] - velocity_prev[i]) / dt
        if eff.eccentricity_a_n[i] != 0.0:
            phase = length[i] / eff.eccentricity_r_m[i] + eff.eccentricity_phi_rad[i]
            ts -= eff.eccentricity_a_n[i] * math.sin(phase)
        out[i] = ts
