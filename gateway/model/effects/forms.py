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
def _lowpass_kernel(t, y, tau, out):
    n, m = y.shape
    for i in range(m):
        out[0, i] = y[0, i]
    for k in range(1, n):
        dt = t[k] - t[k - 1]
        for i in range(m):
            a = 1.0 - math.exp(-dt / tau[i]) if tau[i] > 0.0 else 1.0
            # exact for an input that moves linearly between samples (first-order hold)
            if tau[i] > 0.0 and dt > 0.0:
                slope = (y[k, i] - y[k - 1, i]) / dt
                out[k, i] = (
                    y[k, i]
                    - tau[i] * slope
                    + (out[k - 1, i] - y[k - 1, i] + tau[i] * slope) * (1 - a)
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
