"""The cyclic service: read -> compensate -> write against absolute deadlines.

ros2_control style (the house style): the hardware (a :class:`drivers.base.Driver`), the update
(:class:`gateway.runtime.compensator.Compensator`) and the loop are separate. There is one
loop body (:meth:`CyclicService._loop`); when a cycle starts and how its timing is booked is
a pacing strategy (:mod:`gateway.runtime.pacing`): :class:`~.pacing.PeriodicPacing` waits for
the loop's own absolute deadlines (``next += period``; an overrun is counted and the missed
deadlines skipped), :class:`~.pacing.BusPacing` lets the bus be the clock (CANopen:
the PLC's SYNC; ``read_into`` blocks until the next set). Each cycle

1. waits as its pacing says;
2. reads, checks the setpoints' plausibility (:mod:`gateway.runtime.plausibility`), compensates,
   writes, timing each phase into preallocated statistics
   (:class:`gateway.runtime.loopstats.LoopStats`) that the metrics collector reads at
   scrape time; observers added with
   :meth:`CyclicService.add_observer` see each successful cycle (the demo's scoring, a
   recorder);
3. books its timing with the pacing.

Nothing in a cycle logs, does HTTP or allocates what it can avoid; state changes, warnings
(overruns, bus errors, watchdog) and the systemd notifications are emitted after the
cycle's work, rate-limited (:meth:`CyclicService._report`).

Lifecycle (:class:`drivers.base.Lifecycle`, the value is the wire code of register 125):
STOPPED (not started) -> CONNECTED (driver open, reading) -> ACTIVE (writing) -> FAULT
(bus down or PLC heartbeat frozen) -> back to CONNECTED/ACTIVE; STOPPED at the end. Only
this module catches driver errors: a cycle whose read fails writes nothing and flags every
channel stale (:meth:`CyclicService._failed`); after a few in a row the loop closes the
driver and asks it each cycle to reconnect (:meth:`drivers.base.Driver.poll_connect`, which
waits at most half a period per cycle and spaces attempts with the driver's backoff).

The PLC heartbeat that does not change for ``loop.heartbeat_timeout_s`` stops the tension
writes: one frame with state FAULT, every channel invalid and NaN tensions is written, then
nothing until the heartbeat changes again. Only a changed value (finite: a NaN heartbeat is
"not changed") resets this watchdog: failed cycles, reconnects and SYNC timeouts do not,
and :meth:`CyclicService.plc_heartbeat_age_s` is the true age. Each frame carries the time
of its data and of the last heartbeat change, which the driver's output gate
(:mod:`drivers.gate`) checks when it sends it. The gateway heartbeat is +1 per written
cycle (modulo 2**32; the driver wraps it to its register).
:meth:`CyclicService.stop` (and every catchable terminating signal, see
:data:`STOP_SIGNALS`) ends the loop after the current cycle; the last frame written says
STOPPED (state 0), every channel invalid, NaN tensions.

Clock and sleep are injectable (a fake clock for tests); ``run(cycles=N)`` is bounded.
"""

from __future__ import annotations

import contextlib
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

from drivers.base import Driver, Inputs, Lifecycle, Outputs
from gateway.core.config import Config
from gateway.core.firstrun import compiling
from gateway.errors import DriverError, DriverTimeoutError
from gateway.runtime.compensator import Compensator, warm_up
from gateway.runtime.loopstats import ERROR_KINDS, LoopStats
from gateway.runtime.pacing import Pacing, make_pacing
from gateway.runtime.plausibility import Plausibility
from gateway.runtime.plausibility import warm_up as warm_up_plausibility
from gateway.runtime.sdnotify import Notifier

log = logging.getLogger("cdpr_gateway.loop")

CONNECT_BUDGET_PERIODS = 0.5  # a connection attempt waits at most this much of a cycle
REOPEN_AFTER = 3  # failed cycles in a row before the loop closes and reopens the driver

