"""``mass_change``: the platform's mass changes at a rate the controller does not know
(docs/physics.md sec. 4): the statics hold ``m(t) = m_rec + q (t - t_0)``.

One platform value (not per cable). The diagnosis needs pose, mass and a geometry for it
(the platform tension changes by ``q (t - t_0) dT_p/dm``). Not compensated online: it changes
the platform's wrench, not a cable's sensor chain.
"""

from __future__ import annotations

import numpy as np

from gateway.model.effects.base import Compose, Effect, Online, Param, Values


class MassChange(Effect):
    name = "mass_change"
    stage = "statics"
    params = (Param("q_kg_s", "kg/s", 0.0, step=1e-3, doc="rate of the hidden mass change"),)
    physics = "platform mass m_0 + q t in the statics"
    online = Online(False, "a platform effect: the gateway corrects tensions, not the mass")
    per_cable = False
    needs_mass = True
    wrench = True
    group = "level"
    look = "the residual grows with time in proportion to the cables' share of the platform weight"
    plot = "t"
    separate = "a recording with the platform at several poses over time"
    example = {"q_kg_s": 0.05}

    def mass_delta(self, t: np.ndarray, t0: float, p: Values) -> np.ndarray:
        """The mass (kg) the truth has beyond the recorded one at times ``t`` (N,)."""
        return float(p["q_kg_s"][0]) * (np.asarray(t, dtype=float) - t0)

    def compose(self, old: Values, new: Values, ctx: Compose) -> Values:
        return {"q_kg_s": old["q_kg_s"] + new["q_kg_s"]}


EFFECT = MassChange()
