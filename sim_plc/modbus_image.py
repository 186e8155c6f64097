"""The soft PLC's Modbus register image and request handler: no sockets, no loop.

:class:`ImageRegisters` lays the configured register map of a :class:`ProcessImage` out in
the three areas :mod:`sim_plc.modbus_server` describes (inputs padded to a multiple of
``INPUT_AREA_ALIGN``, outputs, the ``TRUTH_ADDRESS`` side channel) and encodes/decodes
them; :class:`RequestHandler` answers one Modbus PDU (functions 3, 4, 6, 16, 23, or the
exception reply). The MBAP framing and the asyncio server are in
:mod:`sim_plc.modbus_server`, which re-exports these names.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from drivers.registers import (
    MAX_READ_REGISTERS,
    MAX_WRITE_REGISTERS_FC16,
    MAX_WRITE_REGISTERS_FC23,
    FieldCodec,
    Span,
    layout_map,
)
from gateway.core.config import Config
from gateway.core.registermap import RegisterField
from sim_plc.image import ProcessImage

INPUT_AREA_ALIGN = 8
REGISTER_FUNCTIONS = frozenset((3, 4, 6, 16, 23))
TRUTH_ADDRESS = 200  # the side channel: true tensions, then the PLC heartbeat


def truth_fields(cables: int) -> tuple[RegisterField, RegisterField]:
    """The side channel's true tensions (float32) and heartbeat copy (uint16)."""
    truth = RegisterField(TRUTH_ADDRESS, cables, "float32")
    return truth, RegisterField(truth.end, 1, "uint16")


ILLEGAL_FUNCTION, ILLEGAL_ADDRESS, ILLEGAL_VALUE = 1, 2, 3


def _fields(rmap: Any) -> list[RegisterField]:
    return [*rmap.inputs().values(), *rmap.outputs().values()]


