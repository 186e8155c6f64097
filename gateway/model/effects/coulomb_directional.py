"""``coulomb_directional``: Coulomb/Dahl friction whose bearing coefficient differs by
direction (docs/physics.md sec. 4).

Real winches are fitted separately paying out and hauling in: ``mu_out`` is the bearing
coefficient of every pulley of the cable while it pays out (v > 0), ``mu_in`` while it is
hauled in (v < 0), absolute like ``coulomb.mu`` (NaN or absent: keep the nominal);
``f0_n`` as in ``coulomb``. The chain's law is unchanged (Coulomb, or Dahl whose level
then depends on the direction of travel): only its per-direction coefficients
``lambda(+)``, ``lambda(-)`` differ (:func:`gateway.model.chain_schema.coulomb_coefficients`).

While the cable moves, ``sgn(v) lambda_s T`` is ``sgn(v) (lambda_+ + lambda_-) / 2 T`` plus
``(lambda_+ - lambda_-) / 2 T`` of either sign of v: a symmetric Coulomb part and a part
that acts like a gain, but only in motion (at rest friction holds no level).
"""

from __future__ import annotations

import numpy as np

from gateway.model.chain_schema import ChainDraft
from gateway.model.effects import coulomb
from gateway.model.effects.base import (
    Compose,
    Effect,
    FitData,
    ModelFile,
    NominalChain,
    Online,
    Param,
    Spec,
    Values,
)

MU_NAMES = ("mu_out", "mu_in")


class CoulombDirectional(Effect):
    name = "coulomb_directional"
    stage = "chain"
    params = (
        Param(
            "mu_out",
            "1",
            float("nan"),
            low=0.0,
            high=0.5,
            step=1e-3,
            nominal="mu_mean",
            doc="bearing coefficient of every pulley paying out (v > 0), absolute",
        ),
        Param(
            "mu_in",
            "1",
            float("nan"),
            low=0.0,
            high=0.5,
            step=1e-3,
            nominal="mu_mean",
            doc="bearing coefficient of every pulley hauled in (v < 0), absolute",
        ),
        Param("f0_n", "N", 0.0, low=0.0, step=0.1, doc="load-independent level of the chain"),
    )
    physics = (
        "- sgn(v) (lambda_s T + f0), lambda_s from mu_out paying out (v > 0) and from "
        "mu_in hauling in (v < 0), per pulley, absolute"
    )
    online = Online(True, "the chain's per-direction Coulomb level")
    needs_motion = True
    wrench = True
    group = "scale"
    nests = (coulomb.EFFECT,)
    beyond = (1.0, -1.0, 0.0)  # mu_out - mu_in
    look = (
        "the residual scales with the load and differs in size between paying out and "
        "hauling in (plot residual against sgn(v) T: two slopes)"
    )
    plot = "sgn(v)*T"
    separate = "long moves in both directions at several loads, with stops between them"
    example = {"mu_out": 0.024, "mu_in": 0.012}

    def apply_chain(self, draft: ChainDraft, p: Values) -> None:
        for name, target in zip(MU_NAMES, (draft.mu, draft.mu_in), strict=True):
            mu = p[name]
            given = np.isfinite(mu)
            target[given] = np.maximum(mu[given], 0.0)[:, None]
        draft.f0_n = draft.f0_n + p["f0_n"]
        draft.needs_friction()

    def spec(self, d: FitData, nom: NominalChain, resid: np.ndarray, mask: np.ndarray) -> Spec:
        return coulomb.fit_spec(nom, 2)

    def applicable(self, d: FitData, nom: NominalChain) -> bool:
        """Only where pulleys wrap: without a bearing coefficient nothing differs by
        direction (the load-independent level alone is ``coulomb``)."""
        return bool(np.any(np.asarray(nom.wrap_rad, dtype=float) > 0))

    def compose(self, old: Values, new: Values, ctx: Compose) -> Values:
        out = {n: coulomb.move_from_nominal(old[n], new[n], ctx.nominal_mu) for n in MU_NAMES}
        out["f0_n"] = old["f0_n"] + new["f0_n"]
        return out

    def to_model(self, values: Values, ctx: ModelFile) -> None:
        coulomb.fold_negative_f0(self.name, values, MU_NAMES, ctx)


EFFECT = CoulombDirectional()
