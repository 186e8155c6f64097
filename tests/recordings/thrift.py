"""Thrift compact protocol, as far as a Parquet footer needs it: decode and encode.

A Parquet file ends with its footer (``FileMetaData``, Thrift compact protocol), its length
(4 bytes, little endian) and ``PAR1``. The tests craft hostile footers with it
(``test_parquet_counts.py``), and ``bench/parquet_footer.py`` rewrites a growing file's
footer after every row group: how the recorder wrote Parquet until an Arrow IPC stream
converted at close replaced it (``python -m bench parquet_kill`` compares the two). A struct
is a list of :class:`Field` in the order read; a list is a :class:`Seq`; a map a
:class:`Map`; integers, doubles and bytes are Python values; a bool field carries its value
in ``Field.type`` (1 true, 2 false) and ``value`` None."""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

STOP, TRUE, FALSE, BYTE, I16, I32, I64, DOUBLE, BINARY, LIST, SET, MAP, STRUCT = range(13)
MAX_DEPTH = 64  # a footer nests a few levels; deeper is a hostile file


class ThriftError(ValueError):
    """Malformed compact-protocol bytes."""


@dataclass
class Field:
    id: int
    type: int
    value: Any


@dataclass
class Seq:
    elem: int
    items: list[Any]


@dataclass
class Map:
    key: int
    val: int
    items: list[tuple[Any, Any]]


@dataclass
class Raw:
    """Bytes already encoded (a list of ``count`` structs), written as they are."""

    count: int
    data: bytes


class _In:
    def __init__(self, data: bytes) -> None:
        self.data, self.pos = data, 0

    def byte(self) -> int:
        if self.pos >= len(self.data):
            raise ThriftError("truncated")
        self.pos += 1
        return self.data[self.pos - 1]

    def take(self, n: int) -> bytes:
        if n < 0 or self.pos + n > len(self.data):
            raise ThriftError("truncated")
        self.pos += n
        return self.data[self.pos - n : self.pos]

    def varint(self) -> int:
        shift = result = 0
        while True:
            b = self.byte()
            result |= (b & 0x7F) << shift
            if not b & 0x80:
                return result
            shift += 7
            if shift > 63:
                raise ThriftError("varint too long")

    def zigzag(self) -> int:
        n = self.varint()
        return (n >> 1) ^ -(n & 1)


def _read_value(src: _In, ttype: int, depth: int) -> Any:
    if depth > MAX_DEPTH:
        raise ThriftError("nested too deeply")
    if ttype in (TRUE, FALSE):  # inside a container: one byte
        return src.byte() == TRUE
    if ttype == BYTE:
        return src.byte()
    if ttype in (I16, I32, I64):
        return src.zigzag()
    if ttype == DOUBLE:
        return struct.unpack("<d", src.take(8))[0]
    if ttype == BINARY:
        return src.take(src.varint())
    if ttype in (LIST, SET):
        head = src.byte()
        size, elem = head >> 4, head & 0x0F
        if size == 15:
            size = src.varint()
        if size > len(src.data) - src.pos:  # every element takes at least one byte
            raise ThriftError("list longer than the data")
        return Seq(elem, [_read_value(src, elem, depth + 1) for _ in range(size)])
    if ttype == MAP:
        size = src.varint()
        if size == 0:
            return Map(0, 0, [])
        if 2 * size > len(src.data) - src.pos:
            raise ThriftError("map longer than the data")
        kv = src.byte()
        k, v = kv >> 4, kv & 0x0F
        return Map(
            k,
            v,
            [(_read_value(src, k, depth + 1), _read_value(src, v, depth + 1)) for _ in range(size)],
        )
    if ttype == STRUCT:
        return _read_struct(src, depth + 1)
    raise ThriftError(f"unknown type {ttype}")


def _read_struct(src: _In, depth: int) -> list[Field]:
    fields: list[Field] = []
    last = 0
    while True:
        head = src.byte()
        if head == STOP:
            return fields
        ttype, delta = head & 0x0F, head >> 4
        fid = last + delta if delta else src.zigzag()
        value = None if ttype in (TRUE, FALSE) else _read_value(src, ttype, depth)
        fields.append(Field(fid, ttype, value))
        last = fid


def decode_struct(data: bytes) -> list[Field]:
    """The struct encoded in ``data`` (all of it)."""
    src = _In(data)
    fields = _read_struct(src, 0)
    if src.pos != len(data):
        raise ThriftError(f"{len(data) - src.pos} bytes after the struct")
    return fields


def _varint(out: bytearray, n: int) -> None:
    while True:
        if n < 0x80:
            out.append(n)
            return
        out.append((n & 0x7F) | 0x80)
        n >>= 7


def _zigzag(out: bytearray, n: int) -> None:
    _varint(out, (n << 1) ^ (n >> 63))


def _write_value(out: bytearray, ttype: int, value: Any) -> None:
    if ttype in (TRUE, FALSE):
        out.append(TRUE if value else FALSE)
    elif ttype == BYTE:
        out.append(value & 0xFF)
    elif ttype in (I16, I32, I64):
        _zigzag(out, value)
    elif ttype == DOUBLE:
        out += struct.pack("<d", value)
    elif ttype == BINARY:
        _varint(out, len(value))
        out += value
    elif ttype in (LIST, SET):
        count, elem = (
            (value.count, STRUCT) if isinstance(value, Raw) else (len(value.items), value.elem)
        )
        if count < 15:
            out.append((count << 4) | elem)
        else:
            out.append(0xF0 | elem)
            _varint(out, count)
        if isinstance(value, Raw):
            out += value.data
        else:
            for item in value.items:
                _write_value(out, elem, item)
    elif ttype == MAP:
        _varint(out, len(value.items))
        if value.items:
            out.append((value.key << 4) | value.val)
            for k, v in value.items:
                _write_value(out, value.key, k)
                _write_value(out, value.val, v)
    elif ttype == STRUCT:
        out += encode_struct(value)
    else:
        raise ThriftError(f"unknown type {ttype}")


def encode_struct(fields: list[Field]) -> bytes:
    """The compact-protocol bytes of a struct (field ids in the order given)."""
    out = bytearray()
    last = 0
    for f in fields:
        delta = f.id - last
        if 0 < delta <= 15:
            out.append((delta << 4) | f.type)
        else:
            out.append(f.type)
            _zigzag(out, f.id)
        if f.type not in (TRUE, FALSE):
            _write_value(out, f.type, f.value)
        last = f.id
    out.append(STOP)
    return bytes(out)


def field(fields: list[Field], fid: int) -> Field | None:
    return next((f for f in fields if f.id == fid), None)
