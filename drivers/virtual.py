"""In-process driver over a PLC process image (ros2_control's mock hardware).

Registered as ``virtual``. It reads and writes an injected process image directly (any
object with the fields of :class:`PlcImage`: the soft PLC's ``sim_plc.image.ProcessImage``
is one, injected by the demo and the tests; this package never imports the soft PLC; by
default a :class:`VirtualImage` of its own). The raw channels are decoded by the one S7
codec (:class:`drivers.s7.S7Analog`, the same reading as every other driver: overflow,
underflow and counts outside the S7 window are NaN), the setpoints, pose and heartbeat
copied (the plant's truth stays in the image: the gateway never sees it). What the
gateway writes lands in the image's gateway fields, and ``image.gateway_writes`` counts
accepted writes.

Modes:

* free: nothing moves the image but the test; the PLC heartbeat is advanced by one per
  read (``advance_heartbeat``, default when no ``step`` is given) so the gateway's
  watchdog sees a live PLC;
* stepped: ``step()`` is called before every read (e.g. one plant period), so a loop
  driven by a fake clock sees a plant that advances exactly one period per cycle.

Faults are parameters (:class:`VirtualFaults`), counted in reads (1-based): fail or time
out on the Nth read (for ``count`` reads), drop the connection on the Nth read (every read
fails until the driver is reopened), refuse ``fail_opens`` opens, freeze the
heartbeat from a read on (until a read), NaN / stuck / saturated channels from a read on.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from drivers.base import ChannelStatus, Driver, Inputs, Outputs
from drivers.s7 import S7_OVERFLOW, S7Analog
from gateway.errors import DriverInitError, DriverIOError, DriverTimeoutError


class PlcImage(Protocol):
    """What the virtual driver reads and writes (``sim_plc.image.ProcessImage`` fits)."""

    lock: Any
    raw_counts: np.ndarray  # (m,) int16 S7 counts
    velocity_m_s: np.ndarray
    length_m: np.ndarray
    pose: np.ndarray
    plc_heartbeat: int
    corrected_n: np.ndarray
    channel_status: np.ndarray
    wrench: np.ndarray
    gateway_heartbeat: int
    gateway_state: int
    gateway_writes: int


@dataclass
class VirtualImage:
    """The virtual driver's own process image when none is injected (all zero, PLC
    heartbeat advanced by the driver)."""

    cables: int
    raw_counts: np.ndarray = field(init=False)
    velocity_m_s: np.ndarray = field(init=False)
    length_m: np.ndarray = field(init=False)
    pose: np.ndarray = field(init=False)
    corrected_n: np.ndarray = field(init=False)
    channel_status: np.ndarray = field(init=False)
    wrench: np.ndarray = field(init=False)
    plc_heartbeat: int = 0
    gateway_heartbeat: int = 0
    gateway_state: int = 0
    gateway_writes: int = 0
    lock: Any = field(default_factory=threading.Lock, repr=False)

    def __post_init__(self) -> None:
        m = self.cables
        self.raw_counts = np.zeros(m, dtype=np.int16)
        self.velocity_m_s, self.length_m = np.zeros(m), np.zeros(m)
        self.corrected_n = np.zeros(m)
        self.channel_status = np.full(m, int(ChannelStatus.INVALID), dtype=np.uint16)
        self.pose, self.wrench = np.zeros(6), np.zeros(6)


@dataclass
class VirtualFaults:
    """Fault injection, in 1-based read numbers. ``None`` disables a fault."""

    fail_on_read: int | None = None  # DriverIOError from this read on ...
    fail_count: int = 1  # ... for this many reads
    timeout_on_read: int | None = None  # DriverTimeoutError from this read on ...
    timeout_count: int = 1  # ... for this many reads
    fail_opens: int = 0  # the first N opens raise DriverInitError
    drop_on_read: int | None = None  # the connection drops: this and every read fail until reopened
    freeze_heartbeat_from: int | None = None  # PLC heartbeat stops changing ...
    freeze_heartbeat_until: int | None = None  # ... until this read (exclusive)
    nan_channel: int | None = None  # 0-based channel that reads NaN ...
    nan_from: int = 1  # ... from this read on
    stuck_channel: int | None = None  # channel frozen at its value ...
    stuck_from: int = 1
    saturated_channel: int | None = None  # channel at the S7 overflow code ...
    saturated_from: int = 1


class VirtualDriver(Driver):
    """Reads and writes a :class:`ProcessImage` in process; faults by parameter."""

    name = "virtual"

    def __init__(
        self,
        config: Any,
        image: PlcImage | None = None,
        step: Callable[[], None] | None = None,
        faults: VirtualFaults | None = None,
        advance_heartbeat: bool | None = None,
        on_read: Callable[[int], None] | None = None,
    ) -> None:
        super().__init__(config)
        self.image: PlcImage = image if image is not None else VirtualImage(config.cables)
        self.step = step
        self.faults = faults or VirtualFaults()
        self.advance_heartbeat = step is None if advance_heartbeat is None else advance_heartbeat
        self.on_read = on_read  # test hook, called with the read number before reading
        self.reads = 0
        self.opens = 0
        self.dropped = False
        self.analog = S7Analog.from_sensor(config.sensor)
        self._frozen_heartbeat = 0
        self._stuck_value = float("nan")

    # --- hooks ------------------------------------------------------------------------
    def _open(self) -> None:
        self.opens += 1
        if self.opens <= self.faults.fail_opens:
            raise DriverInitError(f"virtual: open {self.opens} refused (fault injection)")
        self.dropped = False

    def _close(self) -> None:
        pass

    def disconnect(self) -> None:
        """The far side goes away: every read and write fails until the driver is reopened."""
        self.dropped = True

    def _read(self, inputs: Inputs) -> None:
        self.reads += 1
        n = self.reads
        if self.on_read is not None:
            self.on_read(n)
        f = self.faults
        if n == f.drop_on_read:
            self.dropped = True
        if self.dropped:
            raise DriverIOError(f"virtual: read {n}: connection dropped (fault injection)")
        if _within(n, f.fail_on_read, f.fail_count):
            raise DriverIOError(f"virtual: read {n} failed (fault injection)")
        if _within(n, f.timeout_on_read, f.timeout_count):
            raise DriverTimeoutError(f"virtual: read {n} timed out (fault injection)")
        if self.step is not None:
            self.step()
        img = self.image
        with img.lock:
            if self.advance_heartbeat:
                img.plc_heartbeat = (img.plc_heartbeat + 1) & 0xFFFF
            self.analog.decode(img.raw_counts, out=inputs.tension_raw_n)
            inputs.velocity_m_s[:] = img.velocity_m_s
            inputs.length_m[:] = img.length_m
            inputs.pose[:] = img.pose
            heartbeat = img.plc_heartbeat
        inputs.plc_heartbeat = self._heartbeat(n, heartbeat)
        self._apply_channel_faults(n, inputs.tension_raw_n)

    def _heartbeat(self, n: int, heartbeat: int) -> int:
        f = self.faults
        if f.freeze_heartbeat_from is None or n < f.freeze_heartbeat_from:
            self._frozen_heartbeat = heartbeat
            return heartbeat
        if f.freeze_heartbeat_until is not None and n >= f.freeze_heartbeat_until:
            return heartbeat
        return self._frozen_heartbeat

    def _apply_channel_faults(self, n: int, tension: np.ndarray) -> None:
        f = self.faults
        if f.nan_channel is not None and n >= f.nan_from:
            tension[f.nan_channel] = np.nan
        if f.stuck_channel is not None and n >= f.stuck_from:
            if n == f.stuck_from:
                self._stuck_value = float(tension[f.stuck_channel])
            tension[f.stuck_channel] = self._stuck_value
        if f.saturated_channel is not None and n >= f.saturated_from:
            tension[f.saturated_channel] = self.analog.decode_count(S7_OVERFLOW)  # NaN

    def _write(self, outputs: Outputs) -> None:
        if self.dropped:
            raise DriverIOError("virtual: write: connection dropped")
        img = self.image
        with img.lock:
            img.corrected_n[:] = outputs.tension_corrected_n
            img.channel_status[:] = outputs.channel_status
            img.wrench[:] = outputs.wrench
            img.gateway_heartbeat = outputs.gateway_heartbeat & 0xFFFF
            img.gateway_state = outputs.gateway_state
            img.gateway_writes += 1


def _within(n: int, start: int | None, count: int) -> bool:
    return start is not None and start <= n < start + count
