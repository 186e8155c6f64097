"""Per-cycle compensation: validate -> substitute -> Dahl step -> corrected tensions, wrench.

One :class:`Compensator` holds every buffer and state the cycle needs, allocated at
construction; :meth:`Compensator.step` allocates nothing (numba kernels and in-place
numpy). Arrays are (m,) per cable unless noted; tensions in N, velocities in m/s, time in s
on the loop's clock.

Scaling (S7 analog counts or register scale -> N) is done by the driver from the register
map; the compensator starts from :attr:`Inputs.tension_raw_n`.

Validation, per channel and cycle (flags are bits of :attr:`Compensator.flags`):

* ``NAN``: the reading (or its setpoint velocity) is not finite;
* ``RANGE``: below ``-RANGE_MARGIN * range_n`` or above ``range_n`` (S7 overflow 32767
  scales to 593 N for a 500 N sensor and is out of range);
* ``STUCK``: unchanged (bit for bit) for ``loop.stuck_after_s`` while the setpoint
  velocity is not zero (a cable at rest may legitimately read a constant);
* ``STALE``: the read failed this cycle, or the driver delivered no new data for longer
  than ``loop.stale_after_s``.

A flagged channel is fed its last good value for at most ``loop.substitute_max_s`` after
that value was read (status 1, SUBSTITUTED); after that, or if it never read good, it is
INVALID (status 2). For an invalid channel the corrected tension, the friction estimate
and every wrench component are NaN (float32 NaN in the registers): the PLC is never handed
a made-up number as if it were good, and a PLC that ignores the status word sees NaN, not a
plausible value. The Dahl model keeps stepping on invalid channels with the last good value
(or 0 N if none) so its state stays finite and follows the setpoint motion.

Then the Dahl chain (``ChainStepper``, sensor -> platform) with the setpoint velocities
gives the corrected platform tensions ``T_p``; the friction estimate is ``T_p - T_s`` (the
sensor value fed to the model); the platform wrench is ``w = -A(pose) T_p`` (forward
statics, physics.md sec. 1) at the pose setpoint.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from drivers.base import ChannelStatus, Inputs, Outputs
from gateway.config import Config
from gateway.model.chain import ChainParams, ChainStepper

FLAG_NAN = 1
FLAG_RANGE = 2
FLAG_STUCK = 4
FLAG_STALE = 8
RANGE_MARGIN = 0.05  # readings down to -5 % of the range are noise around zero, not faults
MOVING_M_S = 1e-6  # |setpoint velocity| above this counts as moving for the stuck check


@njit(cache=True)
def _validate(
    raw, vel, now, lo, hi, stuck_after, substitute_max, stale, last_value, changed_at,
    last_good, good_at, flags, status, used, vel_used,
):  # fmt: skip
    """Flag, substitute and pick the model inputs; return the channels newly flagged."""
    newly = 0
    for i in range(raw.size):
        x = raw[i]
        v = vel[i]
        f = FLAG_STALE if stale else 0
        if not math.isfinite(x) or not math.isfinite(v):
            f |= FLAG_NAN
        elif x < lo or x > hi:
            f |= FLAG_RANGE
        vel_used[i] = v if math.isfinite(v) else 0.0
        if x != last_value[i] or abs(vel_used[i]) < MOVING_M_S:
            changed_at[i] = now
        last_value[i] = x
        if now - changed_at[i] >= stuck_after:
            f |= FLAG_STUCK
        if f != 0 and flags[i] == 0:
            newly += 1
        flags[i] = f
        if f == 0:
            last_good[i] = x
            good_at[i] = now
            status[i] = 0
            used[i] = x
            continue
        status[i] = 1 if now - good_at[i] <= substitute_max else 2
        used[i] = last_good[i] if math.isfinite(last_good[i]) else 0.0
    return newly


@njit(cache=True)
def _mark_stale(now, substitute_max, good_at, flags, status):
    """A cycle without a fresh read: every channel stale, substituted or invalid."""
    newly = 0
    for i in range(flags.size):
        if flags[i] == 0:
            newly += 1
        flags[i] |= FLAG_STALE
        status[i] = 1 if now - good_at[i] <= substitute_max else 2
    return newly


@njit(cache=True)
def _finish(corrected, used, status, friction):
    """Invalid channels -> NaN; friction = corrected - sensor value; any invalid?"""
    bad = False
    for i in range(corrected.size):
        if status[i] == 2:
            corrected[i] = np.nan
            bad = True
        friction[i] = corrected[i] - used[i]
    return bad


@njit(cache=True)
def wrench_into(frame_anchors, platform_anchors, pose, tension, out):
    """Forward statics ``w = -A(pose) @ tension`` into ``out`` (6,), allocation-free.

    ``frame_anchors``, ``platform_anchors``: (m, 3) m; ``pose``: (6,) x, y, z m and
    rx, ry, rz rad with ``R = Rz Ry Rx``; ``tension``: (m,) N. Column i of ``A`` is
    ``[u_i; (R b_i) x u_i]`` with ``u_i`` the unit vector platform -> frame anchor.
    """
    ca, sa = math.cos(pose[3]), math.sin(pose[3])
    cb, sb = math.cos(pose[4]), math.sin(pose[4])
    cg, sg = math.cos(pose[5]), math.sin(pose[5])
    r00, r01, r02 = cg * cb, cg * sb * sa - sg * ca, cg * sb * ca + sg * sa
    r10, r11, r12 = sg * cb, sg * sb * sa + cg * ca, sg * sb * ca - cg * sa
    r20, r21, r22 = -sb, cb * sa, cb * ca
    for k in range(6):
        out[k] = 0.0
    for i in range(tension.size):
        bx, by, bz = platform_anchors[i, 0], platform_anchors[i, 1], platform_anchors[i, 2]
        px = r00 * bx + r01 * by + r02 * bz
        py = r10 * bx + r11 * by + r12 * bz
        pz = r20 * bx + r21 * by + r22 * bz
        lx = frame_anchors[i, 0] - pose[0] - px
        ly = frame_anchors[i, 1] - pose[1] - py
        lz = frame_anchors[i, 2] - pose[2] - pz
        norm = math.sqrt(lx * lx + ly * ly + lz * lz)
        ux, uy, uz = lx / norm, ly / norm, lz / norm
        t = tension[i]
        out[0] -= ux * t
        out[1] -= uy * t
        out[2] -= uz * t
        out[3] -= (py * uz - pz * uy) * t
        out[4] -= (pz * ux - px * uz) * t
        out[5] -= (px * uy - py * ux) * t


class Compensator:
    """Validation, substitution, Dahl compensation and wrench for ``m`` cables."""

    def __init__(self, cfg: Config) -> None:
        m = cfg.cables
        lp = cfg.loop
        self.cables = m
        self.params = ChainParams.from_friction(cfg.friction, m)
        self.stepper = ChainStepper(
            self.params, lp.period_s, True, lp.fixed_point_tol_n, lp.fixed_point_max_iter
        )
        self.range_lo = -RANGE_MARGIN * cfg.sensor.range_n
        self.range_hi = float(cfg.sensor.range_n)
        self.stuck_after_s = lp.stuck_after_s
        self.substitute_max_s = lp.substitute_max_s
        self.stale_after_s = lp.stale_after_s
        self.frame_anchors = np.array(cfg.geometry.frame_anchors_m, dtype=float)
        self.platform_anchors = np.array(cfg.geometry.platform_anchors_m, dtype=float)
        self.raw_n = np.full(m, np.nan)  # last reading (N), as read
        self.used_n = np.zeros(m)  # sensor value fed to the model
        self.velocity_m_s = np.zeros(m)  # setpoint velocity fed to the model
        self.corrected_n = np.full(m, np.nan)
        self.friction_n = np.full(m, np.nan)
        self.wrench = np.full(6, np.nan)
        self.flags = np.zeros(m, dtype=np.uint8)
        self.status = np.full(m, int(ChannelStatus.INVALID), dtype=np.uint16)
        self._last_value = np.full(m, np.nan)
        self._changed_at = np.zeros(m)
        self._last_good = np.full(m, np.nan)
        self._good_at = np.full(m, -np.inf)
        self._last_read_time = math.nan
        self._fresh_at = -math.inf
        self.flag_events = 0  # channels that went from good to flagged (errors{invalid_value})

    def step(self, inputs: Inputs, now_s: float, out: Outputs) -> None:
        """One cycle on a successful read; fills ``out`` tensions, status and wrench."""
        if inputs.read_time_s != self._last_read_time:
            self._last_read_time = inputs.read_time_s
            self._fresh_at = now_s
        stale = now_s - self._fresh_at > self.stale_after_s
        self.raw_n[:] = inputs.tension_raw_n
        self.flag_events += _validate(
            inputs.tension_raw_n, inputs.velocity_m_s, now_s, self.range_lo, self.range_hi,
            self.stuck_after_s, self.substitute_max_s, stale, self._last_value,
            self._changed_at, self._last_good, self._good_at, self.flags, self.status,
            self.used_n, self.velocity_m_s,
        )  # fmt: skip
        self.stepper.step(self.used_n, self.velocity_m_s, self.corrected_n)
        any_invalid = _finish(self.corrected_n, self.used_n, self.status, self.friction_n)
        if any_invalid:
            self.wrench[:] = np.nan
        else:
            wrench_into(
                self.frame_anchors, self.platform_anchors, inputs.pose, self.corrected_n,
                self.wrench,
            )  # fmt: skip
        out.tension_corrected_n[:] = self.corrected_n
        out.channel_status[:] = self.status
        out.wrench[:] = self.wrench

    def mark_unread(self, now_s: float) -> None:
        """A cycle whose read failed: flag every channel stale; the model is not stepped."""
        self.flag_events += _mark_stale(
            now_s, self.substitute_max_s, self._good_at, self.flags, self.status
        )

    def invalidate_outputs(self, out: Outputs) -> None:
        """Fill ``out`` with 'no value': NaN tensions and wrench, every channel invalid."""
        out.tension_corrected_n[:] = np.nan
        out.channel_status[:] = int(ChannelStatus.INVALID)
        out.wrench[:] = np.nan


def warm_up(cfg: Config) -> None:
    """Compile every numba kernel of the cycle now, on throwaway buffers (not in cycle 1)."""
    comp = Compensator(cfg)
    inputs = Inputs.allocate(cfg.cables)
    outputs = Outputs.allocate(cfg.cables)
    inputs.tension_raw_n[:] = 100.0
    inputs.velocity_m_s[:] = 0.01
    inputs.pose[:] = cfg.geometry.home_pose
    for k in range(2):
        inputs.read_time_s = float(k)
        comp.step(inputs, 0.001 * k, outputs)
    comp.mark_unread(1.0)
