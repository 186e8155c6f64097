"""Codec between numpy arrays and 16-bit Modbus register words, and register-map layout.

Registers travel big-endian on the wire, so a block of holding registers *is* a byte
string of ``2 * n`` bytes. :class:`FieldCodec` binds one :class:`RegisterField` to a fixed
byte buffer (a driver's preallocated receive or transmit frame, or a server's register
image) and converts between that buffer and a float64 array without allocating per call.

There is one codec: each field is a row of a structured plan (:data:`PLAN`: where it sits,
its type, word order, scale, S7 window, sentinel) and one compiled kernel each way reads
or writes every row of a plan. :class:`FieldCodec` is one row; :class:`FieldGroup` stacks
the rows of several codecs of one buffer so that a cycle's decode or encode is one call
(each small numpy call costs ~0.5-1 us on 8-element arrays).

Types: int16, uint16, int32, uint32, float32. For 32-bit types ``word_order`` says which
16-bit word comes first (``high_first`` is the Modbus convention, and then the bytes are
simply big-endian; ``low_first`` swaps the two words). Plain fields decode as
``value = raw * scale`` and encode as ``raw = round(value / scale)``. An integer field
never clips a value to a plausible number: NaN, infinities and values its type cannot hold
at its scale are written as its sentinel (``invalid``; default the type's minimum if
signed, its maximum if unsigned), and a float32 field writes NaN. Counters (heartbeats)
wrap modulo the register (2**16 or 2**32; 2**24 for float32).

``format: s7_analog`` (Siemens S7 analog values, int16): decoded and encoded by the one S7
codec (:mod:`drivers.s7`: 0..``adc_full_scale`` counts is 0..``range_n`` newtons, over- and
underrange included; the overflow/underflow codes and the counts no S7 module sends decode
as NaN, so the gateway marks the channel invalid); ``scale`` is not applied.

:func:`layout_map` checks a whole :class:`RegisterMap` (no two fields overlap; the write
span never covers a PLC input register) and computes the contiguous spans a driver
transfers: the inputs and the outputs. :func:`check_outputs` refuses an output map that
cannot carry the contract of the output gate (:mod:`drivers.gate`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import combinations
from typing import Any

import numpy as np

from drivers.codes import MODE_RAW, MODE_SCALED, MODE_WRAP
from drivers.s7 import S7Analog
from gateway.core.config import SensorConfig
from gateway.core.registermap import RegisterField, RegisterMap
from gateway.errors import ConfigError

MAX_READ_REGISTERS = 125  # functions 3, 4, 23 (read part)
MAX_WRITE_REGISTERS_FC16 = 123
MAX_WRITE_REGISTERS_FC23 = 121
RANGE_MARGIN = 0.05  # the compensator's: readings down to -5 % of the range are plausible

# --- the one codec: a plan row per field, one compiled kernel each way ------------------
_KINDS = {"int16": 0, "uint16": 1, "int32": 2, "uint32": 3, "float32": 4}
_TYPE_RANGE = {0: (-32768, 32767), 1: (0, 65535), 2: (-(2**31), 2**31 - 1), 3: (0, 2**32 - 1)}
_DEFAULT_INVALID = {0: -32768, 1: 65535, 2: -(2**31), 3: 2**32 - 1}
FLOAT32_MAX = float(np.finfo(np.float32).max)

PLAN = np.dtype(
    [
        ("start", np.int64),  # byte position of the field in the buffer
        ("count", np.int64),
        ("kind", np.int64),  # _KINDS
        ("swap", np.bool_),  # 32-bit values with the low word first
        ("s7", np.bool_),  # format s7_analog
        ("mode", np.int64),  # MODE_SCALED, MODE_RAW (as is, clipped), MODE_WRAP (modulo)
        ("scale", np.float64),
        ("npc", np.float64),  # S7: newtons per count
        ("s7_lo", np.float64),  # S7 window, counts
        ("s7_hi", np.float64),
        ("type_lo", np.float64),  # the type's range
        ("type_hi", np.float64),
        ("good_lo", np.float64),  # raw values a scaled value may take (the sentinel's side
        ("good_hi", np.float64),  # of the type's range excluded)
        ("invalid", np.float64),  # raw value written for "no value" (NaN for float32)
    ]
)


def invalid_raw(field: RegisterField) -> float:
    """The raw value ``field`` holds for "no value": NaN for float32, else the field's
    ``invalid`` sentinel (default: the type's minimum if signed, maximum if unsigned)."""
    kind = _KINDS[field.type]
    if kind == 4:
        return math.nan
    return float(field.invalid if field.invalid is not None else _DEFAULT_INVALID[kind])


def good_raw_band(field: RegisterField) -> tuple[float, float]:
    """The raw values a scaled value may be written as: the type's range on the side of 0
    away from the sentinel (float32: its finite range). A value outside it is invalid."""
    kind = _KINDS[field.type]
    if kind == 4:
        return -FLOAT32_MAX, FLOAT32_MAX
    lo, hi = _TYPE_RANGE[kind]
    s = invalid_raw(field)
    return (float(s + 1), float(hi)) if s < 0 or s == lo else (float(lo), float(s - 1))


def value_band(field: RegisterField) -> tuple[float, float]:
    """The values (after scaling) ``field`` can carry without clipping or the sentinel."""
    lo, hi = good_raw_band(field)
    if field.format == "s7_analog":
        raise ValueError("value_band: S7 fields are read, not written")
    a, b = lo * field.scale, hi * field.scale
    return min(a, b), max(a, b)


def _plan_row(
    field: RegisterField, start: int, swap: bool, mode: int, analog: S7Analog
) -> tuple[Any, ...]:
    """The :data:`PLAN` record of one field, its columns given by name."""
    kind = _KINDS[field.type]
    type_lo, type_hi = _TYPE_RANGE.get(kind, (0, 0))
    good_lo, good_hi = good_raw_band(field)
    row = {
        "start": start,
        "count": field.count,
        "kind": kind,
        "swap": swap,
        "s7": field.format == "s7_analog",
        "mode": mode,
        "scale": field.scale,
        "npc": analog.newtons_per_count,
        "s7_lo": analog.min_counts,
        "s7_hi": analog.max_counts,
        "type_lo": type_lo,
        "type_hi": type_hi,
        "good_lo": good_lo,
        "good_hi": good_hi,
        "invalid": invalid_raw(field),
    }
    return tuple(row[name] for name in PLAN.names or ())


def _kernels() -> Any:
    """:mod:`drivers.kernels`, imported when the first codec is built (numba loads then,
    not with this module)."""
    from drivers import kernels

    return kernels


class FieldCodec:
    """One register field bound to a byte buffer that holds registers from ``base_address``.

    ``buffer`` must stay the same object (and size) for the codec's lifetime; ``offset`` is
    the byte position of register ``base_address`` inside it (e.g. 9 for the data of a
    function-3 reply frame after the MBAP header, function code and byte count).
    ``wrap``: a counter (heartbeat): encoded modulo the register's range, never scaled.
    The codec is the plan row of the field (:data:`PLAN`) and the one compiled kernel each
    way; :class:`FieldGroup` runs the same kernel over several fields at once.
    """

    def __init__(
        self,
        field: RegisterField,
        buffer: bytearray | memoryview,
        base_address: int,
        offset: int = 0,
        sensor: SensorConfig | None = None,
        wrap: bool = False,
    ) -> None:
        if field.address < base_address:
            raise ConfigError(
                f"register {field.address} lies before the buffer base {base_address}"
            )
        start = offset + 2 * (field.address - base_address)
        if start + 2 * field.words > len(buffer):
            raise ConfigError(
                f"registers {field.address}..{field.end - 1} do not fit the buffer "
                f"(base {base_address}, {len(buffer)} bytes)"
            )
        self.s7 = field.format == "s7_analog"
        if self.s7 and field.type != "int16":
            raise ConfigError(f"register {field.address}: format s7_analog needs type int16")
        self.field = field
        self.count = field.count
        self.buffer = buffer
        self.start = start  # byte position of the field in ``buffer``
        self.wrap = wrap
        self.analog = S7Analog.from_sensor(sensor or SensorConfig())
        self.newtons_per_count = self.analog.newtons_per_count
        swap = field.words == 2 * field.count and field.word_order == "low_first"
        scaled = MODE_WRAP if wrap else MODE_SCALED
        raw = MODE_WRAP if wrap else MODE_RAW
        self.plans = {
            mode: np.array([_plan_row(field, start, swap, mode, self.analog)], dtype=PLAN)
            for mode in (scaled, raw)
        }
        self._scaled, self._raw = self.plans[scaled], self.plans[raw]
        self._buf = np.frombuffer(buffer, dtype=np.uint8)
        self._bits = np.zeros(1, dtype=np.uint32)
        self._k = _kernels()

    def plan_row(self, raw: bool = False) -> np.ndarray:
        return (self._raw if raw else self._scaled)[0]

    def decode(self, out: np.ndarray, raw: bool = False) -> np.ndarray:
        """Decode the bound registers into ``out`` (shape (count,), float64).

        ``raw=True`` skips scaling (S7 counts, unscaled integers); otherwise S7 values come
        out in newtons with NaN outside the S7 window.
        """
        self._k.decode_fields(self._buf, self._raw if raw else self._scaled, self._bits, (out,))
        return out

    def decode_int(self, index: int = 0) -> int:
        """One value as a Python int, unscaled (heartbeats, states)."""
        out = np.zeros(self.count)
        return int(self.decode(out, raw=True)[index])

    def encode(self, values: np.ndarray | float, raw: bool = False) -> None:
        """Encode ``values`` (shape (count,) or a scalar) into the bound registers.

        ``raw=True`` writes values as they are (S7 counts, unscaled integers, clipped).
        """
        if isinstance(values, np.ndarray) and values.dtype != np.float64:
            values = values.astype(np.float64)
        elif isinstance(values, int | float | np.integer | np.floating):
            values = float(values)
        self._k.encode_fields(self._buf, self._raw if raw else self._scaled, self._bits, (values,))


class FieldGroup:
    """Several :class:`FieldCodec` of ONE buffer through the one kernel in one call.

    The plan rows of the codecs (``raw`` flag per codec) are stacked: a cycle's decode of
    a reply and encode of a request is one compiled call instead of one per field. The
    first call with a new combination of value types compiles (numba; cached on disk):
    callers warm the group up outside the cycle.
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
        self.plan = np.array([c.plan_row(r) for c, r in zip(codecs, raw, strict=True)], PLAN)
        self._buf = np.frombuffer(buffer, dtype=np.uint8)
        self._bits = np.zeros(1, dtype=np.uint32)
        self._k = _kernels()

    def decode(self, outs: tuple[np.ndarray, ...]) -> None:
        """Decode codec ``k`` into ``outs[k]`` (float64, shape (count,)), all in one call."""
        self._k.decode_fields(self._buf, self.plan, self._bits, outs)

    def encode(self, values: tuple[Any, ...]) -> None:
        """Encode ``values[k]`` (an array of shape (count,) or a scalar) into codec ``k``."""
        self._k.encode_fields(self._buf, self.plan, self._bits, values)


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


def check_outputs(rmap: RegisterMap, sensor: SensorConfig) -> None:
    """Refuse (ConfigError naming the key) an output map that cannot keep the contract.

    ``corrected_tensions`` must carry the sensor's range ``0..range_n`` at its type and
    scale without clipping, and an integer sentinel must not be a plausible tension (it
    must lie below ``-RANGE_MARGIN * range_n`` or above ``range_n``); the wrench's
    sentinel must not be 0; counters and the state are plain unscaled values.
    """
    for name, f in rmap.outputs().items():
        if f.invalid is not None and f.type == "float32":
            raise ConfigError(f"registers.{name}: invalid: float32 writes NaN, no sentinel")
        if f.invalid is not None:
            lo, hi = _TYPE_RANGE[_KINDS[f.type]]
            if not lo <= f.invalid <= hi:
                raise ConfigError(f"registers.{name}: invalid: {f.invalid} is not a {f.type}")
        if f.format == "s7_analog":
            raise ConfigError(f"registers.{name}: format s7_analog is for the raw channels")
    for name in ("gateway_heartbeat", "gateway_state", "channel_status"):
        f = getattr(rmap, name)
        if f.scale != 1.0:
            raise ConfigError(f"registers.{name}: scale must be 1 (a code, not a measurement)")
    if rmap.plc_heartbeat.scale != 1.0 or rmap.plc_heartbeat.format != "plain":
        raise ConfigError("registers.plc_heartbeat: scale must be 1 and format plain")
    t = rmap.corrected_tensions
    low, high = value_band(t)
    if low > 0.0 or high < sensor.range_n:
        raise ConfigError(
            f"registers.corrected_tensions: {t.type} at scale {t.scale:g} carries "
            f"{low:g}..{high:g} N, not the sensor range 0..{sensor.range_n:g} N "
            "(sensor.range_n): choose float32 or a smaller scale"
        )
    if t.type != "float32":
        s = invalid_raw(t) * t.scale
        if -RANGE_MARGIN * sensor.range_n <= s <= sensor.range_n:
            raise ConfigError(
                f"registers.corrected_tensions: invalid: {invalid_raw(t):g} is {s:g} N, a "
                "plausible tension: a sentinel must lie outside the sensor range"
            )
    w = rmap.wrench
    if w.type != "float32" and invalid_raw(w) == 0:
        raise ConfigError("registers.wrench: invalid: 0 is a plausible wrench")
