"""``presliding``: Dahl pre-sliding instead of the Coulomb chain (docs/physics.md sec. 3, 5).

``sigma_n_m``: the Dahl stiffness; the chain runs the law ``dahl`` (eq. 14) with it. The
fit varies ``log10 sigma`` (a stiffness spans decades).
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
)


class Presliding(Effect):
    name = "presliding"
    stage = "chain"
    params = (
        Param("sigma_n_m", "N/m", 500.0, low=0.0, low_open=True, step=50.0, doc="Dahl stiffness"),
    )
    physics = "Dahl pre-sliding with stiffness sigma instead of the Coulomb chain"
    online = Online(True, "the chain runs Dahl")
    needs_motion = True
    group = "reversal"
    look = (
        "the residual is concentrated just after each reversal, over a few mm of travel "
        "(plot residual against travel since the last reversal)"
    )
    plot = "travel since reversal"
    separate = "many reversals with slow travel right after them"
    example = {"sigma_n_m": 150.0}

    def apply_chain(self, draft: ChainDraft, p: Values) -> None:
        draft.law = "dahl"
        draft.sigma_n_m = np.asarray(p["sigma_n_m"], dtype=float).copy()

    def internal(self, values: Mapping[str, float]) -> np.ndarray:
        return np.array([math.log10(float(values["sigma_n_m"]))])

    def report(self, theta: np.ndarray) -> dict[str, float]:
        return {"sigma_n_m": 10 ** float(theta[0])}

    def report_stderr(self, theta: np.ndarray, se: np.ndarray) -> dict[str, float]:
        return {"sigma_n_m": 10 ** float(theta[0]) * math.log(10.0) * float(se[0])}

    def spec(self, d: FitData, nom: NominalChain, resid: np.ndarray, mask: np.ndarray) -> Spec:
        s0 = math.log10(nom.sigma_n_m) if nom.model == "dahl" else 7.0
        starts = tuple(np.array([s]) for s in (1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 5.0))
        return Spec(np.array([s0]), np.array([0.5]), np.array([7.5]), (), np.array([0.05]), starts)


EFFECT = Presliding()
