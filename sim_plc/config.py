"""The ``sim_plc:`` section of a config file: YAML -> frozen dataclasses.

``load_sim_config(cfg)`` validates ``cfg.sim_plc`` (kept raw by :mod:`gateway.core.config`) with
key paths prefixed ``sim_plc`` and resolves what defaults to other sections: the truth
friction (``sim_plc.friction`` is merged over the config's ``friction:``), the tension
limits of the plant's tension distribution (``sim_plc.tension`` over ``tension:``) and the
initial platform mass (``geometry.platform_mass_kg``). ``sim_plc.distribution`` chooses the
controller's tension distribution (:mod:`sim_plc.distribution`; default: the statics).

Effects (physics.md sec. 4) are switched on by naming them under ``sim_plc.effects``;
``enabled: false`` switches a named one off again. Their parameter names are those of the
diagnosis report (docs/recording-format.md) and the effects registry
(:mod:`gateway.model.effects`). Each parameter is a scalar for every cable or a
list with one value per cable.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from gateway.core.config import Config, FrictionConfig, TensionConfig
from gateway.core.configtypes import convert, require
from gateway.errors import ConfigError
from gateway.model.effects import REGISTRY, Effects, effect_values
from sim_plc.distribution import DistributionConfig

PerCable = float | tuple[float, ...]
Vec6 = tuple[float, float, float, float, float, float]


@dataclass(frozen=True)
class PaperPathConfig:
    """Paper eq. 20 path in mm: x = 200 sin(5 - u), y = 15 (15 - u), z = 10 u.

    ``u`` runs over [u_start, u_end]; u = 0..15 is where y = 15 (15 - u) runs down to 0
    (0.40 x 0.225 x 0.15 m). ``offset_m`` is added to the path (None: the path's bounding
    box, both layers, is centred on ``geometry.home_pose``). Layer k >= 2 is the same path
    lifted by (k - 1) ``layer_height_m``, printed in the opposite direction (a continuous
    bead) after a vertical lift at rest. Each segment starts and stops at rest with
    cycloidal speed ramps of ``ramp_s``.
    """

    speed_m_s: float = 0.04
    layers: int = 2
    u_start: float = 0.0
    u_end: float = 15.0
    layer_height_m: float = 0.02
    ramp_s: float = 0.5
    offset_m: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        require(self.speed_m_s > 0, "speed_m_s must be > 0")
        require(self.layers >= 1, "layers must be >= 1")
        require(self.u_end > self.u_start, "u_end must be > u_start")
        require(self.layer_height_m >= 0, "layer_height_m must be >= 0")
        require(self.ramp_s >= 0, "ramp_s must be >= 0")


@dataclass(frozen=True)
class CyclicConfig:
    """``pose_k(t) = center_k + amplitude_k sin(2 pi f_k t + phase_k)`` in all six DOF.

    Equal frequencies and phases (the default) move the platform back and forth along one
    line in pose space through ``center`` (None: ``geometry.home_pose``), paper Fig. 9.
    """

    amplitude: Vec6 = (0.2, 0.15, 0.1, 0.05, 0.05, 0.08)
    frequency_hz: Vec6 = (0.1, 0.1, 0.1, 0.1, 0.1, 0.1)
    phase_rad: Vec6 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    center: Vec6 | None = None

    def __post_init__(self) -> None:
        require(all(f >= 0 for f in self.frequency_hz), "frequency_hz must be >= 0")


@dataclass(frozen=True)
class RandomConfig:
    """Smooth random motion: per DOF a sum of ``components`` sinusoids with random
    frequencies in [min_frequency_hz, max_frequency_hz] and phases, bounded by
    ``amplitude`` around ``center`` (None: home pose); reverses direction often."""

    seed: int = 7
    amplitude: Vec6 = (0.2, 0.15, 0.1, 0.04, 0.04, 0.06)
    components: int = 4
    min_frequency_hz: float = 0.02
    max_frequency_hz: float = 0.3
    center: Vec6 | None = None

    def __post_init__(self) -> None:
        require(self.components >= 1, "components must be >= 1")
        require(0 < self.min_frequency_hz <= self.max_frequency_hz, "need 0 < min <= max freq")


@dataclass(frozen=True)
class FileTrajectoryConfig:
    """CSV with columns t, x, y, z, rx, ry, rz (s, m, rad) and optionally printing (0/1).

    A relative ``path`` is taken relative to the config file's directory.
    """

    path: str = ""


@dataclass(frozen=True)
class TrajectoryConfig:
    kind: Literal["paper", "cyclic", "random", "file"] = "paper"
    repeat: bool = True  # start again (mass refilled) after a finite trajectory ends
    paper: PaperPathConfig = field(default_factory=PaperPathConfig)
    cyclic: CyclicConfig = field(default_factory=CyclicConfig)
    random: RandomConfig = field(default_factory=RandomConfig)
    file: FileTrajectoryConfig = field(default_factory=FileTrajectoryConfig)


@dataclass(frozen=True)
class EffectsConfig:
    """``sim_plc.effects`` validated by the effects registry (:mod:`gateway.model.effects`).

    ``declared``: as written (``enabled`` removed), by effect id; ``values``: the effects
    that are on, as per-cable arrays (``eccentricity.r_m`` defaults to the friction's
    ``pulley_radius_m``).
    """

    declared: dict[str, dict[str, Any]] = field(default_factory=dict)
    values: Effects = field(default_factory=dict)

    def active(self) -> dict[str, dict[str, Any]]:
        """Effects that are on, by id (physics.md sec. 4), as written."""
        return {name: self.declared[name] for name in self.values}


def _effects(raw: dict[str, Any], cables: int, radius: float, src: str) -> EffectsConfig:
    declared, on = {}, {}
    for name, params in raw.items():
        if params is None:  # named without parameters: off, as before
            params = {"enabled": False}
        params = dict(params) if isinstance(params, dict) else params
        if not isinstance(params, dict):
            raise ConfigError(f"{src}: sim_plc.effects.{name}: expected a mapping")
        enabled = params.pop("enabled", True)
        if not isinstance(enabled, bool):
            raise ConfigError(f"{src}: sim_plc.effects.{name}.enabled: expected true or false")
        declared[name] = params
        if enabled:
            on[name] = params
    try:
        effect_values(declared, cables, radius, "sim_plc.effects")
        values = effect_values(on, cables, radius, "sim_plc.effects")
    except ValueError as exc:
        raise ConfigError(f"{src}: {exc}") from None
    for name, params in values.items():  # the truth keeps physical signs
        for prm in REGISTRY[name].params:
            low = prm.truth_low
            if low is not None and np.any(params[prm.name] < low):
                raise ConfigError(f"{src}: sim_plc.effects.{name}.{prm.name}: must be >= {low:g}")
    return EffectsConfig(declared, values)


@dataclass(frozen=True)
class SimPlcRaw:
    """The ``sim_plc:`` mapping as written (``friction``/``tension`` are partial overrides)."""

    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    period_s: float = 0.001
    extrusion_kg_s: float = 0.1
    initial_mass_kg: float | None = None
    noise_std_n: PerCable = 0.5
    seed: int = 1
    saturation_n: float | None = None
    friction: dict[str, Any] = field(default_factory=dict)
    tension: dict[str, Any] = field(default_factory=dict)
    effects: dict[str, Any] = field(default_factory=dict)
    distribution: DistributionConfig = field(default_factory=DistributionConfig)

    def __post_init__(self) -> None:
        require(1e-4 <= self.period_s <= 1.0, "period_s must be in 0.0001..1")
        require(self.extrusion_kg_s >= 0, "extrusion_kg_s must be >= 0")


@dataclass(frozen=True)
class SimPlcConfig:
    """Resolved soft-PLC settings (see module docstring). ``source``: the config file."""

    trajectory: TrajectoryConfig
    period_s: float
    extrusion_kg_s: float
    initial_mass_kg: float
    noise_std_n: PerCable
    seed: int
    saturation_n: float  # analog sensor output limit (N), above the 500 N range
    friction: FrictionConfig  # truth friction before effects
    tension: TensionConfig  # limits of the plant's tension distribution
    effects: EffectsConfig
    source: str = ""
    base_dir: str = "."
    distribution: DistributionConfig = field(default_factory=DistributionConfig)  # controller's


def per_cable(value: PerCable | None, cables: int, default: float = 0.0) -> np.ndarray:
    """Scalar or per-cable list -> (m,) float array."""
    if value is None:
        return np.full(cables, default)
    if isinstance(value, tuple):
        return np.asarray(value, dtype=float)
    return np.full(cables, float(value))


def _check_noise(noise: PerCable, cables: int, src: str) -> None:
    arr = np.atleast_1d(np.asarray(noise, dtype=float))
    if isinstance(noise, tuple) and len(noise) != cables:
        raise ConfigError(
            f"{src}: sim_plc.noise_std_n: expected one value per cable ({cables}), got {len(noise)}"
        )
    if np.any(arr < 0):
        raise ConfigError(f"{src}: sim_plc.noise_std_n: must be >= 0")


def load_sim_config(cfg: Config) -> SimPlcConfig:
    """Validate ``cfg.sim_plc`` and resolve its defaults; errors name ``sim_plc.<key>``."""
    src = cfg.source
    raw = convert(SimPlcRaw, cfg.sim_plc, "sim_plc", src)
    friction = convert(
        FrictionConfig,
        {**dataclasses.asdict(cfg.friction), "effects": {}, **raw.friction},
        "sim_plc.friction",
        src,
    )
    tension = convert(
        TensionConfig, {**dataclasses.asdict(cfg.tension), **raw.tension}, "sim_plc.tension", src
    )
    _check_noise(raw.noise_std_n, cfg.cables, src)
    effects = _effects(raw.effects, cfg.cables, friction.pulley_radius_m, src)
    mass = cfg.geometry.platform_mass_kg if raw.initial_mass_kg is None else raw.initial_mass_kg
    if mass <= 0:
        raise ConfigError(f"{src}: sim_plc.initial_mass_kg: must be > 0")
    saturation = 1.2 * cfg.sensor.range_n if raw.saturation_n is None else raw.saturation_n
    if saturation <= 0:
        raise ConfigError(f"{src}: sim_plc.saturation_n: must be > 0")
    dist = raw.distribution
    lo = tension.min_n if dist.tau_min_n is None else dist.tau_min_n
    hi = tension.max_n if dist.tau_max_n is None else dist.tau_max_n
    if not lo < hi or (dist.target_n is not None and not lo <= dist.target_n <= hi):
        raise ConfigError(
            f"{src}: sim_plc.distribution: limits {lo:g} .. {hi:g} N (target within them) needed"
        )
    if raw.trajectory.kind == "file" and not raw.trajectory.file.path:
        raise ConfigError(f"{src}: sim_plc.trajectory.file.path: required for kind 'file'")
    return SimPlcConfig(
        trajectory=raw.trajectory,
        period_s=raw.period_s,
        extrusion_kg_s=raw.extrusion_kg_s,
        initial_mass_kg=float(mass),
        noise_std_n=raw.noise_std_n,
        seed=raw.seed,
        saturation_n=float(saturation),
        friction=friction,
        tension=tension,
        effects=effects,
        source=src,
        base_dir=str(Path(src).resolve().parent) if src else ".",
        distribution=dist,
    )
