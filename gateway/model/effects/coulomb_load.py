"""``coulomb_load``: a bearing coefficient that grows with the load (docs/physics.md sec. 4).

``mu1_per_n``: every pulley's bearing coefficient grows with the tension it carries,
``mu_j(T) = mu_j + mu1 |T|`` (a bearing's friction coefficient rises with its load: the
da Vinci transmissions' residual after a constant ``mu`` is ``sgn(v) T``-shaped and grows
with the load). The chain takes it in the Coulomb level, to first order in ``mu1 |T|``:
``F_R = (lambda_j + 2 sin(wrap_j / 2) mu1 |T|) |T|`` (``2 sin(wrap / 2)`` is
``d lambda / d mu`` at small ``mu``; :func:`gateway.model.chain_kernels._level`), so the excess
over a constant coefficient grows with ``T^2``. The chain's column is ``mu_load``; under
Dahl it shares the presliding dynamics. Friction only ever adds: ``mu1 >= 0``; a
correction found on top of a model adds to it.
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
    Values,
)


class CoulombLoad(Effect):
    name = "coulomb_load"
    stage = "chain"
    params = (
        Param(
            "mu1_per_n",
            "1/N",
            0.0,
            low=0.0,
            step=1e-5,
            doc="growth of every pulley's bearing coefficient per newton of its tension",
        ),
    )
    physics = "- sgn(v) lambda(mu + mu1 |T|) T: the bearing coefficient grows with the load"
    online = Online(True, "the chain's Coulomb level")
    needs_motion = True
    wrench = True
    group = "scale"
    look = (
        "the residual flips sign with the direction of motion and grows faster than the "
        "load, with its square (plot residual against sgn(v) T: a parabola, not a line)"
    )
    plot = "sgn(v)*T"
    separate = "travel at several loads (the excess grows as T^2, a coefficient's as T)"
    example = {"mu1_per_n": 6e-5}

    def apply_chain(self, draft: ChainDraft, p: Values) -> None:
        draft.mu_load = draft.mu_load + p["mu1_per_n"]
        draft.needs_friction()

    def applicable(self, d: FitData, nom: NominalChain) -> bool:
        """Only where pulleys wrap: the coefficient acts through the wrap."""
        return bool(np.any(np.asarray(nom.wrap_rad, dtype=float) > 0))

    def compose(self, old: Values, new: Values, ctx: Compose) -> Values:
        return {"mu1_per_n": old["mu1_per_n"] + new["mu1_per_n"]}


EFFECT = CoulombLoad()
