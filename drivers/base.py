"""Fieldbus driver base (the house style: python-can's ``BusABC``, ros2_control's hardware
interface).

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

The contract a loop relies on is declared here, with defaults, and nowhere else:

* pacing: :attr:`Driver.paced_by_bus` (False: the loop keeps its own deadlines; True: the
  bus sets the pace, e.g. the CANopen SYNC, and :meth:`read_into` waits for it);
* sync timing: :attr:`Driver.syncs` (SYNC frames seen) and
  :attr:`Driver.last_sync_timestamp` (``time.time()`` base) of the set last returned;
* counts: :attr:`Driver.reconnects` (connections re-established after one was up),
  :attr:`Driver.reconnect_attempts`, :attr:`Driver.dropped_replies` (foreign, late or
  malformed replies read and thrown away);
* reconnect backoff: one :class:`Backoff` per driver, owned here. Every connection
  attempt (successful or not) schedules the next one ``interval`` later and doubles the
  interval up to ``reconnect_max_s``; only a good data reply (:meth:`read_into` /
  :meth:`exchange` returning normally) resets it. An exception reply, a malformed reply,
  a connection accepted and dropped do not: a PLC in trouble is retried at a growing
  interval, never in a storm. The loop asks :meth:`poll_connect` each cycle and never
  touches the backoff;
* connecting never blocks a cycle for more than the budget the loop gives
  :meth:`poll_connect` (non-blocking drivers implement ``_open_begin``/``_open_advance``);
* one cycle's transfer as one explicit :meth:`exchange` (``outputs`` written and
  ``inputs`` read in one transaction where the bus can: Modbus function 23, see
  :attr:`Driver.combines_write_and_read`); :meth:`write_from` always sends at once;
* every frame passes the output gate (:class:`drivers.gate.Gate`) in
  :meth:`exchange` and :meth:`write_from`, at :attr:`Driver.clock`'s time of sending, just
  before the hook encodes it: a value the PLC may use is finite, fits its register, was
  computed from data no older than ``loop.max_input_age_s`` while the PLC heartbeat
  watchdog was armed; anything else goes out invalid (counted in :attr:`Driver.gated`);
* the time of the data: :attr:`Inputs.read_time_s` is the driver clock when the data was
  requested (or, on a paced bus, when its SYNC came): an upper bound of its age. The loop
  sets :attr:`Driver.clock` to its own clock.

Only this class changes :attr:`Driver.state`.
"""

from __future__ import annotations

import enum
import importlib
import math
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from drivers import gate
from gateway.core.ring import Ring
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


class Lifecycle(enum.IntEnum):
    """The one lifecycle of the gateway (driver and loop); the value is the wire code the
    PLC sees in the gateway state register (125 by default) and the metric
    ``cdpr_gateway_state``.

    ``STOPPED`` (0): not running, closed or ended (alias ``UNCONFIGURED``: a driver not
    yet opened); ``CONNECTED`` (1): open and reading, nothing written yet (alias
    ``CONNECTING``); ``ACTIVE`` (2): writing corrected tensions; ``FAULT`` (3): bus down
    or the PLC heartbeat frozen.
    """

    STOPPED = 0
    CONNECTED = 1
    ACTIVE = 2
    FAULT = 3
    UNCONFIGURED = 0
    CONNECTING = 1


# Former names of the one enum, kept so that code written against them keeps working.
GatewayState = Lifecycle
DriverState = Lifecycle


@dataclass
class Inputs:
    """One cycle's data from the PLC, allocated once. Arrays (m,) unless noted."""

    tension_raw_n: np.ndarray  # scaled sensor readings, N (NaN where unreadable)
    velocity_m_s: np.ndarray  # setpoint cable velocities
    length_m: np.ndarray  # setpoint cable lengths
    pose: np.ndarray  # (6,) x, y, z m; rx, ry, rz rad
    plc_heartbeat: int | float = 0  # float when its register is float32 (NaN: no value)
    read_time_s: float = 0.0  # driver clock when the data was requested (its age's bound)
    platform_mass_kg: float = float("nan")  # when the register map has platform_mass

    @staticmethod
    def allocate(cables: int) -> Inputs:
        return Inputs(
            tension_raw_n=np.zeros(cables),
            velocity_m_s=np.zeros(cables),
            length_m=np.zeros(cables),
            pose=np.zeros(6),
        )


