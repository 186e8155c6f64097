"""The register codec and the register-map layout (drivers/registers.py)."""

from __future__ import annotations

import dataclasses
import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal

from drivers.codes import S7_OVERFLOW, S7_UNDERFLOW
from drivers.registers import (
    FieldCodec,
    FieldGroup,
    Span,
    check_map,
    layout_map,
)
from drivers.s7 import S7Analog, window
from gateway.core.config import SensorConfig
from gateway.core.registermap import RegisterField, RegisterMap
from gateway.errors import ConfigError

SENSOR = SensorConfig(range_n=500.0, adc_full_scale=27648)
INT_RANGES = {
    "int16": (-32768, 32767),
    "uint16": (0, 65535),
    "int32": (-(2**31), 2**31 - 1),
    "uint32": (0, 2**32 - 1),
}


def _codec(field: RegisterField, base: int = 0, extra: int = 3) -> tuple[FieldCodec, bytearray]:
    buf = bytearray(2 * (field.end - base + extra))
    return FieldCodec(field, buf, base, 0, SENSOR), buf


@settings(max_examples=60, deadline=None)
@given(
    type_=st.sampled_from(["int16", "uint16", "int32", "uint32"]),
    order=st.sampled_from(["high_first", "low_first"]),
    data=st.data(),
)
def test_integer_round_trip(type_: str, order: str, data: st.DataObject) -> None:
    lo, hi = INT_RANGES[type_]
    values = np.array(data.draw(st.lists(st.integers(lo, hi), min_size=1, max_size=6)), float)
    field = RegisterField(3, len(values), type_, word_order=order)  # type: ignore[arg-type]
    codec, _ = _codec(field, base=1)
    codec.encode(values)
    out = np.zeros(len(values))
    assert_array_equal(codec.decode(out), values)


@settings(max_examples=60, deadline=None)
@given(
    values=st.lists(st.floats(-1e6, 1e6, width=32), min_size=1, max_size=8),
    order=st.sampled_from(["high_first", "low_first"]),
    scale=st.sampled_from([1.0, 0.01, -2.5]),
)
def test_float32_round_trip(values: list[float], order: str, scale: float) -> None:
    field = RegisterField(0, len(values), "float32", word_order=order, scale=scale)  # type: ignore[arg-type]
    codec, _ = _codec(field)
    x = np.array(values)
    codec.encode(x)
    assert_allclose(codec.decode(np.zeros(len(x))), x, rtol=1e-6, atol=1e-30)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-1000.0, 1000.0), min_size=1, max_size=8))
def test_scaled_int16_rounds_to_nearest_step(values: list[float]) -> None:
    field = RegisterField(0, len(values), "int16", scale=0.1)
    codec, _ = _codec(field)
    x = np.array(values)
    codec.encode(x)
    assert_allclose(codec.decode(np.zeros(len(x))), x, atol=0.05 + 1e-9)


def test_word_order_on_the_wire() -> None:
    # 1.5 as float32 is 0x3FC00000: high word 0x3FC0, low word 0x0000
    hi, buf_hi = _codec(RegisterField(0, 1, "float32", word_order="high_first"), extra=0)
    lo, buf_lo = _codec(RegisterField(0, 1, "float32", word_order="low_first"), extra=0)
    hi.encode(1.5)
    lo.encode(1.5)
    assert bytes(buf_hi) == bytes.fromhex("3fc00000")
    assert bytes(buf_lo) == bytes.fromhex("00003fc0")
    i32, buf = _codec(RegisterField(0, 1, "int32", word_order="low_first"), extra=0)
    i32.encode(0x12345678)
    assert bytes(buf) == bytes.fromhex("56781234")


def test_codec_writes_only_its_registers() -> None:
    field = RegisterField(2, 2, "float32")
    codec, buf = _codec(field, base=0, extra=2)
    buf[:] = b"\xff" * len(buf)
    codec.encode(np.array([0.0, 0.0]))
    assert bytes(buf[:4]) == b"\xff" * 4
    assert bytes(buf[4:12]) == bytes(8)
    assert bytes(buf[12:]) == b"\xff" * 4


