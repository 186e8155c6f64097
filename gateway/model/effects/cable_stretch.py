"""``cable_stretch``: the axial stiffness ``k_n_m`` of the cable between winch and pulleys
(docs/physics.md sec. 3, 4).

The pulleys hold back the tension ``F = sum_j F_j`` (their friction): the cable on the
winch's side of them carries ``F`` less (paying out) or more (hauling in) than the platform
side, and stretches by ``F / k`` less or more. The travel that drives the pulleys'
presliding state is the setpoint travel minus that stretch change,
``d = dx - (F_k - F_{k-1}) / k`` (:func:`gateway.model.chain_kernels._step_cable`, solved per
sample: ``F_k`` depends on ``d``). The cable's compliance in series with the presliding
stiffness softens the transition after a reversal: it starts with the slope
``2 sigma / (1 + 2 sigma / k)`` per pulley instead of ``2 sigma`` and ends in the same tail.

Only the stretch the friction causes is modelled, not the one a changing load causes:
from the sensor side that part is the difference of two *readings*, and the sensor noise
would enter the travel as ``noise / k`` per sample (0.5 N at 1 kHz and ``k = 10^4`` N/m:
0.07 mm per cycle against 0.03 mm of travel at 0.03 m/s), which holds the presliding state
at about half its level (measured: 2.2 N of a 4.1 N mean level). The friction's own
stretch comes from the model's state, the same in the plant, the diagnosis and the
gateway, so it is compensated online.

Absent: ``k = inf`` (a rigid cable; :data:`K_MAX` or more where a number must stand). The
fit varies the compliance ``1 / k`` (0: absent).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from gateway.model.chain_schema import ChainDraft
from gateway.model.effects.backlash import travel_driven
from gateway.model.effects.base import (
    INF,
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

STIFFNESSES = (1e5, 1e4, 3e3, 1e3)
"""Starting points of the fit (N/m), stiffest first: on a recording without stretch it is
the best, and a start's simulation stops once its error exceeds the best so far
(:func:`gateway.diagnose.fit.best_start`), so the softer ones stop sooner (a clean 10-min
8-cable recording: 5.1 -> 4.2 M rows simulated while screening this effect)."""
K_MAX = 1e12
"""A rigid cable's stiffness where a number must stand (a compliance fitted at 0 in a
report; a cable without stretch in a model file's per-cable list, whose numbers are
finite): the chain takes any ``k >= K_MAX`` as rigid."""


class CableStretch(Effect):
    name = "cable_stretch"
    stage = "chain"
    order = 30
    params = (
        Param(
            "k_n_m",
            "N/m",
            INF,
            low=0.0,
            low_open=True,
            step=1e3,
            doc="axial stiffness of the cable between winch and pulleys",
        ),
    )
    physics = "travel driving the friction state: setpoint travel - dF / k (stretch)"
    online = Online(True, "the chain's travel minus the friction's stretch change")
    needs_motion = True
    wrench = True
    group = "reversal"
    look = (
        "the transition after each reversal starts softer than the model's and ends in the "
        "same tail, later on cables that carry more friction (plot residual against travel "
        "since the last reversal)"
    )
    plot = "travel since reversal"
    separate = (
        "reversals at several loads (the stretch adds a travel F / k that grows with the "
        "whole chain's friction, a softer presliding a length per pulley)"
    )
    example = {"k_n_m": 5000.0}

    def apply_chain(self, draft: ChainDraft, p: Values) -> None:
        k = np.asarray(p["k_n_m"], dtype=float)
        draft.stretch_c = np.where(k < K_MAX, 1.0 / np.minimum(k, K_MAX), 0.0)

    def compose(self, old: Values, new: Values, ctx: Compose) -> Values:
        """A compliance found on top of a model's adds to it (in series)."""
        with np.errstate(divide="ignore"):  # both rigid: k = inf
            return {"k_n_m": 1.0 / (1.0 / old["k_n_m"] + 1.0 / new["k_n_m"])}

    def to_model(self, values: Values, ctx: ModelFile) -> None:
        """A rigid cable (``k = inf``, where another cable's stretch was found) is written as
        :data:`K_MAX` (a model file's numbers are finite)."""
        k = values["k_n_m"]
        values["k_n_m"] = np.where(np.isfinite(k), k, K_MAX)

    def applicable(self, d: FitData, nom: NominalChain) -> bool:
        return travel_driven(nom)

    def internal(self, values: Mapping[str, float]) -> np.ndarray:
        return np.array([1.0 / float(values["k_n_m"])])

    def report(self, theta: np.ndarray) -> dict[str, float]:
        return {"k_n_m": 1.0 / max(float(theta[0]), 1.0 / K_MAX)}

    def report_stderr(self, theta: np.ndarray, se: np.ndarray) -> dict[str, float]:
        c = max(float(theta[0]), 1.0 / K_MAX)
        return {"k_n_m": float(se[0]) / c**2}

    def spec(self, d: FitData, nom: NominalChain, resid: np.ndarray, mask: np.ndarray) -> Spec:
        return Spec(
            np.array([0.0]),
            np.array([0.0]),
            np.array([1e-2]),
            (),
            np.array([1e-5]),
            tuple(np.array([1.0 / k]) for k in STIFFNESSES),
        )


EFFECT = CableStretch()
