"""``offset``: the sensor's zero off by ``c`` (docs/physics.md sec. 4): it reads ``+ c``."""

from __future__ import annotations

import numpy as np
from numba import njit

from gateway.model.effects.base import Compose, Effect, Online, Param, Sample, Series, Values


@njit(cache=True)
def inverse_step(p, y, v, v_prev, dt, length):
    """Per cycle: ``y -= c``."""
    for i in range(y.size):
        y[i] -= p[0, i]


class _Stepper:
    def __init__(self, c: np.ndarray) -> None:
        self.c = c

    def step(self, s: Sample, y: np.ndarray) -> np.ndarray:
        return y + self.c


class Offset(Effect):
    name = "offset"
    stage = "sensor"
    order = 20
    params = (Param("c_n", "N", 0.0, step=1.0, doc="zero error"),)
    physics = "+ c"
    online = Online(True, "subtract c")
    online_kernel = inverse_step
    wrench = True
    per_recording = True  # each session re-zeroes the sensor
    group = "level"
    look = "the residual has a constant non-zero mean over the whole recording"
    plot = "t"
    separate = "a longer recording (a drift grows with time, an offset does not)"
    example = {"c_n": 1.5}

    def forward(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        return y + p["c_n"]

    def inverse(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        return y - p["c_n"]

    def stepper(self, p: Values, cables: int, period_s: float) -> _Stepper:
        return _Stepper(np.broadcast_to(np.asarray(p["c_n"], dtype=float), (cables,)).copy())

    def compose(self, old: Values, new: Values, ctx: Compose) -> Values:
        return {"c_n": old["c_n"] + ctx.outer_gain * new["c_n"]}


EFFECT = Offset()
