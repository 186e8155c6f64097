"""The cyclic service: read -> compensate -> write against absolute deadlines.

ros2_control style (style.md): the hardware (a :class:`drivers.base.Driver`), the update
(:class:`gateway.compensator.Compensator`) and the loop are separate. Each cycle

1. waits for its absolute deadline (``next += period``): sleep, then busy-wait the last
   ``loop.busy_wait_s`` for a low start jitter;
2. reads, compensates, writes, timing each phase into preallocated statistics
   (:class:`LoopStats`: histogram bucket counters and ring buffers) that the metrics
   collector reads at scrape time;
3. counts an overrun when it ends after the next deadline and skips the missed cycles
   (the phase of the schedule is kept).

Nothing in a cycle logs, does HTTP or allocates what it can avoid; warnings (overruns,
bus errors, watchdog) are rate-limited and emitted after the cycle's work.

Lifecycle (:class:`LoopState`): unconfigured -> connected (driver open, reading) ->
active (writing) -> fault (bus down or PLC heartbeat frozen) -> back to connected/active;
stopped at the end. Only this module catches driver errors: a cycle whose read fails
writes nothing, flags every channel stale, closes the driver and reconnects (first retry
the next cycle, then exponential backoff ``reconnect_min_s .. reconnect_max_s``).

The PLC heartbeat that does not change for ``loop.heartbeat_timeout_s`` stops the tension
writes: one frame with gateway state FAULT, every channel invalid and NaN tensions is
written, then nothing until the heartbeat changes again. The gateway heartbeat is +1 per
written cycle. :meth:`CyclicService.stop` (and SIGTERM/SIGINT via
:meth:`CyclicService.install_signal_handlers`) end the loop after the current cycle; the
last frame written says STOPPED (state 0), every channel invalid, NaN tensions.

A driver with ``paced_by_bus = True`` (CANopen: the PLC's SYNC is the cycle clock) is
read without waiting for the loop's own deadline; see :meth:`CyclicService._run_paced`.

Clock and sleep are injectable (a fake clock for tests); ``run(cycles=N)`` is bounded.
"""

from __future__ import annotations

import bisect
import contextlib
import enum
import gc
import logging
import math
import signal
import sys
import threading
import time
from collections.abc import Callable
from types import FrameType
from typing import Any

import numpy as np

from drivers.base import Driver, GatewayState, Inputs, Outputs
from gateway.compensator import Compensator, TruthScore, score_into, warm_up
from gateway.config import Config
from gateway.errors import DriverError, DriverTimeoutError

log = logging.getLogger("cdpr_gateway.loop")

CYCLE_BUCKETS_S = (50e-6, 100e-6, 200e-6, 300e-6, 500e-6, 750e-6, 1e-3, 2e-3, 5e-3)
JITTER_BUCKETS_S = (10e-6, 20e-6, 50e-6, 100e-6, 200e-6, 500e-6, 1e-3, 2e-3, 5e-3)
ROUNDTRIP_BUCKETS_S = (50e-6, 100e-6, 200e-6, 300e-6, 500e-6, 750e-6, 1e-3, 2e-3, 5e-3, 0.05)
ERROR_KINDS = ("timeout", "io", "connect", "write", "invalid_value", "heartbeat")
REOPEN_AFTER = 3  # failed cycles in a row before the loop closes and reopens the driver
SCORE_AFTER_S = 0.5  # truth scoring skips the model's warm-up
TRUTH_EVERY_CYCLES = 10  # truth over the bus (simulation only) is read and scored this seldom


class LoopState(enum.Enum):
    UNCONFIGURED = "unconfigured"
    CONNECTED = "connected"
    ACTIVE = "active"
    FAULT = "fault"
    STOPPED = "stopped"


