"""``inertia``: the pulleys' rotating mass between sensor and platform (docs/physics.md sec. 4).

The sensor reads ``T - m_eff a``. The truth (plant, diagnosis) takes ``a`` by second-order
differences with one sample of look-ahead; the gateway, which cannot look ahead, by the
backward difference of the setpoint velocity between new PLC samples
(:mod:`gateway.runtime.compensator` says how ``dt`` is taken).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from gateway.model.effects.base import (
    Compose,
    Effect,
    FitData,
    NominalChain,
    Online,
    Param,
    Sample,
    Series,
    Spec,
    Values,
    fresh,
)


@njit(cache=True)
def inverse_step(p, y, v, v_prev, dt, length):
    """Per cycle: ``y += m_eff (v - v_prev) / dt`` (nothing on the first cycle, dt <= 0)."""
    if dt <= 0.0:
        return
    for i in range(y.size):
        if p[0, i] != 0.0:
            y[i] += p[0, i] * (v[i] - v_prev[i]) / dt


class _Stepper:
    """The plant's form: the central difference over the previous, this and the next sample
    (the forward difference at the first), as ``np.gradient``."""

    def __init__(self, m_eff: np.ndarray) -> None:
        self.m_eff = m_eff

    def step(self, s: Sample, y: np.ndarray) -> np.ndarray:
        t3, v3 = s.t3, s.v3
        if s.k == 0:
            acc = (v3[2] - v3[1]) / (t3[2] - t3[1])
        else:
            dx1, dx2 = t3[1] - t3[0], t3[2] - t3[1]
            a = -(dx2) / (dx1 * (dx1 + dx2))
            b = (dx2 - dx1) / (dx1 * dx2)
            c = dx1 / (dx2 * (dx1 + dx2))
            acc = a * v3[0] + b * v3[1] + c * v3[2]
        return y - self.m_eff * acc


class Inertia(Effect):
    name = "inertia"
    stage = "path"
    order = 10
    params = (
        Param(
            "m_eff_kg",
            "kg",
            0.0,
            step=1.0,
            truth_low=0.0,
            doc="effective rotating mass at the cable",
        ),
    )
    physics = "- m_eff a"
    online = Online(True, "a from the setpoint velocity, backward difference over the cycle's dt")
    online_kernel = inverse_step
    needs_motion = True
    wrench = True
    group = "dynamics"
    look = "the residual follows the cable acceleration without lag (plot residual against a)"
    plot = "a"
    separate = "accelerations held for longer than the sensor's time constant"
    example = {"m_eff_kg": 20.0}

    def forward(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        return y - p["m_eff_kg"] * s.a

    def inverse(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        a = s.a
        out = np.multiply(p["m_eff_kg"], a, out=fresh(s, a, p["m_eff_kg"]))
        del a
        if out.shape != np.shape(y):
            return y + out
        out += y  # y + m a in place: the same values, one (N, m) temporary fewer
        return out

    def stepper(self, p: Values, cables: int, period_s: float) -> _Stepper:
        return _Stepper(np.broadcast_to(p["m_eff_kg"], (cables,)).copy())

    def spec(self, d: FitData, nom: NominalChain, resid: np.ndarray, mask: np.ndarray) -> Spec:
        spec = self.linear_spec(nom)  # a rotating mass is >= 0 (negative: a model-form error)
        return Spec(spec.neutral, np.array([0.0]), spec.upper, spec.linear, spec.step, spec.starts)

    def compose(self, old: Values, new: Values, ctx: Compose) -> Values:
        return {"m_eff_kg": old["m_eff_kg"] + new["m_eff_kg"]}


EFFECT = Inertia()