@pytest.mark.parametrize(
    ("counts", "newtons"),
    [
        (0, 0.0),
        (27648, 500.0),
        (13824, 250.0),
        (32511, 32511 * 500.0 / 27648),
        (-4864, -4864 * 500.0 / 27648),
        (S7_OVERFLOW, np.nan),
        (S7_UNDERFLOW, np.nan),
    ],
)
def test_s7_decode_edge_values(counts: int, newtons: float) -> None:
    codec, _ = _codec(RegisterField(0, 2, "int16", format="s7_analog"))
    codec.encode(np.array([counts, 0]), raw=True)
    out = codec.decode(np.zeros(2))
    assert_allclose(out[0], newtons, rtol=1e-12)
    assert out[1] == 0.0


@pytest.mark.parametrize(
    ("newtons", "counts"),
    [
        (500.0, 27648),
        (0.0, 0),
        (-0.001, 0),
        (580.0, 32072),
        (600.0, S7_OVERFLOW),
        (1e6, S7_OVERFLOW),
        (-1e6, S7_UNDERFLOW),
        (np.nan, S7_OVERFLOW),
    ],
)
def test_s7_encode_saturates_to_codes(newtons: float, counts: int) -> None:
    codec, _ = _codec(RegisterField(0, 1, "int16", format="s7_analog"))
    codec.encode(np.array([newtons]))
    assert codec.decode(np.zeros(1), raw=True)[0] == counts


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(-4864, 32511), min_size=8, max_size=8))
def test_s7_round_trip_in_range(counts: list[int]) -> None:
    codec, _ = _codec(RegisterField(0, 8, "int16", format="s7_analog"))
    codec.encode(np.array(counts), raw=True)
    newtons = codec.decode(np.zeros(8))
    assert_allclose(newtons, np.array(counts) * 500.0 / 27648, rtol=1e-12)
    codec.encode(newtons)  # newtons back to the same counts
    assert_array_equal(codec.decode(np.zeros(8), raw=True), counts)


def test_integer_encode_writes_the_sentinel_never_a_clipped_value() -> None:
    codec, _ = _codec(RegisterField(0, 3, "uint16"))
    codec.encode(np.array([-5.0, 70000.0, np.nan]))  # none fits: the sentinel, 65535
    assert_array_equal(codec.decode(np.zeros(3)), [65535, 65535, 65535])
    codec.encode(np.array([1, 2, 65534], dtype=np.uint16))
    assert_array_equal(codec.decode(np.zeros(3)), [1, 2, 65534])
    raw, _ = _codec(RegisterField(0, 1, "uint16"))
    raw.encode(123456, raw=True)  # raw values (the soft PLC's counts) are clipped
    assert raw.decode_int() == 65535
    signed, _ = _codec(RegisterField(0, 2, "int16", invalid=32767))
    signed.encode(np.array([-32768.0, 32767.0]))  # the sentinel's value itself is refused
    assert_array_equal(signed.decode(np.zeros(2)), [-32768, 32767])
    signed.encode(np.array([32766.0, 40000.0]))
    assert_array_equal(signed.decode(np.zeros(2)), [32766, 32767])


def test_decode_fills_the_given_buffer() -> None:
    codec, _ = _codec(RegisterField(0, 4, "float32"))
    out = np.full(4, 7.0)
    assert codec.decode(out) is out
    assert_array_equal(out, 0.0)


def test_codec_rejects_fields_outside_its_buffer() -> None:
    with pytest.raises(ConfigError, match="do not fit"):
        FieldCodec(RegisterField(10, 4, "float32"), bytearray(8), 0)
    with pytest.raises(ConfigError, match="before the buffer base"):
        FieldCodec(RegisterField(1, 1), bytearray(8), 2)
    with pytest.raises(ConfigError, match="s7_analog needs type int16"):
        FieldCodec(RegisterField(0, 1, "float32", format="s7_analog"), bytearray(8), 0)


def test_default_map_layout() -> None:
    lay = layout_map(RegisterMap())
    assert lay.read_span == Span(0, 53)
    assert lay.write_span == Span(100, 38)
    assert not hasattr(lay, "truth_span")  # the simulation's truth is in no gateway map


