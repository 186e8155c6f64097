"""Per-cycle compensation: validate -> substitute -> fitted effects -> chain -> tensions, wrench.

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

Then the fitted path and sensor effects of the config's ``friction.effects`` that a causal
per-cycle model can undo are removed (:class:`gateway.model.effects.OnlineInverse`: each
effect's compiled per-cycle inverse, e.g. an acceleration from the backward difference of
the setpoint velocity over the time since the last new sample, a pulley phase from the
setpoint length), and the chain (``ChainStepper``, sensor -> platform; the nominal friction
with the fitted chain-side effects it compensates online,
:func:`gateway.model.effects.chain_params`) with the
setpoint velocities gives the corrected platform tensions ``T_p``. An effect that cannot be
undone causally is not compensated (each effect's ``online`` says why; docs/physics.md).
:attr:`Compensator.friction_n` is ``T_p`` minus the sensor value fed to the model (the
whole correction); the platform wrench is ``w = -A(pose) T_p``
(forward statics, docs/physics.md sec. 1) at the pose setpoint.

The kernels take structured state (:class:`Limits`, :class:`ChannelState`, the online
effects' parameter rows, ``KernelParams``) and are called through their compiled entry points
(:mod:`gateway.fastcall`) on the compensator's own buffers.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from drivers.base import ChannelStatus, Inputs, Outputs
from gateway.core.config import Config
from gateway.fastcall import entry_point
from gateway.model import effects as fx
from gateway.model.chain_runs import ChainStepper
from gateway.model.statics import wrench_into
from gateway.runtime.clock import MAX_GAP_PERIODS, SampleClock, warm_travel_m

FLAG_NAN = 1
FLAG_RANGE = 2
FLAG_STUCK = 4
FLAG_STALE = 8
RANGE_MARGIN = 0.05  # readings down to -5 % of the range are noise around zero, not faults
MOVING_M_S = 1e-6  # |setpoint velocity| above this counts as moving for the stuck check
GOOD = int(ChannelStatus.GOOD)
SUBSTITUTED = int(ChannelStatus.SUBSTITUTED)
INVALID = int(ChannelStatus.INVALID)


@njit(cache=True)
def _differs(a: np.ndarray, b: np.ndarray) -> bool:
    """True when some element of ``a`` differs from ``b`` (no allocation)."""
    for i in range(a.size):  # noqa: SIM110 (numba: a plain loop)
        if a[i] != b[i]:
            return True
    return False


class Limits(NamedTuple):
    """Validation limits: range (N) and the stuck / substitution times (s)."""

    lo: float
    hi: float
    stuck_after_s: float
    substitute_max_s: float


class ChannelState(NamedTuple):
    """Per-channel (m,) validation state and the model inputs it selects."""

    last_value: np.ndarray  # last reading, as read
    changed_at: np.ndarray  # when it last changed (or the cable was at rest)
    last_good: np.ndarray  # last good reading (NaN: none yet)
    good_at: np.ndarray  # when it was read
    flags: np.ndarray  # FLAG_* bits of this cycle
    status: np.ndarray  # ChannelStatus
    used: np.ndarray  # sensor value fed to the model
    vel_used: np.ndarray  # setpoint velocity fed to the model

    @staticmethod
    def allocate(cables: int) -> ChannelState:
        return ChannelState(
            np.full(cables, np.nan),
            np.zeros(cables),
            np.full(cables, np.nan),
            np.full(cables, -np.inf),
            np.zeros(cables, dtype=np.uint8),
            np.full(cables, INVALID, dtype=np.uint16),
            np.zeros(cables),
            np.zeros(cables),
        )


@njit(cache=True)
def _validate(lim, st, raw, vel, now, stale):
    """Flag, substitute and pick the model inputs; return the channels newly flagged."""
    newly = 0
    for i in range(raw.size):
        x = raw[i]
        v = vel[i]
        f = FLAG_STALE if stale else 0
        if not math.isfinite(x) or not math.isfinite(v):
            f |= FLAG_NAN
        elif x < lim.lo or x > lim.hi:
            f |= FLAG_RANGE
        st.vel_used[i] = v if math.isfinite(v) else 0.0
        if x != st.last_value[i] or abs(st.vel_used[i]) < MOVING_M_S:
            st.changed_at[i] = now
        st.last_value[i] = x
        if now - st.changed_at[i] >= lim.stuck_after_s:
            f |= FLAG_STUCK
        if f != 0 and st.flags[i] == 0:
            newly += 1
        st.flags[i] = f
        if f == 0:
            st.last_good[i] = x
            st.good_at[i] = now
            st.status[i] = GOOD
            st.used[i] = x
            continue
        st.status[i] = SUBSTITUTED if now - st.good_at[i] <= lim.substitute_max_s else INVALID
        st.used[i] = st.last_good[i] if math.isfinite(st.last_good[i]) else 0.0
    return newly


@njit(cache=True)
def _mark_stale(lim, st, now):
    """A cycle without a fresh read: every channel stale, substituted or invalid."""
    newly = 0
    for i in range(st.flags.size):
        if st.flags[i] == 0:
            newly += 1
        st.flags[i] |= FLAG_STALE
        fresh_enough = now - st.good_at[i] <= lim.substitute_max_s
        st.status[i] = SUBSTITUTED if fresh_enough else INVALID
    return newly


@njit(cache=True)
def _hold_finite(x, last):
    """Non-finite elements of ``x`` take the last finite value (kept in ``last``)."""
    for i in range(x.size):
        if math.isfinite(x[i]):
            last[i] = x[i]
        else:
            x[i] = last[i]


@njit(cache=True)
def _guard_inputs(model_in, used, status):
    """A cable whose model input is not finite is invalid this cycle and the chain is fed
    its sensor value instead: nothing non-finite enters the model."""
    for i in range(model_in.size):
        if not math.isfinite(model_in[i]):
            model_in[i] = used[i]
            status[i] = INVALID


@njit(cache=True)
def _guard_chain(corrected, state, status):
    """A cable whose chain output or state is not finite is invalid this cycle and its
    state is relaxed (the Dahl state once stayed NaN for good)."""
    for i in range(state.shape[0]):
        bad = not math.isfinite(corrected[i])
        for j in range(state.shape[1]):
            bad = bad or not math.isfinite(state[i, j])
        if bad:
            state[i, :] = 0.0
            corrected[i] = np.nan
            status[i] = INVALID


@njit(cache=True)
def _finish(corrected, used, status, friction):
    """Invalid channels -> NaN; friction = corrected - sensor value; any invalid?"""
    bad = False
    for i in range(corrected.size):
        if status[i] == INVALID:
            corrected[i] = np.nan
            bad = True
        friction[i] = corrected[i] - used[i]
    return bad


class Compensator:
    """Validation, substitution, compensation of the fitted effects and wrench, m cables."""

    def __init__(self, cfg: Config, register_modulus: int = 1 << 16) -> None:
        m = cfg.cables
        lp = cfg.loop
        fr = cfg.friction
        self.cables = m
        values = fr.effect_values(m)
        self.params = fx.chain_params(fr, values, m, online_only=True)
        self.stepper = ChainStepper(
            self.params, lp.period_s, True, lp.fixed_point_tol_n, lp.fixed_point_max_iter
        )
        self.limits = Limits(
            -RANGE_MARGIN * cfg.sensor.range_n,
            float(cfg.sensor.range_n),
            lp.stuck_after_s,
            lp.substitute_max_s,
        )
        self.stale_after_s = lp.stale_after_s
        self._loop_period_s = lp.period_s
        self.max_step_s = MAX_GAP_PERIODS * lp.period_s  # the chain's step after an outage
        self._heartbeat_cfg = lp.heartbeat
        # the longest a sample read may have been made before: held with the watchdog
        # armed, then in flight (gateway/runtime/clock.py, docs/security.md)
        self._lag_bound_s = lp.clock_lag_bound_s
        # Modbus polls the PLC: its heartbeat tells a new sample from one read again. On
        # CANopen each cycle is one SYNC's samples and the heartbeat comes every 10th.
        self._by_bus = cfg.bus.driver == "canopen"
        self.clock = self._make_clock(register_modulus)
        # after a step the clock cannot vouch for, the chain resynchronises: the cables
        # are not good until they have travelled this far (clock.warm_travel_m)
        self.warm_travel_m = warm_travel_m(self.params, cfg.sensor.range_n)
        self.travel_m = np.full(m, np.inf)  # setpoint travel since the last resync
        self.resync_at = -math.inf  # when the chain last resynchronised (gateway clock)
        self._cold = False  # some cable has not re-warmed since the last resync
        self._stepped_since_resync = True
        self._travelled = False  # the chain has taken a step since the start
        self.frame_anchors = np.array(cfg.geometry.frame_anchors_m, dtype=float)
        self.platform_anchors = np.array(cfg.geometry.platform_anchors_m, dtype=float)
        self.channels = ChannelState.allocate(m)
        self.raw_n = np.full(m, np.nan)  # last reading (N), as read
        self.used_n = self.channels.used  # sensor value fed to the model
        self.velocity_m_s = self.channels.vel_used  # setpoint velocity fed to the model
        self.flags = self.channels.flags
        self.status = self.channels.status
        self.model_in_n = np.zeros(m)  # sensor side of the chain: gain, offset, path removed
        self.corrected_n = np.full(m, np.nan)
        self.friction_n = np.full(m, np.nan)  # corrected - used: the whole correction
        self.wrench = np.full(6, np.nan)
        self._velocity_prev = np.zeros(m)  # the previous PLC sample's setpoint velocity
        self._velocity_hold = np.zeros(m)  # the one before it (a repeated sample: hold a)
        self._sample_dt = 0.0  # time between the last two new PLC samples
        self._velocity_in = np.zeros(m)  # the cycle's inputs, copied into own buffers
        self._length_in = np.zeros(m)
        self._length_last = np.zeros(m)  # the last finite setpoint length per cable
        self._pose_in = np.zeros(6)
        self._last_read_time = math.nan
        self._fresh_at = -math.inf
        self.flag_events = 0  # channels that went from good to flagged (errors{invalid_value})
        # compiled entries on the own buffers (no per-call type dispatch; fastcall.py)
        self._validate = entry_point(
            _validate, self.limits, self.channels, self.raw_n, self._velocity_in, 0.0, False
        )
        self._online = fx.OnlineInverse(
            values, m, self.model_in_n, self.velocity_m_s, self._velocity_prev, self._length_in
        )
        self._differs = entry_point(_differs, self.velocity_m_s, self._velocity_prev)
        self._finish = entry_point(
            _finish, self.corrected_n, self.used_n, self.status, self.friction_n
        )
        self._wrench = entry_point(
            wrench_into,
            self.frame_anchors,
            self.platform_anchors,
            self._pose_in,
            self.corrected_n,
            self.wrench,
        )

    def _make_clock(self, register_modulus: int) -> SampleClock:
        hb = self._heartbeat_cfg
        modulus = register_modulus if hb.modulus is None else hb.modulus
        return SampleClock(
            hb.kind,
            modulus,
            self._loop_period_s,
            by_bus=self._by_bus,
            toggle_period_s=hb.period_s,
            register_values=register_modulus,
            lag_bound_s=self._lag_bound_s,
        )

    @property
    def heartbeat_modulus(self) -> int:
        """The wrap of the PLC heartbeat's register (0: float32); set by the loop from
        the driver before the first cycle (a declared ``loop.heartbeat.modulus`` wins)."""
        return self.clock.register_values

    @heartbeat_modulus.setter
    def heartbeat_modulus(self, register_modulus: int) -> None:
        resyncs = self.clock.resyncs  # a counter (errors_total{kind="clock"}): never back
        self.clock = self._make_clock(int(register_modulus))
        self.clock.resyncs = resyncs

    @property
    def stuck_after_s(self) -> float:
        return self.limits.stuck_after_s

    @property
    def substitute_max_s(self) -> float:
        return self.limits.substitute_max_s

    def step(self, inputs: Inputs, now_s: float, out: Outputs) -> None:
        """One cycle on a successful read; fills ``out`` tensions, status and wrench.

        The model's time step is the one sample clock's (:class:`~.clock.SampleClock`:
        the PLC's time between the samples it compensates; 0 on the first and for a
        sample read again), so the acceleration (inertia) and the cable travel (Dahl, the
        trapezoid ``(v_prev + v) / 2 dt`` with the previous sample's velocity,
        ``chain_kernels.travel_into``) follow the PLC's samples, not the gateway's reads: a
        sample read twice adds no travel, samples missed in an overrun or a stall (of
        either side) lose none; the chain's step is bounded to ``MAX_GAP_PERIODS`` periods
        (after an outage). A step the clock cannot vouch for (a counter stepping
        back, a jump, a restart, a toggle missed) is not integrated: the chain
        resynchronises (:meth:`_resync`) and every cable is written substituted, then
        invalid, until it has travelled ``warm_travel_m`` since (:meth:`_hold_cold`).
        """
        if inputs.read_time_s != self._last_read_time:
            self._last_read_time = inputs.read_time_s
            self._fresh_at = now_s
        now = float(now_s)
        stale = bool(now - self._fresh_at > self.stale_after_s)
        self.raw_n[:] = inputs.tension_raw_n
        self._velocity_in[:] = inputs.velocity_m_s
        self._length_in[:] = inputs.length_m
        self._pose_in[:] = inputs.pose
        self.flag_events += self._validate(
            self.limits, self.channels, self.raw_n, self._velocity_in, now, stale
        )
        _hold_finite(self._length_in, self._length_last)  # flagged by plausibility
        clock = self.clock
        hb = float(inputs.plc_heartbeat)
        moved = clock.asks_setpoints(hb) and self._differs(self.velocity_m_s, self._velocity_prev)
        clock.tick(now, hb, moved)
        dt = self._online_inputs(clock.new, clock.dt)
        if not clock.vouched and self._travelled:
            self._resync(now)  # (before any travel the start's relaxed chain is as good)
        self._travelled = self._travelled or dt > 0.0
        _guard_inputs(self.model_in_n, self.used_n, self.status)
        self.stepper.step(
            self.model_in_n, self.velocity_m_s, self.corrected_n, min(dt, self.max_step_s)
        )
        _guard_chain(self.corrected_n, self.stepper.state, self.status)
        if self._cold:
            self._hold_cold(now, dt)
        if self._finish(self.corrected_n, self.used_n, self.status, self.friction_n):
            self.wrench[:] = np.nan
        else:
            self._wrench(
                self.frame_anchors,
                self.platform_anchors,
                self._pose_in,
                self.corrected_n,
                self.wrench,
            )
        out.tension_corrected_n[:] = self.corrected_n
        out.channel_status[:] = self.status
        out.wrench[:] = self.wrench

    def _resync(self, now: float) -> None:
        """A step the clock could not vouch for: the chain keeps its state but took no
        travel over the unknown time (the clock's step is 0) and no acceleration across
        it; the cables are cold until they have travelled far enough for the state to
        have forgotten the difference (:func:`~.clock.warm_travel_m`)."""
        if not self._cold:  # substituted for at most substitute_max_s after the first
            self.resync_at = now
        self.travel_m[:] = 0.0
        self._cold = True
        self._stepped_since_resync = False

    def _hold_cold(self, now: float, dt: float) -> None:
        """Count the travel since the resync; a cable short of ``warm_travel_m`` (and
        every cable before the first vouched step after it: the acceleration needs two
        samples) is substituted for at most ``loop.substitute_max_s`` after the resync,
        then invalid."""
        if dt > 0.0:
            step = min(dt, self.max_step_s)
            self.travel_m += 0.5 * np.abs(self._velocity_hold + self.velocity_m_s) * step
            self._stepped_since_resync = True
        cold = self.travel_m < self.warm_travel_m
        if self._stepped_since_resync and not cold.any():
            self._cold = False
            return
        if not self._stepped_since_resync:
            cold[:] = True
        fresh = now - self.resync_at <= self.limits.substitute_max_s
        self.status[cold] = np.maximum(self.status[cold], SUBSTITUTED if fresh else INVALID)

    def _online_inputs(self, new: bool, dt: float) -> float:
        """The online path and sensor effects removed; returns the chain's step (s): the
        clock's step for a new sample, 0 for the same sample again. An acceleration
        (inertia) is the backward difference between *new* PLC samples; a cycle that reads
        the same sample again holds it (a difference of 0 over one cycle, then of two
        samples over the next, would swing the inertia term between 0 and twice its
        size), and a filter with state is not advanced twice."""
        if not new:
            self._online(
                self.used_n,
                self.model_in_n,
                self._velocity_prev,
                self._velocity_hold,
                self._sample_dt,
                self._length_in,
                False,
            )
            return 0.0
        self._online(
            self.used_n,
            self.model_in_n,
            self.velocity_m_s,
            self._velocity_prev,
            dt,
            self._length_in,
        )
        self._velocity_hold[:] = self._velocity_prev
        self._velocity_prev[:] = self.velocity_m_s
        self._sample_dt = dt
        return dt

    def mark_unread(self, now_s: float) -> None:
        """A cycle whose read failed: flag every channel stale; the model is not stepped."""
        self.flag_events += _mark_stale(self.limits, self.channels, float(now_s))

    def invalidate_outputs(self, out: Outputs) -> None:
        """Fill ``out`` with 'no value': NaN tensions and wrench, every channel invalid."""
        out.tension_corrected_n[:] = np.nan
        out.channel_status[:] = INVALID
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
