"""Parquet recordings (docs/recording-format.md, "Parquet"): written row group by row group,
readable after each one; read by column through the CSV reader's checks.

Writing (:class:`ParquetRecordingWriter`, the interface of
:class:`gateway.recordings.writer.RecordingWriter`): every column float64, zstd, the
recording's metadata in the file's key-value metadata and each column's unit in its field
metadata (``unit``). Rows are buffered and written in row groups of ``row_group_rows`` (5 s
at 1 kHz; the last one, at close, may be shorter). pyarrow writes a file's footer only when
it is closed, so a killed writer would leave a file no reader opens; instead each row group
is encoded by pyarrow as a file of its own in memory, and its data pages plus a footer for
every row group so far (the row group's offsets moved to where its pages land,
:mod:`gateway.recordings.thrift`) are written over the previous footer in one ``write``:
after each row group the file on disk is a complete Parquet file (a kill inside that one
``write`` can still cut it; a power loss is not covered: no fsync). A write that fails (a
full disk) puts the previous footer back, so the file keeps every earlier row group. The
file is valid from the start (a footer with the schema and no row group).

Reading (:func:`read_parquet`): the footer is checked before anything is allocated (its
size, the number of rows and columns, every column a number), then each row group is read
column by column straight into the arrays of :class:`gateway.recordings.reader.Recording`
through the same checks and limits as a CSV (time steps, magnitudes, missing values).
Errors name the file, the row (1-based) and the column, like the CSV reader's.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import IO

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from gateway.errors import RecordingError
from gateway.recordings import thrift
from gateway.recordings.thrift import I64, Field, Raw

MAGIC = b"PAR1"
ROW_GROUP_ROWS = 5000  # 5 s at 1 kHz
MAX_FOOTER_BYTES = 64 << 20  # the footer is read whole: refuse a larger one unread
MAX_ROW_GROUP_BYTES = 512 << 20  # uncompressed size of one row group
_UNITS = [
    (re.compile(r"^t$"), "s"),
    (re.compile(r"^velocity_\d+$"), "m/s"),
    (re.compile(r"^tension_\w+_\d+$"), "N"),
    (re.compile(r"^(length_\d+|x|y|z)$"), "m"),
    (re.compile(r"^(rx|ry|rz)$"), "rad"),
    (re.compile(r"^mass$"), "kg"),
    (re.compile(r"^status_\d+$"), "1"),
]
# Parquet's FileMetaData, RowGroup, ColumnChunk and ColumnMetaData field ids (parquet.thrift)
_FMD_NUM_ROWS, _FMD_ROW_GROUPS = 3, 4
_RG_COLUMNS, _RG_FILE_OFFSET, _RG_ORDINAL = 1, 5, 7
_CC_FILE_OFFSET, _CC_META = 2, 3
_CC_INDEX_OFFSETS = (4, 6)  # offset / column index: not written (write_page_index=False)
_CMD_OFFSETS = (9, 10, 11)  # data page, index page, dictionary page
_CMD_BLOOM = 14


def unit_of(name: str) -> str | None:
    """The unit of a recording column (docs/recording-format.md), None if not known."""
    return next((unit for pattern, unit in _UNITS if pattern.match(name)), None)


def schema_for(columns: list[str], metadata: dict[str, str]) -> pa.Schema:
    fields = []
    for name in columns:
        unit = unit_of(name)
        fields.append(pa.field(name, pa.float64(), metadata={"unit": unit} if unit else None))
    return pa.schema(fields, metadata={str(k): str(v) for k, v in metadata.items()})


def _standalone(table: pa.Table) -> bytes:
    """``table`` as one Parquet file of one row group (or none), encoded by pyarrow.

    Measurements (noise on every value) compress poorly as whole float64s; split into
    byte streams (the exponents together, ...) zstd takes ~15 % more off, and the
    dictionary pyarrow would try first (and give up on) costs 3x the time; the status
    columns (three values) keep the dictionary."""
    sink = pa.BufferOutputStream()
    status = [n for n in table.column_names if n.startswith("status_")]
    pq.write_table(
        table,
        sink,
        row_group_size=max(table.num_rows, 1),
        compression="zstd",
        use_dictionary=status,
        use_byte_stream_split=[n for n in table.column_names if n not in status],
        write_page_index=False,
        write_statistics=True,
        store_schema=True,
    )
    return sink.getvalue().to_pybytes()


def _split(data: bytes) -> tuple[bytes, list[Field]]:
    """(the pages between the magic and the footer, the decoded footer)."""
    size = int.from_bytes(data[-8:-4], "little")
    return data[4 : len(data) - 8 - size], thrift.decode_struct(data[len(data) - 8 - size : -8])


def _moved(row_group: list[Field], delta: int, ordinal: int) -> bytes:
    """A row group's encoding with every page offset moved by ``delta`` bytes."""
    for f in row_group:
        if f.id == _RG_FILE_OFFSET:
            f.value += delta
        elif f.id == _RG_ORDINAL:
            f.value = ordinal
        elif f.id == _RG_COLUMNS:
            for chunk in f.value.items:
                for c in chunk:
                    if c.id == _CC_FILE_OFFSET and c.value:
                        c.value += delta
                    elif c.id in _CC_INDEX_OFFSETS:
                        raise AssertionError("page indexes are not written")
                    elif c.id == _CC_META:
                        for m in c.value:
                            if m.id in _CMD_OFFSETS:
                                m.value += delta
                            elif m.id == _CMD_BLOOM:
                                raise AssertionError("bloom filters are not written")
    return thrift.encode_struct(row_group)


