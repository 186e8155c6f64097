"""The effects of the catalogue (docs/physics.md sec. 4): one module per effect.

Each module (:data:`.registry.MODULES` lists them in the catalogue's order) defines one
:class:`~.base.Effect` object carrying every behaviour the project needs of that effect
(:mod:`.base` lists them); :mod:`.registry` collects them, and everything that serves all
effects loops over it. (The signal helpers ``delay`` and ``lowpass`` are in :mod:`.forms`:
the package's names ``delay`` and ``lowpass`` are the effect modules.) Adding an effect:
write its module, list it in :data:`.registry.MODULES`, add its section to
docs/physics.md and its tests. A chain-side effect that needs a parameter the chain does
not have yet declares it once, a row of :data:`gateway.model.chain_schema.COLUMNS` (the draft it
edits, the chain's parameters and the kernels' columns follow from it), and puts its term
in the chain's law (:func:`gateway.model.chain_kernels._level` for the Coulomb level); a new
friction law gets a row in :data:`gateway.model.chain_schema.LAWS`.
"""

from __future__ import annotations

from gateway.model.effects.base import (
    Effect,
    Effects,
    Param,
    Sample,
    Series,
    SeriesData,
    Spec,
    Values,
)
from gateway.model.effects.forms import acceleration, causal_acceleration, displacement
from gateway.model.effects.registry import (
    ACTING,
    EFFECT_NAMES,
    ONLINE_EFFECTS,
    REGISTRY,
    ForwardStepper,
    OnlineInverse,
    chain_params,
    compensate_online,
    effect_values,
    forward,
    inverse,
    mass_delta,
    ordered,
    stage_of,
    to_mapping,
)

__all__ = [
    "ACTING",
    "EFFECT_NAMES",
    "ONLINE_EFFECTS",
    "REGISTRY",
    "Effect",
    "Effects",
    "ForwardStepper",
    "OnlineInverse",
    "Param",
    "Sample",
    "Series",
    "SeriesData",
    "Spec",
    "Values",
    "acceleration",
    "causal_acceleration",
    "chain_params",
    "compensate_online",
    "displacement",
    "effect_values",
    "forward",
    "inverse",
    "mass_delta",
    "ordered",
    "stage_of",
    "to_mapping",
]
