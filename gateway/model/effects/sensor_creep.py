"""``sensor_creep``: strain-gauge creep of the load cell (docs/physics.md sec. 4).

After a load change the reading shows ``1 - c`` of it at once and creeps the remaining
fraction ``c`` in with the time constant ``tau``:
``reading = (1 - c) T + c s``, ``s = 1 / (tau p + 1) T`` (the exact first-order filter of
:func:`gateway.model.effects.forms.lowpass`, started at rest on the first value). At a
steady load it reads the load (a creep calibrated out at rest is no gain); ``c = 1`` is
``lowpass`` (it nests it); ``c < 0`` overshoots and creeps back.

Per sample, with ``e = exp(-dt / tau)``, ``q = tau / dt (1 - e)``, the filter's step is
``s_k = (1 - q) T_k + q T_{k-1} + (s_{k-1} - T_{k-1}) e`` (exact for ``T`` linear between
samples): the reading is linear in ``T_k`` given the past, and the inverse
``T_k = (y_k - c (q T_{k-1} + (s_{k-1} - T_{k-1}) e)) / (1 - c q)`` is causal and exact for
the discrete form. The gateway runs it every cycle (:func:`inverse_step`, its state
``T_{k-1}``, ``s_{k-1}`` in the rows after the parameters); it amplifies the sensor noise by
at most ``1 / (1 - c)`` for ``0 <= c < 1`` (at ``c = 1`` it is the low-pass's differentiator).
The fit varies ``c`` (linear) and ``log10 tau``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from numba import njit

from gateway.model.effects import lowpass as lowpass_effect
from gateway.model.effects.base import (
    Effect,
    FitData,
    NominalChain,
    Online,
    Param,
    Sample,
    Series,
    Spec,
    Values,
    speeds,
)
from gateway.model.effects.forms import LowpassStepper, lowpass

TAUS_S = (0.1, 0.3, 1.0, 3.0)
"""Starting points of the fit's time constant (s)."""
C_FIT = 0.5
TAU_MIN_S = 0.05
"""The fit's bounds: ``|c| <= 0.5``, ``tau >= 50 ms``. A creep moves a fraction of a load
change, slowly (strain gauges creep over seconds to minutes); a fit free to go to ``c = 1``
or to a few ms is a low-pass and takes the fast edges a low-pass or a delay explains
(measured: with either freedom a hidden delay or a hidden low-pass was reported as the
other on some cables of a lively 20-s recording)."""


@njit(cache=True)
def inverse_step(p, y, v, v_prev, dt, length):
    """Per cycle, in place: ``y`` (the reading) -> the load (module docstring). ``p`` rows:
    ``c``, ``tau``, then the state ``T_{k-1}``, ``s_{k-1}`` (written here). ``dt <= 0`` (the
    first sample) or ``tau <= 0``: the reading passes and the filter rests on it."""
    for i in range(y.size):
        c, tau = p[0, i], p[1, i]
        t_new = y[i]
        s_new = t_new
        if tau > 0.0 and dt > 0.0:
            e = math.exp(-dt / tau)
            q = tau / dt * (1.0 - e)
            base = q * p[2, i] + (p[3, i] - p[2, i]) * e
            t_new = (y[i] - c * base) / (1.0 - c * q)
            s_new = (1.0 - q) * t_new + base
        p[2, i] = t_new
        p[3, i] = s_new
        y[i] = t_new


@njit(cache=True)
def _inverse_batch(t, y, p, out):
    """:func:`inverse_step` over the rows of ``y`` (N, m) at times ``t`` (N,)."""
    for k in range(y.shape[0]):
        out[k] = y[k]
        inverse_step(p, out[k], out[k], out[k], t[k] - t[k - 1] if k else 0.0, out[k])


class _Stepper:
    def __init__(self, c: np.ndarray, tau: np.ndarray) -> None:
        self.c = c
        self.active = bool(np.any((c != 0) & (tau > 0)))
        self.filter = LowpassStepper(tau)

    def step(self, s: Sample, y: np.ndarray) -> np.ndarray:
        if not self.active:
            return y
        return (1.0 - self.c) * y + self.c * self.filter.step(s.k, s.t, y)


