"""Platform tensions from pose and mass (statics), and their sensitivity to the mass.

Used when a recording has no ``tension_platform_i`` columns (then every sample is solved)
and for ``mass_change`` (``dT_p/dm`` per sample, needs pose and mass columns). The wrench
is gravity plus the d'Alembert term ``-m a`` (``a`` from the recorded positions by finite
differences), as in :mod:`gateway.model.statics`; the tension limits are the config's.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from gateway.core.config import Config
from gateway.errors import ConfigError, InfeasiblePoseError, RecordingError
from gateway.model import kinematics, statics
from gateway.model.effects.forms import acceleration
from gateway.recordings.reader import Recording

SENSITIVITY_POINTS = 2000
"""Samples at which dT_p/dm is solved (interpolated in time in between)."""


def _wrenches(cfg: Config, rec: Recording, idx: np.ndarray, mass: np.ndarray) -> np.ndarray:
    pos = rec.pose[:, :3]  # type: ignore[index]
    acc = acceleration(rec.t, acceleration(rec.t, pos))[idx]  # np.gradient's, piece by piece
    return statics.external_wrench_batch(mass, rec.pose[idx], acc, cfg.geometry)  # type: ignore[index]


def require_geometry(cfg: Config | None, rec: Recording, why: str) -> Config:
    """``cfg`` when it has a geometry for ``rec``'s cables; ConfigError/RecordingError naming
    ``why`` (what needs it) otherwise."""
    if cfg is None:
        raise ConfigError(
            f"{rec.source}: {why} needs the robot's geometry: give --model a full config "
            "file with a 'geometry:' section"
        )
    if cfg.cables != rec.cables:
        raise RecordingError(
            f"{rec.source}: {rec.cables} cables, but the geometry in {cfg.source} has {cfg.cables}"
        )
    return cfg


def _solve(cfg: Config, rec: Recording, idx: np.ndarray, mass: np.ndarray) -> np.ndarray:
    a_mats = kinematics.structure_matrix_batch(
        np.asarray(cfg.geometry.frame_anchors_m),
        np.asarray(cfg.geometry.platform_anchors_m),
        rec.pose[idx],  # type: ignore[index]
    )
    w = _wrenches(cfg, rec, idx, mass)
    return statics.distribute_tensions_batch(a_mats, w, cfg.tension.min_n, cfg.tension.max_n)


def platform_tensions(rec: Recording, cfg: Config | None) -> np.ndarray:
    """(N, m) platform tensions from the recorded pose and mass, every sample."""
    cfg = require_geometry(cfg, rec, "a recording without tension_platform_i columns")
    idx = np.arange(rec.samples)
    try:
        return _solve(cfg, rec, idx, rec.mass)  # type: ignore[arg-type]
    except InfeasiblePoseError as exc:
        raise RecordingError(f"{rec.source}: platform tensions from pose and mass: {exc}") from exc


@dataclass(frozen=True)
class MassSensitivity:
    """``dT_p/dm`` (N/kg) solved at ``SENSITIVITY_POINTS`` knot times ``t_knots`` (k,),
    ``values`` (k, m), linearly interpolated in time where read: one cable's (N,) series
    exists only while that cable is worked on (8 bytes per sample and cable not held)."""

    t_knots: np.ndarray
    values: np.ndarray

    @property
    def cables(self) -> int:
        return int(self.values.shape[1])

    def column(self, t: np.ndarray, i: int) -> np.ndarray:
        """(N,) cable ``i``'s (0-based) sensitivity at the times ``t``."""
        return np.interp(t, self.t_knots, self.values[:, i])

    def full(self, t: np.ndarray) -> np.ndarray:
        """(N, m) every cable's sensitivity at the times ``t``."""
        return np.column_stack([self.column(t, i) for i in range(self.cables)])


def mass_sensitivity(
    rec: Recording, cfg: Config | None, say: Callable[[str], None] | None = None
) -> MassSensitivity | None:
    """``dT_p/dm`` in N/kg (:class:`MassSensitivity`; ``.full(rec.t)`` for the (N, m)
    array), or None when pose, mass or geometry are missing."""
    if rec.pose is None or rec.mass is None or cfg is None or cfg.cables != rec.cables:
        return None
    idx = np.unique(
        np.linspace(0, rec.samples - 1, min(rec.samples, SENSITIVITY_POINTS)).astype(int)
    )
    if say:
        say(f"mass sensitivity of the platform tensions at {idx.size} poses")
    mass = rec.mass[idx]
    try:
        lo = _solve(cfg, rec, idx, mass)
        hi = _solve(cfg, rec, idx, mass + 1.0)
    except InfeasiblePoseError:
        return None
    return MassSensitivity(rec.t[idx], hi - lo)