class ParquetRecordingWriter:
    """A Parquet recording written in row groups; a complete file after each one.

    ``path``, ``columns``, ``rows``, ``bytes`` (the file's size), :meth:`write_rows` and
    :meth:`close` as :class:`gateway.recordings.writer.RecordingWriter`; ``fileobj``
    replaces the file opened from ``path`` (tests: a full disk); it must be seekable.
    """

    def __init__(
        self,
        path: str | Path,
        columns: list[str],
        metadata: dict[str, str] | None = None,
        fileobj: IO[bytes] | None = None,
        row_group_rows: int = ROW_GROUP_ROWS,
    ) -> None:
        self.path = Path(path)
        self.columns = list(columns)
        self.rows = 0  # rows handed to write_rows
        self.rows_on_disk = 0  # rows in row groups on disk
        self.row_group_rows = max(1, row_group_rows)
        self.schema = schema_for(self.columns, metadata or {})
        self._raw: IO[bytes] = fileobj if fileobj is not None else open(self.path, "w+b")  # noqa: SIM115
        self._pending: list[np.ndarray] = []
        self._pending_rows = 0
        self._groups: list[bytes] = []  # each row group's encoding, offsets in this file
        _, self._template = _split(_standalone(self.schema.empty_table()))
        self._end = 4  # where the next row group's pages go: after the magic
        self._tail = self._footer(0)  # what follows the pages: footer, its length, magic
        self._raw.write(MAGIC + self._tail)
        self._raw.flush()
        self.bytes = self._end + len(self._tail)

    def _footer(self, rows: int) -> bytes:
        """Footer, its length and the magic for the row groups so far, ``rows`` in all."""
        fields = []
        for f in self._template:
            if f.id == _FMD_NUM_ROWS:
                f = Field(f.id, I64, rows)
            elif f.id == _FMD_ROW_GROUPS:
                f = Field(f.id, thrift.LIST, Raw(len(self._groups), b"".join(self._groups)))
            fields.append(f)
        footer = thrift.encode_struct(fields)
        return footer + len(footer).to_bytes(4, "little") + MAGIC

    def _put(self, pages: bytes, rows: int, tail: bytes) -> None:
        """Write ``pages`` and ``tail`` over the previous tail in one write; on failure the
        previous tail goes back (the file stays what it was)."""
        try:
            self._raw.seek(self._end)
            self._raw.write(pages + tail)
            self._raw.truncate()
            self._raw.flush()
        except (OSError, ValueError):
            self._restore()
            raise
        self._end += len(pages)
        self._tail = tail
        self.rows_on_disk += rows
        self.bytes = self._end + len(tail)

    def _restore(self) -> None:
        try:
            self._raw.seek(self._end)
            self._raw.truncate()
            self._raw.write(self._tail)
            self._raw.flush()
        except (OSError, ValueError):
            pass  # the file lacks its footer now: nothing more can be done

    def write_rows(self, table: np.ndarray) -> None:
        """Buffer ``table`` (rows, len(columns)); write each full row group."""
        if table.shape[0] == 0:
            return
        self._pending.append(np.array(table, dtype=np.float64))
        self._pending_rows += table.shape[0]
        self.rows += table.shape[0]
        if self._pending_rows < self.row_group_rows:
            return
        block = np.concatenate(self._pending) if len(self._pending) > 1 else self._pending[0]
        self._pending, self._pending_rows = [block], block.shape[0]
        while self._pending_rows >= self.row_group_rows:
            self._write_group(self.row_group_rows)

    def flush(self) -> None:
        """Write what is buffered as one row group (nothing if nothing is)."""
        if self._pending_rows:
            self._write_group(self._pending_rows)

    def _write_group(self, rows: int) -> None:
        block = np.concatenate(self._pending) if len(self._pending) > 1 else self._pending[0]
        group, rest = block[:rows], block[rows:]
        table = pa.Table.from_arrays(
            [pa.array(group[:, c]) for c in range(group.shape[1])], schema=self.schema
        )
        pages, footer = _split(_standalone(table))
        groups = thrift.field(footer, _FMD_ROW_GROUPS)
        assert groups is not None and len(groups.value.items) == 1
        self._groups.append(_moved(groups.value.items[0], self._end - 4, len(self._groups)))
        try:
            self._put(pages, rows, self._footer(self.rows_on_disk + rows))
        except BaseException:
            self._groups.pop()
            raise
        self._pending, self._pending_rows = ([rest] if len(rest) else []), len(rest)

    def close(self) -> None:
        try:
            self.flush()
        finally:
            self._raw.close()


