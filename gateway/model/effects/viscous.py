"""``viscous``: friction proportional to the cable speed (docs/physics.md sec. 4).

``c_ns_m``: added to the nominal ``viscous_ns_m`` (summed over the pulleys): the platform
side carries ``c v`` more than the chain's Coulomb/Dahl part. A correction may be
negative; the total (nominal plus correction) and a truth are >= 0.
"""

from __future__ import annotations

import numpy as np

from gateway.model.chain_schema import ChainDraft
from gateway.model.effects.base import (
    Compose,
    Effect,
    FitData,
    NominalChain,
    Online,
    Param,
    Spec,
    Values,
)


class Viscous(Effect):
    name = "viscous"
    stage = "chain"
    params = (
        Param(
            "c_ns_m",
            "N s/m",
            0.0,
            step=1.0,
            truth_low=0.0,
            doc="viscous coefficient added to the nominal",
        ),
    )
    physics = "- c v (added to the nominal viscous_ns_m)"
    online = Online(True, "+ c v_set")
    needs_motion = True
    wrench = True
    group = "speed"
    look = (
        "the residual grows in proportion to the cable speed, opposite to v "
        "(plot residual against v)"
    )
    plot = "v"
    separate = "travel at several constant speeds"
    example = {"c_ns_m": 25.0}

    def apply_chain(self, draft: ChainDraft, p: Values) -> None:
        draft.viscous_ns_m = draft.viscous_ns_m + p["c_ns_m"]

    def spec(self, d: FitData, nom: NominalChain, resid: np.ndarray, mask: np.ndarray) -> Spec:
        spec = self.linear_spec(nom)  # physical bound: the total coefficient is >= 0
        low = -float(np.min(np.asarray(nom.viscous_ns_m, dtype=float)))
        return Spec(spec.neutral, np.array([low]), spec.upper, spec.linear, spec.step, spec.starts)

    def compose(self, old: Values, new: Values, ctx: Compose) -> Values:
        return {"c_ns_m": old["c_ns_m"] + new["c_ns_m"]}


EFFECT = Viscous()
