"""The catalogue of effects (physics.md sec. 5): names, parameters, units, meanings.

One entry per effect id. Each parameter has the name the diagnosis report, the plant's
``sim_plc.effects`` and a model file's ``friction.effects`` all use (recording.md), its
unit and its value when the effect is absent. :func:`effect_values` validates a mapping
``{effect: {parameter: scalar or per-cable list}}`` into per-cable arrays, naming the
offending key on error; :func:`chain_params` folds the friction-side effects into one
:class:`gateway.model.chain.ChainParams` for every user (plant, scenarios, diagnosis,
gateway).

Meanings (the one reading every user shares):

* ``coulomb.mu``: the bearing coefficient of *every* pulley of that cable, absolute (it
  replaces the nominal per-pulley ``mu``; NaN or absent: keep the nominal);
  ``coulomb.f0_n``: load-independent Coulomb level of the whole chain (N), split evenly
  over the pulleys and added to each pulley's Coulomb level ``F_R``, so under Dahl it
  shares the pre-sliding dynamics (``F_R = lambda T + f0 / n``).
* ``presliding.sigma_n_m``: Dahl stiffness; switches the chain to Dahl.
* ``viscous.c_ns_m``: added to the nominal ``viscous_ns_m`` (N s/m, summed over pulleys).
* ``stribeck``: ``F_R`` times ``1 + k exp(-(v / v_s)^2)``.
* ``eccentricity``: ``+ a sin(x / r + phi)`` with ``x`` the cable length (m) where it is
  known (plant, gateway: the setpoint length), else the travel since the first sample.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

Stage = Literal["chain", "path", "sensor", "statics"]
Effects = dict[str, dict[str, np.ndarray]]
"""Validated effect values: ``{effect: {parameter: (m,) array}}`` (``q_kg_s``: (1,))."""


@dataclass(frozen=True)
class Param:
    """One parameter: report name, unit, value when absent, admissible range."""

    name: str
    unit: str
    default: float
    low: float = -math.inf
    low_open: bool = False
    doc: str = ""

    def check(self, value: np.ndarray) -> str | None:
        """None when every finite value is admissible, else the reason."""
        v = value[np.isfinite(value)]
        if self.low_open and np.any(v <= self.low):
            return f"must be > {self.low:g}"
        if not self.low_open and np.any(v < self.low):
            return f"must be >= {self.low:g}"
        return None


@dataclass(frozen=True)
class Effect:
    """An effect of the catalogue: where it acts, its parameters, its physics."""

    name: str
    stage: Stage
    params: tuple[Param, ...]
    physics: str
    online: str
    per_cable: bool = True

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)


def _p(name: str, unit: str, default: float, low: float = -math.inf, open_: bool = False) -> Param:
    return Param(name, unit, default, low, open_)


REGISTRY: dict[str, Effect] = {
    e.name: e
    for e in (
        Effect(
            "coulomb",
            "chain",
            (_p("mu", "1", math.nan, 0.0), _p("f0_n", "N", 0.0, 0.0)),
            "- sgn(v) (lambda T + f0): per-pulley mu (absolute), load-independent f0",
            "yes: the chain's Coulomb level",
        ),
        Effect(
            "presliding",
            "chain",
            (_p("sigma_n_m", "N/m", 500.0, 0.0, True),),
            "Dahl pre-sliding with stiffness sigma instead of the Coulomb chain",
            "yes: the chain runs Dahl",
        ),
        Effect(
            "viscous",
            "chain",
            (_p("c_ns_m", "N s/m", 0.0),),
            "- c v (added to the nominal viscous_ns_m)",
            "yes: + c v_set",
        ),
        Effect(
            "stribeck",
            "chain",
            (_p("k", "1", 0.0, 0.0), _p("v_s_m_s", "m/s", 0.01, 0.0, True)),
            "Coulomb level times 1 + k exp(-(v / v_s)^2)",
            "yes: with v_set",
        ),
        Effect(
            "inertia",
            "path",
            (_p("m_eff_kg", "kg", 0.0),),
            "- m_eff a",
            "yes: a from the setpoint velocity, backward difference over the cycle's dt",
        ),
        Effect("delay", "sensor", (_p("d_s", "s", 0.0, 0.0),), "reading T_s(t - d)", "no"),
        Effect(
            "lowpass", "sensor", (_p("tau_s", "s", 0.0, 0.0),), "reading 1/(tau s + 1) T_s", "no"
        ),
        Effect(
            "gain",
            "sensor",
            (_p("g", "1", 0.0, -1.0, True),),
            "(1 + g) T_s",
            "yes: divide by 1 + g",
        ),
        Effect("offset", "sensor", (_p("c_n", "N", 0.0),), "+ c", "yes: subtract c"),
        Effect("drift", "sensor", (_p("k_n_s", "N/s", 0.0),), "+ k t", "no"),
        Effect(
            "eccentricity",
            "path",
            (_p("a_n", "N", 0.0), _p("r_m", "m", 0.05, 0.0, True), _p("phi_rad", "rad", 0.0)),
            "+ a sin(x / r + phi), x the cable length",
            "yes: x the setpoint length",
        ),
        Effect(
            "mass_change",
            "statics",
            (_p("q_kg_s", "kg/s", 0.0),),
            "platform mass m_0 + q t in the statics",
            "no (a platform effect: the gateway corrects tensions, not the mass)",
            per_cable=False,
        ),
    )
}
EFFECT_NAMES: tuple[str, ...] = tuple(REGISTRY)
CHAIN_EFFECTS: tuple[str, ...] = tuple(n for n, e in REGISTRY.items() if e.stage == "chain")
ONLINE_EFFECTS: tuple[str, ...] = tuple(
    n for n, e in REGISTRY.items() if e.online.startswith("yes")
)
"""Effects the gateway's per-cycle compensation applies."""