# --- reading ------------------------------------------------------------------------------
def _one_line(exc: BaseException) -> str:
    """pyarrow's message on one line (some span two: 'Couldn't deserialize thrift ...')."""
    return " ".join(str(exc).split())


def _open(path: Path) -> pq.ParquetFile:
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            fh.seek(max(0, size - 8))
            end = fh.read(8)
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    if size < 12 or end[4:] != MAGIC:
        raise RecordingError(f"{path}: not a Parquet file (no footer: cut short or not Parquet)")
    footer = int.from_bytes(end[:4], "little")
    if footer > min(MAX_FOOTER_BYTES, size - 12):
        raise RecordingError(f"{path}: Parquet footer of {footer} bytes (limit {MAX_FOOTER_BYTES})")
    try:
        return pq.ParquetFile(
            path,
            pre_buffer=False,
            thrift_string_size_limit=MAX_FOOTER_BYTES,
            thrift_container_size_limit=1 << 20,
        )
    except (pa.ArrowException, OSError) as exc:
        raise RecordingError(f"{path}: not a readable Parquet file: {_one_line(exc)}") from exc
    except UnicodeDecodeError as exc:  # pyarrow decodes the schema's names as it opens
        raise RecordingError(
            f"{path}: not a readable Parquet file: text in its footer is not UTF-8 "
            f"(byte {exc.object[exc.start : exc.start + 1]!r})"
        ) from exc


def parquet_metadata(path: Path, pf: pq.ParquetFile, max_items: int, max_chars: int):
    """The file's key-value metadata as text (pyarrow's own ``ARROW:schema`` left out)."""
    raw = pf.schema_arrow.metadata or {}
    meta: dict[str, str] = {}
    for key, value in raw.items():
        if key.startswith(b"ARROW:"):
            continue
        if len(meta) >= max_items:
            raise RecordingError(f"{path}: more than {max_items} metadata entries")
        if len(key) + len(value) > max_chars:
            raise RecordingError(f"{path}: metadata {key[:40]!r}: longer than {max_chars} bytes")
        meta[key.decode("utf-8", "replace")] = value.decode("utf-8", "replace")
    return meta


