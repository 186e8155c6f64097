"""``maxwell_slip``: generalised Maxwell-slip presliding (docs/physics.md sec. 3, 4).

The chain runs the law ``maxwell_slip`` (:data:`gateway.model.chain_schema.LAWS`): each pulley's
friction is the sum of ``K`` Dahl elements in parallel, element ``q`` with the breakaway
level ``w_q F_R`` (the levels sum to the Coulomb level ``F_R``) and the stiffness
``w_q sigma_q``; each is stepped exactly like the Dahl state (eq. 14) over the same travel.
One element with ``w = 1`` is Dahl.

Parameterisation, and why: ``K = 2`` elements whose relaxation lengths ``F_R / sigma_q``
stand in the fixed ratio :data:`RATIO` (10), so two numbers describe the law:

* ``sigma_n_m``: the stiffness scale, ``sigma_1 = sigma`` (the stiff element relaxes over
  ``F_R / sigma``), ``sigma_2 = sigma / RATIO`` (the soft one over ten times that);
* ``w``: the fraction of the level the stiff element holds (the soft one ``1 - w``).

Each element's state relative to its level, ``z_q = F_q / (w_q F_R)``, follows
``dz/dx = (sigma_q / F_R) (1 - z sgn dx)`` whatever ``w_q``, so at a fixed ``sigma`` the
friction is linear in ``w``: the fit has one nonlinear parameter (``log10 sigma``, started
on a grid like ``presliding``) and one linear one, solved in one step. Free fractions of
more elements, or a free ratio, trade off against each other on ordinary motion (a sum of
exponentials in the travel is ill-conditioned beyond two terms a decade apart), and a
constraint that the fractions sum to one would not be a box the fit can hold. ``w = 1`` is
``presliding`` with ``sigma`` (and ``w = 0`` with ``sigma / RATIO``): it nests
``presliding`` and is kept only where it fits held-out data clearly better.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from gateway.model.chain_schema import ChainDraft
from gateway.model.effects import presliding
from gateway.model.effects.base import (
    Effect,
    FitData,
    NominalChain,
    Online,
    Param,
    Spec,
    Values,
)

RATIO = 10.0
"""The soft element's relaxation length over the stiff one's."""


def elements(sigma: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The chain's element fractions and stiffnesses per unit fraction, (m, 2) each."""
    w = np.asarray(w, dtype=float)
    sigma = np.asarray(sigma, dtype=float)
    return np.column_stack([w, 1.0 - w]), np.column_stack([sigma, sigma / RATIO])


class MaxwellSlip(Effect):
    name = "maxwell_slip"
    stage = "chain"
    order = 10  # after presliding: it sets the law and the stiffness
    params = (
        Param(
            "sigma_n_m",
            "N/m",
            float("nan"),
            low=0.0,
            low_open=True,
            step=50.0,
            nominal="sigma_n_m",
            doc="stiffness scale: the stiff element's (the soft one's is 1/10 of it)",
        ),
        Param(
            "w",
            "1",
            1.0,
            low=0.0,
            high=1.0,
            step=0.05,
            doc="fraction of the Coulomb level held by the stiff element",
        ),
    )
    physics = (
        "two Dahl elements per pulley: levels w F_R and (1 - w) F_R, relaxation lengths "
        "F_R / sigma and 10 F_R / sigma"
    )
    online = Online(True, "the chain runs Maxwell-slip")
    needs_motion = True
    wrench = True
    group = "reversal"
    nests = (presliding.EFFECT,)
    look = (
        "the residual is concentrated just after each reversal, with a fast part over the "
        "first fraction of a millimetre and a slower tail (plot residual against travel "
        "since the last reversal)"
    )
    plot = "travel since reversal"
    separate = (
        "many reversals with slow travel right after them, several mm each (a single "
        "Dahl state relaxes with one length, two elements with two)"
    )
    example = {"sigma_n_m": 5000.0, "w": 0.5}

    def apply_chain(self, draft: ChainDraft, p: Values) -> None:
        sigma = np.asarray(p["sigma_n_m"], dtype=float)
        sigma = np.where(np.isfinite(sigma), sigma, draft.sigma_n_m)
        draft.law = "maxwell_slip"
        draft.sigma_n_m = sigma
        draft.slip_w, draft.slip_sigma = elements(sigma, p["w"])

    def internal(self, values: Mapping[str, float]) -> np.ndarray:
        return np.array([math.log10(float(values["sigma_n_m"])), float(values["w"])])

    def report(self, theta: np.ndarray) -> dict[str, float]:
        return {"sigma_n_m": 10 ** float(theta[0]), "w": float(theta[1])}

    def report_stderr(self, theta: np.ndarray, se: np.ndarray) -> dict[str, float]:
        return {
            "sigma_n_m": 10 ** float(theta[0]) * math.log(10.0) * float(se[0]),
            "w": float(se[1]),
        }

    def spec(self, d: FitData, nom: NominalChain, resid: np.ndarray, mask: np.ndarray) -> Spec:
        s0 = math.log10(nom.sigma_n_m) if nom.model == "dahl" else 7.0
        grid = (2.5, 3.0, 3.5, 4.0, 4.5, 5.0)
        starts = tuple(np.array([s, 0.5]) for s in grid)
        return Spec(
            np.array([s0, 1.0]),
            np.array([0.5, 0.0]),
            np.array([7.5, 1.0]),
            (1,),
            np.array([0.05, 0.05]),
            starts,
        )


EFFECT = MaxwellSlip()