@dataclass
class Outputs:
    """One cycle's data to the PLC, allocated once."""

    tension_corrected_n: np.ndarray  # (m,)
    channel_status: np.ndarray  # (m,) uint16, ChannelStatus values
    wrench: np.ndarray  # (6,) N, N m
    gateway_heartbeat: int = 0
    gateway_state: int = int(Lifecycle.CONNECTED)
    data_at: float = math.nan  # read_time_s of the inputs the frame was computed from
    heartbeat_at: float = -math.inf  # when the PLC heartbeat last changed (-inf: never seen)

    def stamp(self, data_at: float, heartbeat_at: float) -> Outputs:
        """Say when the frame's data was requested and when the PLC heartbeat last
        changed (driver clock): the output gate sends nothing good without both."""
        self.data_at, self.heartbeat_at = float(data_at), float(heartbeat_at)
        return self

    @staticmethod
    def allocate(cables: int) -> Outputs:
        return Outputs(
            tension_corrected_n=np.zeros(cables),
            channel_status=np.full(cables, int(ChannelStatus.INVALID), dtype=np.uint16),
            wrench=np.zeros(6),
        )


@dataclass
class Backoff:
    """Spacing of connection attempts: ``min_s`` doubling up to ``max_s``.

    :meth:`attempt` records an attempt at ``now`` (the next one is allowed one interval
    later, and the interval doubles); :meth:`reset` (a good data reply) makes the next
    attempt immediate with the shortest interval.
    """

    min_s: float = 0.05
    max_s: float = 2.0
    interval_s: float = field(init=False)
    next_at: float = field(init=False, default=-math.inf)

    def __post_init__(self) -> None:
        self.interval_s = self.min_s

    def ready(self, now: float) -> bool:
        return now >= self.next_at

    def attempt(self, now: float) -> float:
        """Record an attempt; return the wait until the next one may start."""
        wait = self.interval_s
        self.next_at = now + wait
        self.interval_s = min(2.0 * self.interval_s, self.max_s)
        return wait

    def reset(self) -> None:
        self.interval_s = self.min_s
        self.next_at = -math.inf


ROUNDTRIP_HISTORY = 4096