# Every signal whose default action ends the process and that a handler can catch: each
# ends the loop after the current cycle and the STOPPED frame is written. SIGPIPE is left
# ignored (Python's default: a broken socket is an error of that write, handled as one);
# SIGKILL and SIGSTOP cannot be caught (the PLC must watch the gateway heartbeat).
STOP_SIGNALS: tuple[signal.Signals, ...] = tuple(
    getattr(signal, name)
    for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT", "SIGUSR1", "SIGUSR2", "SIGALRM")
    if hasattr(signal, name)
)

Observer = Callable[[Inputs, Compensator, float], None]


def cycle_kernels() -> list[Any]:
    """A kernel of each source file the cycle compiles (:func:`gateway.core.firstrun.compiling`),
    one it compiles whatever the model: the chain's travel (the chain's kernel is the plain
    or the general one by the model; a sentinel the cycle never compiled would say
    "compiling" on every start)."""
    from drivers import kernels
    from gateway.model import chain_kernels
    from gateway.runtime import compensator, plausibility

    return [compensator._finish, plausibility._check, chain_kernels.travel_into, kernels.gate]


def describe_bus(cfg: Config) -> str:
    """``modbus_tcp 127.0.0.1:5020 unit 1`` and the like, for log lines."""
    bus = cfg.bus.driver
    if bus == "modbus_tcp":
        m = cfg.bus.modbus_tcp
        return m.endpoint + (" (TLS)" if m.tls is not None else "")
    if bus == "canopen":
        return cfg.bus.canopen.endpoint
    return bus


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
        wall_clock: Callable[[], float] = time.time,
        notifier: Notifier | None = None,
    ) -> None:
        self.cfg = cfg
        self.driver = driver
        # what the log names: the configured bus, or no bus at all for the in-process PLC
        # (`demo --offline` named modbus_tcp 127.0.0.1:5020 with no socket open)
        self.where = (
            "virtual (the in-process PLC, no bus)"
            if getattr(driver, "name", "") == "virtual"
            else describe_bus(cfg)
        )
        self.clock = clock
        self.sleep = sleep
        self.period_s = cfg.loop.period_s
        self.inputs = Inputs.allocate(cfg.cables)
        self.outputs = Outputs.allocate(cfg.cables)
        with compiling("gateway", cycle_kernels(), log.info):  # said, on a first run
            warm_up(cfg)
            warm_up_plausibility(cfg)
            driver.output_gate  # noqa: B018 - built (compiled) now, not in the first cycle
        self.comp = Compensator(cfg)
        self.plausibility = Plausibility(cfg)
        self.stats = LoopStats(history)
        self.pacing: Pacing = make_pacing(driver, cfg.loop, clock, sleep, wall_clock, self.stats)
        driver.clock = clock  # the output gate and the data's time on the loop's clock
        self.comp.heartbeat_modulus = driver.plc_heartbeat_modulus  # the register's wrap
        self.notifier = notifier
        self.state = Lifecycle.STOPPED
        self.heartbeat_fault = False
        self.last_error: BaseException | None = None  # the driver error behind a fault
        self._observers: list[Observer] = []
        self._stop = threading.Event()
        self._fault_written = False
        self._last_hb: float | None = None  # the PLC heartbeat's last finite value
        self._hb_changed_at = -math.inf  # when it last changed (-inf: not seen changing)
        self._hb_watched_from = math.nan  # when it was first read
        self._hb_seen_at = math.nan  # when the read that last showed _last_hb was requested
        self._data_at = math.nan  # loop clock of the last successful read
        self._got_data = False
        self._ever_connected = False
        self.last_connect_error = ""  # the cause of the last failed connection attempt
        self.write_blocked = ""  # why the bus takes no frame now (CANopen NMT), else ""
        self._open = False
        self._failures = 0
        self._pending: Outputs | None = None  # written with the next read (function 23)
        self._configured = False
        self._reporter = _Reporter(self)
        self.recorder: Any = None  # recording hook: a gateway.service.recorder.Recorder, set by run
        self.metrics: Any = None  # metrics hook: a gateway.service.metrics_shm.MetricsBlock

    @property
    def paced(self) -> bool:
        """True when the bus sets the pace (CANopen SYNC)."""
        return self.pacing.by_bus

    def add_observer(self, observer: Observer) -> None:
        """Call ``observer(inputs, compensator, now_s)`` after each successful compensation.

        Observers run inside the cycle: they must be quick and must not raise.
        """
        self._observers.append(observer)

    # --- lifecycle ----------------------------------------------------------------------
    def configure(self) -> None:
        """Open the driver (STOPPED -> CONNECTED); on failure, FAULT and retry later."""
        self._configured = True
        self._connect(self.clock())

    def stop(self) -> None:
        """Ask the loop to end after the current cycle (safe from signals and threads)."""
        self._stop.set()

    def install_signal_handlers(
        self, signals: tuple[signal.Signals, ...] = STOP_SIGNALS
    ) -> dict[int, Any]:
        """Every signal of ``signals`` calls :meth:`stop`; returns the previous handlers."""

        def handler(signum: int, frame: FrameType | None) -> None:
            self.stop()

        return {s: signal.signal(s, handler) for s in signals}

    def run(self, cycles: int | None = None) -> LoopStats:
        """Run ``cycles`` cycles (``None``: until :meth:`stop`); then write STOPPED."""
        if not self._configured:
            self.configure()
        self._reporter.ready()  # configured: ready, whether or not the PLC answers yet
        gc.collect()
        gc.freeze()  # everything allocated so far is permanent: no GC pauses scanning it
        # Another thread (metrics scrape, an in-process PLC) holds the GIL for up to the
        # switch interval (5 ms by default) before the loop gets it back: shorten it.
        switch = sys.getswitchinterval()
        sys.setswitchinterval(min(switch, self.period_s / 5))
        try:
            self._loop(cycles)
        finally:
            sys.setswitchinterval(switch)
            self._shutdown()
        return self.stats

    def _loop(self, cycles: int | None) -> None:
        """The one loop body: wait (pacing), cycle, book the timing, report."""
        pacing, stats = self.pacing, self.stats
        pacing.begin()
        done = 0
        while not self._stop.is_set() and (cycles is None or done < cycles):
            start = pacing.wait(self._open)
            self._got_data = False
            reanchor = self._cycle(start)
            end = self.clock()
            pacing.finish(start, end, self._data_at if self._got_data else None, reanchor)
            stats.cycles += 1
            done += 1
            self._reporter.report(end)
            if self.metrics is not None:  # into shared memory at most every 50 ms, no lock
                self.metrics.publish_due(end)

    # --- one cycle ----------------------------------------------------------------------
    def _cycle(self, now: float) -> bool:
        """One read -> compensate -> write; True when the schedule must be re-anchored."""
        if not self._open:
            self._connect(now)
            self.comp.mark_unread(now)
            return self._open
        pending, self._pending = self._pending, None
        try:
            self.driver.exchange(pending, self.inputs)
        except DriverTimeoutError as exc:
            self._failed(now, "timeout", exc)
            return False
        except DriverError as exc:
            self._failed(now, "io", exc)
            return False
        self._failures = 0
        clock, stats, inputs, comp = self.clock, self.stats, self.inputs, self.comp
        t1 = clock()
        self._data_at = t1
        self._got_data = True
        stats.add_roundtrip_from(self.driver.roundtrip_s)
        if self.plausibility.check(inputs):
            stats.errors["implausible"] += 1
        comp.step(inputs, t1, self.outputs)
        stats.errors["invalid_value"] = comp.flag_events
        stats.errors["clock"] = comp.clock.resyncs
        self._watch_heartbeat(t1)
        self.outputs.stamp(inputs.read_time_s, self._hb_changed_at)  # the gate checks both
        for observer in self._observers:
            observer(inputs, comp, t1)
        t2 = clock()
        self._write()
        stats.add_phases(t1 - now, t2 - t1, clock() - t2)
        if self.recorder is not None:  # recording hook: copies into a ring, never blocks
            self.recorder.push(t1, inputs, self.outputs)
        return False

    def _watch_heartbeat(self, now: float) -> None:
        """Only a changed, finite heartbeat value resets the watchdog (module doc)."""
        hb, seen_at = self.inputs.plc_heartbeat, self.inputs.read_time_s
        if self._hb_watched_from != self._hb_watched_from:
            self._hb_watched_from = now
        if not math.isfinite(hb):
            pass  # NaN / inf: no value, not a change
        elif self._last_hb is None:
            self._last_hb, self._hb_seen_at = hb, seen_at  # the watch starts: no change yet
        elif hb != self._last_hb:
            # it changed after the old value was last read: date it then (the earliest it
            # can have been), so a change seen across a stall is as old as the stall
            self._last_hb, self._hb_changed_at = hb, self._hb_seen_at
            self._hb_seen_at = seen_at
            timeout = self.cfg.loop.heartbeat_timeout_s
            if self.heartbeat_fault and now - self._hb_changed_at <= timeout:
                self.heartbeat_fault = False
                self._fault_written = False
            return
        else:
            self._hb_seen_at = seen_at
        if not self.heartbeat_fault and now - self._heartbeat_since() > (
            self.cfg.loop.heartbeat_timeout_s
        ):
            self.heartbeat_fault = True
            self.stats.errors["heartbeat"] += 1

    def _write(self) -> None:
        out = self.outputs
        self.write_blocked = self.driver.write_blocked()
        if self.write_blocked:  # e.g. stopped by the NMT master: connected, not writing
            self.state = Lifecycle.CONNECTED
            return
        if self.heartbeat_fault:
            if self._fault_written:
                return
            self.comp.invalidate_outputs(out)
            out.gateway_state = int(Lifecycle.FAULT)
            self.state = Lifecycle.FAULT
        else:
            out.gateway_state = int(Lifecycle.ACTIVE)
        out.gateway_heartbeat = (out.gateway_heartbeat + 1) & 0xFFFFFFFF
        try:
            if self.driver.combines_write_and_read and not self.heartbeat_fault:
                self._pending = out  # goes out with the next cycle's read, one exchange
            else:
                self.driver.write_from(out)
            if self.heartbeat_fault:
                self._fault_written = True
        except DriverError as exc:
            self._failed(self.clock(), "write", exc)
            return
        self.stats.written += 1
        if not self.heartbeat_fault:
            self.state = Lifecycle.ACTIVE

    # --- ages, read at scrape time ------------------------------------------------------
    def sample_age_s(self) -> float:
        """Seconds since the last successful read (NaN before the first)."""
        return self.clock() - self._data_at

    def plc_heartbeat_age_s(self) -> float:
        """Seconds since the PLC heartbeat last changed, or since it was first read if it
        has not changed since (NaN before the first read). Errors never reset it."""
        return self.clock() - self._heartbeat_since()

    def _heartbeat_since(self) -> float:
        changed = self._hb_changed_at
        return changed if changed > -math.inf else self._hb_watched_from

    # --- connection (reconnect with backoff) --------------------------------------------
    @property
    def bus_up(self) -> bool:
        """The driver is open and its last transaction succeeded."""
        return self._open and self._failures == 0

    @property
    def reconnects(self) -> int:
        """Connections the driver re-established after one was up."""
        return self.driver.reconnects

    def _failed(self, now: float, kind: str, exc: BaseException) -> None:
        """A failed transaction: nothing written this cycle, channels stale.

        The driver is kept open (CANopen waits for the next SYNC, a Modbus timeout may be
        followed by a good reply); after ``REOPEN_AFTER`` failed cycles in a row the loop
        closes it and asks it to reconnect (the driver's backoff spaces the attempts).
        """
        self.stats.errors[kind] += 1
        self.last_error = exc
        self.comp.mark_unread(now)
        self.state = Lifecycle.FAULT
        self._failures += 1
        self._pending = None
        if self._failures >= REOPEN_AFTER:
            self._close_driver()

    def _connect(self, now: float) -> None:
        """Advance the driver's connection by at most half a period, so the schedule
        holds (its backoff decides when an attempt starts; the loop never resets it)."""
        try:
            if not self.driver.poll_connect(now, CONNECT_BUDGET_PERIODS * self.period_s):
                return
            self._open = True
        except DriverError as exc:
            if self._ever_connected or self.stats.cycles:
                self.stats.errors["connect"] += 1
            self.last_error = exc
            self.last_connect_error = str(exc)
            self.state = Lifecycle.FAULT
            return
        self.stats.reconnects = self.driver.reconnects
        self._ever_connected = True
        self._pending = None
        self._failures = 0
        self.state = Lifecycle.CONNECTED

    def _close_driver(self) -> None:
        self._open = False
        with contextlib.suppress(DriverError):
            self.driver.close()

    def _shutdown(self) -> None:
        """Write STOPPED (every channel invalid, no tensions) and close the driver."""
        if self._open:
            out = self.outputs
            self.comp.invalidate_outputs(out)
            out.gateway_state = int(Lifecycle.STOPPED)
            out.gateway_heartbeat = (out.gateway_heartbeat + 1) & 0xFFFFFFFF
            try:
                self.driver.write_from(out)
                self.stats.written += 1
            except DriverError as exc:
                log.warning("could not write the stopped state: %s", exc)
        self._close_driver()
        self._reporter.stopped(self.clock())  # an outage that ended says so before the stop
        self.state = Lifecycle.STOPPED
        gc.unfreeze()


