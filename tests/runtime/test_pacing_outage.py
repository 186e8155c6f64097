"""Timing is booked only for cycles that exchanged data with the PLC.

With no PLC the loop still wakes every period to retry, and an attempt may take most of a
period: those wake-ups are neither cycles (``cycle_seconds``), nor late (``jitter``), nor
overruns; otherwise the overrun alert (a share of ``cycle_seconds_count``) fires on a
gateway whose only problem is a PLC that is off."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.virtual import VirtualDriver, VirtualFaults
from gateway.runtime.loop import CyclicService
from gateway.service.metrics import make_registry
from tests.loop_helpers import FakeClock, config, live_image, run_frozen


class SlowAttempts(VirtualDriver):
    """Each connection step costs ``attempt_s`` of the (fake) loop clock."""

    def __init__(self, *args, clock: FakeClock, attempt_s: float, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.clock, self.attempt_s = clock, attempt_s

    def poll_connect(self, now=None, budget_s=0.0):
        self.clock.advance(self.attempt_s)
        return super().poll_connect(now, budget_s)


def run(fail_opens: int, attempt_s: float, cycles: int) -> tuple[CyclicService, object]:
    cfg = config(busy_wait_s=0.0)
    clock = FakeClock()
    faults = VirtualFaults(fail_opens=fail_opens)
    drv = SlowAttempts(cfg, image=live_image(cfg), faults=faults, clock=clock, attempt_s=attempt_s)
    svc = CyclicService(cfg, drv, clock=clock, sleep=clock.sleep, history=1024)
    run_frozen(svc, cycles)
    return svc, make_registry(svc)


@settings(max_examples=20, deadline=None)
@given(attempt_s=st.floats(0.0, 0.01), cycles=st.integers(1, 400))
def test_no_plc_no_cycles_booked_and_no_overruns(attempt_s: float, cycles: int) -> None:
    svc, reg = run(10**9, attempt_s, cycles)
    assert svc.stats.cycles == cycles  # the loop kept waking up to retry
    assert reg.get_sample_value("cdpr_gateway_overruns_total") == 0
    assert reg.get_sample_value("cdpr_gateway_cycle_seconds_count") == 0
    assert reg.get_sample_value("cdpr_gateway_jitter_seconds_count") == 0


def test_cycles_with_data_are_booked_after_the_plc_answers() -> None:
    svc, reg = run(3, 0.002, 500)
    booked = reg.get_sample_value("cdpr_gateway_cycle_seconds_count")
    assert 0 < booked < 500
    assert booked == pytest.approx(svc.stats.written, abs=2)  # a cycle with data writes
    assert reg.get_sample_value("cdpr_gateway_jitter_seconds_count") == booked