class SensorCreep(Effect):
    name = "sensor_creep"
    stage = "sensor"
    order = 5  # first: the creep is in the strain gauge, before gain and zero
    params = (
        Param(
            "c",
            "1",
            0.0,
            low=-1.0,
            high=1.0,
            step=0.01,
            doc="fraction of a load change that arrives by creep",
        ),
        Param(
            "tau_s", "s", 1.0, low=0.0, low_open=True, step=0.05, doc="time constant of the creep"
        ),
    )
    physics = "(1 - c) T_s + c 1/(tau s + 1) T_s"
    online = Online(True, "exact causal inverse of the discrete creep, per cycle")
    online_kernel = inverse_step
    online_state = 2
    wrench = True
    group = "dynamics"
    nests = (lowpass_effect.EFFECT,)
    look = (
        "after every load change the measurement first falls short of the model by a "
        "fraction of the change and then creeps to it over a fixed time (overlay the two "
        "around a load change)"
    )
    plot = "dT/dt"
    separate = (
        "load changes held for longer than tau (a creep keeps closing the gap for tau, a "
        "low-pass settles within its own, much shorter, time constant)"
    )
    example = {"c": 0.05, "tau_s": 0.3}

    def forward(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        c, tau = p["c"], p["tau_s"]
        if not np.any((c != 0) & (tau > 0)):
            return y
        tau_cols = tau if np.ndim(y) > 1 else float(tau[0])
        c_cols = c if np.ndim(y) > 1 else float(c[0])
        return (1.0 - c_cols) * y + c_cols * lowpass(s.t, y, tau_cols)

    def inverse(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        y = np.asarray(y, dtype=float)
        y2 = np.ascontiguousarray(y.reshape(len(y), -1))
        m = y2.shape[1]
        rows = np.zeros((4, m))
        rows[0] = np.broadcast_to(p["c"], (m,))
        rows[1] = np.broadcast_to(p["tau_s"], (m,))
        out = np.empty_like(y2)
        _inverse_batch(np.asarray(s.t, dtype=float), y2, rows, out)
        return out.reshape(y.shape)

    def stepper(self, p: Values, cables: int, period_s: float) -> _Stepper:
        def arr(name: str) -> np.ndarray:
            return np.broadcast_to(np.asarray(p[name], dtype=float), (cables,)).copy()

        return _Stepper(arr("c"), arr("tau_s"))

    def present(self, values: Values, nom: NominalChain) -> np.ndarray:
        """Where ``c`` is not zero (the time constant means nothing without it)."""
        return np.asarray(values["c"], dtype=float) != 0.0

    def internal(self, values: Mapping[str, float]) -> np.ndarray:
        return np.array([float(values["c"]), math.log10(float(values["tau_s"]))])

    def report(self, theta: np.ndarray) -> dict[str, float]:
        return {"c": float(theta[0]), "tau_s": 10 ** float(theta[1])}

    def report_stderr(self, theta: np.ndarray, se: np.ndarray) -> dict[str, float]:
        return {"c": float(se[0]), "tau_s": 10 ** float(theta[1]) * math.log(10.0) * float(se[1])}

    def significance(self, theta: np.ndarray, se: np.ndarray, neutral: np.ndarray) -> float:
        """``c`` over its standard error (the time constant means nothing without it)."""
        return float(abs(theta[0]) / se[0]) if se[0] > 0 else 0.0

    def spec(self, d: FitData, nom: NominalChain, resid: np.ndarray, mask: np.ndarray) -> Spec:
        _, dt = speeds(d)
        span = float(d.t[-1] - d.t[0]) if d.t.size > 1 else 1.0
        lo = math.log10(max(TAU_MIN_S, 3 * dt))
        hi = max(math.log10(max(span / 3, 6 * dt)), lo + 0.5)
        starts = tuple(
            np.array([0.0, math.log10(tau)]) for tau in TAUS_S if lo <= math.log10(tau) <= hi
        )
        return Spec(
            np.array([0.0, 0.0]),
            np.array([-C_FIT, lo]),
            np.array([C_FIT, hi]),
            (0,),
            np.array([0.01, 0.05]),
            starts or (np.array([0.0, 0.5 * (lo + hi)]),),
        )


EFFECT = SensorCreep()
