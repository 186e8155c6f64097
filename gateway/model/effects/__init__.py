"""The effects registry (physics.md sec. 5): one place for every effect of the catalogue.

* :mod:`.registry`: each effect's name, parameters (report names, units, defaults), where
  it acts, whether the gateway compensates it online; :func:`effect_values` validates a
  ``{effect: {parameter: value}}`` mapping into per-cable arrays.
* :func:`chain_params`: the nominal friction plus the friction-side effects as one
  :class:`~gateway.model.chain.ChainParams` (the plant, the scenarios, the diagnosis
  and the gateway all call it, so ``coulomb.mu`` means the same everywhere).
* :func:`path_sensor` / :func:`online_effects`: the path and sensor effects' parameters
  for the batch forms (:mod:`.forms`) and for the gateway's per-cycle form.
* :func:`compensate_online`: the gateway's compensation in batch form (the reference
  the per-cycle :class:`gateway.runtime.compensator.Compensator` is tested against).
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from gateway.model.chain import ChainParams, ModelName, compensate
from gateway.model.effects.forms import (
    ForwardStepper,
    OnlineEffects,
    PathSensorEffects,
    acceleration,
    apply_path_effects,
    apply_sensor_effects,
    causal_acceleration,
    delay,
    displacement,
    lowpass,
    online_inputs_into,
    remove_path_effects,
    remove_sensor_effects,
)
from gateway.model.effects.registry import (
    CHAIN_EFFECTS,
    EFFECT_NAMES,
    ONLINE_EFFECTS,
    REGISTRY,
    Effect,
    Effects,
    Param,
    eccentricity_phase_at_length,
    effect_values,
    to_mapping,
)

__all__ = [
    "CHAIN_EFFECTS",
    "EFFECT_NAMES",
    "ONLINE_EFFECTS",
    "REGISTRY",
    "Effect",
    "Effects",
    "ForwardStepper",
    "OnlineEffects",
    "Param",
    "PathSensorEffects",
    "acceleration",
    "apply_path_effects",
    "apply_sensor_effects",
    "causal_acceleration",
    "chain_params",
    "compensate_online",
    "delay",
    "displacement",
    "eccentricity_phase_at_length",
    "effect_values",
    "lowpass",
    "online_effects",
    "online_inputs_into",
    "path_sensor",
    "remove_path_effects",
    "remove_sensor_effects",
    "to_mapping",
]


class NominalFriction(Protocol):
    """What :func:`chain_params` reads of a nominal model (``FrictionConfig`` has it)."""

    @property
    def model(self) -> str: ...
    @property
    def wrap_rad(self) -> Any: ...
    @property
    def mu(self) -> Any: ...
    @property
    def sigma_n_m(self) -> float: ...
    @property
    def beta(self) -> float: ...
    @property
    def viscous_ns_m(self) -> Any: ...


def chain_params(nominal: NominalFriction, eff: Effects, cables: int) -> ChainParams:
    """The nominal chain with the friction-side effects of ``eff`` applied, ``cables`` wide.

    ``nominal.mu``: per pulley (n,) or (m, n); ``coulomb.mu`` (per cable) replaces every
    pulley's mu of that cable (absolute; NaN keeps the nominal); ``coulomb.f0_n`` is the
    chain's load-independent level; ``presliding`` switches to Dahl with its sigma;
    ``viscous.c_ns_m`` adds to the nominal; ``stribeck`` sets k and v_s. Coulomb or
    Stribeck on a ``none`` nominal switch it to ``coulomb``.
    """
    wrap = np.asarray(nominal.wrap_rad, dtype=float).reshape(-1)
    mu = np.broadcast_to(np.asarray(nominal.mu, dtype=float), (cables, wrap.size)).copy()
    model: str = nominal.model
    sigma = np.broadcast_to(np.asarray(nominal.sigma_n_m, dtype=float), (cables,)).copy()
    viscous = np.broadcast_to(np.asarray(nominal.viscous_ns_m, dtype=float), (cables,)).copy()
    f0, k, v_s = np.zeros(cables), np.zeros(cables), np.full(cables, 0.01)
    if "coulomb" in eff:
        new_mu = eff["coulomb"]["mu"]
        given = np.isfinite(new_mu)
        mu[given] = new_mu[given, None]
        f0 = eff["coulomb"]["f0_n"]
    if "presliding" in eff:
        model, sigma = "dahl", eff["presliding"]["sigma_n_m"]
    if "viscous" in eff:
        viscous = viscous + eff["viscous"]["c_ns_m"]
    if "stribeck" in eff:
        k, v_s = eff["stribeck"]["k"], eff["stribeck"]["v_s_m_s"]
    if model == "none" and ("coulomb" in eff or "stribeck" in eff):
        model = "coulomb"
    m: ModelName = model  # type: ignore[assignment]
    return ChainParams.build(m, cables, wrap, mu, sigma, nominal.beta, f0, k, v_s, viscous)


def path_sensor(eff: Effects, cables: int, pulley_radius_m: float = 0.05) -> PathSensorEffects:
    """Per-cable (m,) parameters of the path and sensor effects (0 where off)."""

    def get(name: str, param: str, default: float = 0.0) -> np.ndarray:
        if name not in eff:
            return np.full(cables, default)
        return np.asarray(eff[name][param], dtype=float)

    return PathSensorEffects(
        inertia_kg=get("inertia", "m_eff_kg"),
        eccentricity_a_n=get("eccentricity", "a_n"),
        eccentricity_r_m=get("eccentricity", "r_m", pulley_radius_m),
        eccentricity_phi_rad=get("eccentricity", "phi_rad"),
        gain=get("gain", "g"),
        offset_n=get("offset", "c_n"),
        drift_n_s=get("drift", "k_n_s"),
        lowpass_tau_s=get("lowpass", "tau_s"),
        delay_s=get("delay", "d_s"),
    )


def online_effects(eff: Effects, cables: int, pulley_radius_m: float = 0.05) -> OnlineEffects:
    """Parameters of the path and sensor effects the gateway removes per cycle."""
    return OnlineEffects.from_path_sensor(path_sensor(eff, cables, pulley_radius_m), cables)


def compensate_online(
    params: ChainParams,
    online: OnlineEffects,
    t: np.ndarray,
    reading: np.ndarray,
    velocity: np.ndarray,
    length: np.ndarray,
) -> np.ndarray:
    """Batch form of the gateway's compensation: reading (N, m) -> platform tension (N, m).

    Gain and offset removed, then inertia (:func:`causal_acceleration` of the setpoint
    velocity) and eccentricity (setpoint ``length``), then the chain (sensor -> platform)
    with ``dt`` from ``t``.
    """
    ts = remove_sensor_effects(reading, online)
    ts = remove_path_effects(ts, causal_acceleration(t, velocity), length, online)
    return compensate(params, ts, velocity, t)
