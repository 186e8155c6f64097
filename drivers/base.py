"""Fieldbus driver base (style.md: python-can's ``BusABC``, ros2_control's hardware interface).

A driver moves one cycle's data between the PLC and two preallocated buffers:

* :class:`Inputs` (read from the PLC): scaled force channels in N, setpoint cable
  velocities and lengths, pose setpoint, the PLC heartbeat;
* :class:`Outputs` (written to the PLC): corrected tensions, channel status, gateway
  heartbeat and state, estimated platform wrench.

Public methods wrap protected hooks (``_open``, ``_read``, ``_write``, ``_close``), time
every transaction into :attr:`Driver.roundtrip_s` (a ring buffer read at scrape time) and
keep the state machine ``unconfigured -> connected -> active -> fault``. Errors are
:class:`DriverError` subclasses, other libraries' errors chained with ``from``; only the
loop catches them. ``close()`` is safe to call twice; a driver is a context manager.

A driver that can write and read in one transaction (Modbus function 23) may defer the
write of :meth:`write_from` to the next :meth:`read_into`; :meth:`flush` forces it out.
"""

from __future__ import annotations

import enum
import importlib
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gateway.errors import DriverError, DriverInitError

DRIVERS: dict[str, str] = {
    "modbus_tcp": "drivers.modbus_tcp:ModbusTcpDriver",
    "canopen": "drivers.canopen:CanopenDriver",
    "virtual": "drivers.virtual:VirtualDriver",
}


class ChannelStatus(enum.IntEnum):
    GOOD = 0
    SUBSTITUTED = 1
    INVALID = 2


class GatewayState(enum.IntEnum):
    """Written to the PLC (register 125 by default)."""

    STOPPED = 0
    CONNECTING = 1
    ACTIVE = 2
    FAULT = 3


class DriverState(enum.Enum):
    UNCONFIGURED = "unconfigured"
    CONNECTED = "connected"  # reading
    ACTIVE = "active"  # writing
    FAULT = "fault"


@dataclass
class Inputs:
    """One cycle's data from the PLC, allocated once. Arrays (m,) unless noted."""

    tension_raw_n: np.ndarray  # scaled sensor readings, N (NaN where unreadable)
    velocity_m_s: np.ndarray  # setpoint cable velocities
    length_m: np.ndarray  # setpoint cable lengths
    pose: np.ndarray  # (6,) x, y, z m; rx, ry, rz rad
    plc_heartbeat: int = 0
    read_time_s: float = 0.0  # time.monotonic() when the reply arrived
    true_tension_n: np.ndarray | None = None  # soft PLC only (registers 200-215)
    platform_mass_kg: float = float("nan")  # when the register map has platform_mass

    @staticmethod
    def allocate(cables: int, with_truth: bool = False) -> Inputs:
        return Inputs(
            tension_raw_n=np.zeros(cables),
            velocity_m_s=np.zeros(cables),
            length_m=np.zeros(cables),
            pose=np.zeros(6),
            true_tension_n=np.zeros(cables) if with_truth else None,
        )


@dataclass
class Outputs:
    """One cycle's data to the PLC, allocated once."""

    tension_corrected_n: np.ndarray  # (m,)
    channel_status: np.ndarray  # (m,) uint16, ChannelStatus values
    wrench: np.ndarray  # (6,) N, N m
    gateway_heartbeat: int = 0
    gateway_state: int = int(GatewayState.CONNECTING)

    @staticmethod
    def allocate(cables: int) -> Outputs:
        return Outputs(
            tension_corrected_n=np.zeros(cables),
            channel_status=np.full(cables, int(ChannelStatus.INVALID), dtype=np.uint16),
            wrench=np.zeros(6),
        )


@dataclass
class RoundtripRing:
    """Last ``size`` transaction durations (s); written in the cycle, read at scrape time."""

    size: int = 4096
    values: np.ndarray = field(init=False)
    count: int = 0

    def __post_init__(self) -> None:
        self.values = np.zeros(self.size)

    def add(self, seconds: float) -> None:
        self.values[self.count % self.size] = seconds
        self.count += 1

    def recent(self) -> np.ndarray:
        return self.values[: min(self.count, self.size)]


class Driver(ABC):
    """Base of every fieldbus driver. Subclasses implement the protected hooks."""

    name = "abstract"

    def __init__(self, config: Any) -> None:
        self.config = config
        self.cables: int = config.cables
        self.state = DriverState.UNCONFIGURED
        self.roundtrip_s = RoundtripRing()
        self.reconnects = 0
        self._closed = False

    # --- public API -------------------------------------------------------------------
    def open(self) -> None:
        """Connect; raise :class:`DriverInitError` (chained) when the PLC cannot be reached."""
        try:
            self._open()
        except DriverError:
            self.state = DriverState.FAULT
            raise
        except Exception as exc:  # other libraries' errors become ours, chained
            self.state = DriverState.FAULT
            raise DriverInitError(f"{self.name}: cannot open: {exc}") from exc
        self.state = DriverState.CONNECTED
        self._closed = False

    def read_into(self, inputs: Inputs) -> None:
        """Fill ``inputs`` from the PLC (and send a deferred write). Raises DriverIOError."""
        start = time.perf_counter()
        try:
            self._read(inputs)
        except DriverError:
            self.state = DriverState.FAULT
            raise
        self.roundtrip_s.add(time.perf_counter() - start)
        inputs.read_time_s = time.monotonic()

    def write_from(self, outputs: Outputs) -> None:
        """Send ``outputs`` (now, or with the next read when the bus combines them)."""
        try:
            self._write(outputs)
        except DriverError:
            self.state = DriverState.FAULT
            raise
        self.state = DriverState.ACTIVE

    def flush(self) -> None:  # noqa: B027 - a hook with a do-nothing default on purpose
        """Send a deferred write now (default: writes are never deferred)."""

    def close(self) -> None:
        """Disconnect; safe to call more than once."""
        if self._closed:
            return
        self._closed = True
        try:
            self._close()
        finally:
            self.state = DriverState.UNCONFIGURED

    @property
    def connected(self) -> bool:
        return self.state in (DriverState.CONNECTED, DriverState.ACTIVE)

    def __enter__(self) -> Driver:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- hooks ------------------------------------------------------------------------
    @abstractmethod
    def _open(self) -> None: ...

    @abstractmethod
    def _read(self, inputs: Inputs) -> None: ...

    @abstractmethod
    def _write(self, outputs: Outputs) -> None: ...

    @abstractmethod
    def _close(self) -> None: ...


def driver_class(name: str) -> type[Driver]:
    """Look a driver up by name and import only that one."""
    try:
        target = DRIVERS[name]
    except KeyError:
        known = ", ".join(sorted(DRIVERS))
        raise DriverInitError(f"unknown driver {name!r} (known: {known})") from None
    module_name, cls_name = target.split(":")
    cls: type[Driver] = getattr(importlib.import_module(module_name), cls_name)
    return cls


def make_driver(config: Any, name: str | None = None) -> Driver:
    """The driver named in ``config.bus.driver`` (or ``name``), constructed, not opened."""
    return driver_class(name or config.bus.driver)(config)
