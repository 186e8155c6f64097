"""``stribeck``: a Coulomb level raised at low speed (docs/physics.md sec. 4).

``F_R`` times ``1 + k exp(-(v / v_s)^2)``: ``k`` the excess at standstill, ``v_s_m_s`` the
speed over which it fades. The fit varies ``log10 v_s``, bounded to at most 1/8 of the
cable's typical speed (above that it would mimic a Coulomb change).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from gateway.model.chain_schema import ChainDraft
from gateway.model.effects.base import (
    Effect,
    FitData,
    NominalChain,
    Online,
    Param,
    Spec,
    Values,
    speeds,
)


class Stribeck(Effect):
    name = "stribeck"
    stage = "chain"
    params = (
        Param("k", "1", 0.0, low=0.0, step=0.05, doc="excess of the level at standstill"),
        Param(
            "v_s_m_s",
            "m/s",
            0.01,
            low=0.0,
            low_open=True,
            step=1e-3,
            doc="speed over which the excess fades",
        ),
    )
    physics = "Coulomb level times 1 + k exp(-(v / v_s)^2)"
    online = Online(True, "with v_set")
    needs_motion = True
    group = "speed"
    look = (
        "the residual is largest at low speed on either side of a reversal and fades with "
        "speed (plot residual against v near zero)"
    )
    plot = "v"
    separate = "slow travel (below v_s) held for longer than a reversal"
    example = {"k": 2.0, "v_s_m_s": 0.012}

    def apply_chain(self, draft: ChainDraft, p: Values) -> None:
        draft.stribeck_k = np.asarray(p["k"], dtype=float).copy()
        draft.stribeck_v_m_s = np.asarray(p["v_s_m_s"], dtype=float).copy()
        draft.needs_friction()

    def internal(self, values: Mapping[str, float]) -> np.ndarray:
        return np.array([float(values["k"]), math.log10(float(values["v_s_m_s"]))])

    def report(self, theta: np.ndarray) -> dict[str, float]:
        return {"k": float(theta[0]), "v_s_m_s": 10 ** float(theta[1])}

    def report_stderr(self, theta: np.ndarray, se: np.ndarray) -> dict[str, float]:
        v_s = 10 ** float(theta[1])
        return {"k": float(se[0]), "v_s_m_s": v_s * math.log(10.0) * float(se[1])}

    def spec(self, d: FitData, nom: NominalChain, resid: np.ndarray, mask: np.ndarray) -> Spec:
        v95, _ = speeds(d)
        lv = math.log10(v95)
        starts = tuple(np.array([0.0, lv + o]) for o in (-2.5, -2.0, -1.5, -1.0))
        return Spec(
            np.array([0.0, lv - 1.5]),
            np.array([0.0, lv - 4.0]),
            np.array([20.0, lv - 0.9]),
            (0,),
            np.array([0.05, 0.05]),
            starts,
        )


EFFECT = Stribeck()
