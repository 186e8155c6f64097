"""The driver contract's connection side, on a fake clock (no wall time).

* One owner of the reconnect backoff: the driver base class. The loop asks
  ``poll_connect`` and never resets it; only a good data reply does.
* A connection attempt never holds a cycle for more than the budget the loop gives
  (one period): the loop keeps its rate while a connect hangs.
"""

from __future__ import annotations

import pytest

from drivers.base import Backoff
from drivers.virtual import VirtualDriver, VirtualFaults
from gateway.runtime.loop import CyclicService
from tests.loop_helpers import FakeClock, config, live_image

PERIOD = 0.001


class HangingConnect(VirtualDriver):
    """A driver whose connection attempts never complete: each ``_open_advance`` waits
    its whole budget on the fake clock (like a SYN that is never answered)."""

    def __init__(self, cfg, clock: FakeClock, **kw) -> None:
        super().__init__(cfg, **kw)
        self.clock = clock
        self.budgets: list[float] = []

    def _open_begin(self) -> bool:
        return False

    def _open_advance(self, budget_s: float) -> bool:
        self.budgets.append(budget_s)
        self.clock.advance(budget_s)
        return False


def test_backoff_doubles_to_its_maximum_and_a_good_reply_resets_it() -> None:
    b = Backoff(0.05, 0.3)
    waits = [b.attempt(10.0) for _ in range(5)]
    assert waits == pytest.approx([0.05, 0.1, 0.2, 0.3, 0.3])
    assert not b.ready(10.29) and b.ready(10.3)
    b.reset()
    assert b.ready(0.0) and b.interval_s == 0.05


def test_a_hanging_connect_never_stalls_the_cycle() -> None:
    cfg = config(busy_wait_s=0.0)
    clock = FakeClock()
    drv = HangingConnect(cfg, clock, image=live_image(cfg))
    svc = CyclicService(cfg, drv, clock=clock, sleep=clock.sleep, history=1024)
    start = clock.now
    stats = svc.run(cycles=500)
    assert stats.cycles == 500
    assert drv.budgets and max(drv.budgets) <= PERIOD / 2  # half a period at most
    # 500 cycles took about 500 periods: the connect attempt did not hold the loop
    assert clock.now - start == pytest.approx(500 * PERIOD, rel=0.05)
    assert not svc.bus_up


def test_the_loop_never_resets_the_backoff_of_an_erroring_plc() -> None:
    """Every read fails (an exception reply, say) while every connect succeeds: the loop
    reopens after three failed cycles, at 0, 0.05, 0.15, 0.35, 0.75 s: not every cycle."""
    cfg = config(busy_wait_s=0.0)
    clock = FakeClock()
    drv = VirtualDriver(
        cfg, image=live_image(cfg), faults=VirtualFaults(fail_on_read=1, fail_count=10**9)
    )
    svc = CyclicService(cfg, drv, clock=clock, sleep=clock.sleep, history=1024)
    svc.run(cycles=1000)  # one second
    assert drv.opens == 5
    assert drv.backoff.interval_s == pytest.approx(1.6)
    assert svc.stats.errors["io"] == 3 * 5


def test_a_good_reply_resets_the_backoff_so_a_later_drop_reconnects_at_once() -> None:
    cfg = config(busy_wait_s=0.0)
    clock = FakeClock()
    drv = VirtualDriver(cfg, image=live_image(cfg), faults=VirtualFaults(drop_on_read=300))
    svc = CyclicService(cfg, drv, clock=clock, sleep=clock.sleep, history=1024)
    svc.run(cycles=310)
    assert drv.opens == 2  # reads 300-302 failed, the reopen came on the next cycle
    assert svc.reconnects == 1
