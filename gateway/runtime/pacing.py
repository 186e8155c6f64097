"""When a cycle starts and how its timing is booked (ros2_control's sleeping policies).

The loop body is one (:meth:`gateway.runtime.loop.CyclicService._loop`); a pacing strategy
answers three questions for it:

* :meth:`Pacing.wait`: block until the next cycle may start, return its start time;
* :meth:`Pacing.finish`: book the cycle's jitter, duration and overruns into
  :class:`gateway.runtime.loopstats.LoopStats` and plan the next start;
* :attr:`Pacing.by_bus`: whether the bus, not the loop, is the clock.

:class:`PeriodicPacing` keeps absolute deadlines (``next += period``), sleeping and then
busy-waiting the last ``loop.busy_wait_s``; a cycle that ends after the next deadline is an
overrun and the missed deadlines are skipped (the phase is kept). A (re)connect attempt,
which may block, re-anchors the schedule. Only cycles that got the PLC's data are booked
(as :class:`BusPacing` does): retries while the PLC is unreachable are not cycles.

:class:`BusPacing` is for drivers paced by the bus (CANopen: the PLC's SYNC):
``read_into`` itself waits for the next set, so the loop does not wait while the bus is
up. Jitter is the lateness of the data after its SYNC (the driver's
``last_sync_timestamp``, wall-clock base); the cycle time runs from the data's arrival to
the end of the write; an overrun is a cycle after which SYNCs were missed (the driver's
``syncs`` advanced by more than one), each one skipped. While the bus is down it falls back
to the loop's own period for the retries.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any

from gateway.core.config import LoopConfig
from gateway.runtime.loopstats import LoopStats


class Pacing(ABC):
    """The timing half of the loop; see the module doc."""

    by_bus = False

    def __init__(
        self,
        loop: LoopConfig,
        clock: Callable[[], float],
        sleep: Callable[[float], None],
        stats: LoopStats,
    ) -> None:
        self.period_s = loop.period_s
        self.busy_wait_s = loop.busy_wait_s
        self.clock = clock
        self.sleep = sleep
        self.stats = stats
        self.deadline = 0.0

    def begin(self) -> None:
        """The schedule starts now."""
        self.deadline = self.clock()

    @abstractmethod
    def wait(self, bus_open: bool) -> float:
        """Block until the next cycle may start; return its start (loop clock)."""

    @abstractmethod
    def finish(self, start: float, end: float, data_at: float | None, reanchor: bool) -> None:
        """Book one cycle: ``data_at`` is when its data arrived (None: no data)."""

    def wait_until(self, deadline: float) -> None:
        remaining = deadline - self.clock()
        if remaining > self.busy_wait_s:
            self.sleep(remaining - self.busy_wait_s)
        while self.clock() < deadline:
            pass


class PeriodicPacing(Pacing):
    """The loop's own absolute deadlines.

    Only a cycle that got the PLC's data is booked (its lateness, duration and overruns):
    a wake-up that retries a connection or a read that failed is no cycle of the service,
    and an attempt that takes most of a period would otherwise count as overruns while
    nothing runs (the overrun alert fired on a gateway whose PLC was off). Missed deadlines
    are skipped either way."""

    late = 0.0  # lateness of the current cycle's start, booked by finish() if it had data

    def wait(self, bus_open: bool) -> float:
        self.wait_until(self.deadline)
        start = self.clock()
        self.late = start - self.deadline
        return start

    def finish(self, start: float, end: float, data_at: float | None, reanchor: bool) -> None:
        period, booked = self.period_s, data_at is not None
        if booked:
            self.stats.add_jitter(self.late)
            self.stats.add_cycle(end - start)
        if reanchor:  # a (re)connect attempt may block: restart the schedule
            self.deadline = self.clock() + period
            return
        self.deadline += period
        if end > self.deadline:
            missed = int((end - self.deadline) // period) + 1
            self.deadline += missed * period
            if booked:
                self.stats.add_overrun(missed)


class BusPacing(Pacing):
    """The bus is the clock: the driver's read waits for the next SYNC's data."""

    by_bus = True

    def __init__(
        self,
        loop: LoopConfig,
        clock: Callable[[], float],
        sleep: Callable[[float], None],
        stats: LoopStats,
        driver: Any,
        wall_clock: Callable[[], float],
    ) -> None:
        super().__init__(loop, clock, sleep, stats)
        self.driver = driver
        self.wall_clock = wall_clock
        self.syncs_before = 0

    def wait(self, bus_open: bool) -> float:
        if not bus_open:
            self.wait_until(self.deadline)
        self.syncs_before = self.driver.syncs
        return self.clock()

    def finish(self, start: float, end: float, data_at: float | None, reanchor: bool) -> None:
        if data_at is not None:  # a set arrived: its SYNC's lateness, the work
            sync_at = self.driver.last_sync_timestamp
            if sync_at > 0.0:
                self.stats.add_jitter(max(0.0, self.wall_clock() - sync_at))
            self.stats.add_cycle(end - data_at)
            missed = self.driver.syncs - self.syncs_before - 1
            if missed > 0 and self.syncs_before > 0:
                self.stats.add_overrun(missed)
        self.deadline = end + self.period_s


def make_pacing(
    driver: Any,
    loop: LoopConfig,
    clock: Callable[[], float],
    sleep: Callable[[float], None],
    wall_clock: Callable[[], float],
    stats: LoopStats,
) -> Pacing:
    """:class:`BusPacing` for a driver paced by its bus, else :class:`PeriodicPacing`."""
    if driver.paced_by_bus:
        return BusPacing(loop, clock, sleep, stats, driver, wall_clock)
    return PeriodicPacing(loop, clock, sleep, stats)