def check_schema(path: Path, pf: pq.ParquetFile, max_columns: int) -> list[str]:
    """Column names; every column a number (integers, floats, bools), nothing nested."""
    schema = pf.schema_arrow
    if len(schema) > max_columns:
        raise RecordingError(f"{path}: more than {max_columns} columns")
    seen: set[str] = set()
    for f in schema:
        if not f.name or f.name in seen:
            why = "appears twice" if f.name else "has no name"
            raise RecordingError(f"{path}: schema: column {f.name!r} {why}")
        seen.add(f.name)
        t = f.type
        if not (pa.types.is_integer(t) or pa.types.is_floating(t) or pa.types.is_boolean(t)):
            raise RecordingError(f"{path}: schema: column {f.name!r}: type {t} is not a number")
    return list(schema.names)


def iter_row_groups(path: Path, pf: pq.ParquetFile, names: list[str]):
    """(first row, 1-based, and the row group as a (rows, columns) float array), one row
    group at a time, each column read by itself; nulls become NaN."""
    md = pf.metadata
    first = 1
    for i in range(md.num_row_groups):
        group = md.row_group(i)
        if first - 1 + group.num_rows > md.num_rows:  # checked against the limit before
            raise RecordingError(f"{path}: row group {i}: more rows than the file says it has")
        if group.total_byte_size > MAX_ROW_GROUP_BYTES:
            raise RecordingError(
                f"{path}: row group {i}: {group.total_byte_size} bytes (limit "
                f"{MAX_ROW_GROUP_BYTES}); write smaller row groups"
            )
        block = np.empty((group.num_rows, len(names)))
        for c, name in enumerate(names):
            try:
                col = pf.read_row_group(i, columns=[name], use_threads=False).column(0)
            except (pa.ArrowException, OSError) as exc:
                raise RecordingError(
                    f"{path}: row group {i} (row {first} on): column {name!r}: cannot read: "
                    f"{_one_line(exc)}"
                ) from exc
            if len(col) != group.num_rows:  # the pages hold another count than the footer
                raise RecordingError(
                    f"{path}: row group {i}: column {name!r}: {len(col)} values decoded for "
                    f"{group.num_rows} rows"
                )
            block[:, c] = col.to_numpy(zero_copy_only=False).astype(np.float64, copy=False)
        yield first, block
        first += group.num_rows


def check_counts(path: Path, pf: pq.ParquetFile) -> None:
    """Trust no count the footer states: the file's rows are the sum of its row groups',
    each row group's rows are every column chunk's values (flat columns: one value, or
    null, per row), no count is negative, and every column chunk lies inside the file.
    A lying count crashed the reader (numpy: negative dimensions) or dropped rows silently
    (a row group claiming 7 000 of its 12 000 rows); now it is one line naming the row
    group, and :func:`iter_row_groups` checks each column read against it again."""
    md = pf.metadata
    size = path.stat().st_size
    if md.num_rows < 0:
        raise RecordingError(f"{path}: the footer claims {md.num_rows} rows")
    total = 0
    for i in range(md.num_row_groups):
        group = md.row_group(i)
        rows = group.num_rows
        if rows < 0:
            raise RecordingError(f"{path}: row group {i}: claims {rows} rows")
        total += rows
        for c in range(group.num_columns):
            chunk = group.column(c)
            where = f"{path}: row group {i}: column {chunk.path_in_schema!r}"
            if chunk.num_values != rows:
                raise RecordingError(
                    f"{where}: {chunk.num_values} values for the group's {rows} rows"
                )
            start = chunk.data_page_offset
            if chunk.has_dictionary_page and chunk.dictionary_page_offset is not None:
                start = min(start, chunk.dictionary_page_offset)
            length = chunk.total_compressed_size
            if start < 4 or length < 0 or start + length > size - 8:
                raise RecordingError(
                    f"{where}: its pages ({start}, {length} bytes) lie outside the {size}-byte file"
                )
    if total != md.num_rows:
        raise RecordingError(
            f"{path}: the footer claims {md.num_rows} rows, its row groups hold {total}"
        )


def open_checked(path: Path, max_columns: int) -> tuple[pq.ParquetFile, list[str]]:
    """The file and its column names, the footer, its counts and the schema checked."""
    pf = _open(path)
    names = check_schema(path, pf, max_columns)
    try:
        check_counts(path, pf)
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    return pf, names