class Histogram:
    """Prometheus-style histogram: per-bucket counts (not cumulative), sum and count."""

    def __init__(self, bounds: tuple[float, ...]) -> None:
        self.bounds = bounds
        self.counts = [0] * (len(bounds) + 1)  # last: above every bound (+Inf only)
        self.sum = 0.0
        self.count = 0

    def add(self, value: float) -> None:
        self.counts[bisect.bisect_left(self.bounds, value)] += 1
        self.sum += value
        self.count += 1

    def cumulative(self) -> list[tuple[str, int]]:
        """``[(le, cumulative count), ..., ('+Inf', count)]`` for the exposition."""
        out, total = [], 0
        for bound, n in zip((*self.bounds, math.inf), self.counts, strict=True):
            total += n
            out.append(("+Inf" if bound == math.inf else repr(bound), total))
        return out


class Ring:
    """The last ``size`` values (s); written in the cycle, read for percentiles."""

    def __init__(self, size: int) -> None:
        self.values = np.zeros(size)
        self.count = 0

    def add(self, value: float) -> None:
        self.values[self.count % self.values.size] = value
        self.count += 1

    def recent(self) -> np.ndarray:
        return self.values[: min(self.count, self.values.size)]

    def percentile(self, q: float) -> float:
        data = self.recent()
        return float(np.percentile(data, q)) if data.size else math.nan


class LoopStats:
    """Everything the loop measures, preallocated; read at scrape time."""

    def __init__(self, history: int = 1 << 16) -> None:
        self.cycle = Histogram(CYCLE_BUCKETS_S)
        self.jitter = Histogram(JITTER_BUCKETS_S)
        self.roundtrip = Histogram(ROUNDTRIP_BUCKETS_S)
        self.cycle_ring = Ring(history)
        self.jitter_ring = Ring(history)
        self.roundtrip_ring = Ring(history)
        self.read_ring = Ring(history)
        self.compensate_ring = Ring(history)
        self.write_ring = Ring(history)
        self.cycles = 0  # cycles executed
        self.written = 0  # cycles whose outputs were written
        self.overruns = 0  # cycles that ended after the next deadline
        self.skipped = 0  # deadlines skipped because of overruns
        self.reconnects = 0  # successful reconnections after a loss
        self.errors = dict.fromkeys(ERROR_KINDS, 0)


def _reconnect_limits(cfg: Config) -> tuple[float, float]:
    bus = getattr(cfg.bus, cfg.bus.driver, None)
    return (
        float(getattr(bus, "reconnect_min_s", 0.05)),
        float(getattr(bus, "reconnect_max_s", 2.0)),
    )


