"""``spring``: a force linear in the cable length (docs/physics.md sec. 4): the sensor reads
``+ k (x - l0)``, ``x`` the cable length where it is known (the soft PLC and the gateway:
the setpoint length) and the travel since the first sample where it is not.

An elastic element between sensor and platform (a return spring, a cable guide, the
stiffness of a flexure) stretched with the cable: zero at the length ``l0``. The fit varies
``(k, k l0)``, both linear (``k l0`` is the part a constant offset would hold); a length
fitted against the travel since the first sample converts to the cable length with
``l0_L = l0 + L_0`` (:meth:`Spring.from_fit`). ``k = 0`` is an ``offset`` of ``-k l0``:
the spring nests it and is kept only where the length shows on held-out data.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numba import njit

from gateway.model.effects import offset
from gateway.model.effects.base import (
    Compose,
    Effect,
    FitData,
    ModelFile,
    NominalChain,
    Online,
    Param,
    Sample,
    Series,
    Spec,
    Values,
    fresh,
)

MIN_SPAN_M = 0.001
"""Travel a cable must cover for a force linear in its length to show (else an offset).
A millimetre, not a centimetre: a short transmission carries springs too (a surgical
instrument's capstan strokes 5 mm and its residual falls with -700 N/m of spindle
position); what tells a spring from an offset is the nesting test on held-out blocks, the
span only rules out a cable that barely moves."""


@njit(cache=True)
def inverse_step(p, y, v, v_prev, dt, length):
    """Per cycle: ``y -= k (L - l0)``, ``L`` the setpoint length."""
    for i in range(y.size):
        if p[0, i] != 0.0:
            y[i] -= p[0, i] * (length[i] - p[1, i])


class _Stepper:
    def __init__(self, k: np.ndarray, l0: np.ndarray) -> None:
        self.k, self.l0 = k, l0

    def step(self, s: Sample, y: np.ndarray) -> np.ndarray:
        return y + self.k * (s.x - self.l0)


class Spring(Effect):
    name = "spring"
    stage = "path"
    order = 30
    params = (
        Param("k_n_m", "N/m", 0.0, step=1.0, doc="stiffness: force per metre of cable length"),
        Param("l0_m", "m", 0.0, step=0.01, doc="the length at which the force is zero"),
    )
    physics = "+ k (x - l0), x the cable length"
    online = Online(True, "x the setpoint length")
    online_kernel = inverse_step
    needs_motion = True
    wrench = True
    group = "level"
    nests = (offset.EFFECT,)
    beyond = (1.0, 0.0)  # the stiffness k
    look = (
        "the residual grows in proportion to the cable length, the same going out and "
        "coming back (plot residual against x)"
    )
    plot = "x"
    separate = (
        "moves back and forth over the same lengths (a spring returns with the length, a "
        "drift grows with time and an offset stays)"
    )
    example = {"k_n_m": 20.0, "l0_m": 2.8}

    def forward(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        return y + p["k_n_m"] * (s.x - p["l0_m"])

    def inverse(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        x = s.x
        out = np.subtract(x, p["l0_m"], out=fresh(s, x, p["l0_m"]))
        del x
        out *= p["k_n_m"]
        if out.shape != np.shape(y):
            return y - out
        return np.subtract(y, out, out=out)  # in place: the same values, two temporaries fewer

    def stepper(self, p: Values, cables: int, period_s: float) -> _Stepper:
        def arr(name: str) -> np.ndarray:
            return np.broadcast_to(np.asarray(p[name], dtype=float), (cables,)).copy()

        return _Stepper(arr("k_n_m"), arr("l0_m"))

    def present(self, values: Values, nom: NominalChain) -> np.ndarray:
        """Where the stiffness is not zero (the length means nothing without it)."""
        return np.asarray(values["k_n_m"], dtype=float) != 0.0

    def internal(self, values: Mapping[str, float]) -> np.ndarray:
        k = float(values["k_n_m"])
        return np.array([k, k * float(values["l0_m"])])

    def report(self, theta: np.ndarray) -> dict[str, float]:
        k, kl = float(theta[0]), float(theta[1])
        return {"k_n_m": k, "l0_m": kl / k if k != 0.0 else 0.0}

    def report_stderr(self, theta: np.ndarray, se: np.ndarray) -> dict[str, float]:
        k, kl = float(theta[0]), float(theta[1])
        k = k if k != 0.0 else 1e-12  # the length means nothing without a stiffness
        return {
            "k_n_m": float(se[0]),
            "l0_m": float(np.hypot(se[1] / k, kl * se[0] / k**2)),
        }

    def applicable(self, d: FitData, nom: NominalChain) -> bool:
        return (float(np.ptp(d.x)) if d.x.size else 0.0) >= MIN_SPAN_M

    def spec(self, d: FitData, nom: NominalChain, resid: np.ndarray, mask: np.ndarray) -> Spec:
        """``(k, k l0)`` both linear; scales 1 N/m and 1 N. Started at ``k`` = 1 N/m, not at
        0: at ``k = 0`` the report form ``k (x - l0)`` holds no ``k l0`` (``l0 = k l0 / k``
        is taken as 0 there), so a linear step from 0 solved ``k`` alone, a spring through
        the first sample's length (measured: a spring whose ``k (L_0 - l0)`` was 0.5 N
        screened worse than an offset and, nesting it, was never tried after it)."""
        spec = self.linear_spec(nom)
        start = spec.neutral + np.array([1.0, 0.0])
        return Spec(spec.neutral, spec.lower, spec.upper, (0, 1), np.array([1.0, 1.0]), (start,))

    def compose(self, old: Values, new: Values, ctx: Compose) -> Values:
        """Two springs are one: ``k = k_old + k_new`` and ``k l0`` adds the same way."""
        k = old["k_n_m"] + new["k_n_m"]
        kl = old["k_n_m"] * old["l0_m"] + new["k_n_m"] * new["l0_m"]
        safe = np.where(k != 0.0, k, 1.0)
        return {"k_n_m": k, "l0_m": np.where(k != 0.0, kl / safe, old["l0_m"])}

    def from_fit(self, values: Values, ctx: ModelFile) -> None:
        """A length fitted against the travel since the first sample -> the cable length,
        where the recording has lengths."""
        if ctx.length0 is not None:
            values["l0_m"] = values["l0_m"] + np.asarray(ctx.length0, dtype=float)


EFFECT = Spring()
