"""``drift``: the sensor's zero moving linearly in time (docs/physics.md sec. 4): it reads
``+ k (t - t_0)``, ``t_0`` the recording's first time.

Not compensated online: ``t_0`` is the recording's time origin, which the running gateway
does not share, and extrapolating a drift over hours would add a growing error;
recalibrate the zero (a fitted ``offset``) instead.
"""

from __future__ import annotations

import numpy as np

from gateway.model.effects.base import Compose, Effect, Online, Param, Sample, Series, Values


class _Stepper:
    def __init__(self, k: np.ndarray) -> None:
        self.k = k
        self.t0 = 0.0

    def step(self, s: Sample, y: np.ndarray) -> np.ndarray:
        if s.k == 0:
            self.t0 = s.t
        return y + self.k * (s.t - self.t0)


def _elapsed(s: Series, y: np.ndarray) -> np.ndarray:
    t = np.asarray(s.t, dtype=float)
    return (t - s.t0).reshape((-1,) + (1,) * (np.ndim(y) - 1))


class Drift(Effect):
    name = "drift"
    stage = "sensor"
    order = 30
    params = (Param("k_n_s", "N/s", 0.0, step=1e-3, doc="rate of the zero's change"),)
    physics = "+ k t"
    online = Online(
        False,
        "the drift refers to the recording's time origin, which the running gateway does not "
        "share; recalibrate the zero (an offset) instead",
    )
    wrench = True
    per_recording = True  # each session re-zeroes the sensor
    group = "level"
    look = "the mean residual grows linearly with time (plot residual against t)"
    plot = "t"
    separate = "a longer recording (a drift grows with time, an offset does not)"
    example = {"k_n_s": 0.05}

    def forward(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        return y + p["k_n_s"] * _elapsed(s, y)

    def inverse(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        out = p["k_n_s"] * _elapsed(s, y)
        if out.shape != np.shape(y):
            return y - out
        return np.subtract(y, out, out=out)  # in place: the same values, one temporary fewer

    def stepper(self, p: Values, cables: int, period_s: float) -> _Stepper:
        return _Stepper(np.broadcast_to(np.asarray(p["k_n_s"], dtype=float), (cables,)).copy())

    def compose(self, old: Values, new: Values, ctx: Compose) -> Values:
        return {"k_n_s": old["k_n_s"] + ctx.outer_gain * new["k_n_s"]}


EFFECT = Drift()
