"""In-process driver over a :class:`sim_plc.image.ProcessImage` (ros2_control's mock hardware).

Registered as ``virtual``. It reads and writes the process image directly: the raw
channels are scaled from the S7 analog format (``0..adc_full_scale = 0..range_n``), the
setpoints, pose and heartbeat copied (the plant's truth stays in the image: the gateway
never sees it). What the gateway writes lands in the image's
gateway fields, and ``image.gateway_writes`` counts accepted writes.

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

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivers.base import Driver, Inputs, Outputs
from gateway.errors import DriverInitError, DriverIOError, DriverTimeoutError
from sim_plc.image import ProcessImage

S7_OVERFLOW = 32767  # S7 analog overflow code


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
        image: ProcessImage | None = None,
        step: Callable[[], None] | None = None,
        faults: VirtualFaults | None = None,
        advance_heartbeat: bool | None = None,
        on_read: Callable[[int], None] | None = None,
    ) -> None:
        super().__init__(config)
        self.image = image if image is not None else ProcessImage(config.cables)
        self.step = step
        self.faults = faults or VirtualFaults()
        self.advance_heartbeat = step is None if advance_heartbeat is None else advance_heartbeat
        self.on_read = on_read  # test hook, called with the read number before reading
        self.reads = 0
        self.opens = 0
        self.dropped = False
        self._scale = config.sensor.range_n / config.sensor.adc_full_scale
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
            np.multiply(img.raw_counts, self._scale, out=inputs.tension_raw_n)
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
            tension[f.saturated_channel] = S7_OVERFLOW * self._scale

    def _write(self, outputs: Outputs) -> None:
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
