"""Driver harnesses for the contract suite (tests/drivers/test_driver_contract.py).

Every driver joins the suite with ONE harness factory here and one subclass of the
contract class in the test module (python-can's ``back2back_test.py`` style). A factory is
a context manager that starts whatever the driver talks to (soft PLC server, CANopen
nodes, nothing for the in-process driver) around a :class:`sim_plc.image.ProcessImage`
and yields a :class:`DriverHarness`.

The harness' driver is constructed, not opened. ``propagate()`` is called after the test
changed the image and before it reads, and after a write before it checks the image: use
it to run SYNC cycles or wait for PDOs. ``stop()`` takes the far side away so that
further I/O must fail with a DriverError.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

from drivers.base import Driver, make_driver
from drivers.canopen import CanopenDriver
from drivers.virtual import VirtualDriver
from gateway.core.config import load_config
from sim_plc.canopen_nodes import CanopenPlc
from sim_plc.image import ProcessImage
from tests.canopen_helpers import canopen_config, virtual_bus_factory
from tests.modbus_helpers import filled_image, plc_server

CANOPEN_SYNC_PERIOD_S = 0.002  # the soft PLC's SYNC thread: easy on a shared machine
# a read waits this long for a whole SYNC cycle of PDOs: 0.1 s (50 SYNC periods) was not
# enough with both cores busy (make test beside another job: "missing PDOs 0x290, 0x181,
# 0x281 within 120.0 ms" once); no contract test times a read, a good reply ends the wait
CANOPEN_READ_TIMEOUT_S = 0.5
CANOPEN_SETTLE_S = 0.02  # ~10 SYNC cycles: what the image holds is on the bus
CONTRACT_MODBUS_TIMEOUT_S = 5.0


@dataclass
class DriverHarness:
    driver: Driver  # constructed, not opened
    image: ProcessImage  # the PLC side the driver reads from and writes to
    stop: Callable[[], None]  # take the PLC side away (I/O must then fail)
    propagate: Callable[[], None] = field(default=lambda: None)


HarnessFactory = Callable[[], contextlib.AbstractContextManager[DriverHarness]]


@contextlib.contextmanager
def modbus_tcp_harness() -> Iterator[DriverHarness]:
    with plc_server(filled_image()) as (server, image, cfg):
        # the contract is about behaviour, not latency: a reply may wait out a stall of the
        # shared CI machine (a 1-s timeout once failed a reopen there); a stopped server
        # still fails at once (connection refused or reset), so no test waits this long
        mb = dataclasses.replace(cfg.bus.modbus_tcp, timeout_s=CONTRACT_MODBUS_TIMEOUT_S)
        cfg = dataclasses.replace(cfg, bus=dataclasses.replace(cfg.bus, modbus_tcp=mb))
        yield DriverHarness(make_driver(cfg, "modbus_tcp"), image, stop=server.stop)


@contextlib.contextmanager
def canopen_harness() -> Iterator[DriverHarness]:
    """The soft PLC's CANopen nodes in real time on a private python-can virtual channel."""
    cfg = canopen_config()
    can_cfg = dataclasses.replace(cfg.bus.canopen, sync_period_s=CANOPEN_SYNC_PERIOD_S)
    cfg = dataclasses.replace(cfg, bus=dataclasses.replace(cfg.bus, canopen=can_cfg))
    image = filled_image(cfg.cables)
    plc = CanopenPlc(cfg, image, virtual_bus_factory(can_cfg.channel))
    plc.start(realtime=True)
    try:
        driver = CanopenDriver(cfg, timeout_s=CANOPEN_READ_TIMEOUT_S)
        yield DriverHarness(
            driver, image, stop=plc.stop, propagate=lambda: time.sleep(CANOPEN_SETTLE_S)
        )
    finally:
        plc.stop()


@contextlib.contextmanager
def virtual_harness() -> Iterator[DriverHarness]:
    """The in-process driver over an injected image; the test is the PLC."""
    cfg = load_config()
    image = filled_image(cfg.cables)
    driver = VirtualDriver(cfg, image=image, advance_heartbeat=False)
    yield DriverHarness(driver, image, stop=driver.disconnect)


HARNESSES: dict[str, HarnessFactory] = {
    "modbus_tcp": modbus_tcp_harness,
    "canopen": canopen_harness,
    "virtual": virtual_harness,
}