class Driver(ABC):
    """Base of every fieldbus driver. Subclasses implement the protected hooks."""

    name = "abstract"
    #: False: the loop keeps its own deadlines; True: :meth:`read_into` waits for the
    #: bus's cycle (CANopen SYNC), so the loop reads without sleeping first.
    paced_by_bus: ClassVar[bool] = False
    #: The budget (s) :meth:`open` gives each ``_open_advance`` call while it blocks.
    OPEN_POLL_S: ClassVar[float] = 0.05
    #: What :attr:`gated` counts, by index (``cdpr_gateway_gated_total{reason}``).
    GATE_REASONS: ClassVar[tuple[str, ...]] = gate.REASONS

    def __init__(self, config: Any) -> None:
        self.config = config
        self.cables: int = config.cables
        self.state = DriverState.UNCONFIGURED
        self.roundtrip_s = Ring(ROUNDTRIP_HISTORY)  # transaction durations (s)
        self.backoff = Backoff()
        self.reconnects = 0  # connections re-established after one was up
        self.reconnect_attempts = 0  # connection attempts, first one included
        self.dropped_replies = 0  # replies read and thrown away (foreign, late, malformed)
        self.syncs = 0  # bus SYNCs seen (paced drivers)
        self.last_sync_timestamp = 0.0  # time.time() base, SYNC of the set last returned
        self._closed = False
        self._connecting = False
        self._ever_connected = False
        self.clock = time.monotonic  # the loop replaces it with its own clock
        self.plc_heartbeat_modulus = 1 << 16  # the PLC heartbeat's wrap (0: a float)
        self._gate: gate.Gate | None = None

    def write_blocked(self) -> str:
        """Why the bus does not take a frame now ("" when it does), e.g. a CANopen node
        an NMT master stopped: the loop then writes nothing and reports CONNECTED."""
        return ""

    def output_bands(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """(corrected tension, wrench) values the written registers can carry."""
        f32 = float(np.finfo(np.float32).max)
        return (-f32, f32), (-f32, f32)

    @property
    def output_gate(self) -> gate.Gate:
        """The output gate of this driver's frames (built once, on first use)."""
        if self._gate is None:
            lp = self.config.loop
            tension, wrench = self.output_bands()
            limits = gate.limits(tension, wrench, lp.input_age_limit_s, lp.heartbeat_timeout_s)
            self._gate = gate.Gate(limits, self.cables)
        return self._gate

    @property
    def gated(self) -> np.ndarray:
        """Values the gate wrote invalid, by reason (:attr:`GATE_REASONS`)."""
        return self.output_gate.counts

    def _gate_frame(self, outputs: Outputs) -> int:
        """The output gate at this moment (module doc of :mod:`drivers.gate`); the number
        of values it stopped. A driver may call it again right before sending."""
        o = outputs
        return self.output_gate(
            self.clock(),
            o.data_at,
            o.heartbeat_at,
            o.tension_corrected_n,
            o.channel_status,
            o.wrench,
        )

    @property
    def combines_write_and_read(self) -> bool:
        """True when :meth:`exchange` writes and reads in ONE transaction (the loop then
        hands a cycle's outputs to the next cycle's exchange instead of writing them)."""
        return False

    # --- connecting ---------------------------------------------------------------------
    def open(self) -> None:
        """Connect now (blocking, not held back by the backoff); raise
        :class:`DriverInitError` (chained, with the cause) when the PLC cannot be reached."""
        self._begin_attempt(time.monotonic())
        done = self._guard_open(self._open_begin)
        while not done:
            done = self._guard_open(lambda: self._open_advance(self.OPEN_POLL_S))
        self._opened()

    def ready_to_connect(self, now: float | None = None) -> bool:
        """True when an attempt is in progress or the backoff allows a new one."""
        now = time.monotonic() if now is None else now
        return self._connecting or self.backoff.ready(now)

    def poll_connect(self, now: float | None = None, budget_s: float = 0.0) -> bool:
        """Advance the connection by at most ``budget_s``; True once connected.

        Starts an attempt when none is in progress and the backoff allows one (else
        returns False at once); a failed attempt raises :class:`DriverInitError` with
        the cause, and the next one waits for the (grown) backoff interval.
        """
        if self.connected and not self._connecting:
            return True
        now = time.monotonic() if now is None else now
        if not self._connecting:
            if not self.backoff.ready(now):
                return False
            self._begin_attempt(now)
            if self._guard_open(self._open_begin):
                self._opened()
                return True
        if self._guard_open(lambda: self._open_advance(budget_s)):
            self._opened()
            return True
        return False

    def _begin_attempt(self, now: float) -> None:
        self.backoff.attempt(now)
        self.reconnect_attempts += 1
        self._connecting = True
        self._closed = False

    def _guard_open(self, step: Any) -> bool:
        try:
            return bool(step())
        except DriverError:
            self._connecting = False
            self.state = DriverState.FAULT
            raise
        except Exception as exc:  # other libraries' errors become ours, chained
            self._connecting = False
            self.state = DriverState.FAULT
            raise DriverInitError(f"{self.name}: cannot open: {exc}") from exc

    def _opened(self) -> None:
        self.output_gate  # noqa: B018 - built (compiled) now, not on the first frame
        self._connecting = False
        if self._ever_connected:
            self.reconnects += 1
        self._ever_connected = True
        self.state = DriverState.CONNECTED
        self._closed = False

    # --- transfers ----------------------------------------------------------------------
    def read_into(self, inputs: Inputs) -> None:
        """Fill ``inputs`` from the PLC. Raises DriverIOError / DriverTimeoutError."""
        self.exchange(None, inputs)

    def exchange(self, outputs: Outputs | None, inputs: Inputs) -> None:
        """One cycle's transfer: write ``outputs`` (None: nothing to write) and read
        ``inputs``, in one transaction where the bus can (Modbus function 23), else write
        then read. A normal return is a good data reply: the reconnect backoff resets."""
        if outputs is not None:
            self._gate_frame(outputs)
        inputs.read_time_s = self.clock()  # a driver that knows better overwrites it
        start = time.perf_counter()
        try:
            self._exchange(outputs, inputs)
        except DriverError:
            self.state = DriverState.FAULT
            raise
        self.roundtrip_s.add(time.perf_counter() - start)
        self.backoff.reset()
        if outputs is not None:
            self.state = DriverState.ACTIVE
        elif self.state is not DriverState.ACTIVE:
            self.state = DriverState.CONNECTED

    def write_from(self, outputs: Outputs) -> None:
        """Send ``outputs`` now (through the output gate)."""
        self._gate_frame(outputs)
        try:
            self._write(outputs)
        except DriverError:
            self.state = DriverState.FAULT
            raise
        self.state = DriverState.ACTIVE

    def close(self) -> None:
        """Disconnect (or abandon an attempt in progress); safe to call more than once."""
        if self._closed and not self._connecting:
            return
        self._closed = True
        self._connecting = False
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
    def _open(self) -> None:
        """Connect, blocking briefly (drivers without a non-blocking connect)."""
        raise NotImplementedError

    def _open_begin(self) -> bool:
        """Start connecting; True when connected already (default: :meth:`_open`)."""
        self._open()
        return True

    def _open_advance(self, budget_s: float) -> bool:
        """Advance an attempt for at most ``budget_s``; True once connected."""
        return True

    def _exchange(self, outputs: Outputs | None, inputs: Inputs) -> None:
        if outputs is not None:
            self._write(outputs)
        self._read(inputs)

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
