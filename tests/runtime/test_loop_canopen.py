"""The gateway's loop over CANopen on python-can's virtual bus, paced by the PLC's SYNC.

The soft PLC's CANopen nodes run in real time on a private virtual channel; a stand-in
plant (sim_plc.demo.StandInPlant) moves the process image at about 1 kHz; the gateway
reads the analog module's PDOs after each SYNC and its corrected tensions track the
plant's true tensions far better than the raw channels do.
"""

from __future__ import annotations

import dataclasses
import itertools
import threading
import time

import numpy as np
import pytest

pytest.importorskip("can")
pytest.importorskip("canopen")

from drivers.base import Lifecycle
from drivers.canopen import CanopenDriver
from gateway.core.config import Config
from gateway.runtime.loop import CyclicService
from sim_plc.canopen_nodes import CanopenPlc
from sim_plc.demo import StandInPlant, TruthScorer
from sim_plc.image import ProcessImage
from tests.loop_helpers import config

_channels = itertools.count()


class PlantThread:
    """Steps the stand-in plant every period on a daemon thread (bounded by ``stop``)."""

    def __init__(self, plant: StandInPlant, period_s: float) -> None:
        self.plant, self.period_s = plant, period_s
        self.stop_event = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        deadline = time.perf_counter()
        while not self.stop_event.is_set():
            self.plant.step()
            deadline += self.period_s
            rest = deadline - time.perf_counter()
            if rest > 0:
                time.sleep(rest)
            elif rest < -0.1:
                deadline = time.perf_counter()

    def __enter__(self) -> PlantThread:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop_event.set()
        self.thread.join(timeout=10)


def virtual_canopen_config() -> Config:
    """The test config on a private python-can virtual channel (no cross-talk)."""
    base = config()
    channel = f"cdpr-loop-test-{next(_channels)}-{id(base)}"
    can_cfg = dataclasses.replace(base.bus.canopen, interface="virtual", channel=channel)
    return dataclasses.replace(
        base, bus=dataclasses.replace(base.bus, driver="canopen", canopen=can_cfg)
    )


def test_gateway_over_canopen_virtual_bus_compensates():
    cfg = virtual_canopen_config()
    image = ProcessImage(cfg.cables)
    plant = StandInPlant(cfg, image)
    plant.step()

    def truth(out: np.ndarray) -> None:  # the test's own view of the plant
        with image.lock:
            out[:] = image.true_tension_n

    plc = CanopenPlc(cfg, image)
    service = CyclicService(cfg, CanopenDriver(cfg))
    scorer = TruthScorer(cfg.cables, truth)
    service.add_observer(scorer)
    assert service.paced
    with PlantThread(plant, cfg.loop.period_s):
        plc.start(realtime=True)
        try:
            worker = threading.Thread(target=service.run, daemon=True)
            worker.start()
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and service.stats.written < 2500:
                time.sleep(0.1)
            with image.lock:
                state_seen = image.gateway_state
                corrected_seen = image.corrected_n.copy()
            service.stop()
            worker.join(timeout=30)
            assert not worker.is_alive()
        finally:
            plc.stop()
    assert service.stats.written >= 2500
    assert state_seen == Lifecycle.ACTIVE
    assert np.all(np.isfinite(corrected_seen))
    assert scorer.score.samples.min() > 1000
    raw, corrected = scorer.score.rmse()
    assert corrected.mean() < 0.5 * raw.mean(), (raw, corrected)
    assert service.stats.jitter.count > 1000  # lateness after SYNC was measured


def test_nmt_stop_of_the_gateway_node_shows_in_the_state_and_the_log(caplog):
    """An NMT stop of the gateway's node (no PDOs go out) left the state at
    2 (active) and the connection at 1, and nothing was logged (5 of 5)."""
    import can

    from gateway.service.metrics import make_registry

    cfg = virtual_canopen_config()
    image = ProcessImage(cfg.cables)
    plant = StandInPlant(cfg, image)
    plant.step()
    plc = CanopenPlc(cfg, image)
    # a generous read timeout: on a loaded machine a reopen after timeouts would reboot
    # the node (self-starting: operational again), which is not what this test is about
    service = CyclicService(cfg, CanopenDriver(cfg, timeout_s=0.25))
    registry = make_registry(service)
    master = can.Bus(interface="virtual", channel=cfg.bus.canopen.channel)
    node = cfg.bus.canopen.gateway_node_id

    def nmt(command: int) -> None:
        master.send(
            can.Message(arbitration_id=0, data=bytes((command, node)), is_extended_id=False)
        )

    def wait(predicate, seconds: float = 20.0) -> bool:
        end = time.monotonic() + seconds
        while time.monotonic() < end and not predicate():
            time.sleep(0.02)
        return predicate()

    def state() -> float | None:
        return registry.get_sample_value("cdpr_gateway_state")

    with PlantThread(plant, cfg.loop.period_s), caplog.at_level("INFO"):
        plc.start(realtime=True)
        worker = threading.Thread(target=service.run, daemon=True)
        try:
            worker.start()
            assert wait(lambda: state() == Lifecycle.ACTIVE and image.gateway_writes > 200)
            nmt(0x02)  # stop
            assert wait(lambda: "STOPPED" in service.write_blocked)
            assert wait(lambda: state() == Lifecycle.CONNECTED)
            with image.lock:
                writes = image.gateway_writes
            time.sleep(0.3)
            with image.lock:
                assert image.gateway_writes == writes  # no PDOs while stopped
            nmt(0x01)  # start
            assert wait(lambda: state() == Lifecycle.ACTIVE)
            assert wait(lambda: image.gateway_writes > writes + 50)
        finally:
            service.stop()
            worker.join(timeout=30)
            plc.stop()
            master.shutdown()
    text = caplog.text
    assert "NMT state STOPPED" in text and "not writing" in text
    assert "writing again" in text


