"""``lowpass``: the sensor rounds off fast changes (docs/physics.md sec. 4): it reads through
``1 / (tau s + 1)``, exact for an input linear between samples (uneven sampling handled).

Not compensated online: inverting the filter is a differentiator that amplifies the
sensor noise by ``tau / dt``. Offline (a model read back) it is undone as
``y + tau dy/dt``.
"""

from __future__ import annotations

import numpy as np

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

TIME_GRID = (1, 2, 3, 5, 8, 13, 20, 35, 60, 100, 200)
"""Starting points of a time constant or a delay, in sample periods."""


def time_spec(d: FitData) -> Spec:
    """A time (s) from 0 to 300 periods (at least 1 s), started on :data:`TIME_GRID`."""
    _, dt = speeds(d)
    return Spec(
        np.array([0.0]),
        np.array([0.0]),
        np.array([max(1.0, 300 * dt)]),
        (),
        np.array([dt / 4]),
        tuple(np.array([g * dt]) for g in TIME_GRID),
    )


class _Stepper:
    def __init__(self, tau: np.ndarray) -> None:
        self.active = bool(np.any(tau > 0))
        self.filter = LowpassStepper(tau)

    def step(self, s: Sample, y: np.ndarray) -> np.ndarray:
        if not self.active:
            return y
        return self.filter.step(s.k, s.t, y).copy()


class Lowpass(Effect):
    name = "lowpass"
    stage = "sensor"
    order = 40
    params = (Param("tau_s", "s", 0.0, low=0.0, step=1e-3, doc="time constant"),)
    physics = "reading 1/(tau s + 1) T_s"
    online = Online(
        False, "inverting the filter is a differentiator that amplifies the noise by tau / dt"
    )
    group = "dynamics"
    look = (
        "the measurement rounds off every fast edge of the model exponentially "
        "(overlay the two around a reversal)"
    )
    plot = "dT/dt"
    separate = "load steps or reversals faster than 5 ms"
    example = {"tau_s": 0.01}

    def forward(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        if not np.any(p["tau_s"] > 0):
            return y
        return lowpass(s.t, y, p["tau_s"])

    def inverse(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        return y + p["tau_s"] * np.gradient(y, s.t, axis=0)

    def stepper(self, p: Values, cables: int, period_s: float) -> _Stepper:
        return _Stepper(np.broadcast_to(np.asarray(p["tau_s"], dtype=float), (cables,)).copy())

    def spec(self, d: FitData, nom: NominalChain, resid: np.ndarray, mask: np.ndarray) -> Spec:
        return time_spec(d)


EFFECT = Lowpass()
