"""The effects of the catalogue (docs/physics.md sec. 4): one module per effect.

Each module (``coulomb``, ``coulomb_directional``, ``presliding``, ``viscous``, ``stribeck``,
``inertia``, ``eccentricity``, ``gain``, ``offset``, ``drift``, ``lowpass``, ``delay``,
``mass_change``, ``maxwell_slip``, ``cable_stretch``, ``backlash``, ``sensor_creep``,
``spring``) defines one :class:`~.base.Effect` object carrying every behaviour the
project needs of that effect (:mod:`.base` lists them); :mod:`.registry` collects them, and
everything that serves all effects loops over it. (The signal helpers ``delay`` and
``lowpass`` are in :mod:`.forms`: the package's names ``delay`` and ``lowpass`` are the
effect modules.) Adding an effect: write its module, list
it in :data:`.registry.MODULES`, add its section to docs/physics.md and its tests (a new
chain-side friction law also gets a row in :data:`gateway.model.chain.LAWS`).
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