def test_sync_timeouts_do_not_reset_the_heartbeat_watchdog():
    """Over CANopen: SYNC timeouts while the PLC heartbeat was silent re-armed
    the watchdog (243 and 328 active sets, one run with no fault frame in 1 s, the age
    metric at 0.008 s after 1 s of silence). Now: the fault comes, nothing good after it,
    and the age grows through the timeouts."""
    from gateway.service.metrics import make_registry

    cfg = virtual_canopen_config()
    image = ProcessImage(cfg.cables)
    image.lock = threading.RLock()  # type: ignore[assignment]  # the freezer nests it
    plant = StandInPlant(cfg, image)
    plant.step()
    plc = CanopenPlc(cfg, image)
    service = CyclicService(cfg, CanopenDriver(cfg))
    registry = make_registry(service)
    frozen = threading.Event()

    class Freezer(PlantThread):
        def _run(self) -> None:  # the plant moves; its heartbeat stops when frozen is set
            while not self.stop_event.wait(self.period_s):
                with image.lock:  # the PLC never sees the step's +1 being taken back
                    hb = image.plc_heartbeat
                    self.plant.step()
                    if frozen.is_set():
                        image.plc_heartbeat = hb

    seen: list[tuple[float, int, bool]] = []
    delivered: list[tuple[float, float]] = []  # (time, PLC heartbeat) of each set read

    def heartbeats(inputs, comp, now) -> None:
        delivered.append((time.monotonic(), float(inputs.plc_heartbeat)))

    service.add_observer(heartbeats)
    with Freezer(plant, cfg.loop.period_s):
        plc.start(realtime=True)
        worker = threading.Thread(target=service.run, daemon=True)
        try:
            worker.start()
            end = time.monotonic() + 30
            while time.monotonic() < end and service.stats.written < 300:
                time.sleep(0.01)
            frozen.set()
            frozen_at = time.monotonic()
            for k in range(60):  # 1.2 s: SYNC off 30 ms of every 60 ms (timeouts)
                plc.sync_enabled = k % 2 == 1
                t_end = time.monotonic() + 0.03
                while time.monotonic() < t_end:
                    with image.lock:
                        good = bool(np.any(image.channel_status <= 1))
                        seen.append((time.monotonic(), image.gateway_writes, good))
                    time.sleep(0.002)
            plc.sync_enabled = True
            age = registry.get_sample_value("cdpr_gateway_plc_heartbeat_age_seconds")
            asked_at = time.monotonic()
        finally:
            service.stop()
            worker.join(timeout=30)
            plc.stop()
    # the last change the bus delivered (the heartbeat rides a slow PDO: sent every 10
    # SYNCs, late by the SYNC gaps, it can arrive ~0.1 s after the freeze on a loaded
    # machine); a write is dated by its first sighting in the PLC's image
    changes = [t for (t, h), (_, h0) in zip(delivered[1:], delivered, strict=False) if h != h0]
    assert changes and changes[-1] > frozen_at - 0.5
    last_change = changes[-1]
    limit = last_change + cfg.loop.heartbeat_timeout_s + 0.03
    first: dict[int, tuple[float, bool]] = {}
    for t, w, good in seen:
        first.setdefault(w, (t, good))
    late = sorted(w for w, (t, good) in first.items() if t > limit and good)
    assert not late, f"good frames written after the timeout: {late[:5]} of {len(first)}"
    assert service.stats.errors["heartbeat"] >= 1
    assert service.stats.errors["timeout"] >= 5  # the SYNC gaps were timeouts
    assert age is not None and age >= asked_at - last_change - 0.03, (age, asked_at, last_change)
    assert asked_at - last_change > 0.5  # the silence outlasted the timeout many times
