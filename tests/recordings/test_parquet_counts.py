"""A Parquet footer's counts are not trusted (issue 30 item 4): any one count made to lie
(the file's rows, a row group's rows, a column chunk's values, a chunk's place in the file)
is a one-line refusal naming the file and the row group, or the file reads whole; it is
never read with rows missing or added, and never a traceback. The lies are written with
the project's own Thrift codec into a file pyarrow wrote."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gateway.errors import RecordingError
from gateway.recordings.reader import read_recording
from tests.recordings import thrift

ROWS, GROUPS = 300, 3
COLUMNS = ["t", "velocity_1", "tension_sensor_1", "tension_platform_1"]
# FileMetaData.num_rows / row_groups; RowGroup.columns / num_rows; ColumnChunk.meta_data;
# ColumnMetaData.num_values / total_compressed_size / data_page_offset
FMD_ROWS, FMD_GROUPS, RG_COLUMNS, RG_ROWS, CC_META = 3, 4, 1, 3, 3
CMD_VALUES, CMD_COMPRESSED, CMD_DATA_PAGE = 5, 7, 9


@pytest.fixture(scope="module")
def honest(tmp_path_factory) -> Path:
    rng = np.random.default_rng(1)
    data = {c: rng.normal(100, 10, ROWS) for c in COLUMNS}
    data["t"] = np.arange(ROWS) * 1e-3
    path = tmp_path_factory.mktemp("pq") / "honest.parquet"
    pq.write_table(pa.table(data), path, row_group_size=ROWS // GROUPS, compression="none")
    return path


def lie(data: bytes, where: str, group: int, column: int, value: int) -> bytes:
    """``data`` with one count of its footer replaced by ``value``."""
    size = int.from_bytes(data[-8:-4], "little")
    footer = thrift.decode_struct(data[len(data) - 8 - size : -8])
    if where == "file_rows":
        thrift.field(footer, FMD_ROWS).value = value  # type: ignore[union-attr]
    else:
        rg = thrift.field(footer, FMD_GROUPS).value.items[group]  # type: ignore[union-attr]
        if where == "group_rows":
            thrift.field(rg, RG_ROWS).value = value  # type: ignore[union-attr]
        else:
            chunk = thrift.field(rg, RG_COLUMNS).value.items[column]  # type: ignore[union-attr]
            meta = thrift.field(chunk, CC_META).value  # type: ignore[union-attr]
            fid = {"values": CMD_VALUES, "compressed": CMD_COMPRESSED, "page": CMD_DATA_PAGE}
            thrift.field(meta, fid[where]).value = value  # type: ignore[union-attr]
    new = thrift.encode_struct(footer)
    return data[: len(data) - 8 - size] + new + len(new).to_bytes(4, "little") + b"PAR1"


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    where=st.sampled_from(["file_rows", "group_rows", "values", "compressed", "page"]),
    group=st.integers(0, GROUPS - 1),
    column=st.integers(0, len(COLUMNS) - 1),
    value=st.one_of(
        st.integers(-(2**40), -1),
        st.integers(0, 2 * ROWS),
        st.integers(2 * ROWS, 2**40),
    ),
)
def test_a_lying_count_is_refused_or_harmless(tmp_path, honest, where, group, column, value):
    path = tmp_path / "lying.parquet"
    path.write_bytes(lie(honest.read_bytes(), where, group, column, value))
    try:
        rec = read_recording(path)
    except RecordingError as exc:
        text = str(exc)
        assert text.startswith(str(path)) and "\n" not in text, text
        if where != "file_rows":
            assert f"row group {group}" in text or "not a readable Parquet" in text, text
        return
    # read: then whole, every row as written
    assert rec.t.size == ROWS
    np.testing.assert_array_equal(rec.t, np.arange(ROWS) * 1e-3)


@pytest.mark.parametrize(
    ("where", "value", "says"),
    [
        ("group_rows", -1, "row group 1: claims -1 rows"),
        ("group_rows", 70, "row group 1: column 't': 100 values for the group's 70 rows"),
        ("group_rows", 200, "values for the group's 200 rows"),
        ("values", 0, "row group 1: column 'tension_sensor_1': 0 values"),
        ("values", -1, "-1 values"),
        ("file_rows", 250, "claims 250 rows, its row groups hold 300"),
    ],
)
def test_the_holes_of_the_hostile_round(tmp_path, honest, where, value, says):
    """Each crashed `export` and `diagnose` with a numpy traceback or read 7000 of 12000
    rows on main."""
    path = tmp_path / "lying.parquet"
    path.write_bytes(lie(honest.read_bytes(), where, 1, 2 if where == "values" else 0, value))
    with pytest.raises(RecordingError, match=says.replace("(", r"\(").replace(")", r"\)")):
        read_recording(path)
