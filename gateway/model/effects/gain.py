"""``gain``: the sensor's scale off by ``g`` (docs/physics.md sec. 4): it reads ``(1 + g) T``.

A reading keeps its sign: ``1 + g > 0``. A gain found on top of a model multiplies the
model's (``(1 + g)(1 + g') - 1``), and scales every additive sensor correction found inside
it (:meth:`Effect.gain_factor`).
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
)


@njit(cache=True)
def inverse_step(p, y, v, v_prev, dt, length):
    """Per cycle: ``y /= 1 + g``."""
    for i in range(y.size):
        y[i] /= 1.0 + p[0, i]


class _Stepper:
    def __init__(self, g: np.ndarray) -> None:
        self.scale = 1.0 + g

    def step(self, s: Sample, y: np.ndarray) -> np.ndarray:
        return self.scale * y


class Gain(Effect):
    name = "gain"
    stage = "sensor"
    order = 10
    params = (Param("g", "1", 0.0, low=-1.0, low_open=True, step=1e-3, doc="relative scale error"),)
    physics = "(1 + g) T_s"
    online = Online(True, "divide by 1 + g")
    online_kernel = inverse_step
    wrench = True
    group = "scale"
    look = (
        "the residual is proportional to the tension whatever the direction "
        "(plot residual against T)"
    )
    plot = "T"
    separate = "standstill at several loads (a gain acts at rest, friction does not)"
    example = {"g": 0.006}

    def forward(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        return (1.0 + p["g"]) * y

    def inverse(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        return y / (1.0 + p["g"])

    def stepper(self, p: Values, cables: int, period_s: float) -> _Stepper:
        return _Stepper(np.broadcast_to(np.asarray(p["g"], dtype=float), (cables,)).copy())

    def gain_factor(self, p: Values) -> np.ndarray:
        return 1.0 + p["g"]

    def spec(self, d: FitData, nom: NominalChain, resid: np.ndarray, mask: np.ndarray) -> Spec:
        spec = self.linear_spec(nom)  # the reading keeps its sign: 1 + g > 0
        return Spec(spec.neutral, np.array([-0.9]), spec.upper, spec.linear, spec.step, spec.starts)

    def compose(self, old: Values, new: Values, ctx: Compose) -> Values:
        return {"g": (1.0 + old["g"]) * (1.0 + new["g"]) - 1.0}


EFFECT = Gain()
