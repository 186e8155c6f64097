"""CANopen driver: the gateway as a CANopen node (python-can for frames, canopen for the EDS).

Nodes and PDOs (the EDS files in ``config/`` are the source of truth; COB-IDs below for the
defaults gateway node 0x20, analog node 0x10, PLC master node 0x01)::

    COB-ID  producer -> consumer   content (each int16 unless noted)        when
    0x080   PLC      -> all        SYNC, no data                            every 1 ms
    0x190   analog   -> gw, PLC    6401h.1-4 raw channels 1-4 (S7 counts)   after each SYNC (type 1)
    0x290   analog   -> gw, PLC    6401h.5-8 raw channels 5-8               after each SYNC (type 1)
    0x181   PLC      -> gw         2001h.1-4 setpoint velocity 1-4          every cycle
    0x281   PLC      -> gw         2001h.5-8 setpoint velocity 5-8          every cycle
    0x381   PLC      -> gw         2004h PLC heartbeat u16, 2003h.1-3 x,y,z cycles k%10 == 0
    0x481   PLC      -> gw         2003h.4-6 rx, ry, rz (6 bytes)           cycles k%10 == 1
    0x1C1   PLC      -> gw         2002h.1-4 setpoint length 1-4 (u16)      cycles k%10 == 2
    0x2C1   PLC      -> gw         2002h.5-8 setpoint length 5-8 (u16)      cycles k%10 == 3
    0x1A0   gw       -> PLC        2100h.1-4 corrected tension 1-4          each write (type 254)
    0x2A0   gw       -> PLC        2100h.5-8 corrected tension 5-8          each write
    0x3A0   gw       -> PLC        2101h status word u16, 2102h gateway     each write
                                   heartbeat u16, 2103h gateway state u8

0x1C1/0x2C1 are outside the predefined connection set (they are TPDO1/2 of node 0x41,
which must not exist on this bus). The driver re-targets RPDO1/2 to 0x180/0x280 +
``analog_node_id`` and TPDO1-3 follow ``gateway_node_id`` ($NODEID in the EDS).

Scaling (module constants; resolution = one count, the quantisation error is half of it):

* raw force: S7 analog counts as the module delivers them, decoded by the one S7 codec
  (:class:`drivers.s7.S7Analog`): 0..27648 = 0..sensor range (500 N: 0.0181 N/count),
  over/underrange included; the overflow/underflow codes and counts outside the S7
  window give NaN.
* velocity: 2e-5 m/s per count, range +-0.655 m/s (clamped). The Dahl state integrates
  v*dt; a 1e-5 m/s error over 1 ms moves it by 1e-8 m, i.e. 5e-6 N at sigma = 500 N/m.
* length: 1e-4 m per count, u16, 0..6.5535 m. Pose: 1e-4 m and 1e-4 rad per count,
  +-3.2767 m / rad.
* corrected tension: 0.02 N per count, +-655.32 N (clamped); 0x7FFF = no value (NaN).
  Resolution 0.02 N is below the sensor's own ADC step (0.018 N) plus its noise.
* status word: 2 bits per channel, channel i (0-based) in bits 2i..2i+1 (0 good,
  1 substituted, 2 invalid).

Bus load at 1 Mbit/s (1000 bit times per 1 ms cycle). A classic data frame with n data
bytes takes 47 + 8n bit times including the 3-bit interframe space, plus up to
floor((34 + 8n - 1) / 4) stuff bits: SYNC 47..55, 8-byte PDO 111..135, 5-byte PDO 87..105.
Every cycle: SYNC + 6 eight-byte PDOs (analog x2, velocity x2, corrected tension x2) +
the 5-byte status PDO = 8 frames = 800 bit times nominal (80 %), 970 worst-case stuffing
(97 %). In 4 of every 10 cycles one slow PLC PDO (6..8 bytes) is added: 911 nominal
(91 %), 1105 worst case: the lowest-priority frame can slip into the next millisecond.
Average 84 % nominal. This is the limit of classic CAN at 1 kHz with 8 channels:
anything more per cycle (the estimated wrench, EMCY, SDO traffic) needs a 2 ms cycle,
a second CAN line, or CAN FD. float32 everywhere would need 4 frames per 8 values and
cannot fit.

The node's own heartbeat (1017h, 100 ms: one 1-byte frame per 100 cycles, ~0.06 %) fits.
NMT: boot-up at open, self-starting (operational), heartbeat producer, NMT commands and
SDO requests served in the read (see docs/canopen.md); no TPDOs while not operational.

Timing: :meth:`CanopenDriver.read_into` returns the newest complete set (SYNC followed by
all four per-cycle RPDOs) that has not been returned before, waiting up to
``timeout_s`` (default 2.5 SYNC periods) for it; otherwise :class:`DriverTimeoutError`.
The first set after open also waits (10 SYNC periods longer) until every RPDO, the slow
ones (heartbeat, pose, lengths) included, has arrived once: no zeros are handed out as a
pose or a heartbeat.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any

import can
import canopen

from drivers.base import Driver, Inputs, Outputs
from drivers.canopen_pdo import (
    ANGLE_RAD_PER_COUNT,
    LENGTH_M_PER_COUNT,
    POSITION_M_PER_COUNT,
    TENSION_MAX_N,
    TENSION_MIN_N,
    TENSION_N_PER_COUNT,
    VELOCITY_M_S_PER_COUNT,
    PdoLayout,
    encode_tension,
    import_eds,
    load_pdo_layouts,
    new_slots,
    pack_pdo,
    pack_status,
    resolve_path,
    unpack_pdo,
)
from drivers.s7 import S7Analog
from gateway.errors import ConfigError, DriverInitError, DriverIOError, DriverTimeoutError

log = logging.getLogger("cdpr_gateway.canopen")

PLC_NODE_ID = 0x01
PLC_MASTER_EDS = "plc_master.eds"
SYNC_COB_ID = 0x080
NMT_COB_ID = 0x000
NMT_START, NMT_PRE_OPERATIONAL, NMT_RESET_COMMUNICATION = 0x01, 0x80, 0x82
NMT_OPERATIONAL_STATE = 5
VIRTUAL_NOTE = (
    "bus.canopen.interface is 'virtual': python-can's virtual bus connects only buses "
    "inside ONE process; a PLC (or candump) in another process never sees this node. "
    "Use socketcan (docs/canopen.md) to talk across processes."
)

# application objects (gateway.eds, plc_master.eds)
OBJ_RAW = 0x2000
OBJ_VELOCITY = 0x2001
OBJ_LENGTH = 0x2002
OBJ_POSE = 0x2003
OBJ_PLC_HEARTBEAT = 0x2004
OBJ_CORRECTED = 0x2100
OBJ_STATUS = 0x2101
OBJ_GW_HEARTBEAT = 0x2102
OBJ_GW_STATE = 0x2103
OBJ_ANALOG_IN = 0x6401  # CiA 401 read analog input 16-bit
PER_CYCLE_OBJECTS = frozenset({OBJ_RAW, OBJ_VELOCITY})  # RPDOs required after every SYNC

SLOW_PERIOD_CYCLES = 10
READ_TIMEOUT_PERIODS = 2.5
DRAIN_LIMIT = 100_000


def open_bus(cfg: Any) -> can.BusABC:
    """A python-can bus from a ``CanopenConfig`` (interface, channel, bitrate)."""
    return can.Bus(interface=cfg.interface, channel=cfg.channel, bitrate=cfg.bitrate)


class CanopenDriver(Driver):
    """The gateway as CANopen node ``bus.canopen.gateway_node_id`` (config/gateway.eds).

    ``bus``: an existing python-can bus to use (not shut down by :meth:`close`); default
    one is created from ``config.bus.canopen`` at :meth:`open`. ``timeout_s``: how long
    a read waits for a complete SYNC set (default 2.5 SYNC periods).
    """

    name = "canopen"
    #: The bus sets the pace: read_into blocks until the next SYNC set, so a loop should
    #: call it without sleeping to its own deadline first (SYNC is the cycle clock).
    paced_by_bus = True

    def __init__(
        self, config: Any, bus: can.BusABC | None = None, timeout_s: float | None = None
    ) -> None:
        super().__init__(config)
        self.can_cfg = config.bus.canopen
        self.timeout_s = (
            timeout_s or self.can_cfg.timeout_s or READ_TIMEOUT_PERIODS * self.can_cfg.sync_period_s
        )
        self.analog = S7Analog.from_sensor(config.sensor)
        if config.sensor.range_n > TENSION_MAX_N:
            raise ConfigError(
                f"sensor.range_n: {config.sensor.range_n:g} N cannot be written over CANopen "
                f"(2100h: {TENSION_N_PER_COUNT:g} N per count, at most {TENSION_MAX_N:g} N)"
            )
        self._external_bus = bus
        self._bus: can.BusABC | None = None
        self._rx: dict[int, tuple[PdoLayout, int]] = {}  # cob_id -> (layout, required bit)
        self._tx: list[PdoLayout] = []
        self._slots: dict[int, list[int]] = {}
        self._tx_slots: dict[int, list[int]] = {}
        self._required = 0
        self._received = 0
        self._seen_bits: dict[int, int] = {}
        self._all_rpdos = 0
        self._seen = 0  # RPDOs received at least once since open (bit per RPDO)
        self._sync_seen = False
        self._sync_timestamp = 0.0
        self.sets = 0  # complete SYNC sets returned by read_into
        self.ignored_frames = 0  # error/remote frames and unknown COB-IDs
        self._network: canopen.Network | None = None
        self._node: canopen.LocalNode | None = None
        self._sdo_rx = -1

    def write_blocked(self) -> str:
        """No PDOs unless the node is operational (CiA 301): stopped or pre-operational
        by the NMT master, the gateway writes nothing and says so."""
        state = self.nmt_state if self._node is not None else "OPERATIONAL"
        if state == "OPERATIONAL":
            return ""
        return f"canopen node {self.can_cfg.gateway_node_id:#04x}: NMT state {state}"

    def output_bands(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """The corrected-tension PDO's counts (0x7FFF is "no value"); no wrench on CANopen."""
        return (TENSION_MIN_N, TENSION_MAX_N), (-math.inf, math.inf)

    # --- hooks ----------------------------------------------------------------------------
    def _open(self) -> None:
        cfg = self.can_cfg
        tpdos, rpdos = load_pdo_layouts(cfg.gateway_eds, cfg.gateway_node_id)
        analog_tpdos, _ = load_pdo_layouts(cfg.analog_eds, cfg.analog_node_id)
        for number in (1, 2):  # consume the analog module's TPDO1/2 (predefined set)
            if number not in rpdos or number not in analog_tpdos:
                raise DriverInitError(f"{cfg.gateway_eds}: RPDO{number} or analog TPDO missing")
            if rpdos[number].codec.format != analog_tpdos[number].codec.format:
                raise DriverInitError(
                    f"{cfg.gateway_eds}: RPDO{number} does not match TPDO{number} of "
                    f"{cfg.analog_eds}"
                )
            rpdos[number] = rpdos[number].retarget(analog_tpdos[number].cob_id)
        self._check_channels(rpdos)
        self._rx, self._required, self._seen_bits = {}, 0, {}
        for bit, layout in enumerate(rpdos.values()):
            required = any(i in PER_CYCLE_OBJECTS for i, _ in layout.entries)
            self._rx[layout.cob_id] = (layout, (1 << bit) if required else 0)
            self._required |= (1 << bit) if required else 0
            self._seen_bits[layout.cob_id] = 1 << bit
        self._all_rpdos = (1 << len(rpdos)) - 1
        self._seen = 0
        self._tx = list(tpdos.values())
        self._slots = new_slots(rpdos)
        self._tx_slots = new_slots(tpdos)
        self._bus = self._external_bus if self._external_bus is not None else open_bus(cfg)
        if cfg.interface == "virtual":
            log.warning(VIRTUAL_NOTE)
        self._drain()
        self._sync_seen, self._received = False, 0
        self._start_nmt()

    # --- NMT slave and heartbeat producer (CiA 301, the canopen library's LocalNode) ----
    def _start_nmt(self) -> None:
        """Boot-up message, then the 1017h heartbeat; the node starts itself (operational).

        The canopen ``Network`` sends on this driver's bus but has no notifier: this
        driver reads the bus, and hands NMT commands (COB-ID 0) and SDO requests
        (0x600 + node id) to the node in :meth:`_handle`.
        """
        cfg = self.can_cfg
        path = resolve_path(cfg.gateway_eds)
        try:
            od = import_eds(path, cfg.gateway_node_id)
        except Exception as exc:
            raise DriverInitError(f"{path}: cannot load EDS: {exc}") from exc
        network = canopen.Network()
        network.bus = self._bus
        node = canopen.LocalNode(cfg.gateway_node_id, od)
        network.add_node(node)
        self._network, self._node = network, node
        self._sdo_rx = node.sdo.rx_cobid
        self._boot()

    def _boot(self) -> None:
        assert self._node is not None
        nmt = self._node.nmt
        nmt.send_command(NMT_RESET_COMMUNICATION)  # INITIALISING: sends the boot-up frame
        nmt.send_command(NMT_PRE_OPERATIONAL)  # starts the heartbeat (1017h, ms)
        nmt.send_command(NMT_START)  # a self-starting node: PDOs flow without a master

    @property
    def nmt_state(self) -> str:
        """The node's NMT state (``OPERATIONAL``, ``STOPPED``, ``PRE-OPERATIONAL``, ...)."""
        return self._node.nmt.state if self._node is not None else "INITIALISING"

    def _on_nmt_or_sdo(self, msg: can.Message) -> None:
        assert self._network is not None and self._node is not None
        self._network.notify(msg.arbitration_id, msg.data, msg.timestamp)
        if self._node.nmt.state == "INITIALISING":  # reset node / communication
            self._boot()

    def _check_channels(self, rpdos: dict[int, PdoLayout]) -> None:
        for obj in PER_CYCLE_OBJECTS:
            count = sum(1 for lay in rpdos.values() for i, _ in lay.entries if i == obj)
            if count != self.cables:
                raise DriverInitError(
                    f"{self.can_cfg.gateway_eds}: RPDOs map {count} entries of {obj:04X}h, "
                    f"config has {self.cables} cables"
                )

    def _drain(self) -> None:
        """Drop frames queued before open (bounded)."""
        assert self._bus is not None
        for _ in range(DRAIN_LIMIT):
            if self._bus.recv(0) is None:
                return

    def _read(self, inputs: Inputs) -> None:
        if self._bus is None:
            raise DriverIOError("canopen: read on a closed driver")
        timeout = self.timeout_s
        if self._seen != self._all_rpdos:  # after open: wait for the slow PDOs once
            timeout += SLOW_PERIOD_CYCLES * self.can_cfg.sync_period_s
        deadline = time.monotonic() + timeout
        try:
            complete = self._collect(deadline)
        except can.CanError as exc:
            raise DriverIOError(f"canopen: receive failed: {exc}") from exc
        if not complete:
            missing = [
                f"0x{lay.cob_id:03X}"
                for lay, bit in self._rx.values()
                if bit and not self._received & bit
            ]
            what = "no SYNC" if not self._sync_seen else "missing PDOs " + ", ".join(missing)
            if self._sync_seen and not missing:
                what = "no slow PDO yet (heartbeat, pose, lengths)"
            raise DriverTimeoutError(f"canopen: {what} within {timeout * 1e3:.1f} ms")
        self._sync_seen, self._received = False, 0
        self.sets += 1
        self.last_sync_timestamp = self._sync_timestamp
        # the data belongs to its SYNC: its age counts from the SYNC's arrival
        since_sync = max(time.time() - self._sync_timestamp, 0.0)
        inputs.read_time_s = min(inputs.read_time_s, self.clock() - since_sync)
        self._fill(inputs)

    def _collect(self, deadline: float) -> bool:
        """Receive until a SYNC and all per-cycle RPDOs after it are in and the queue is
        empty (a newer SYNC restarts the set). False when ``deadline`` passes first."""
        bus = self._bus
        assert bus is not None
        for _ in range(DRAIN_LIMIT):
            if (
                self._sync_seen
                and self._received == self._required
                and self._seen == self._all_rpdos
            ):
                msg = bus.recv(0)
                if msg is None:
                    return True
            else:
                # past the deadline, frames already queued are still taken (a stall of
                # this thread must not turn into a timeout)
                remaining = deadline - time.monotonic()
                msg = bus.recv(remaining if remaining > 0 else 0.0)
                if msg is None:
                    return False
            self._handle(msg)
        return False

    def _handle(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame:
            self.ignored_frames += 1
            return
        cob_id = msg.arbitration_id
        if cob_id == SYNC_COB_ID:
            self.syncs += 1
            self._sync_seen, self._received = True, 0
            self._sync_timestamp = msg.timestamp
            return
        if (cob_id == NMT_COB_ID or cob_id == self._sdo_rx) and self._node is not None:
            self._on_nmt_or_sdo(msg)
            return
        entry = self._rx.get(cob_id)
        if entry is None:
            self.ignored_frames += 1
            return
        layout, bit = entry
        unpack_pdo(layout, msg.data, self._slots)
        self._seen |= self._seen_bits[cob_id]
        if self._sync_seen:
            self._received |= bit

    def _fill(self, inputs: Inputs) -> None:
        slots, decode = self._slots, self.analog.decode_count
        raw, vel = slots[OBJ_RAW], slots[OBJ_VELOCITY]
        length = slots.get(OBJ_LENGTH)
        for i in range(self.cables):
            inputs.tension_raw_n[i] = decode(raw[i])
            inputs.velocity_m_s[i] = vel[i] * VELOCITY_M_S_PER_COUNT
            if length is not None:
                inputs.length_m[i] = length[i] * LENGTH_M_PER_COUNT
        pose = slots.get(OBJ_POSE)
        if pose is not None:
            for j in range(6):
                scale = POSITION_M_PER_COUNT if j < 3 else ANGLE_RAD_PER_COUNT
                inputs.pose[j] = pose[j] * scale
        if OBJ_PLC_HEARTBEAT in slots:
            inputs.plc_heartbeat = slots[OBJ_PLC_HEARTBEAT][0]

    def _write(self, outputs: Outputs) -> None:
        bus = self._bus
        if bus is None:
            raise DriverIOError("canopen: write on a closed driver")
        tx = self._tx_slots
        if OBJ_CORRECTED in tx:
            corrected = tx[OBJ_CORRECTED]
            for i in range(self.cables):
                corrected[i] = encode_tension(float(outputs.tension_corrected_n[i]))
        if OBJ_STATUS in tx:
            tx[OBJ_STATUS][0] = pack_status(outputs.channel_status)
        if OBJ_GW_HEARTBEAT in tx:
            tx[OBJ_GW_HEARTBEAT][0] = int(outputs.gateway_heartbeat) & 0xFFFF
        if OBJ_GW_STATE in tx:
            tx[OBJ_GW_STATE][0] = int(outputs.gateway_state) & 0xFF
        if self._node is not None and self._node.nmt.state != "OPERATIONAL":
            return  # stopped / pre-operational by the master: no PDOs (CiA 301)
        try:
            for layout in self._tx:
                data = pack_pdo(layout, tx)
                bus.send(can.Message(arbitration_id=layout.cob_id, data=data, is_extended_id=False))
        except can.CanError as exc:
            raise DriverIOError(f"canopen: send failed: {exc}") from exc

    def _close(self) -> None:
        if self._node is not None:
            self._node.nmt.stop_heartbeat()
            self._node = None
        bus, self._bus = self._bus, None
        if bus is not None and bus is not self._external_bus:
            bus.shutdown()
