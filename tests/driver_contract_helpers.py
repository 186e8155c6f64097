"""Driver harnesses for the contract suite (tests/test_driver_contract.py).

Every driver joins the suite with ONE entry in :data:`HARNESSES`: a name and a factory,
a context manager that starts whatever the driver talks to (soft PLC server, virtual CAN
bus nodes, ...) around a :class:`sim_plc.image.ProcessImage` and yields a
:class:`DriverHarness`. Example for another driver::

    @contextlib.contextmanager
    def canopen_harness() -> Iterator[DriverHarness]:
        image = ProcessImage(8)
        with start_canopen_plc(cfg, image) as plc:          # the driver's far side
            yield DriverHarness(make_driver(cfg, "canopen"), image, stop=plc.stop,
                                propagate=lambda: plc.sync(3))

    HARNESSES["canopen"] = canopen_harness

The harness' driver is constructed, not opened. ``propagate()`` is called after the test
changed the image and before it reads, and after a write (and ``flush()``) before it
checks the image: use it to run SYNC cycles or wait for PDOs. ``stop()`` takes the far
side away so that further I/O must fail with a DriverError.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

from drivers.base import Driver, make_driver
from sim_plc.image import ProcessImage
from tests.modbus_helpers import filled_image, plc_server


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
        yield DriverHarness(make_driver(cfg, "modbus_tcp"), image, stop=server.stop)


HARNESSES: dict[str, HarnessFactory] = {
    "modbus_tcp": modbus_tcp_harness,
}
