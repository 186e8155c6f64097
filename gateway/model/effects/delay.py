"""``delay``: the sensor's reading arrives late by ``d`` (docs/physics.md sec. 4): it reads
``T_s(t - d)`` (linear interpolation; before the first sample the first value holds).

Not compensated online: the gateway cannot advance a reading causally, and shifting the
model's velocity by ``d`` would only line the friction estimate up with a reading that is
still late. Offline (a model read back) the reading is advanced by ``d``.
"""

from __future__ import annotations

import math

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
)
from gateway.model.effects.forms import delay
from gateway.model.effects.lowpass import time_spec


class _Stepper:
    """Keeps the last ``d / period + 3`` readings and interpolates at ``t - d``."""

    def __init__(self, d: np.ndarray, period_s: float) -> None:
        self.d = d
        self.active = bool(np.any(d))
        size = math.ceil(float(d.max(initial=0.0)) / period_s) + 3
        self.hist_t, self.hist_y = np.zeros(size), np.zeros((size, d.size))

    def step(self, s: Sample, y: np.ndarray) -> np.ndarray:
        if s.k == 0:
            self.hist_t[:] = s.t - np.arange(self.hist_t.size)[::-1] * 1.0
            self.hist_y[:] = y
        else:
            self.hist_t[:-1], self.hist_y[:-1] = self.hist_t[1:], self.hist_y[1:]
            self.hist_t[-1], self.hist_y[-1] = s.t, y
        if not self.active:
            return y
        return np.array(
            [np.interp(s.t - d, self.hist_t, self.hist_y[:, i]) for i, d in enumerate(self.d)]
        )


class Delay(Effect):
    name = "delay"
    stage = "sensor"
    order = 50
    params = (Param("d_s", "s", 0.0, low=0.0, step=1e-3, doc="time the reading arrives late"),)
    physics = "reading T_s(t - d)"
    online = Online(False, "the gateway cannot advance a reading causally")
    group = "dynamics"
    look = (
        "the measurement lags the model by a fixed time, visible at every fast edge "
        "(overlay the two around a reversal)"
    )
    plot = "dT/dt"
    separate = "load steps or reversals faster than 5 ms"
    example = {"d_s": 0.01}

    def forward(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        if not np.any(p["d_s"] != 0):
            return y
        d = p["d_s"]
        return delay(s.t, y, float(d[0]) if np.ndim(y) == 1 else d)

    def inverse(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        t = np.asarray(s.t, dtype=float)
        if np.ndim(y) == 1:
            return np.interp(t + float(p["d_s"][0]), t, y)
        d = np.broadcast_to(np.asarray(p["d_s"], dtype=float), (y.shape[1],))
        return np.stack([np.interp(t + d[i], t, y[:, i]) for i in range(y.shape[1])], axis=1)

    def stepper(self, p: Values, cables: int, period_s: float) -> _Stepper:
        return _Stepper(
            np.broadcast_to(np.asarray(p["d_s"], dtype=float), (cables,)).copy(), period_s
        )

    def spec(self, d: FitData, nom: NominalChain, resid: np.ndarray, mask: np.ndarray) -> Spec:
        return time_spec(d)


EFFECT = Delay()
