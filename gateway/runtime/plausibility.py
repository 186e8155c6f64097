"""Plausibility of the PLC's setpoints, bounded by the robot's geometry and ``limits:``.

A setpoint the robot cannot have is not passed on as good (a pose of 1e20 m gave a
wrench of 1549.6 N written with every channel good). Per cycle, before compensation:

* cable velocity ``|v_i| <= limits.max_cable_speed_m_s``;
* cable length ``0 <= l_i <= l_max``, ``l_max`` the diagonal of the frame's bounding box
  plus the largest platform anchor radius plus ``limits.workspace_margin_m``;
* pose position inside the frame's bounding box (anchors' min..max on each axis) widened
  by ``limits.workspace_margin_m``; rotations ``|r_k| <= limits.max_rotation_rad``.

An implausible velocity or length makes that cable's setpoint velocity NaN, so the
compensator flags the channel (substituted, then invalid). An implausible pose makes the
pose NaN (the wrench becomes NaN) and every cable's velocity NaN: every channel is flagged,
because a PLC that sends an impossible pose cannot be trusted for the rest of the frame.
A non-finite velocity, length or pose is implausible too (every comparison is written so
that NaN fails it: a NaN cable length once passed and poisoned a fitted eccentricity).
The loop counts the cycles with an implausible value in ``errors_total{kind="implausible"}``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from drivers.base import Inputs
from gateway.core.config import Config


class Bounds(NamedTuple):
    """What the robot can have: ``box`` (2, 3) the position's lower and upper bounds (m),
    the largest cable speed (m/s), cable length (m) and |rotation| (rad)."""

    box: np.ndarray
    speed_max: float
    length_max: float
    rotation_max: float


@njit(cache=True)
def _check(bounds, velocity, length, pose):
    """Replace implausible setpoints by NaN in place; return how many were implausible.
    Every comparison is written so that NaN fails it."""
    box = bounds.box
    bad = 0
    pose_bad = False
    for k in range(3):
        if not box[0, k] <= pose[k] <= box[1, k]:
            pose_bad = True
        if not abs(pose[3 + k]) <= bounds.rotation_max:
            pose_bad = True
    if pose_bad:
        bad += 1
        for k in range(6):
            pose[k] = np.nan
    for i in range(velocity.size):
        v, lng = velocity[i], length[i]
        if not abs(v) <= bounds.speed_max or not 0.0 <= lng <= bounds.length_max:
            bad += 1
            velocity[i] = np.nan
        elif pose_bad:
            velocity[i] = np.nan
    return bad


class Plausibility:
    """The bounds of one robot; :meth:`check` runs in the cycle, allocation-free."""

    def __init__(self, cfg: Config) -> None:
        limits = cfg.limits
        frame = np.array(cfg.geometry.frame_anchors_m, dtype=float)
        platform = np.array(cfg.geometry.platform_anchors_m, dtype=float)
        margin = limits.workspace_margin_m
        self.lo = frame.min(axis=0) - margin
        self.hi = frame.max(axis=0) + margin
        radius = float(np.linalg.norm(platform, axis=1).max())
        self.length_max = float(np.linalg.norm(self.hi - self.lo)) + radius + margin
        self.speed_max = limits.max_cable_speed_m_s
        self.rotation_max = limits.max_rotation_rad
        box = np.ascontiguousarray(np.stack([self.lo, self.hi]))
        self.bounds = Bounds(box, float(self.speed_max), self.length_max, float(self.rotation_max))

    def check(self, inputs: Inputs) -> int:
        """Flag implausible setpoints of ``inputs`` (NaN in place); return their number."""
        bad: int = _check(self.bounds, inputs.velocity_m_s, inputs.length_m, inputs.pose)
        return bad

    def describe(self) -> str:
        lo = ", ".join(f"{x:g}" for x in self.lo)
        hi = ", ".join(f"{x:g}" for x in self.hi)
        return (
            f"position ({lo})..({hi}) m, |rotation| <= {self.rotation_max:g} rad, "
            f"|cable speed| <= {self.speed_max:g} m/s, cable length 0..{self.length_max:.3g} m"
        )


def warm_up(cfg: Config) -> None:
    """Compile the kernel now, not in the first cycle."""
    inputs = Inputs.allocate(cfg.cables)
    inputs.pose[:] = cfg.geometry.home_pose
    inputs.length_m[:] = 1.0
    Plausibility(cfg).check(inputs)
