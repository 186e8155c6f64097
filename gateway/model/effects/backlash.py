"""``backlash``: a dead zone in the travel that drives the friction state (docs/physics.md
sec. 3, 4).

``width_m``: after a reversal the setpoint travels ``b`` before the pulleys' presliding
state starts to change (the play operator of :func:`gateway.model.chain_kernels._play`: the drive
stands inside ``[-b/2, b/2]`` of the setpoint and follows it at the edges; it starts
centred). It acts on the state the travel drives (Dahl, Maxwell-slip); a Coulomb chain's
friction follows the sign of the velocity and has nothing for it to delay
(:meth:`Backlash.applicable`). The travel is the setpoint's, so the gateway compensates it
per cycle (no reading enters it).
"""

from __future__ import annotations

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

WIDTHS_MM = (0.3, 1.0, 3.0, 8.0, 20.0)
"""Starting points of the fit (mm)."""


def travel_driven(nom: NominalChain) -> bool:
    """Whether the nominal chain has a state the travel drives (not Coulomb, not none)."""
    return nom.model not in ("coulomb", "none")


class Backlash(Effect):
    name = "backlash"
    stage = "chain"
    order = 20
    params = (
        Param(
            "width_m",
            "m",
            0.0,
            low=0.0,
            step=1e-4,
            doc="travel after a reversal before the friction starts to change",
        ),
    )
    physics = "the friction state driven through a dead zone of width b in the travel"
    online = Online(True, "the chain's travel through the dead zone (the setpoint's)")
    needs_motion = True
    wrench = True
    group = "reversal"
    look = (
        "after each reversal the residual holds while the cable travels a fixed distance, "
        "then the transition runs late (plot residual against travel since the last reversal)"
    )
    plot = "travel since reversal"
    separate = (
        "reversals of several sizes with slow travel after them (a dead zone delays the "
        "transition by a fixed travel, a softer presliding stretches it)"
    )
    example = {"width_m": 0.003}

    def apply_chain(self, draft: ChainDraft, p: Values) -> None:
        draft.backlash_m = np.asarray(p["width_m"], dtype=float).copy()

    def applicable(self, d: FitData, nom: NominalChain) -> bool:
        return travel_driven(nom)

    def spec(self, d: FitData, nom: NominalChain, resid: np.ndarray, mask: np.ndarray) -> Spec:
        span = max(float(np.ptp(d.x)) if d.x.size else 0.0, 0.05)
        return Spec(
            np.array([0.0]),
            np.array([0.0]),
            np.array([min(0.1, span)]),
            (),
            np.array([1e-4]),
            tuple(np.array([w * 1e-3]) for w in WIDTHS_MM),
        )


EFFECT = Backlash()