def _areas(cfg: Config) -> tuple[Span, Span, Span | None]:
    """The input (padded), output and side-channel (truth) areas of the configured map.

    The truth area is left out when the configured map uses any of its registers.
    """
    rmap = cfg.bus.modbus_tcp.registers
    layout = layout_map(rmap)
    inputs = Span.covering(list(layout.inputs.values()))
    outputs = layout.write_span
    truth: Span | None = Span.covering(list(truth_fields(cfg.cables)))
    assert truth is not None
    if any(truth.start < f.end and f.address < truth.end for f in _fields(rmap)):
        truth = None
    padded_end = -(-inputs.end // INPUT_AREA_ALIGN) * INPUT_AREA_ALIGN
    others = [outputs.start] + ([truth.start] if truth is not None else [])
    limit = min([s for s in others if s >= inputs.end] + [65536])
    inputs = Span(inputs.start, min(padded_end, limit) - inputs.start)
    return inputs, outputs, truth


class ImageRegisters:
    """The register image of one :class:`ProcessImage` and its codecs (no I/O, no loop).

    Words are kept big-endian in ``data`` (``2 * (end - base)`` bytes from ``base``).
    """

    def __init__(self, cfg: Config, image: ProcessImage) -> None:
        self.image = image
        self.rmap = cfg.bus.modbus_tcp.registers
        self.input_area, self.output_area, self.truth_area = _areas(cfg)
        areas = [a for a in (self.input_area, self.output_area, self.truth_area) if a]
        self.base = min(a.start for a in areas)
        self.end = max(a.end for a in areas)
        self.data = bytearray(2 * (self.end - self.base))
        self.words = np.frombuffer(self.data, dtype=">u2")
        sensor = cfg.sensor

        def codec(f: RegisterField) -> FieldCodec:
            return FieldCodec(f, self.data, self.base, 0, sensor)

        r = self.rmap
        self._in = [
            (codec(r.raw_tensions), "raw_counts", True),
            (codec(r.setpoint_velocities), "velocity_m_s", False),
            (codec(r.setpoint_lengths), "length_m", False),
            (codec(r.pose), "pose", False),
            (codec(r.plc_heartbeat), "plc_heartbeat", True),
        ]
        if r.platform_mass is not None:
            self._in.append((codec(r.platform_mass), "platform_mass_kg", False))
        self._out = [
            (codec(r.corrected_tensions), "corrected_n"),
            (codec(r.channel_status), "channel_status"),
            (codec(r.gateway_heartbeat), "gateway_heartbeat"),
            (codec(r.gateway_state), "gateway_state"),
            (codec(r.wrench), "wrench"),
        ]
        self._truth = None
        if self.truth_area is not None:
            truth, heartbeat = truth_fields(cfg.cables)
            self._truth = (codec(truth), codec(heartbeat))
        self._scratch = {c.field.address: np.zeros(c.count) for c, _ in self._out}
        # encoded and decoded once now: the codecs' compiled kernels load here, while the
        # server starts, not on the first request (at a load of 8 that took over 2 s, a
        # client's whole timeout; a PLC client would lose its first exchange)
        with image.lock:
            self.refresh()
        for c, _ in self._out:
            c.decode(self._scratch[c.field.address])

    def areas(self) -> list[tuple[Span, bool]]:
        """The served areas as (span, writable): only the outputs are writable."""
        areas = [(self.input_area, False), (self.output_area, True)]
        if self.truth_area is not None:
            areas.append((self.truth_area, False))
        return areas

    def refresh(self) -> None:
        """Encode the whole image into ``data``; the caller holds ``image.lock``."""
        img = self.image
        for c, name, raw in self._in:
            c.encode(getattr(img, name), raw=raw)
        for c, name in self._out:
            value = getattr(img, name)
            c.encode(value & 0xFFFF if isinstance(value, int) else value)
        if self._truth is not None:
            self._truth[0].encode(img.true_tension_n)
            self._truth[1].encode(img.plc_heartbeat, raw=True)

    def read(self, address: int, count: int) -> bytes:
        """Current registers ``address .. address + count - 1`` from the image, as the
        big-endian bytes a reply carries."""
        with self.image.lock:
            self.refresh()
        off = 2 * (address - self.base)
        return bytes(self.data[off : off + 2 * count])

    def write(self, address: int, payload: bytes | memoryview) -> None:
        """Apply a gateway write (big-endian words) to the outputs, decode it into the image."""
        n = len(payload) // 2
        lo, hi = address, address + n
        off = address - self.base
        img = self.image
        with img.lock:
            self.refresh()
            self.words[off : off + n] = np.frombuffer(payload, dtype=">u2")
            for c, name in self._out:
                f = c.field
                if f.address < hi and lo < f.end:
                    buf = c.decode(self._scratch[f.address])
                    if isinstance(getattr(img, name), int):
                        setattr(img, name, int(buf[0]))
                    else:
                        getattr(img, name)[...] = buf
            img.gateway_writes += 1


def _exception(function: int, code: int) -> bytes:
    return bytes(((0x80 | function) & 0xFF, code))


class RequestHandler:
    """Executes one request PDU against :class:`ImageRegisters`; returns the reply PDU."""

    def __init__(self, registers: ImageRegisters) -> None:
        self.registers = registers
        self._readable = [span for span, _ in registers.areas()]
        self._writable = registers.output_area

    def readable(self, address: int, count: int) -> bool:
        return any(s.start <= address and address + count <= s.end for s in self._readable)

    def writable(self, address: int, count: int) -> bool:
        out = self._writable
        return out.start <= address and address + count <= out.end

    def handle(self, pdu: bytes) -> bytes:
        """The reply PDU to request ``pdu`` (function code onwards; at least one byte)."""
        fc = pdu[0]
        if fc == 3 or fc == 4:
            return self._read(fc, pdu)
        if fc == 23:
            return self._read_write(pdu)
        if fc == 16:
            return self._write_multiple(pdu)
        if fc == 6:
            return self._write_single(pdu)
        return _exception(fc, ILLEGAL_FUNCTION)

    def _read(self, fc: int, pdu: bytes) -> bytes:
        if len(pdu) != 5:
            return _exception(fc, ILLEGAL_VALUE)
        address, count = struct.unpack_from(">HH", pdu, 1)
        if not 1 <= count <= MAX_READ_REGISTERS:
            return _exception(fc, ILLEGAL_VALUE)
        if not self.readable(address, count):
            return _exception(fc, ILLEGAL_ADDRESS)
        return bytes((fc, 2 * count)) + self.registers.read(address, count)

    def _write_single(self, pdu: bytes) -> bytes:
        if len(pdu) != 5:
            return _exception(6, ILLEGAL_VALUE)
        address = struct.unpack_from(">H", pdu, 1)[0]
        if not self.writable(address, 1):
            return _exception(6, ILLEGAL_ADDRESS)
        self.registers.write(address, pdu[3:5])
        return pdu

    def _write_multiple(self, pdu: bytes) -> bytes:
        if len(pdu) < 6:
            return _exception(16, ILLEGAL_VALUE)
        address, count, nbytes = struct.unpack_from(">HHB", pdu, 1)
        ok = 1 <= count <= MAX_WRITE_REGISTERS_FC16 and nbytes == 2 * count
        if not ok or len(pdu) != 6 + nbytes:
            return _exception(16, ILLEGAL_VALUE)
        if not self.writable(address, count):
            return _exception(16, ILLEGAL_ADDRESS)
        self.registers.write(address, pdu[6:])
        return pdu[:5]

    def _read_write(self, pdu: bytes) -> bytes:
        """Function 23: the write is done before the read (the spec's order)."""
        if len(pdu) < 10:
            return _exception(23, ILLEGAL_VALUE)
        r_addr, r_count, w_addr, w_count, nbytes = struct.unpack_from(">HHHHB", pdu, 1)
        ok = 1 <= r_count <= MAX_READ_REGISTERS and 1 <= w_count <= MAX_WRITE_REGISTERS_FC23
        if not ok or nbytes != 2 * w_count or len(pdu) != 10 + nbytes:
            return _exception(23, ILLEGAL_VALUE)
        if not (self.writable(w_addr, w_count) and self.readable(r_addr, r_count)):
            return _exception(23, ILLEGAL_ADDRESS)
        self.registers.write(w_addr, pdu[10:])
        return bytes((23, 2 * r_count)) + self.registers.read(r_addr, r_count)
