"""Shared fixtures for the CANopen tests: a config on a private virtual channel, the soft
PLC's nodes and the gateway driver on it (one process, python-can ``virtual``)."""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import can
import numpy as np
import pytest

from drivers.base import Inputs, Outputs
from drivers.canopen import SLOW_PERIOD_CYCLES, CanopenDriver
from gateway.core.config import Config, load_config
from sim_plc.canopen_nodes import CanopenPlc
from sim_plc.image import ProcessImage

_channels = itertools.count()


def canopen_config(channel: str | None = None) -> Config:
    """The default config with ``bus.driver = canopen`` on a fresh virtual channel."""
    cfg = load_config()
    name = channel or f"cdpr-test-{next(_channels)}-{id(cfg)}"
    can_cfg = dataclasses.replace(cfg.bus.canopen, interface="virtual", channel=name)
    bus = dataclasses.replace(cfg.bus, driver="canopen", canopen=can_cfg)
    return dataclasses.replace(cfg, bus=bus)


def virtual_bus_factory(channel: str) -> Callable[[], can.BusABC]:
    return lambda: can.Bus(interface="virtual", channel=channel)


@dataclass
class CanopenRig:
    cfg: Config
    image: ProcessImage
    plc: CanopenPlc
    driver: CanopenDriver
    inputs: Inputs
    outputs: Outputs

    def cycle(self) -> None:
        """One stepped cycle: SYNC + PDOs, then the driver reads them."""
        self.plc.step()
        self.driver.read_into(self.inputs)


def fill_image(image: ProcessImage, seed: int = 1) -> None:
    """Distinct in-range values in every PLC input of the image."""
    rng = np.random.default_rng(seed)
    with image.lock:
        image.raw_counts[:] = rng.integers(0, 27648, image.cables)
        image.velocity_m_s[:] = rng.uniform(-0.6, 0.6, image.cables)
        image.length_m[:] = rng.uniform(0.5, 6.0, image.cables)
        image.pose[:] = np.concatenate([rng.uniform(-2.0, 3.0, 3), rng.uniform(-3.0, 3.0, 3)])
        image.plc_heartbeat = int(rng.integers(0, 65536))


@pytest.fixture
def rig() -> Iterator[CanopenRig]:
    cfg = canopen_config()
    image = ProcessImage(cfg.cables)
    plc = CanopenPlc(cfg, image, virtual_bus_factory(cfg.bus.canopen.channel))
    gw_bus = can.Bus(interface="virtual", channel=cfg.bus.canopen.channel)
    driver = CanopenDriver(cfg, bus=gw_bus, timeout_s=0.02)
    plc.start()
    driver.open()
    inputs = Inputs.allocate(cfg.cables)
    for _ in range(SLOW_PERIOD_CYCLES):  # the first set after open needs every slow PDO
        plc.step()
    driver.read_into(inputs)
    try:
        yield CanopenRig(cfg, image, plc, driver, inputs, Outputs.allocate(cfg.cables))
    finally:
        driver.close()
        plc.stop()
        gw_bus.shutdown()


# --- cross-process nodes (run as `python tests/canopen_helpers.py plc|gateway GROUP PORT`) ---
NETNS_CYCLES = 300


def _udp_bus(group: str, port: int) -> can.BusABC:
    return can.Bus(interface="udp_multicast", channel=group, port=port, fd=False)


def expected_counts(cables: int) -> np.ndarray:
    return (np.arange(cables) * 3000 + 111).astype(np.int16)


def netns_plc_main(group: str, port: int, seconds: float) -> dict[str, object]:
    """The soft PLC's nodes in real time until the gateway's last write arrived."""
    import time

    cfg = canopen_config()
    image = ProcessImage(cfg.cables)
    image.raw_counts[:] = expected_counts(cfg.cables)
    plc = CanopenPlc(cfg, image, lambda: _udp_bus(group, port))
    plc.start(realtime=True)
    end = time.monotonic() + seconds
    try:
        # the gateway's heartbeat counts its writes: stop once its last one is in
        while time.monotonic() < end and image.gateway_heartbeat < NETNS_CYCLES:
            time.sleep(0.01)
    finally:
        plc.stop()
    return {
        "cycles": plc.cycles,
        "gateway_writes": image.gateway_writes,
        "corrected_n": image.corrected_n.tolist(),
        "gateway_heartbeat": image.gateway_heartbeat,
    }


def netns_gateway_main(group: str, port: int, seconds: float) -> dict[str, object]:
    """The gateway driver: read a set, write tension = raw, NETNS_CYCLES times."""
    import time

    from gateway.errors import DriverTimeoutError

    cfg = canopen_config()
    bus = _udp_bus(group, port)
    driver = CanopenDriver(cfg, bus=bus, timeout_s=0.05)
    inputs, outputs = Inputs.allocate(cfg.cables), Outputs.allocate(cfg.cables)
    outputs.channel_status[:] = 0  # good: an invalid channel carries no value
    good = timeouts = 0
    end = time.monotonic() + seconds
    driver.open()
    try:
        while good < NETNS_CYCLES and time.monotonic() < end:
            try:
                driver.read_into(inputs)
            except DriverTimeoutError:
                timeouts += 1
                continue
            good += 1
            outputs.tension_corrected_n[:] = inputs.tension_raw_n
            outputs.gateway_heartbeat = good
            now = driver.clock()  # fresh data, a live PLC (the output gate checks both)
            driver.write_from(outputs.stamp(now, now))
    finally:
        driver.close()
        bus.shutdown()
    return {"good": good, "timeouts": timeouts, "tension_raw_n": inputs.tension_raw_n.tolist()}


if __name__ == "__main__":
    import json
    import sys

    role, group_arg, port_arg, seconds_arg = sys.argv[1:5]
    main = netns_plc_main if role == "plc" else netns_gateway_main
    print(json.dumps(main(group_arg, int(port_arg), float(seconds_arg))), flush=True)
