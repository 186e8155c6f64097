"""The Thrift compact codec the Parquet writer rewrites footers with: decode(encode(x)) == x
for generated structs, pyarrow's own footers round-trip byte for byte, and any bytes either
decode or raise ThriftError (never another exception)."""

from __future__ import annotations

import contextlib

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.recordings import thrift
from tests.recordings.thrift import Field, Map, Seq

INTS = st.integers(-(2**63), 2**63 - 1)
SCALARS = {
    thrift.BYTE: st.integers(0, 255),
    thrift.I16: st.integers(-(2**15), 2**15 - 1),
    thrift.I32: st.integers(-(2**31), 2**31 - 1),
    thrift.I64: INTS,
    thrift.DOUBLE: st.floats(allow_nan=False),
    thrift.BINARY: st.binary(max_size=40),
}


def values(depth: int) -> st.SearchStrategy[tuple[int, object]]:
    """(type, value) pairs, containers nested up to ``depth``."""
    scalar = st.sampled_from(sorted(SCALARS)).flatmap(lambda t: SCALARS[t].map(lambda v: (t, v)))
    if depth == 0:
        return scalar
    inner = values(depth - 1)
    seq = st.sampled_from(sorted(SCALARS)).flatmap(
        lambda t: st.lists(SCALARS[t], max_size=20).map(lambda xs: (thrift.LIST, Seq(t, xs)))
    )
    # an empty map carries no key and value types on the wire: maps have entries here
    mp = st.lists(
        st.tuples(SCALARS[thrift.I32], SCALARS[thrift.BINARY]), min_size=1, max_size=5
    ).map(lambda kv: (thrift.MAP, Map(thrift.I32, thrift.BINARY, kv)))
    sub = structs(depth - 1).map(lambda s: (thrift.STRUCT, s))
    return st.one_of(scalar, seq, mp, sub, inner)


def structs(depth: int) -> st.SearchStrategy[list[Field]]:
    def build(items: list[tuple[int, tuple[int, object], bool]]) -> list[Field]:
        out = []
        for fid, (ttype, value), flag in items:
            if ttype == thrift.BYTE and flag:  # a bool field: its value is its type
                out.append(Field(fid, thrift.TRUE if value % 2 else thrift.FALSE, None))
            else:
                out.append(Field(fid, ttype, value))
        return out

    item = st.tuples(st.integers(1, 400), values(depth) if depth else values(0), st.booleans())
    return st.lists(item, max_size=8, unique_by=lambda x: x[0]).map(build)


@settings(max_examples=60, deadline=None)
@given(structs(3))
def test_encode_then_decode_gives_the_struct_back(fields: list[Field]) -> None:
    assert thrift.decode_struct(thrift.encode_struct(fields)) == fields


def test_pyarrows_footer_round_trips_byte_for_byte() -> None:
    sink = pa.BufferOutputStream()
    table = pa.table({"t": np.arange(100.0), "status_1": np.zeros(100)})
    pq.write_table(table, sink, compression="zstd", write_page_index=False)
    data = sink.getvalue().to_pybytes()
    size = int.from_bytes(data[-8:-4], "little")
    footer = data[-8 - size : -8]
    assert thrift.encode_struct(thrift.decode_struct(footer)) == footer


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200))
def test_any_bytes_decode_or_raise_thrift_error(data: bytes) -> None:
    with contextlib.suppress(thrift.ThriftError):
        thrift.decode_struct(data)
