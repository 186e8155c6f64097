"""Faults on the CANopen bus seen through the whole gateway.

A silent analog module (its PDOs lost) and a missing SYNC: the gateway writes nothing
computed from a failed read (its heartbeat at the PLC stops moving), counts the timeouts,
and once the fault clears resumes writing good channels within a bounded time.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np
import pytest

pytest.importorskip("can")
pytest.importorskip("canopen")

from drivers.base import ChannelStatus
from drivers.canopen import CanopenDriver
from gateway.runtime.loop import CyclicService
from sim_plc.canopen_nodes import CanopenPlc
from sim_plc.demo import StandInPlant
from sim_plc.image import ProcessImage
from tests.runtime.test_loop_canopen import PlantThread, virtual_canopen_config


def _wait(predicate: Callable[[], bool], timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


def _silence_analog(plc: CanopenPlc, on: bool) -> None:
    plc.analog.enabled = not on


def _stop_sync(plc: CanopenPlc, on: bool) -> None:
    plc.sync_enabled = not on


@pytest.mark.parametrize("fault", [_silence_analog, _stop_sync], ids=["lost-pdos", "no-sync"])
def test_canopen_fault_stops_writes_is_counted_and_recovers(fault) -> None:
    cfg = virtual_canopen_config()
    image = ProcessImage(cfg.cables)
    plant = StandInPlant(cfg, image)
    plant.step()
    plc = CanopenPlc(cfg, image)
    service = CyclicService(cfg, CanopenDriver(cfg))

    def heartbeat() -> int:
        with image.lock:
            return int(image.gateway_heartbeat)

    with PlantThread(plant, cfg.loop.period_s):
        plc.start(realtime=True)
        worker = threading.Thread(target=service.run, daemon=True)
        worker.start()
        try:
            assert _wait(lambda: service.stats.written >= 300, 30), "gateway never wrote"
            timeouts_before = service.stats.errors["timeout"]
            fault(plc, True)
            time.sleep(0.1)  # the frames already on the bus are consumed
            frozen = heartbeat()
            time.sleep(0.3)
            assert heartbeat() == frozen, "the gateway wrote without a fresh read"
            assert service.stats.errors["timeout"] > timeouts_before
            fault(plc, False)
            assert _wait(lambda: heartbeat() > frozen + 100, 10), "no recovery"
            with image.lock:
                status = image.channel_status.copy()
                corrected = image.corrected_n.copy()
        finally:
            service.stop()
            worker.join(timeout=30)
            plc.stop()
    assert not worker.is_alive()
    assert np.all(status == int(ChannelStatus.GOOD)), status
    assert np.all(np.isfinite(corrected))
