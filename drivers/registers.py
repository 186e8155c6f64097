"""Codec between numpy arrays and 16-bit Modbus register words, and register-map layout.

Registers travel big-endian on the wire, so a block of holding registers *is* a byte
string of ``2 * n`` bytes. :class:`FieldCodec` binds one :class:`RegisterField` to a fixed
byte buffer (a driver's preallocated receive or transmit frame, or a server's register
image) and converts between that buffer and a float64 array, vectorised and without
allocating per call: the numpy views onto the buffer and the scratch arrays are made once.

Types: int16, uint16, int32, uint32, float32. For 32-bit types ``word_order`` says which
16-bit word comes first (``high_first`` is the Modbus convention, and then the bytes are
simply big-endian; ``low_first`` swaps the two words). Plain fields decode as
``value = raw * scale`` and encode as ``raw = round(value / scale)`` (integers clipped to
the type's range, NaN -> 0).

:class:`FieldGroup` binds several codecs of one buffer (a driver's whole reply or request
frame) and decodes or encodes all of them in ONE compiled call, with exactly the results
of the codecs one by one (tests check bit for bit): a cycle's decode is one call instead
of a dozen small numpy calls (each costs ~0.5-1 us on 8-element arrays).

``format: s7_analog`` (Siemens S7 analog values, int16): decoded and encoded by the one S7
codec, :class:`drivers.s7.S7Analog` (see there for the reading: 0..``adc_full_scale``
counts is 0..``range_n`` newtons, over- and underrange included; the overflow/underflow
codes and the counts no S7 module sends decode as NaN, so the gateway marks the channel
invalid); ``scale`` is not applied.

:func:`layout_map` checks a whole :class:`RegisterMap` (no two fields overlap; the write
span never covers a PLC input register) and computes the contiguous spans a driver
transfers: the inputs and the outputs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from itertools import combinations
from typing import Any

import numpy as np
from numba import literal_unroll, njit, types
from numba.extending import overload

from drivers.s7 import S7_OVERFLOW, S7_UNDERFLOW, S7Analog
from gateway.core.config import RegisterField, RegisterMap, SensorConfig
from gateway.errors import ConfigError

MAX_READ_REGISTERS = 125  # functions 3, 4, 23 (read part)
MAX_WRITE_REGISTERS_FC16 = 123
MAX_WRITE_REGISTERS_FC23 = 121

_DTYPES: dict[str, np.dtype] = {
    "int16": np.dtype(">i2"),
    "uint16": np.dtype(">u2"),
    "int32": np.dtype(">i4"),
    "uint32": np.dtype(">u4"),
    "float32": np.dtype(">f4"),
}


def field_dtype(field: RegisterField) -> np.dtype:
    """The big-endian numpy dtype of one value of ``field`` (high word first)."""
    return _DTYPES[field.type]


class FieldCodec:
    """One register field bound to a byte buffer that holds registers from ``base_address``.

    ``buffer`` must stay the same object (and size) for the codec's lifetime; ``offset`` is
    the byte position of register ``base_address`` inside it (e.g. 9 for the data of a
    function-3 reply frame after the MBAP header, function code and byte count).
    """

    def __init__(
        self,
        field: RegisterField,
        buffer: bytearray | memoryview,
        base_address: int,
        offset: int = 0,
        sensor: SensorConfig | None = None,
    ) -> None:
        if field.address < base_address:
            raise ConfigError(
                f"register {field.address} lies before the buffer base {base_address}"
            )
        self.field = field
        self.count = field.count
        self.dtype = field_dtype(field)
        start = offset + 2 * (field.address - base_address)
        if start + 2 * field.words > len(buffer):
            raise ConfigError(
                f"registers {field.address}..{field.end - 1} do not fit the buffer "
                f"(base {base_address}, {len(buffer)} bytes)"
            )
        self.swap = field.words == 2 * field.count and field.word_order == "low_first"
        self.buffer = buffer
        self.start = start  # byte position of the field in ``buffer``
        self._words = np.frombuffer(buffer, dtype=">u2", count=field.words, offset=start)
        if self.swap:  # values are assembled in a scratch copy with the words swapped
            self._scratch = np.empty(field.words, dtype=">u2")
            self._values = self._scratch.view(self.dtype)
        else:
            self._values = np.frombuffer(buffer, dtype=self.dtype, count=self.count, offset=start)
        self.s7 = field.format == "s7_analog"
        if self.s7 and field.type != "int16":
            raise ConfigError(f"register {field.address}: format s7_analog needs type int16")
        sensor = sensor or SensorConfig()
        self.analog = S7Analog.from_sensor(sensor)
        self.newtons_per_count = self.analog.newtons_per_count
        self._lut = self.analog.table if self.s7 else None
        self._mask = np.empty(self.count, dtype=bool)
        self._mask2 = np.empty(self.count, dtype=bool)
        self._float = np.empty(self.count)
        info = np.iinfo(self.dtype) if self.dtype.kind in "iu" else None
        self._limits = (float(info.min), float(info.max)) if info is not None else None

    # --- decode ----------------------------------------------------------------------
    def _source(self) -> np.ndarray:
        if self.swap:
            self._scratch[0::2] = self._words[1::2]
            self._scratch[1::2] = self._words[0::2]
        return self._values

    def decode(self, out: np.ndarray, raw: bool = False) -> np.ndarray:
        """Decode the bound registers into ``out`` (shape (count,), float64).

        ``raw=True`` skips scaling (S7 counts, unscaled integers); otherwise S7 values come
        out in newtons with NaN for the overflow/underflow codes.
        """
        src = self._source()
        if raw:
            np.copyto(out, src, casting="unsafe")
        elif self._lut is not None:  # S7: one lookup does scaling and the codes
            np.take(self._lut, self._words, out=out)
        elif self.field.scale == 1.0:
            np.copyto(out, src, casting="unsafe")
        else:
            np.multiply(src, self.field.scale, out=out)
        return out

    def decode_int(self, index: int = 0) -> int:
        """One value as a Python int, unscaled (heartbeats, states)."""
        return int(self._source()[index])

    # --- encode ----------------------------------------------------------------------
    def encode(self, values: np.ndarray | float, raw: bool = False) -> None:
        """Encode ``values`` (shape (count,) or a scalar) into the bound registers.

        ``raw=True`` writes values as they are (S7 counts, unscaled integers, clipped).
        """
        if self._direct(values, raw):
            return
        f = self._float
        f[...] = values
        if self.s7 and not raw:
            a = self.analog  # the S7 codec's encoding, without allocating
            np.divide(f, a.newtons_per_count, out=f)
            np.rint(f, out=f)
            np.isnan(f, out=self._mask)
            np.greater(f, a.max_counts, out=self._mask2)
            np.logical_or(self._mask, self._mask2, out=self._mask)
            np.copyto(f, S7_OVERFLOW, where=self._mask)
            np.less(f, a.min_counts, out=self._mask2)
            np.copyto(f, S7_UNDERFLOW, where=self._mask2)
        elif not raw and self.field.scale != 1.0:
            np.divide(f, self.field.scale, out=f)
        if self._limits is not None:
            np.rint(f, out=f)
            np.isnan(f, out=self._mask)
            np.copyto(f, 0.0, where=self._mask)
            np.clip(f, self._limits[0], self._limits[1], out=f)
        self._values[...] = f
        self._store()

    def _store(self) -> None:
        if self.swap:
            self._words[0::2] = self._scratch[1::2]
            self._words[1::2] = self._scratch[0::2]

    def _direct(self, values: np.ndarray | float, raw: bool) -> bool:
        """Fast paths that need no scaling, rounding or clipping; True when done."""
        if self.s7 and not raw:
            return False
        if not raw and self.field.scale != 1.0:
            return False
        if self._limits is None:  # float32: numpy casts, NaN stays NaN
            self._values[...] = values
        elif isinstance(values, int | np.integer):
            lo, hi = self._limits
            self._values[...] = min(max(int(values), int(lo)), int(hi))
        elif isinstance(values, np.ndarray) and np.can_cast(values.dtype, self.dtype):
            self._values[...] = values
        else:
            return False
        self._store()
        return True


# --- several fields in one compiled call -------------------------------------------------
_TYPE_CODES = {"int16": 0, "uint16": 1, "int32": 2, "uint32": 3, "float32": 4}
# columns of a FieldGroup plan row (float64; the integers are exact)
_START, _COUNT, _TYPE, _SWAP, _S7, _SCALE, _NPC, _MIN, _MAX, _LO, _HI, _RAW = range(12)
_INT_LIMITS = {0: (-32768.0, 32767.0), 1: (0.0, 65535.0), 2: (-(2.0**31), 2.0**31 - 1),
               3: (0.0, 2.0**32 - 1), 4: (0.0, 0.0)}  # fmt: skip


def _size(value):  # untyped: the overload must have the same signature
    """Element count of an array; -1 for a scalar (broadcast to the field)."""
    raise NotImplementedError  # compiled only (see the overload)


def _get(value, i):
    """Element ``i`` of an array, or the scalar itself, as float64."""
    raise NotImplementedError  # compiled only (see the overload)


@overload(_size)
def _size_impl(value):
    if isinstance(value, types.Array):
        return lambda value: value.size
    return lambda value: -1


@overload(_get)
def _get_impl(value, i):
    if isinstance(value, types.Array):
        return lambda value, i: float(value[i])
    return lambda value, i: float(value)


@njit(cache=True, inline="always")
def _decode_one(u, kind, s7, scale, npc, lo, hi, bits, as_f32):
    """The value of the bits ``u`` (one 16-bit word, or two assembled high word first),
    as FieldCodec.decode computes it (``scale`` 1.0 / ``s7`` False for raw values)."""
    if kind == 4:
        bits[0] = u
        f = as_f32[0]
        # numpy multiplies a float32 field by a Python float scale in float32 (NEP 50)
        return float(f) if scale == 1.0 else float(f * np.float32(scale))
    if kind == 0 and u >= 32768:
        u -= 65536
    elif kind == 2 and u >= 2**31:
        u -= 2**32
    if s7:  # the S7 window: counts * N/count, else NaN
        return u * npc if lo <= u <= hi else np.nan
    return float(u) if scale == 1.0 else u * scale


@njit(cache=True, inline="always")
def _encode_one(x, kind, s7, scale, npc, row, bits, as_f32):
    """The bits FieldCodec.encode stores for ``x`` (``scale`` 1.0 / ``s7`` False for raw
    values); ``row``: (S7 min counts, S7 max counts, type min, type max)."""
    f = x
    if s7:  # the S7 codec's encoding
        f = np.rint(x / npc)
        if np.isnan(f) or f > row[1]:
            f = float(S7_OVERFLOW)
        elif f < row[0]:
            f = float(S7_UNDERFLOW)
    elif scale != 1.0:
        f = x / scale
    if kind == 4:
        as_f32[0] = np.float32(f)
        return np.int64(bits[0])
    f = np.rint(f)
    if np.isnan(f):
        f = 0.0
    f = min(max(f, row[2]), row[3])
    return np.int64(f) & (0xFFFF if kind <= 1 else 0xFFFFFFFF)


@njit(cache=True)
def _decode_group(buf, plan, bits, outs):
    as_f32 = bits.view(np.float32)  # float32 bit patterns are assembled in ``bits``
    k = 0
    for out in literal_unroll(outs):
        n, kind, raw = int(plan[k, _COUNT]), int(plan[k, _TYPE]), plan[k, _RAW] != 0.0
        if out.size != n:
            raise ValueError("FieldGroup.decode: an output's size differs from its field's count")
        start, step, swap = int(plan[k, _START]), 2 if kind <= 1 else 4, plan[k, _SWAP] != 0.0
        s7 = plan[k, _S7] != 0.0 and not raw
        scale = 1.0 if raw else plan[k, _SCALE]
        npc, lo, hi = plan[k, _NPC], plan[k, _MIN], plan[k, _MAX]
        for i in range(n):
            p = start + step * i
            u = (np.int64(buf[p]) << 8) | np.int64(buf[p + 1])
            if kind >= 2:
                w = (np.int64(buf[p + 2]) << 8) | np.int64(buf[p + 3])
                u = (w << 16) | u if swap else (u << 16) | w
            out[i] = _decode_one(u, kind, s7, scale, npc, lo, hi, bits, as_f32)
        k += 1  # noqa: SIM113 (literal_unroll has no enumerate)


@njit(cache=True)
def _encode_group(buf, plan, bits, values):
    as_f32 = bits.view(np.float32)
    k = 0
    for value in literal_unroll(values):
        n, kind, raw = int(plan[k, _COUNT]), int(plan[k, _TYPE]), plan[k, _RAW] != 0.0
        size = _size(value)
        if size >= 0 and size != n:
            raise ValueError("FieldGroup.encode: a value's size differs from its field's count")
        start, step, swap = int(plan[k, _START]), 2 if kind <= 1 else 4, plan[k, _SWAP] != 0.0
        s7 = plan[k, _S7] != 0.0 and not raw
        scale = 1.0 if raw else plan[k, _SCALE]
        row = (plan[k, _MIN], plan[k, _MAX], plan[k, _LO], plan[k, _HI])
        npc = plan[k, _NPC]
        for i in range(n):
            u = _encode_one(_get(value, i), kind, s7, scale, npc, row, bits, as_f32)
            p = start + step * i
            if kind <= 1:
                buf[p], buf[p + 1] = (u >> 8) & 0xFF, u & 0xFF
                continue
            hi, lo = (u >> 16) & 0xFFFF, u & 0xFFFF
            if swap:
                hi, lo = lo, hi
            buf[p], buf[p + 1] = (hi >> 8) & 0xFF, hi & 0xFF
            buf[p + 2], buf[p + 3] = (lo >> 8) & 0xFF, lo & 0xFF
        k += 1


class FieldGroup:
    """Several :class:`FieldCodec` of ONE buffer, decoded or encoded in one compiled call.

    The results are those of the codecs one by one (``decode(out, raw)``,
    ``encode(values, raw)`` with the group's ``raw`` flag per codec), without the dozen
    small numpy calls they make: the per-cycle decode of a reply and encode of a request.
    The first call with a new combination of value types compiles (numba; cached on
    disk): callers warm the group up outside the cycle.
    """

    def __init__(self, codecs: Sequence[FieldCodec], raw: Sequence[bool] | None = None) -> None:
        if not codecs:
            raise ValueError("FieldGroup needs at least one codec")
        raw = [False] * len(codecs) if raw is None else list(raw)
        if len(raw) != len(codecs):
            raise ValueError("FieldGroup: one raw flag per codec")
        buffer = codecs[0].buffer
        if any(c.buffer is not buffer for c in codecs):
            raise ValueError("FieldGroup: every codec must be bound to the same buffer")
        self.codecs = tuple(codecs)
        self.plan = np.array([_plan_row(c, r) for c, r in zip(codecs, raw, strict=True)])
        self._buf = np.frombuffer(buffer, dtype=np.uint8)
        self._bits = np.zeros(1, dtype=np.uint32)

    def decode(self, outs: tuple[np.ndarray, ...]) -> None:
        """Decode codec ``k`` into ``outs[k]`` (float64, shape (count,)), all in one call."""
        _decode_group(self._buf, self.plan, self._bits, outs)

    def encode(self, values: tuple[Any, ...]) -> None:
        """Encode ``values[k]`` (an array of shape (count,) or a scalar) into codec ``k``."""
        _encode_group(self._buf, self.plan, self._bits, values)


def _plan_row(codec: FieldCodec, raw: bool) -> list[float]:
    f, a = codec.field, codec.analog
    kind = _TYPE_CODES[f.type]
    lo, hi = _INT_LIMITS[kind]
    row = [0.0] * 12
    row[_START], row[_COUNT], row[_TYPE] = codec.start, codec.count, kind
    row[_SWAP], row[_S7], row[_SCALE] = float(codec.swap), float(codec.s7), f.scale
    row[_NPC], row[_MIN], row[_MAX] = a.newtons_per_count, a.min_counts, a.max_counts
    row[_LO], row[_HI], row[_RAW] = lo, hi, float(raw)
    return row


@dataclass(frozen=True)
class Span:
    """A contiguous block of holding registers ``start .. start + count - 1``."""

    start: int
    count: int

    @property
    def end(self) -> int:
        return self.start + self.count

    @staticmethod
    def covering(fields: list[RegisterField]) -> Span:
        start = min(f.address for f in fields)
        return Span(start, max(f.end for f in fields) - start)


@dataclass(frozen=True)
class MapLayout:
    """The transfers of one register map: what a driver reads and writes each cycle."""

    inputs: dict[str, RegisterField]
    outputs: dict[str, RegisterField]
    read_span: Span  # the inputs
    write_span: Span  # the outputs


def _overlap(a: RegisterField, b: RegisterField) -> bool:
    return a.address < b.end and b.address < a.end


def check_map(rmap: RegisterMap) -> None:
    """Raise :class:`ConfigError` naming the fields when registers overlap.

    No two fields may share a register, and no written register (the whole write span,
    gaps included, since one function-16/23 write covers it) may be a PLC input register.
    """
    named = {**rmap.inputs(), **rmap.outputs()}
    for (na, a), (nb, b) in combinations(named.items(), 2):
        if _overlap(a, b):
            raise ConfigError(
                f"registers: {na} ({a.address}..{a.end - 1}) overlaps {nb} "
                f"({b.address}..{b.end - 1})"
            )
    write = Span.covering(list(rmap.outputs().values()))
    plc_owned = {k: v for k, v in named.items() if k not in rmap.outputs()}
    for name, f in plc_owned.items():
        if f.address < write.end and write.start < f.end:
            raise ConfigError(
                f"registers: the write span {write.start}..{write.end - 1} covers the PLC's "
                f"{name} ({f.address}..{f.end - 1})"
            )
    for name, f in named.items():
        if f.format == "s7_analog" and f.type != "int16":
            raise ConfigError(f"registers.{name}: format s7_analog needs type int16")


def layout_map(rmap: RegisterMap) -> MapLayout:
    """Check ``rmap`` and compute its spans; spans too long for one transaction are errors."""
    check_map(rmap)
    inputs, outputs = rmap.inputs(), rmap.outputs()
    read_span = Span.covering(list(inputs.values()))
    write_span = Span.covering(list(outputs.values()))
    if read_span.count > MAX_READ_REGISTERS:
        raise ConfigError(
            f"registers: the inputs span {read_span.start}..{read_span.end - 1} "
            f"({read_span.count} registers) exceeds one read ({MAX_READ_REGISTERS})"
        )
    if write_span.count > MAX_WRITE_REGISTERS_FC23:
        raise ConfigError(
            f"registers: the outputs span {write_span.start}..{write_span.end - 1} "
            f"({write_span.count} registers) exceeds one write ({MAX_WRITE_REGISTERS_FC23})"
        )
    return MapLayout(inputs, outputs, read_span, write_span)