@pytest.mark.parametrize(
    ("change", "names"),
    [
        ({"corrected_tensions": RegisterField(52, 8, "float32")}, ("plc_heartbeat", "corrected")),
        ({"wrench": RegisterField(120, 6, "float32")}, ("channel_status", "wrench")),
        ({"gateway_state": RegisterField(52, 1)}, ("gateway_state", "plc_heartbeat")),
    ],
)
def test_overlapping_fields_are_refused(change: dict, names: tuple[str, str]) -> None:
    rmap = dataclasses.replace(RegisterMap(), **change)
    with pytest.raises(ConfigError) as err:
        check_map(rmap)
    assert all(n in str(err.value) for n in names)


def test_write_span_may_not_cover_plc_registers() -> None:
    # the heartbeat sits in a gap of the outputs: one write of 100..137 would clobber it
    rmap = dataclasses.replace(RegisterMap(), plc_heartbeat=RegisterField(125, 1))
    rmap = dataclasses.replace(rmap, gateway_state=RegisterField(138, 1))
    with pytest.raises(ConfigError, match=r"write span 100\.\.138 covers the PLC.s plc_heartbeat"):
        check_map(rmap)


def test_spans_longer_than_one_transaction_are_refused() -> None:
    rmap = dataclasses.replace(RegisterMap(), plc_heartbeat=RegisterField(130 + 200, 1))
    with pytest.raises(ConfigError, match="exceeds one read"):
        layout_map(rmap)


# --- the one S7 codec (drivers/s7.py) -------------------------------------------------
@pytest.mark.parametrize(
    ("counts", "newtons"),
    [
        (32512, np.nan),  # above the overrange: no S7 module sends it
        (32600, np.nan),
        (32766, np.nan),
        (-4865, np.nan),  # below the underrange
        (-5000, np.nan),
        (-32767, np.nan),
        (27649, 27649 * 500.0 / 27648),  # overrange is a measurement
        (-1, -500.0 / 27648),  # underrange too
    ],
)
def test_s7_window_is_the_one_reading(counts: int, newtons: float) -> None:
    analog = S7Analog(500.0)
    assert_allclose(analog.decode_count(counts), newtons, rtol=1e-12)
    assert_allclose(analog.decode(np.array([counts], dtype=np.int16)), [newtons], rtol=1e-12)
    codec, _ = _codec(RegisterField(0, 1, "int16", format="s7_analog"))
    codec.encode(np.array([counts]), raw=True)
    assert_allclose(codec.decode(np.zeros(1)), [newtons], rtol=1e-12)


def test_s7_window_scales_with_the_full_scale() -> None:
    assert window(27648) == (-4864, 32511)
    assert window(10000) == (-1759, 11758)
    assert window(32767) == (-5764, 32766)  # the codes stay codes


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-2000.0, 2000.0) | st.just(math.nan), min_size=1, max_size=16))
def test_s7_encode_then_decode_is_within_half_a_count_or_nan(values: list[float]) -> None:
    analog = S7Analog(500.0)
    x = np.array(values)
    back = analog.decode(analog.encode(x))
    inside = np.isfinite(x) & (x >= -4864 * analog.newtons_per_count)
    inside &= x <= 32511 * analog.newtons_per_count
    assert_allclose(back[inside], x[inside], atol=analog.newtons_per_count / 2 + 1e-9)
    assert np.all(np.isnan(back[~inside]))
    codec, _ = _codec(RegisterField(0, x.size, "int16", format="s7_analog"))
    codec.encode(x)  # the register codec encodes exactly like the S7 codec
    assert_array_equal(codec.decode(np.zeros(x.size), raw=True), analog.encode(x))


def test_plant_adc_uses_the_codec() -> None:
    from sim_plc.plant import counts_to_newton, digitise

    x = np.array([0.0, 250.0, 587.0, 600.0, -100.0, np.nan])
    counts = digitise(x, 500.0, 27648, saturation_n=1e9)
    assert_array_equal(counts, S7Analog(500.0).encode(x))
    assert_allclose(counts_to_newton(counts, 500.0, 27648), S7Analog(500.0).decode(counts))


