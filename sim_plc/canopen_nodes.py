"""The soft PLC's CANopen nodes: the PLC as master and the CiA 401 analog input module.

One cycle (:meth:`CanopenPlc.step`, or every ``sync_period_s`` in the real-time thread):

1. the master takes the gateway's TPDOs received since the last cycle into the image
   (corrected tensions, channel status, gateway heartbeat and state);
2. the master sends SYNC (0x080);
3. the analog module (its own bus object, as it is its own device) sends TPDO1/2 with
   the image's raw counts. In this simulation the module is triggered by the master's
   call right after the SYNC rather than by receiving the SYNC frame: same frame order
   on the bus, without a thread hop;
4. the master sends TPDO1/2 (setpoint velocities) and, in cycles ``k % 10 == 0..3``, one
   of TPDO3-6 (heartbeat + x, y, z; rx, ry, rz; lengths 1-4; lengths 5-8).

PDO mapping, scaling and the bus load: ``drivers/canopen.py``. Node ids: master
``drivers.canopen.PLC_NODE_ID`` (EDS ``config/plc_master.eds``), analog module
``analog_node_id``, gateway ``gateway_node_id`` (its TPDO COB-IDs follow it).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import can

from drivers.canopen import (
    DRAIN_LIMIT,
    OBJ_ANALOG_IN,
    OBJ_CORRECTED,
    OBJ_GW_HEARTBEAT,
    OBJ_GW_STATE,
    OBJ_LENGTH,
    OBJ_PLC_HEARTBEAT,
    OBJ_POSE,
    OBJ_STATUS,
    OBJ_VELOCITY,
    SLOW_PERIOD_CYCLES,
    SYNC_COB_ID,
    open_bus,
)
from drivers.canopen_pdo import (
    ANGLE_RAD_PER_COUNT,
    LENGTH_M_PER_COUNT,
    POSITION_M_PER_COUNT,
    VELOCITY_M_S_PER_COUNT,
    PdoLayout,
    decode_tension,
    load_pdo_layouts,
    new_slots,
    pack_pdo,
    to_int16,
    unpack_pdo,
    unpack_status,
)
from gateway.errors import DriverIOError
from sim_plc.image import ProcessImage

BusFactory = Callable[[], can.BusABC]
FAST_TPDOS = (1, 2)  # master TPDOs sent every cycle
SLOW_TPDOS = (3, 4, 5, 6)  # master TPDOs sent in cycles k % 10 == 0, 1, 2, 3


def _message(layout: PdoLayout, slots: dict[int, list[int]]) -> can.Message:
    return can.Message(
        arbitration_id=layout.cob_id, data=pack_pdo(layout, slots), is_extended_id=False
    )


class AnalogInputModule:
    """CiA 401 node: after each SYNC sends TPDO1/2 with 6401h = the image's raw counts.

    ``enabled = False`` makes it fall silent (a failed module), ``True`` resumes.
    """

    def __init__(self, cfg: Any, image: ProcessImage, bus: can.BusABC) -> None:
        self.image = image
        self.bus = bus
        tpdos, _ = load_pdo_layouts(cfg.analog_eds, cfg.analog_node_id)
        self.tpdos = [tpdos[n] for n in sorted(tpdos) if tpdos[n].trans_type <= 240]
        self.slots = new_slots(tpdos)
        self.enabled = True

    def on_sync(self) -> None:
        if not self.enabled:
            return
        counts = self.slots[OBJ_ANALOG_IN]
        with self.image.lock:
            raw = self.image.raw_counts.tolist()
        counts[: len(raw)] = raw[: len(counts)]
        for layout in self.tpdos:
            self.bus.send(_message(layout, self.slots))


class CanopenPlc:
    """The soft PLC on CANopen: SYNC master, setpoint PDOs, analog module, gateway PDOs in.

    ``cfg``: a ``CanopenConfig`` (or a full ``Config``, its ``bus.canopen`` is used).
    ``bus_factory``: returns a new python-can bus on the shared channel (called twice:
    master and analog module); default: from ``cfg`` (interface, channel, bitrate).
    Stepped mode: ``start()`` then ``step()`` per cycle. Real time: ``start(realtime=True)``
    sends SYNC every ``sync_period_s`` from its own thread. ``stop()`` is safe twice.
    """

    def __init__(
        self,
        cfg: Any,
        image: ProcessImage,
        bus_factory: BusFactory | None = None,
        *,
        master_eds: str | None = None,
        spin_s: float = 0.0,
    ) -> None:
        self.cfg = cfg.bus.canopen if hasattr(cfg, "bus") else cfg
        self.image = image
        self.bus_factory = bus_factory or (lambda: open_bus(self.cfg))
        self.spin_s = spin_s
        tpdos, rpdos = load_pdo_layouts(master_eds or self.cfg.plc_eds, self.cfg.plc_node_id)
        self.fast = [tpdos[n] for n in FAST_TPDOS]
        self.slow = [tpdos[n] for n in SLOW_TPDOS]
        gw = self.cfg.gateway_node_id  # the gateway's TPDOn is 0x80 + n * 0x100 + node id
        cob = {n: 0x80 + 0x100 * n + gw for n in rpdos}
        self.rx = {cob[n]: lay.retarget(cob[n]) for n, lay in rpdos.items()}
        self.tx_slots = new_slots(tpdos)
        self.rx_slots = new_slots(rpdos)
        self.sync_enabled = True
        self.cycles = 0  # SYNC cycles emitted
        self.gateway_frames = 0
        self.malformed_frames = 0
        self.analog: AnalogInputModule | None = None
        self._bus: can.BusABC | None = None
        self._analog_bus: can.BusABC | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.overruns = 0
        self.sync_times_s: list[float] = []  # perf_counter of each SYNC, when recording
        self.record_sync_times = False

    # --- lifecycle ------------------------------------------------------------------------
    def start(self, realtime: bool = False) -> None:
        """Open the buses (once); with ``realtime`` also start the SYNC thread."""
        if self._bus is None:
            self._bus = self.bus_factory()
            self._analog_bus = self.bus_factory()
            self.analog = AnalogInputModule(self.cfg, self.image, self._analog_bus)
        if realtime and self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="canopen-plc", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        """Stop the thread and shut the buses down; safe to call twice."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for bus in (self._bus, self._analog_bus):
            if bus is not None:
                bus.shutdown()
        self._bus = self._analog_bus = None

    def __enter__(self) -> CanopenPlc:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --- one cycle --------------------------------------------------------------------
    def step(self) -> None:
        """One PLC cycle: take the gateway's PDOs in, SYNC, analog TPDOs, setpoint PDOs."""
        bus = self._bus
        if bus is None or self.analog is None:
            raise RuntimeError("CanopenPlc.step: not started")
        self.poll()
        if not self.sync_enabled:
            return
        self._load_setpoints()
        bus.send(can.Message(arbitration_id=SYNC_COB_ID, data=b"", is_extended_id=False))
        if self.record_sync_times:
            self.sync_times_s.append(time.perf_counter())
        self.analog.on_sync()
        for layout in self.fast:
            bus.send(_message(layout, self.tx_slots))
        phase = self.cycles % SLOW_PERIOD_CYCLES
        if phase < len(self.slow):
            bus.send(_message(self.slow[phase], self.tx_slots))
        self.cycles += 1

    def _load_setpoints(self) -> None:
        s = self.tx_slots
        img = self.image
        with img.lock:
            vel = img.velocity_m_s.tolist()
            length = img.length_m.tolist()
            pose = img.pose.tolist()
            heartbeat = int(img.plc_heartbeat) & 0xFFFF
        s[OBJ_VELOCITY][:] = [to_int16(v, VELOCITY_M_S_PER_COUNT) for v in vel]
        s[OBJ_LENGTH][:] = [
            max(0, min(0xFFFF, round(v / LENGTH_M_PER_COUNT))) if v == v else 0 for v in length
        ]
        scales = (POSITION_M_PER_COUNT,) * 3 + (ANGLE_RAD_PER_COUNT,) * 3
        s[OBJ_POSE][:] = [to_int16(v, k) for v, k in zip(pose, scales, strict=True)]
        s[OBJ_PLC_HEARTBEAT][0] = heartbeat

    def poll(self) -> int:
        """Take every gateway PDO already received into the image; returns the count."""
        bus = self._bus
        if bus is None:
            return 0
        taken = 0
        for _ in range(DRAIN_LIMIT):
            msg = bus.recv(0)
            if msg is None:
                break
            layout = self.rx.get(msg.arbitration_id)
            if layout is None or msg.is_error_frame or msg.is_remote_frame:
                continue
            try:
                unpack_pdo(layout, msg.data, self.rx_slots)
            except DriverIOError:  # short frame: CiA 301 would send an EMCY; skip it
                self.malformed_frames += 1
                continue
            self._apply(layout)
            taken += 1
        self.gateway_frames += taken
        return taken

    def _apply(self, layout: PdoLayout) -> None:
        s, img = self.rx_slots, self.image
        objects = {i for i, _ in layout.entries}
        with img.lock:
            if OBJ_CORRECTED in objects:
                corrected = s[OBJ_CORRECTED]
                for i in range(min(img.cables, len(corrected))):
                    img.corrected_n[i] = decode_tension(corrected[i])
            if OBJ_STATUS in objects:
                unpack_status(s[OBJ_STATUS][0], img.channel_status)
                img.gateway_heartbeat = s[OBJ_GW_HEARTBEAT][0]
                img.gateway_state = s[OBJ_GW_STATE][0]
                img.gateway_writes += 1

    # --- real time --------------------------------------------------------------------
    def _run(self) -> None:
        period = self.cfg.sync_period_s
        next_t = time.perf_counter() + period
        while not self._stop.is_set():
            now = time.perf_counter()
            if next_t - now > self.spin_s:
                time.sleep(next_t - now - self.spin_s)
            while time.perf_counter() < next_t:
                pass
            try:
                self.step()
            except can.CanError:
                if self._stop.is_set():
                    return
                raise
            next_t += period
            late = time.perf_counter() - next_t
            if late > 0:  # missed whole periods: skip them, count the overrun
                skipped = int(late // period) + 1
                self.overruns += skipped
                next_t += skipped * period
