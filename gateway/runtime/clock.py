"""The one sample clock: the PLC heartbeat (or the gateway's own clock) -> the time step.

Every online effect, the inertia's acceleration and the friction chain's cable travel are
stepped with one time step per new PLC sample, and that step is made here only
(:meth:`SampleClock.tick`, called once per successful cycle by
:class:`gateway.runtime.compensator.Compensator`). What the heartbeat register says is
declared in the config (``loop.heartbeat``, :class:`gateway.core.config.HeartbeatConfig`):

* ``counter`` (the default; ``modulus``: its wrap, default the register's range, a float32
  register counts without a wrap): the register counts PLC samples. A new value ``k``
  samples after the last one is a new sample and the step is ``k`` times the PLC's sample
  spacing, averaged over past samples (:meth:`SampleClock._spacing`; single arrival times
  carry the bus jitter). New setpoint velocities under an unchanged (or NaN) heartbeat
  are a new sample on the gateway's clock, as before the declaration (the watchdog stops
  the writes of a PLC whose heartbeat stays frozen);
* ``toggle``: the register changes every PLC cycle (a 0/1 life bit); only *that* it
  changed is used. The step is the declared PLC cycle ``period_s``;
* ``none``: the register carries no timing. A read whose heartbeat or setpoint velocities
  differ from the last is a new sample and the step is the gateway's own time since the
  last new sample.

On a bus that paces the gateway (CANopen: each cycle is one SYNC's samples, the heartbeat
comes in every 10th) every cycle is a new sample and the step is the time since the
previous cycle, whatever the kind.

A step the clock cannot vouch for is never integrated (:attr:`SampleClock.vouched` False,
:attr:`SampleClock.dt` 0); the compensator then resynchronises the chain and writes the
cables substituted, then invalid, until the chain has re-warmed (docs/security.md):

* a counter step the count itself cannot tell from a step back: ``k`` samples on with
  ``k >= modulus / 2`` (serial-number arithmetic, RFC 1982: a 16-bit step back of 1 reads
  65 535 on), and a step after which one more wrap, ``k + modulus`` samples, also fits
  the time below (``k`` is known only modulo the modulus: a 16-bit counter at 1 ms after
  a gap of 43.7 s, or with a ``loop.heartbeat_timeout_s`` of that); a value outside the
  declared modulus; a float step that is no whole count; a step over
  ``MAX_GAP_PERIODS`` before the spacing is known;
* a counter whose count runs ahead of the gateway's clock: ``k`` samples counted in
  ``e`` seconds of the gateway's time since the last new sample with
  ``k * spacing > (e + lag_bound_s) * (1 + SPACING_TOLERANCE)``. The PLC's samples are
  made on its time base and read late, never early; the last sample was read at most
  ``lag_bound_s`` after it was made (``loop.heartbeat_timeout_s``: the longest a PLC can
  hold its newest sample with the watchdog armed, + ``loop.max_input_age_s``: the oldest a
  reply may be), so at most ``e + lag_bound_s`` of PLC time can have passed. A PLC (or a
  bus, or this process) catching up after a stall, however bursty, counts no more: its
  delta is its own count of the samples made and is integrated. A restart, a jump on by
  more than the time allows, is not. The check is per step, against the gateway's clock
  since the previous sample only: an error in the averaged spacing never accumulates
  into it (a check of the count since the start against the time since the start took
  the first sample's delay for the PLC's and refused the soft PLC catching up 8 samples
  after its first chunk: issue 30 item 1's revert);
* a toggle that changed more than ``TOGGLE_MAX_GAP`` cycles after its last change, or has
  not changed for longer: it may have changed twice or three times, or the PLC held,
  which no reading can tell apart (a read that shows no change is then not vouched for
  either: it may be a new sample).

A gap the clock can vouch for in time (an outage: a counter that advanced no faster than
the gateway's clock allows; ``none`` and CANopen, whose clock is the gateway's) is a step
of its full length for the online effects; the chain's travel over it is bounded by the
compensator to ``MAX_GAP_PERIODS`` periods, as before (the setpoint motion in it is
unknown; docs/security.md names this as not covered).

The clock is scalar state, stepped once per cycle, allocating nothing;
:func:`warm_travel_m` (the re-warm travel) is computed once, at construction.
"""

