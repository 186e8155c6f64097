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
from drivers.canopen import CanopenDriver
from gateway.config import Config, load_config
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
    try:
        yield CanopenRig(
            cfg, image, plc, driver, Inputs.allocate(cfg.cables), Outputs.allocate(cfg.cables)
        )
    finally:
        driver.close()
        plc.stop()
        gw_bus.shutdown()