class CyclicService:
    """The gateway's cycle around one driver. Not thread-safe except :meth:`stop`."""

    def __init__(
        self,
        cfg: Config,
        driver: Driver,
        *,
        clock: Callable[[], float] = time.perf_counter,
        sleep: Callable[[float], None] = time.sleep,
        history: int = 1 << 16,
        with_truth: bool = False,
        wall_clock: Callable[[], float] = time.time,
        truth_source: Callable[[Inputs], None] | None = None,
    ) -> None:
        self.cfg = cfg
        self.driver = driver
        self.clock = clock
        self.sleep = sleep
        self.period_s = cfg.loop.period_s
        self.busy_wait_s = cfg.loop.busy_wait_s
        self.inputs = Inputs.allocate(cfg.cables, with_truth)
        self.outputs = Outputs.allocate(cfg.cables)
        warm_up(cfg)
        self.comp = Compensator(cfg)
        self.stats = LoopStats(history)
        self.truth = TruthScore(cfg.cables) if with_truth else None
        # a truth source in this process is free; the driver's costs a bus transaction
        self._truth_every = 1 if truth_source is not None else TRUTH_EVERY_CYCLES
        self._truth_countdown = 1
        self.state = LoopState.UNCONFIGURED
        self.heartbeat_fault = False
        self._stop = threading.Event()
        self._fault_written = False
        self._last_hb: int | None = None
        self._hb_changed_at = 0.0
        self._ever_connected = False
        self._open = False
        self._failures = 0
        self._read_truth: Callable[[Inputs], None] | None = truth_source or getattr(
            driver, "read_truth", None
        )
        self.wall_clock = wall_clock
        self.paced = bool(getattr(driver, "paced_by_bus", False))
        self._data_at = 0.0
        self._backoff_min, self._backoff_max = _reconnect_limits(cfg)
        self._backoff = self._backoff_min
        self._reconnect_at = -math.inf
        self._started_at = 0.0
        self._logged = dict.fromkeys((*ERROR_KINDS, "overruns", "reconnects"), 0)
        self._next_check = -math.inf
        self.recorder: Any = None  # recording hook: a gateway.recorder.Recorder, set by run

    # --- lifecycle ----------------------------------------------------------------------
    def configure(self) -> None:
        """Open the driver (unconfigured -> connected); on failure, fault and retry later."""
        now = self.clock()
        self._started_at = now
        self._connect(now)

    def stop(self) -> None:
        """Ask the loop to end after the current cycle (safe from signals and threads)."""
        self._stop.set()

    def install_signal_handlers(self) -> dict[int, Any]:
        """SIGTERM and SIGINT call :meth:`stop`; returns the previous handlers."""

        def handler(signum: int, frame: FrameType | None) -> None:
            self.stop()

        return {s: signal.signal(s, handler) for s in (signal.SIGTERM, signal.SIGINT)}

    def run(self, cycles: int | None = None) -> LoopStats:
        """Run ``cycles`` cycles (``None``: until :meth:`stop`); then write STOPPED."""
        if self.state is LoopState.UNCONFIGURED:
            self.configure()
        gc.collect()
        gc.freeze()  # everything allocated so far is permanent: no GC pauses scanning it
        # Another thread (metrics scrape, an in-process PLC) holds the GIL for up to the
        # switch interval (5 ms by default) before the loop gets it back: shorten it.
        switch = sys.getswitchinterval()
        sys.setswitchinterval(min(switch, self.period_s / 5))
        try:
            self._run(cycles)
        finally:
            sys.setswitchinterval(switch)
            self._shutdown()
        return self.stats

    def _run(self, cycles: int | None) -> None:
        if self.paced:
            self._run_paced(cycles)
            return
        period = self.period_s
        deadline = self.clock()
        done = 0
        while not self._stop.is_set() and (cycles is None or done < cycles):
            self._wait_until(deadline)
            start = self.clock()
            self._add_jitter(start - deadline)
            reanchor = self._cycle(start)
            end = self.clock()
            self._add_cycle(end - start)
            self.stats.cycles += 1
            done += 1
            if reanchor:  # a (re)connect attempt may block: restart the schedule
                deadline = self.clock() + period
            else:
                deadline += period
                if end > deadline:
                    missed = int((end - deadline) // period) + 1
                    deadline += missed * period
                    self.stats.overruns += 1
                    self.stats.skipped += missed
            self._report(end)

    def _run_paced(self, cycles: int | None) -> None:
        """The bus is the clock (CANopen SYNC): ``read_into`` waits for the next set.

        Jitter is the lateness of the data after its SYNC (the driver's
        ``last_sync_timestamp``, wall-clock base); the cycle time runs from the data's
        arrival to the end of the write; an overrun is a cycle after which SYNCs were
        missed (the driver's ``syncs`` advanced by more than one), each one skipped.
        While the bus is down the loop falls back to its own deadlines for the retries.
        """
        done = 0
        deadline = self.clock()
        drv = self.driver
        while not self._stop.is_set() and (cycles is None or done < cycles):
            if not self._open:
                self._wait_until(deadline)
            syncs_before = int(getattr(drv, "syncs", 0))
            start = self.clock()
            self._data_at = start
            self._cycle(start)
            end = self.clock()
            if self._data_at != start:  # a set arrived: its SYNC's lateness, the work
                sync_at = float(getattr(drv, "last_sync_timestamp", 0.0))
                if sync_at > 0.0:
                    self._add_jitter(max(0.0, self.wall_clock() - sync_at))
                self._add_cycle(end - self._data_at)
                missed = int(getattr(drv, "syncs", 0)) - syncs_before - 1
                if missed > 0 and syncs_before > 0:
                    self.stats.overruns += 1
                    self.stats.skipped += missed
            deadline = end + self.period_s
            self.stats.cycles += 1
            done += 1
            self._report(end)

    def _add_jitter(self, seconds: float) -> None:
        self.stats.jitter.add(seconds)
        self.stats.jitter_ring.add(seconds)

    def _add_cycle(self, seconds: float) -> None:
        self.stats.cycle.add(seconds)
        self.stats.cycle_ring.add(seconds)

    def _wait_until(self, deadline: float) -> None:
        remaining = deadline - self.clock()
        if remaining > self.busy_wait_s:
            self.sleep(remaining - self.busy_wait_s)
        while self.clock() < deadline:
            pass

    # --- one cycle ----------------------------------------------------------------------
    def _cycle(self, now: float) -> bool:
        """One read -> compensate -> write; True when the schedule must be re-anchored."""
        if not self._open:
            if now >= self._reconnect_at:
                self._connect(now)
                return True
            self.comp.mark_unread(now)
            return False
        try:
            self.driver.read_into(self.inputs)
        except DriverTimeoutError:
            self._failed(now, "timeout")
            return False
        except DriverError:
            self._failed(now, "io")
            return False
        self._failures = 0
        t1 = self.clock()
        self._data_at = t1
        rt = self.driver.roundtrip_s
        last = float(rt.values[(rt.count - 1) % rt.size])
        self.stats.roundtrip.add(last)
        self.stats.roundtrip_ring.add(last)
        scored = self.truth is not None and self._read_truth is None  # came with the read
        if self.truth is not None and self._read_truth is not None:
            self._truth_countdown -= 1
            if self._truth_countdown <= 0:  # truth costs a transaction: sample it
                self._truth_countdown = self._truth_every
                try:
                    self._read_truth(self.inputs)  # its own transaction when the map needs one
                except DriverError:
                    self._failed(now, "io")
                    return False
                scored = True
        self.stats.read_ring.add(t1 - now)
        self.comp.step(self.inputs, t1, self.outputs)
        self.stats.errors["invalid_value"] = self.comp.flag_events
        self._watch_heartbeat(t1)
        if scored and self.inputs.true_tension_n is not None:
            self._score(t1)
        t2 = self.clock()
        self.stats.compensate_ring.add(t2 - t1)
        self._write()
        self.stats.write_ring.add(self.clock() - t2)
        if self.recorder is not None:  # recording hook: copies into a ring, never blocks
            self.recorder.push(t1, self.inputs, self.outputs)
        return False

    def _score(self, now: float) -> None:
        if now - self._started_at < SCORE_AFTER_S or self.truth is None:
            return
        c = self.comp
        score_into(
            self.inputs.true_tension_n, c.raw_n, c.corrected_n, c.status,
            self.truth.raw_sq, self.truth.corrected_sq, self.truth.samples,
        )  # fmt: skip

    def _watch_heartbeat(self, now: float) -> None:
        hb = self.inputs.plc_heartbeat
        if hb != self._last_hb:
            self._last_hb = hb
            self._hb_changed_at = now
            if self.heartbeat_fault:
                self.heartbeat_fault = False
                self._fault_written = False
        elif not self.heartbeat_fault and now - self._hb_changed_at > (
            self.cfg.loop.heartbeat_timeout_s
        ):
            self.heartbeat_fault = True
            self.stats.errors["heartbeat"] += 1

    def _write(self) -> None:
        out = self.outputs
        if self.heartbeat_fault:
            if self._fault_written:
                return
            self.comp.invalidate_outputs(out)
            out.gateway_state = int(GatewayState.FAULT)
            self.state = LoopState.FAULT
        else:
            out.gateway_state = int(GatewayState.ACTIVE)
        out.gateway_heartbeat = (out.gateway_heartbeat + 1) & 0xFFFF
        try:
            self.driver.write_from(out)
            if self.heartbeat_fault:
                self.driver.flush()
                self._fault_written = True
        except DriverError:
            self._failed(self.clock(), "write")
            return
        self.stats.written += 1
        if not self.heartbeat_fault:
            self.state = LoopState.ACTIVE

    # --- connection ---------------------------------------------------------------------
    @property
    def bus_up(self) -> bool:
        """The driver is open and its last transaction succeeded."""
        return self._open and self._failures == 0

    @property
    def reconnects(self) -> int:
        """Reopens by the loop plus reconnections the driver made by itself."""
        return self.stats.reconnects + int(getattr(self.driver, "reconnects", 0))

    def _failed(self, now: float, kind: str) -> None:
        """A failed transaction: nothing written this cycle, channels stale.

        The driver is kept open (drivers heal themselves: Modbus reconnects with its own
        backoff, CANopen waits for the next SYNC); after ``REOPEN_AFTER`` failed cycles in
        a row the loop closes it and reopens it with backoff.
        """
        self.stats.errors[kind] += 1
        self.comp.mark_unread(now)
        self.state = LoopState.FAULT
        self._last_hb = None  # after an outage, watch the PLC heartbeat afresh
        self._failures += 1
        if self._failures >= REOPEN_AFTER:
            self._close_driver()
            self._reconnect_at = now  # first reopen on the next cycle, then backoff

    def _connect(self, now: float) -> None:
        try:
            self._close_driver()
            self.driver.open()
            self._open = True
        except DriverError:
            if self._ever_connected or self.stats.cycles:
                self.stats.errors["connect"] += 1
            self.state = LoopState.FAULT
            self._reconnect_at = now + self._backoff
            self._backoff = min(self._backoff * 2.0, self._backoff_max)
            return
        if self._ever_connected:
            self.stats.reconnects += 1
        self._ever_connected = True
        self._backoff = self._backoff_min
        self._failures = 0
        self._last_hb = None  # a restarted PLC: watch its heartbeat afresh
        self.state = LoopState.CONNECTED

    def _close_driver(self) -> None:
        self._open = False
        with contextlib.suppress(DriverError):
            self.driver.close()

    def _shutdown(self) -> None:
        """Write STOPPED (every channel invalid, no tensions) and close the driver."""
        if self._open:
            out = self.outputs
            self.comp.invalidate_outputs(out)
            out.gateway_state = int(GatewayState.STOPPED)
            out.gateway_heartbeat = (out.gateway_heartbeat + 1) & 0xFFFF
            try:
                self.driver.write_from(out)
                self.driver.flush()
                self.stats.written += 1
            except DriverError as exc:
                log.warning("could not write the stopped state: %s", exc)
        self._close_driver()
        self.state = LoopState.STOPPED
        gc.unfreeze()

    # --- reporting, outside the cycle's work ------------------------------------------
    def _report(self, now: float) -> None:
        """Rate-limited warnings about what changed since the last one."""
        if now < self._next_check:
            return
        self._next_check = now + 0.5
        current = {**self.stats.errors, "overruns": self.stats.overruns}
        current["reconnects"] = self.reconnects
        changed = {k: v - self._logged[k] for k, v in current.items() if v != self._logged[k]}
        if not changed:
            return
        self._logged = current
        self._next_check = now + self.cfg.loop.overrun_warning_interval_s
        detail = ", ".join(f"{k} +{v}" for k, v in changed.items())
        log.warning("gateway: %s (state %s)", detail, self.state.value)