def _values(raw: Any, size: int, key: str) -> np.ndarray:
    if isinstance(raw, bool):
        raise ValueError(f"{key}: expected a number or a list of numbers, got {raw!r}")
    try:
        arr = np.asarray(raw, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{key}: expected a number or a list of numbers, got {raw!r}") from None
    if arr.ndim == 0:
        return np.full(size, float(arr))
    if arr.shape != (size,):
        raise ValueError(f"{key}: expected a scalar or {size} values, got {arr.size}")
    return arr.copy()


def effect_values(
    raw: Mapping[str, Any] | None,
    cables: int,
    pulley_radius_m: float = 0.05,
    where: str = "effects",
) -> Effects:
    """Validate ``{effect: {param: scalar | per-cable list}}``; missing params get defaults.

    Errors are ``ValueError`` whose message starts with the dotted key (``where.effect.p``).
    ``eccentricity.r_m`` defaults to ``pulley_radius_m``. ``mass_change.q_kg_s`` is one
    platform value (shape (1,)).
    """
    out: Effects = {}
    for name, params in (raw or {}).items():
        key = f"{where}.{name}"
        eff = REGISTRY.get(str(name))
        if eff is None:
            raise ValueError(f"{key}: unknown effect (known: {', '.join(EFFECT_NAMES)})")
        params = {} if params is None else params
        if not isinstance(params, Mapping):
            raise ValueError(f"{key}: expected a mapping of parameters")
        for p in params:
            if p not in eff.param_names:
                known = ", ".join(eff.param_names)
                raise ValueError(f"{key}.{p}: unknown parameter (known: {known})")
        size = cables if eff.per_cable else 1
        vals = {}
        for prm in eff.params:
            default = pulley_radius_m if prm.name == "r_m" else prm.default
            given = params.get(prm.name)  # absent or null: the default
            v = _values(default if given is None else given, size, f"{key}.{prm.name}")
            if prm.name != "mu" and not np.all(np.isfinite(v)):
                raise ValueError(f"{key}.{prm.name}: values must be finite")
            reason = prm.check(v)
            if reason:
                raise ValueError(f"{key}.{prm.name}: {reason}")
            vals[prm.name] = v
        out[eff.name] = vals
    return out


def to_mapping(eff: Effects) -> dict[str, dict[str, float | list[float]]]:
    """Plain YAML-ready form of validated values: a scalar where all cables agree.

    ``coulomb.mu`` that is NaN everywhere (keep the nominal) is left out.
    """
    out: dict[str, dict[str, float | list[float]]] = {}
    for name in EFFECT_NAMES:
        if name not in eff:
            continue
        params: dict[str, float | list[float]] = {}
        for p, v in eff[name].items():
            if p == "mu" and np.all(np.isnan(v)):
                continue
            same = v.size == 1 or bool(np.all(v == v[0]))
            params[p] = float(v[0]) if same else [float(x) for x in v]
        out[name] = params
    return out


def eccentricity_phase_at_length(phi_rad: float, r_m: float, length0_m: float) -> float:
    """Phase for ``x`` = cable length, from a phase fitted with ``x`` = travel since a
    sample whose length was ``length0_m``: ``a sin((L - L0)/r + phi) = a sin(L/r + phi')``.
    Wrapped to (-pi, pi]."""
    phi = phi_rad - length0_m / r_m
    return math.atan2(math.sin(phi), math.cos(phi))