# --- the one codec against an independent reference (struct, Python floats) ------------
# Every distinct tuple of value types compiles once (numba, cached on disk): the tests use
# groups of four fields so that few signatures are compiled; what varies is the data, the
# field types, word orders, scales, S7 format and raw flags (the plan, not the signature).
GROUP_FIELDS = st.tuples(
    st.sampled_from(["int16", "uint16", "int32", "uint32", "float32"]),
    st.sampled_from(["high_first", "low_first"]),
    st.sampled_from([1.0, 0.01, -2.5, 0.1]),
    st.booleans(),  # s7_analog (int16 only)
    st.booleans(),  # raw
    st.integers(1, 8),
)
FOUR_FIELDS = st.lists(GROUP_FIELDS, min_size=4, max_size=4)
_CODES = {"int16": "h", "uint16": "H", "int32": "i", "uint32": "I", "float32": "f"}
_SENTINEL = {"int16": -32768, "uint16": 65535, "int32": -(2**31), "uint32": 2**32 - 1}


def _group_layout(specs: list[tuple]) -> tuple[list[RegisterField], list[bool], int]:
    fields, raws, address = [], [], 2
    for type_, order, scale, s7, raw, count in specs:
        s7 = s7 and type_ == "int16"
        fields.append(
            RegisterField(
                address,
                count,
                type_,
                word_order=order,
                scale=scale,
                format="s7_analog" if s7 else "plain",
            )
        )
        raws.append(raw)
        address = fields[-1].end + 1  # a gap register between fields
    return fields, raws, 2 * (address + 1)


def _swap(data: bytes, field: RegisterField) -> bytes:
    """The bytes of one value in high-word-first order (32-bit ``low_first`` swapped)."""
    if len(data) == 4 and field.word_order == "low_first":
        return data[2:] + data[:2]
    return data


def _ref_decode(field: RegisterField, buf: bytes, raw: bool) -> list[float]:
    size = 4 if field.words == 2 * field.count else 2
    out = []
    for i in range(field.count):
        at = 2 * field.address + size * i
        (v,) = struct.unpack(">" + _CODES[field.type], _swap(buf[at : at + size], field))
        if field.type == "float32":
            f32 = np.float32(v)
            out.append(
                float(f32) if raw or field.scale == 1.0 else float(f32 * np.float32(field.scale))
            )
        elif raw:
            out.append(float(v))
        elif field.format == "s7_analog":
            analog = S7Analog(500.0)
            ok = analog.min_counts <= v <= analog.max_counts
            out.append(v * analog.newtons_per_count if ok else math.nan)
        else:
            out.append(float(v) if field.scale == 1.0 else v * field.scale)
    return out


def _ref_encode_one(field: RegisterField, x: float, raw: bool) -> bytes:
    code = _CODES[field.type]
    if field.type == "float32":
        f = x if raw else x / field.scale
        return _swap(struct.pack(">f", np.float32(f)), field)  # numpy's cast: inf beyond
    lo, hi = {"h": (-32768, 32767), "H": (0, 65535), "i": (-(2**31), 2**31 - 1)}.get(
        code, (0, 2**32 - 1)
    )
    if raw:
        f = 0 if math.isnan(x) else min(max(np.rint(x), lo), hi)
    elif field.format == "s7_analog":
        n = np.rint(x / S7Analog(500.0).newtons_per_count)
        f = 32767 if math.isnan(n) or n > 32511 else -32768 if n < -4864 else n
    else:
        f = np.rint(x / field.scale)
        s = _SENTINEL[field.type]
        good_lo, good_hi = (s + 1, hi) if s == lo else (lo, s - 1)
        f = s if math.isnan(f) or not good_lo <= f <= good_hi else f
    return _swap(struct.pack(">" + code, int(f)), field)


def _ref_encode(field: RegisterField, value, raw: bool, buf: bytearray) -> None:
    size = 4 if field.words == 2 * field.count else 2
    values = np.broadcast_to(np.asarray(value, dtype=float), (field.count,))
    for i, x in enumerate(values):
        at = 2 * field.address + size * i
        buf[at : at + size] = _ref_encode_one(field, float(x), raw)


@settings(max_examples=80, deadline=None)
@given(specs=FOUR_FIELDS, data=st.binary(min_size=400, max_size=400))
def test_decode_equals_the_reference(specs: list[tuple], data: bytes) -> None:
    fields, raws, size = _group_layout(specs)
    buf = bytearray(data[:size].ljust(size, b"\x00"))
    codecs = [FieldCodec(f, buf, 0, 0, SENSOR) for f in fields]
    outs = tuple(np.full(f.count, 7.0) for f in fields)
    FieldGroup(codecs, raws).decode(outs)
    for codec, raw, got in zip(codecs, raws, outs, strict=True):
        with np.errstate(all="ignore"):  # numpy warns when it casts a signalling NaN
            want = np.array(_ref_decode(codec.field, bytes(buf), raw))
            one = codec.decode(np.zeros(codec.count), raw=raw)  # a codec alone: the same
        assert_array_equal(got, want)  # NaN where NaN
        assert_array_equal(got.view(np.uint64), one.view(np.uint64))


