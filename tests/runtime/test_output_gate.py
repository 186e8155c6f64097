"""Regressions of the output contract through the loop (fake clock, virtual driver).

Each test reproduces one failure of the second hostile round and fails on the code before
the output gate: the watchdog reset by bus errors and reconnects, a stalled gateway's
pipelined (function-23 style) frame sent as good, a NaN PLC heartbeat crashing the loop,
the heartbeat-age metric reading fresh while the PLC is silent.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.base import ChannelStatus, Inputs, Lifecycle, Outputs
from drivers.virtual import VirtualDriver
from gateway.errors import DriverIOError
from gateway.runtime.loop import CyclicService
from tests.loop_helpers import FakeClock, config, live_image

GOOD = int(ChannelStatus.GOOD)
SUBSTITUTED = int(ChannelStatus.SUBSTITUTED)


class RecordingDriver(VirtualDriver):
    """The virtual driver, recording every frame it writes with the loop clock's time."""

    def __init__(self, cfg, clock, combined: bool = False, **kw) -> None:
        super().__init__(cfg, **kw)
        self.frames: list[tuple[float, np.ndarray, np.ndarray, int]] = []
        self._clock_for_frames = clock
        self._combined = combined

    @property
    def combines_write_and_read(self) -> bool:
        return self._combined

    def _write(self, outputs: Outputs) -> None:
        super()._write(outputs)
        self.frames.append(
            (
                self._clock_for_frames.now,
                outputs.channel_status.copy(),
                outputs.tension_corrected_n.copy(),
                int(outputs.gateway_state),
            )
        )


def _service(cfg, clock, **kw):
    img = live_image(cfg)
    drv = RecordingDriver(cfg, clock, image=img, **kw)
    svc = CyclicService(cfg, drv, clock=clock, sleep=clock.sleep, history=4096)
    return svc, drv, img


def _good_after(frames, t: float) -> list[float]:
    return [ft for ft, status, _, _ in frames if ft > t and np.any(status <= SUBSTITUTED)]


def test_bus_errors_do_not_reset_the_heartbeat_watchdog():
    """PLC heartbeat frozen, values live, one failed read every 40: the old
    loop reset its heartbeat reference on each failure and wrote thousands of good
    frames; now the fault comes after the timeout and no good value follows it."""
    cfg = config(busy_wait_s=0.0, heartbeat_timeout_s=0.1)
    clock = FakeClock()
    svc, drv, img = _service(cfg, clock, advance_heartbeat=False)
    frozen_at: dict[str, float] = {}

    def glitch(n: int) -> None:
        if n < 20:
            img.plc_heartbeat = (img.plc_heartbeat + 1) & 0xFFFF  # alive, then frozen
        elif n == 20:
            frozen_at["t"] = clock.now
        if n % 40 == 0:
            raise DriverIOError("exception 4 (fault injection)")

    drv.on_read = glitch
    svc.run(cycles=1500)
    assert svc.stats.errors["heartbeat"] >= 1
    limit = frozen_at["t"] + cfg.loop.heartbeat_timeout_s + 2 * cfg.loop.period_s
    assert _good_after(drv.frames, limit) == []


def test_reconnects_do_not_reset_the_heartbeat_watchdog():
    """The PLC drops the connection every 80 reads while its heartbeat is
    frozen: the reconnect path must not re-arm the watchdog."""
    cfg = config(busy_wait_s=0.0, heartbeat_timeout_s=0.1)
    clock = FakeClock()
    svc, drv, img = _service(cfg, clock, advance_heartbeat=False)
    frozen_at: dict[str, float] = {}
    ages: list[tuple[float, float]] = []

    def drop(n: int) -> None:
        if n < 20:
            img.plc_heartbeat = (img.plc_heartbeat + 1) & 0xFFFF
        elif n == 20:
            frozen_at["t"] = clock.now
        if n % 80 == 0:
            drv.disconnect()
        ages.append((clock.now, svc.plc_heartbeat_age_s()))

    drv.on_read = drop
    svc.run(cycles=1500)
    assert svc.reconnects >= 3
    limit = frozen_at["t"] + cfg.loop.heartbeat_timeout_s + 2 * cfg.loop.period_s
    assert _good_after(drv.frames, limit) == []
    # the age metric reports the true age: never younger than the time since the freeze
    for t, age in ages:
        if t > frozen_at["t"] + 0.01:
            assert age >= t - frozen_at["t"] - 2 * cfg.loop.period_s


@pytest.mark.parametrize(("stall_s", "reason", "frames"), [(2.0, "heartbeat", 2), (0.02, "age", 1)])
def test_a_stalled_gateway_never_sends_its_old_frame_as_good(
    stall_s: float, reason: str, frames: int
):
    """a frame computed before a 2-s stall (SIGSTOP, a swapped page) and sent
    with the next read (function 23 pipelines it) went out with every status 0. A stall
    shorter than the heartbeat timeout is stopped by the data's age alone. After a stall
    longer than the timeout the first heartbeat change seen is dated before the stall
    (it may have happened any time since the old value was read): one more frame
    invalid, then good ones."""
    cfg = config(busy_wait_s=0.0, stuck_after_s=10.0)  # the image's readings are constant
    clock = FakeClock()
    svc, drv, _ = _service(cfg, clock, combined=True)
    stall: dict = {"cycle": 50, "at": math.nan}

    def stall_after_compute(inputs: Inputs, comp, now: float) -> None:
        if svc.stats.cycles == stall["cycle"]:
            stall["gated"] = drv.gated.copy()
            clock.advance(stall_s)
            stall["at"] = clock.now

    svc.add_observer(stall_after_compute)
    svc.run(cycles=80)
    after = [f for f in drv.frames if f[0] >= stall["at"]]
    assert after, "frames were written after the stall"
    _, status, tension, _ = after[0]  # the pipelined frame computed before the stall
    assert np.all(status == ChannelStatus.INVALID)
    assert np.all(np.isnan(tension))
    stopped = drv.gated - stall["gated"]
    assert stopped[list(drv.GATE_REASONS).index(reason)] == 8 * frames == stopped.sum()
    assert np.any(after[3][1] == GOOD)  # frames computed after the stall are good again


def test_a_nan_float_plc_heartbeat_counts_as_unchanged():
    """a float PLC heartbeat carrying NaN crashed the gateway (int(NaN));
    NaN is "not changed": the watchdog faults after its timeout, nothing good after it."""
    cfg = config(busy_wait_s=0.0, heartbeat_timeout_s=0.05)
    clock = FakeClock()
    svc, drv, img = _service(cfg, clock, advance_heartbeat=False)
    nan_from = {}

    def feed(n: int) -> None:
        if n < 20:
            img.plc_heartbeat = float(n)
        else:
            nan_from.setdefault("t", clock.now)
            img.plc_heartbeat = math.nan

    drv.on_read = feed
    svc.run(cycles=300)
    assert svc.stats.errors["heartbeat"] == 1
    limit = nan_from["t"] + cfg.loop.heartbeat_timeout_s + 2 * cfg.loop.period_s
    assert _good_after(drv.frames, limit) == []
    assert svc.state is Lifecycle.STOPPED