from __future__ import annotations

import math

import numpy as np

from gateway.core.config import SPACING_TOLERANCE
from gateway.model.chain_schema import LOAD, ChainParams, coulomb_coefficients, kernel_params

PLC_PERIOD_GAIN = 0.01  # the PLC's sample spacing is averaged over ~100 samples
SPACING_OUTLIER = 3.0  # a spacing this far off the average is a hold or a stall, not data
SPACING_OUTLIER_RUN = 20  # this many in a row: the PLC's period changed, start afresh
# Heartbeat steps up to this many samples enter the PLC's averaged sample spacing.
MAX_STEP_PERIODS = 10
# The chain's travel over a longer gap is bounded to this many periods (the setpoint
# motion in between is unknown); a counter step over it needs a known spacing.
MAX_GAP_PERIODS = 100
# A toggle that changes within this many PLC cycles of its last change changed once.
TOGGLE_MAX_GAP = 1.5
KINDS = ("counter", "toggle", "none")
# The chain counts as re-warmed after a resync when the Dahl state has forgotten its
# start to this much (N, per cable; docs/security.md derives the travel it takes).
WARM_TOL_N = 0.05


class SampleClock:
    """The time step of each cycle's PLC sample; see the module doc.

    After :meth:`tick`: :attr:`new` (this read is a new PLC sample), :attr:`dt` (the PLC
    time since the previous sample, s; 0 for the same sample again, the first one and a
    step not vouched) and :attr:`vouched` (False: the step was not integrated, the model
    must resynchronise).
    """

    def __init__(
        self,
        kind: str,
        modulus: int,
        loop_period_s: float,
        *,
        by_bus: bool = False,
        toggle_period_s: float | None = None,
        register_values: int | None = None,
        lag_bound_s: float = 0.11,
    ) -> None:
        if kind not in KINDS:
            raise ValueError(f"heartbeat kind must be one of {', '.join(KINDS)}, got {kind!r}")
        self.kind = kind
        self.modulus = int(modulus)  # 0: a float counter, no wrap
        # the register's own range: values outside a smaller declared modulus are refused
        self.register_values = self.modulus if register_values is None else int(register_values)
        self.by_bus = by_bus
        self.toggle_period_s = float(toggle_period_s or loop_period_s)
        # the longest a sample read may have been made before (heartbeat_timeout + age)
        self.lag_bound_s = float(lag_bound_s)
        self.new = False
        self.dt = 0.0
        self.vouched = True
        self.resyncs = 0  # reads not vouched for since the start
        self._heartbeat = math.nan  # the last finite heartbeat
        self._sample_at = math.nan  # when the last new sample arrived (gateway clock)
        self._cycle_at = math.nan  # when the last cycle ran (paced by the bus)
        self.plc_period_s = math.nan  # the PLC's sample spacing, averaged over samples
        self._outliers = 0  # spacings in a row too far off the average to move it
        self._spacings = 0  # spacings averaged so far (a running mean until 1 / gain)

    def asks_setpoints(self, heartbeat: float) -> bool:
        """Whether :meth:`tick` with this ``heartbeat`` reads ``moved`` (the caller then
        compares the setpoint velocities; a counter that stepped does not need them)."""
        if self.by_bus or self.kind == "toggle":
            return False
        if self.kind == "none":
            return True
        return not (math.isfinite(heartbeat) and heartbeat != self._heartbeat)

    def tick(self, now: float, heartbeat: float, moved: bool) -> None:
        """One successful read at ``now`` (gateway clock) with the PLC ``heartbeat``;
        ``moved``: its setpoint velocities differ from the last sample's. ``resyncs``
        counts the reads not vouched for."""
        self.new, self.dt, self.vouched = False, 0.0, True
        if self.by_bus:
            self._on_gateway_clock(now, True, self._cycle_at)
            self._cycle_at = now
        elif self.kind == "counter":
            self._counter(now, heartbeat)
            if not self.new and moved:  # new setpoints, no count (as before): arrival time
                self._on_gateway_clock(now, True, self._sample_at)
        elif self.kind == "toggle":
            self._toggle(now, heartbeat)
        else:
            changed = math.isfinite(heartbeat) and heartbeat != self._heartbeat
            if math.isfinite(heartbeat):
                self._heartbeat = heartbeat
            self._on_gateway_clock(now, moved or changed, self._sample_at)
        if not self.vouched:
            self.dt = 0.0
            self.resyncs += 1
        if self.new:
            self._sample_at = now

    def _on_gateway_clock(self, now: float, new: bool, since: float) -> None:
        if not new:
            return
        self.new = True
        if since == since:
            dt = now - since
            self.vouched = dt >= 0.0
            self.dt = max(dt, 0.0)

    def _toggle(self, now: float, heartbeat: float) -> None:
        if not math.isfinite(heartbeat) or heartbeat == self._heartbeat:
            # the same sample again, unless it has not changed for longer than a cycle: then
            # the PLC held or it changed twice, and this read may be a new sample
            self.vouched = not now - self._sample_at > TOGGLE_MAX_GAP * self.toggle_period_s
            return
        first = self._heartbeat != self._heartbeat
        self._heartbeat = heartbeat
        self.new = True
        if first:
            return
        gap = now - self._sample_at
        self.vouched = 0.0 <= gap <= TOGGLE_MAX_GAP * self.toggle_period_s
        self.dt = self.toggle_period_s

    def _counter(self, now: float, heartbeat: float) -> None:
        if not math.isfinite(heartbeat):
            return  # this read carries no heartbeat: taken for the same sample
        prev = self._heartbeat
        self._heartbeat = heartbeat
        if prev != prev:
            self.new = True  # the first sample: no step
            return
        steps = self._steps(prev, heartbeat)
        if steps == 0:
            return
        self.new = True
        elapsed = now - self._sample_at
        period = self.plc_period_s
        if steps < 0 or (steps > MAX_GAP_PERIODS and period != period):
            self.vouched = False  # no count, or no spacing yet to tell a gap from a jump
            return
        if period == period and not self.count_agrees(steps, elapsed, period):
            self.vouched = False
            return
        if steps <= MAX_STEP_PERIODS and elapsed > 0.0:
            self.plc_period_s = self._spacing(elapsed / steps)
        period = self.plc_period_s
        self.dt = steps * period if period == period else max(elapsed, 0.0)

    def count_agrees(self, steps: int, elapsed: float, period: float) -> bool:
        """Whether ``steps`` counted samples can have been made in ``elapsed`` seconds of
        the gateway's clock since the last new sample (module doc): no more PLC time than
        the time passed plus the lag bound (with the spacing's tolerance), a step under
        half the modulus, and a gap in which the counter cannot have wrapped."""
        allowed = (max(elapsed, 0.0) + self.lag_bound_s) * (1.0 + SPACING_TOLERANCE)
        m = self.modulus
        if m and (2 * steps >= m or (steps + m) * period <= allowed):
            return False  # a step back, or k known only modulo the modulus: a wrap more fits
        return steps * period <= allowed

    def _steps(self, prev: float, heartbeat: float) -> int:
        """Samples between two heartbeats; -1 for what is no count."""
        bad = -1
        if heartbeat != int(heartbeat):
            return bad
        if not self.modulus:
            d = heartbeat - prev
            return int(d) if d == int(d) and d >= 0 else bad
        if self.modulus < self.register_values and not 0 <= heartbeat < self.modulus:
            return bad  # cannot be a counter of the declared modulus
        return (int(heartbeat) - int(prev)) % self.modulus

    def _spacing(self, spacing: float) -> float:
        """The PLC's averaged sample spacing after one more ``spacing``: the running mean
        of the first ``1 / PLC_PERIOD_GAIN`` spacings, then an exponential average (a start
        from one jittered spacing took ~100 samples to settle, and the chain's travel was
        off by that much meanwhile). A spacing off the average by more than a factor
        ``SPACING_OUTLIER`` (the PLC held its samples, or this process stalled) does not
        move it; ``SPACING_OUTLIER_RUN`` of them in a row restart it (the PLC's period
        changed)."""
        est = self.plc_period_s
        if est != est or self._outliers >= SPACING_OUTLIER_RUN:
            self._outliers = 0
            self._spacings = 1
            return spacing
        if not est / SPACING_OUTLIER <= spacing <= est * SPACING_OUTLIER:
            self._outliers += 1
            return est
        self._outliers = 0
        self._spacings += 1
        return est + max(PLC_PERIOD_GAIN, 1.0 / self._spacings) * (spacing - est)


