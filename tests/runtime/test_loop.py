"""The cyclic service on a fake clock with the virtual driver (no wall-time assertions)."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest

from drivers.base import ChannelStatus, Lifecycle
from drivers.virtual import VirtualDriver, VirtualFaults
from gateway.runtime.loop import CyclicService
from tests.loop_helpers import FakeClock, config, finite, live_image

PERIOD = 0.001


def make(faults: VirtualFaults | None = None, on_read=None, **loop):
    cfg = config(busy_wait_s=0.0, **loop)
    img = live_image(cfg)
    clock = FakeClock()
    drv = VirtualDriver(cfg, image=img, faults=faults, on_read=on_read)
    svc = CyclicService(cfg, drv, clock=clock, sleep=clock.sleep, history=4096)
    return svc, drv, img, clock


def test_deadlines_are_absolute_and_every_cycle_writes():
    svc, _, img, clock = make()
    start = clock.now
    stats = svc.run(cycles=200)
    assert stats.cycles == 200
    assert stats.overruns == 0
    assert stats.written == 201  # 200 cycles + the STOPPED frame
    assert img.gateway_heartbeat == 201
    # 200 cycles starting at t0 end just after t0 + 199 periods: no drift
    assert clock.now - start == pytest.approx(199 * PERIOD, abs=1e-4)
    assert stats.jitter_ring.recent().max() < 1e-5
    assert stats.cycle.count == 200 and sum(stats.cycle.counts) == 200


def test_overrun_is_counted_and_missed_cycles_skipped():
    clock_box = {}

    def slow(n: int) -> None:
        if n == 10:
            clock_box["clock"].advance(2.5 * PERIOD)

    svc, _, _, clock = make(on_read=slow)
    clock_box["clock"] = clock
    start = clock.now
    stats = svc.run(cycles=50)
    assert stats.overruns == 1
    assert stats.skipped == 2
    # the schedule keeps its phase: 49 periods + the 2 skipped deadlines
    assert clock.now - start == pytest.approx(51 * PERIOD, abs=1e-4)
    assert stats.jitter_ring.recent().max() < 1e-5  # the next cycle starts on a deadline


def test_failed_read_writes_nothing_and_the_next_cycle_resumes():
    writes_at_read: dict[int, int] = {}
    holder = {}

    def record(n: int) -> None:
        writes_at_read[n] = holder["img"].gateway_writes

    svc, drv, img, _ = make(VirtualFaults(fail_on_read=5), on_read=record)
    holder["img"] = img
    stats = svc.run(cycles=30)
    assert writes_at_read[5] == 4
    assert writes_at_read[6] == 4  # the failed cycle wrote nothing
    assert writes_at_read[7] == 5
    assert stats.errors["io"] == 1
    assert svc.reconnects == 0 and drv.opens == 1  # one failure: the driver heals itself
    assert stats.written == 30  # 29 good cycles + the STOPPED frame
    assert svc.state is Lifecycle.STOPPED


def test_dropped_connection_is_reopened_and_the_loop_resumes():
    writes_at_read: dict[int, int] = {}
    holder = {}

    def record(n: int) -> None:
        writes_at_read[n] = holder["img"].gateway_writes

    svc, drv, img, _ = make(VirtualFaults(drop_on_read=5), on_read=record)
    holder["img"] = img
    stats = svc.run(cycles=30)
    # reads 5, 6, 7 fail (REOPEN_AFTER = 3), cycle 8 reopens, read 8 (cycle 9) succeeds
    assert writes_at_read[8] == 4
    assert writes_at_read[9] == 5
    assert stats.errors["io"] == 3
    assert svc.reconnects == 1 and drv.opens == 2
    assert stats.written == 30 - 4 + 1
    assert finite(img.corrected_n) is False  # the STOPPED frame carries no tensions


def test_failed_read_flags_channels_stale_and_keeps_last_good():
    svc, _, img, _ = make(VirtualFaults(fail_on_read=5, fail_count=100))
    svc.run(cycles=5)
    assert np.all(svc.comp.flags & 8)  # FLAG_STALE
    assert np.all(svc.comp.status == ChannelStatus.SUBSTITUTED)
    assert img.gateway_writes == 4 + 1  # nothing from the failed cycle; the STOPPED frame
    assert img.gateway_state == Lifecycle.STOPPED  # the bus was still open at stop


def test_timeouts_are_counted_by_kind():
    svc, _, _, _ = make(VirtualFaults(timeout_on_read=3, timeout_count=2))
    stats = svc.run(cycles=10)
    assert stats.errors["timeout"] == 2
    assert stats.errors["io"] == 0
    assert svc.reconnects == 0


def test_reopen_backoff_grows_while_the_plc_is_away():
    svc, drv, _, _ = make(VirtualFaults(drop_on_read=5))
    drv.faults.fail_opens = 0

    def refuse_from_now(n: int) -> None:
        if n == 5:
            drv.faults.fail_opens = 4  # opens 2..4 refused, open 5 succeeds

    drv.on_read = refuse_from_now
    stats = svc.run(cycles=600)
    assert drv.opens == 5
    assert stats.errors["connect"] == 3
    assert svc.reconnects == 1
    # refused at ~cycle 8, retried after 0.05, 0.1, 0.2 s: back near cycle 8 + 350
    first_good = 5 + 3 + 350
    assert stats.written == pytest.approx(600 - first_good + 4 + 1, abs=12)


def test_initial_connect_retries_with_exponential_backoff():
    svc, drv, img, _ = make(VirtualFaults(fail_opens=3))
    first_write: dict[str, int] = {}

    def record(n: int) -> None:
        first_write.setdefault("cycle", svc.stats.cycles)

    drv.on_read = record
    svc.run(cycles=500)
    assert drv.opens == 4
    # retries after 0.05, then 0.1, then 0.2 s: the first read is near cycle 350
    assert 340 <= first_write["cycle"] <= 360
    assert svc.stats.errors["connect"] == 2  # the start-up failure is not an error count
    assert img.gateway_writes > 100


def test_frozen_plc_heartbeat_stops_writes_and_faults_then_resumes():
    seen: dict[int, tuple[int, int]] = {}
    holder = {}

    def record(n: int) -> None:
        img = holder["img"]
        seen[n] = (img.gateway_writes, img.gateway_state)

    faults = VirtualFaults(freeze_heartbeat_from=10, freeze_heartbeat_until=200)
    svc, _, img, _ = make(faults, on_read=record, heartbeat_timeout_s=0.05)
    holder["img"] = img
    svc.run(cycles=250)
    writes_fault, state_fault = seen[120]
    assert state_fault == Lifecycle.FAULT
    assert seen[190] == (writes_fault, Lifecycle.FAULT)  # nothing written while frozen
    assert 55 <= writes_fault <= 65
    assert seen[210][1] == Lifecycle.ACTIVE and seen[210][0] > writes_fault
    assert svc.stats.errors["heartbeat"] == 1


def test_fault_frame_carries_no_tensions():
    faults = VirtualFaults(freeze_heartbeat_from=2)
    svc, _, img, _ = make(faults, heartbeat_timeout_s=0.01)
    snapshot = {}

    def record(n: int) -> None:
        if n == 40:
            snapshot["corrected"] = img.corrected_n.copy()
            snapshot["status"] = img.channel_status.copy()
            snapshot["state"] = img.gateway_state

    svc.driver.on_read = record  # type: ignore[attr-defined]
    svc.run(cycles=45)
    assert snapshot["state"] == Lifecycle.FAULT
    assert np.all(np.isnan(snapshot["corrected"]))
    assert np.all(snapshot["status"] == ChannelStatus.INVALID)
    assert svc.state is Lifecycle.STOPPED


def test_stop_writes_stopped_state_and_invalid_channels():
    holder = {}

    def record(n: int) -> None:
        if n == 30:
            holder["svc"].stop()

    svc, _, img, _ = make(on_read=record)
    holder["svc"] = svc
    stats = svc.run(cycles=1000)
    assert stats.cycles == 30
    assert img.gateway_state == Lifecycle.STOPPED == 0
    assert np.all(img.channel_status == ChannelStatus.INVALID)
    assert np.all(np.isnan(img.corrected_n))
    assert svc.state is Lifecycle.STOPPED


def test_sigterm_ends_the_loop_cleanly():
    def record(n: int) -> None:
        if n == 20:
            os.kill(os.getpid(), signal.SIGTERM)

    svc, _, img, _ = make(on_read=record)
    previous = svc.install_signal_handlers()
    try:
        stats = svc.run(cycles=1000)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    assert stats.cycles <= 21
    assert img.gateway_state == Lifecycle.STOPPED


def test_good_cycles_write_finite_tensions_and_active_state():
    seen = {}
    holder = {}

    def record(n: int) -> None:
        if n == 50:
            seen["state"] = holder["img"].gateway_state
            seen["corrected"] = holder["img"].corrected_n.copy()

    svc, _, img, _ = make(on_read=record)
    holder["img"] = img
    svc.run(cycles=60)
    assert seen["state"] == Lifecycle.ACTIVE
    assert finite(seen["corrected"])
    # paying out (v > 0): the platform carries more tension than the sensor reads
    assert np.all(seen["corrected"] > 199.0)


def test_saturated_channel_is_substituted_then_invalid_in_the_registers():
    snap = {}
    holder = {}

    def record(n: int) -> None:
        snap[n] = (holder["img"].channel_status[2], holder["img"].corrected_n[2])

    faults = VirtualFaults(saturated_channel=2, saturated_from=20)
    svc, _, img, _ = make(faults, on_read=record, substitute_max_s=0.03)
    holder["img"] = img
    svc.run(cycles=100)
    assert snap[19][0] == ChannelStatus.GOOD
    assert snap[30][0] == ChannelStatus.SUBSTITUTED and np.isfinite(snap[30][1])
    assert snap[80][0] == ChannelStatus.INVALID and np.isnan(snap[80][1])
    assert snap[80][0] != svc.comp.status[0]  # the other channels stay good
    assert svc.stats.errors["invalid_value"] == 1


def test_cycles_do_not_accumulate_allocations():
    import tracemalloc

    from tests.loop_helpers import Wobble

    cfg = config(busy_wait_s=0.0)
    img = live_image(cfg)
    clock = FakeClock()
    drv = VirtualDriver(cfg, image=img, step=Wobble(img))
    svc = CyclicService(cfg, drv, clock=clock, sleep=clock.sleep, history=4096)
    svc.configure()
    svc._loop(300)  # warm-up: numba dispatch, first-time caches
    tracemalloc.start()
    try:
        before, _ = tracemalloc.get_traced_memory()
        svc._loop(2000)
        after, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert svc.stats.written >= 2300
    assert after - before < 4096  # nothing retained per cycle
    assert peak - before < 32768  # and no large temporaries


class PacedVirtual(VirtualDriver):
    """A bus-paced driver: each read waits one SYNC period on the fake clock."""

    paced_by_bus = True

    def __init__(self, cfg, clock: FakeClock, **kw) -> None:
        super().__init__(cfg, **kw)
        self.clock = clock
        self.syncs = 0
        self.last_sync_timestamp = 0.0
        self.lag_on: dict[int, int] = {}

    def _read(self, inputs) -> None:
        extra = self.lag_on.get(self.reads + 1, 0)
        self.clock.advance(PERIOD * (1 + extra))
        self.syncs += 1 + extra
        self.last_sync_timestamp = self.clock.now - 20e-6  # data 20 us after SYNC
        super()._read(inputs)


def test_bus_paced_driver_sets_the_pace_and_missed_syncs_are_overruns():
    cfg = config(busy_wait_s=0.0)
    clock = FakeClock()
    drv = PacedVirtual(cfg, clock, image=live_image(cfg))
    drv.lag_on = {40: 2}  # two SYNCs pass before read 40 returns
    svc = CyclicService(
        cfg, drv, clock=clock, sleep=clock.sleep, history=1024, wall_clock=lambda: clock.now
    )
    assert svc.paced
    start = clock.now
    stats = svc.run(cycles=100)
    assert clock.slept == 0.0  # the loop never slept: the bus paced it
    assert clock.now - start == pytest.approx(102 * PERIOD, abs=1e-4)
    assert stats.overruns == 1 and stats.skipped == 2
    assert stats.cycles == 100 and stats.written == 101
    assert stats.jitter_ring.recent() == pytest.approx(20e-6, abs=1e-6)


def test_overrun_warnings_are_rate_limited(caplog):
    holder = {}

    def slow(n: int) -> None:
        if n % 100 == 0:  # an overrun every 100 cycles
            holder["clock"].advance(1.5 * PERIOD)

    svc, _, _, clock = make(on_read=slow, overrun_warning_interval_s=1.0)
    holder["clock"] = clock
    with caplog.at_level("WARNING", logger="cdpr_gateway.loop"):
        stats = svc.run(cycles=2500)
    assert stats.overruns == 25
    warnings = [r for r in caplog.records if "overruns" in r.getMessage()]
    # one at the first overrun, then at most one per second of loop time (~2.5 s)
    assert 2 <= len(warnings) <= 4
    assert (
        sum(int(r.getMessage().split("overruns +")[1].split()[0].rstrip(",")) for r in warnings)
        <= 25
    )


# --- plausibility of the setpoints -----------------------------------------


def test_pose_of_1e20_m_is_flagged_counted_and_gives_no_wrench():
    snap = {}
    holder = {}

    def record(n: int) -> None:
        img = holder["img"]
        if n == 30:
            img.pose[0] = 1e20  # from read 30 on
        if n == 40:
            snap["status"] = img.channel_status.copy()
            snap["wrench"] = img.wrench.copy()

    svc, _, img, _ = make(on_read=record)
    holder["img"] = img
    good_wrench = None

    def observe(inputs, comp, now):
        nonlocal good_wrench
        if good_wrench is None and np.all(np.isfinite(comp.wrench)):
            good_wrench = comp.wrench.copy()

    svc.add_observer(observe)
    svc.run(cycles=45)
    assert good_wrench is not None and np.all(np.isfinite(good_wrench))  # before: a wrench
    assert np.all(np.isnan(snap["wrench"]))  # after: none
    assert np.all(snap["status"] != ChannelStatus.GOOD)  # every channel flagged
    assert svc.stats.errors["implausible"] == 45 - 30 + 1


def test_velocity_of_3_4e38_m_s_flags_that_channel_only():
    snap = {}
    holder = {}

    def record(n: int) -> None:
        img = holder["img"]
        if n == 20:
            img.velocity_m_s[3] = 3.4e38
        if n == 30:
            snap["status"] = img.channel_status.copy()
            snap["corrected"] = img.corrected_n.copy()

    svc, _, img, _ = make(on_read=record, substitute_max_s=0.005)
    holder["img"] = img
    svc.run(cycles=35)
    assert snap["status"][3] == ChannelStatus.INVALID and np.isnan(snap["corrected"][3])
    others = np.delete(snap["status"], 3)
    assert np.all(others == ChannelStatus.GOOD)
    assert svc.stats.errors["implausible"] == 35 - 20 + 1
    assert svc.stats.errors["invalid_value"] == 1


def test_plausibility_bounds_come_from_the_geometry():
    from gateway.runtime.plausibility import Plausibility

    cfg = config()
    bounds = Plausibility(cfg)
    np.testing.assert_allclose(bounds.lo, [-2.5, -2.0, -0.5], atol=1e-12)  # frame - 0.5 m
    np.testing.assert_allclose(bounds.hi, [2.5, 2.0, 3.5], atol=1e-12)
    from drivers.base import Inputs

    inputs = Inputs.allocate(cfg.cables)
    inputs.pose[:] = cfg.geometry.home_pose
    inputs.length_m[:] = 2.0
    assert bounds.check(inputs) == 0 and np.all(np.isfinite(inputs.pose))
    inputs.length_m[5] = 1e6  # no cable of this frame is a kilometre long
    assert bounds.check(inputs) == 1 and np.isnan(inputs.velocity_m_s[5])


def test_a_step_the_sample_clock_refuses_is_counted_as_a_clock_error():
    # a PLC restart: its heartbeat counter back at 0 after 100 reads. The step is not
    # integrated (the chain resynchronises), and the operator sees it counted
    # (errors_total{kind="clock"}), also across a heartbeat register re-declared later
    holder = {}

    def restart(n: int) -> None:
        if n == 100:
            holder["img"].plc_heartbeat = 0

    svc, _, img, _ = make(on_read=restart)
    holder["img"] = img
    svc.run(cycles=300)
    assert svc.stats.errors["clock"] == 1
    svc.comp.heartbeat_modulus = 65536  # a new clock (the driver's register) keeps the count
    assert svc.comp.clock.resyncs == 1