def _floats(n: int) -> st.SearchStrategy[np.ndarray]:
    elems = st.one_of(
        st.floats(allow_nan=True, allow_infinity=True),
        st.floats(-70000.0, 70000.0),  # around the integer types' ranges and S7 counts
        st.integers(-40000, 40000).map(float),
    )
    return st.lists(elems, min_size=n, max_size=n).map(np.array)


@settings(max_examples=120, deadline=None)
@given(specs=FOUR_FIELDS, data=st.data())
def test_encode_equals_the_reference(specs: list[tuple], data: st.DataObject) -> None:
    # the value types of the driver's request: float64 array, uint16 array, int, int
    fields, raws, size = _group_layout(specs)
    counts = [f.count for f in fields]
    values = (
        data.draw(_floats(counts[0])),
        np.array(
            data.draw(st.lists(st.integers(0, 65535), min_size=counts[1], max_size=counts[1])),
            dtype=np.uint16,
        ),
        data.draw(st.integers(-(2**33), 2**33)),
        data.draw(st.integers(0, 70000)),
    )
    want, fused = bytearray(b"\xa5" * size), bytearray(b"\xa5" * size)
    with np.errstate(all="ignore"):  # casts to float32 overflow to inf
        for f, raw, v in zip(fields, raws, values, strict=True):
            _ref_encode(f, v, raw, want)
    FieldGroup([FieldCodec(f, fused, 0, 0, SENSOR) for f in fields], raws).encode(values)
    assert fused == want


@settings(max_examples=60, deadline=None)
@given(specs=FOUR_FIELDS, data=st.data())
def test_encode_float_scalars_and_int_arrays(specs: list[tuple], data: st.DataObject) -> None:
    fields, raws, size = _group_layout(specs)
    counts = [f.count for f in fields]
    values = (
        data.draw(st.floats(allow_nan=True, allow_infinity=True)),
        np.array(
            data.draw(
                st.lists(st.integers(-(2**40), 2**40), min_size=counts[1], max_size=counts[1])
            ),
            dtype=np.int64,
        ),
        data.draw(_floats(counts[2])),
        data.draw(_floats(counts[3])),
    )
    want, fused = bytearray(b"\x5a" * size), bytearray(b"\x5a" * size)
    with np.errstate(all="ignore"):
        for f, raw, v in zip(fields, raws, values, strict=True):
            _ref_encode(f, v, raw, want)
    FieldGroup([FieldCodec(f, fused, 0, 0, SENSOR) for f in fields], raws).encode(values)
    assert fused == want


@settings(max_examples=60, deadline=None)
@given(
    type_=st.sampled_from(["int16", "uint16", "int32", "uint32", "float32"]),
    value=st.integers(0, 2**40),
)
def test_counters_wrap_modulo_their_register(type_: str, value: int) -> None:
    field = RegisterField(0, 1, type_)  # type: ignore[arg-type]
    buf = bytearray(8)
    FieldCodec(field, buf, 0, 0, SENSOR, wrap=True).encode(value)
    bits = 16 if type_ in ("int16", "uint16") else 32
    if type_ == "float32":
        assert struct.unpack(">f", buf[:4])[0] == value % 2**24
    else:
        (got,) = struct.unpack(">" + _CODES[type_].upper(), buf[: bits // 8])
        assert got == value % 2**bits


def test_group_refuses_mixed_buffers_and_wrong_sizes() -> None:
    a, b = bytearray(16), bytearray(16)
    field = RegisterField(0, 2, "float32")
    with pytest.raises(ValueError, match="same buffer"):
        FieldGroup([FieldCodec(field, a, 0), FieldCodec(RegisterField(4, 1), b, 0)])
    group = FieldGroup([FieldCodec(field, a, 0)])
    with pytest.raises(ValueError, match="size"):
        group.decode((np.zeros(3),))
    with pytest.raises(ValueError, match="size"):
        group.encode((np.zeros(1),))