def warm_travel_m(params: ChainParams, range_n: float, tol_n: float = WARM_TOL_N) -> float:
    """Cable travel (m) after which a resynchronised chain's state is within ``tol_n`` of
    any other start, per cable: ``X = (F_R / sigma) g`` with ``F_R`` the largest Coulomb
    level a pulley can reach (sensor range, the platform side of every pulley, Stribeck
    peak, ``f0``, a coefficient that grows with the tension: ``coulomb_load``) and
    ``sigma`` the least stiffness (of a Maxwell-slip element too). Two Dahl states
    stepped over the same travel ``dx`` approach each other by the factor
    ``exp(-sigma |dx| / F_R)`` (beta = 1, docs/physics.md), from at most ``2 F_R`` apart,
    so ``g = ln(2 / eps)`` with ``eps = tol / (n F_R)`` for ``n`` pulleys; for beta != 1
    the closed-form step takes the relative state ``z`` from 2 to ``eps`` in
    ``g = (eps^(1 - beta) - 2^(1 - beta)) / (beta - 1)``. 0 for a chain with no state
    (none, Coulomb)."""
    if params.model not in ("dahl", "maxwell_slip") or params.pulleys == 0:
        return 0.0
    lam_pos, lam_neg = coulomb_coefficients(params)
    lam0 = np.maximum(np.abs(lam_pos), np.abs(lam_neg))  # (m, n)
    growth = np.abs(kernel_params(params).lam[:, :, LOAD])  # the coefficient's, per N
    lam, tension = lam0, float(range_n)
    for _ in range(50):  # lambda + growth T at the largest T, which grows with it
        lam_sum = float(np.max(np.sum(lam, axis=1)))
        bound = float(range_n) * (1.0 + lam_sum) / max(1.0 - lam_sum, 1e-3)
        lam = lam0 + growth * bound
        if bound <= tension * (1.0 + 1e-9):
            break
        tension = bound
    strib = 1.0 + float(np.max(np.abs(params.stribeck_k), initial=0.0))
    f0 = float(np.max(np.abs(params.f0_n), initial=0.0))
    level = float(np.max(lam)) * tension * strib + f0
    if level <= 0.0:
        return 0.0
    sigma = float(np.min(params.sigma_n_m))
    if params.model == "maxwell_slip":
        sigma = min(sigma, float(np.min(params.slip_sigma)))
    n = params.pulleys
    eps = tol_n / (n * level)  # the target on the relative state z = 1 - s F / F_R
    if eps >= 2.0:
        return 0.0
    beta = float(params.beta)
    if beta == 1.0:
        g = math.log(2.0 / eps)
    else:
        g = (eps ** (1.0 - beta) - 2.0 ** (1.0 - beta)) / (beta - 1.0)
    return level / sigma * g