def _cause(where: str, error: BaseException | None) -> str:
    """The driver's error text, prefixed with the bus unless it names the address."""
    text = str(error) if error is not None else "no error reported"
    address = where.split(" ")[1] if " " in where else where
    return text if address in text else f"{where}: {text}"


# An outage (the bus or the PLC heartbeat) ends when the loop has stayed active this long:
# interruptions closer together are one episode, said twice (its start, a WARNING, and its
# end, an INFO line with its length and how many interruptions it had). The CANopen demo on
# a loaded machine said 205 "recovered" and 153 summary WARNINGs in 5 s, one per missed
# SYNC, with its table saying "reconnects 4".
SETTLED_S = 0.25


class _Reporter:
    """What the loop says, outside the cycle's work: state changes (each outage once, when
    it starts and when it has settled), the rate-limited summary of counters, and the
    systemd notifications."""

    def __init__(self, service: CyclicService) -> None:
        self.svc = service
        self.logged = dict.fromkeys((*ERROR_KINDS, "overruns", "reconnects"), 0)
        self.next_check = -math.inf
        self.state = Lifecycle.STOPPED
        self.heartbeat_fault = False
        self.fault_since = math.nan  # loop clock when the current outage began
        self.cause = ""  # the last fault line of the current outage
        self.active_since = math.nan  # loop clock when the outage's last interruption ended
        self.interruptions = 0  # of the current outage
        self.longest_s = 0.0  # its longest interruption
        self.heartbeat_outage = False  # the outage began with the PLC heartbeat, not the bus
        self.interrupted_at = math.nan  # loop clock of the last interruption's start
        self.ready_sent = False
        self.write_blocked = ""
        notifier = service.notifier
        self.watchdog_s = notifier.watchdog_interval_s if notifier is not None else math.inf
        self.next_watchdog = -math.inf

    def report(self, now: float) -> None:
        svc = self.svc
        if svc.state is not self.state or svc.heartbeat_fault is not self.heartbeat_fault:
            self._state_changed(now)
        if svc.write_blocked != self.write_blocked:
            if svc.write_blocked:
                log.warning("not writing: %s; writing resumes when operational", svc.write_blocked)
                self._status(f"not writing: {svc.write_blocked}")
            else:
                log.warning("writing again: %s is operational", self.write_blocked.split(":")[0])
            self.write_blocked = svc.write_blocked
        if svc.notifier is not None and now >= self.next_watchdog:
            self.next_watchdog = now + self.watchdog_s
            svc.notifier.notify("WATCHDOG=1")
        if (
            svc.state is Lifecycle.ACTIVE
            and not math.isnan(self.active_since)
            and now - self.active_since >= SETTLED_S
        ):
            self._settled(now)
        if now >= self.next_check and math.isnan(self.fault_since):
            self._summary(now)  # within an outage its end says it; the summary waits

    def _state_changed(self, now: float) -> None:
        svc, old, new = self.svc, self.state, self.svc.state
        self.state, self.heartbeat_fault = new, svc.heartbeat_fault
        where = svc.where
        in_outage = not math.isnan(self.fault_since)
        if new is Lifecycle.FAULT:
            if svc.heartbeat_fault:
                line = (
                    f"fault: the PLC heartbeat has not changed for "
                    f"{svc.cfg.loop.heartbeat_timeout_s:g} s; tension writes stopped"
                )
            elif old is Lifecycle.STOPPED and not svc._ever_connected:
                line = f"cannot reach the PLC yet: {_cause(where, svc.last_error)}; retrying"
            else:
                line = f"disconnected from the PLC: {_cause(where, svc.last_error)}; reconnecting"
            # within one outage a reopen that fails again, or a new interruption before it
            # settled, is said only at DEBUG: its end counts them
            level = logging.WARNING if not in_outage else logging.DEBUG
            if not in_outage:
                self.fault_since = now
                self.interruptions, self.longest_s = 0, 0.0
                self.heartbeat_outage = svc.heartbeat_fault
            if old is not Lifecycle.FAULT:
                self.interruptions += 1
            if not math.isnan(self.active_since):
                self.active_since = math.nan
            self.interrupted_at = now
            self.cause = line
            log.log(level, "%s", line)
            self._status(line)
        elif new is Lifecycle.CONNECTED:
            log.log(
                logging.DEBUG if in_outage else logging.INFO, "connected to the PLC at %s", where
            )
        elif new is Lifecycle.ACTIVE:
            if in_outage:  # said once it has settled (_settled), or when the loop stops
                self.active_since = now
                self.longest_s = max(self.longest_s, now - self.interrupted_at)
                log.debug("active again at %s (settling)", where)
            else:
                log.info("connected to the PLC at %s; active, writing corrected tensions", where)
            self._status("active")

    def _settled(self, now: float) -> None:
        """The outage's one closing line, at INFO (its start was the WARNING)."""
        where = self.svc.where
        what = (
            "the PLC heartbeat changes again"
            if self.heartbeat_outage
            else f"connected to the PLC at {where}"
        )
        span = self.active_since - self.fault_since
        more = ""
        if self.interruptions > 1:
            more = (
                f" ({self.interruptions} interruptions, the longest {self.longest_s * 1e3:.0f} ms)"
            )
        log.info("recovered: %s, active again after %.1f s%s", what, span, more)
        self.fault_since = self.active_since = math.nan
        self.cause = ""
        self.next_check = now  # the next summary (if any) says the state is active

    def ready(self) -> None:
        """READY=1 once, when the service is configured: a PLC that does not answer yet
        is retried by the loop (the README's 'ready once configured'), so systemd's start
        does not wait for it (TimeoutStartSec)."""
        if self.svc.notifier is not None and not self.ready_sent:
            self.ready_sent = True
            self.svc.notifier.notify("READY=1")

    def _status(self, line: str) -> None:
        if self.svc.notifier is not None:
            self.svc.notifier.notify(f"STATUS={line}")

    def _summary(self, now: float) -> None:
        """Rate-limited warning about the counters that changed since the last one."""
        svc = self.svc
        self.next_check = now + 0.5
        current = {**svc.stats.errors, "overruns": svc.stats.overruns}
        current["reconnects"] = svc.reconnects
        changed = {k: v - self.logged[k] for k, v in current.items() if v != self.logged[k]}
        if not changed:
            return
        self.logged = current
        self.next_check = now + svc.cfg.loop.overrun_warning_interval_s
        detail = ", ".join(f"{k} +{v}" for k, v in changed.items())
        log.warning("gateway: %s (state %s)", detail, svc.state.name.lower())

    def stopped(self, now: float) -> None:
        if not math.isnan(self.active_since):
            self._settled(now)
        if self.svc.notifier is not None:
            self.svc.notifier.notify("STOPPING=1")
