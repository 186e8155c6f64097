"""The footer-rewriting Parquet writer the recorder used until issue 30 item 3, kept as the
reference of ``python -m bench parquet_kill``: each row group encoded by pyarrow as a file
of its own in memory, its pages plus a footer for every row group so far (offsets moved,
with the Thrift codec of ``tests/recordings/thrift.py``) written over the previous footer
in one ``write``. A complete Parquet file after every row group; the footer grows by
~5.7 kB per row group (57 columns) and is rewritten whole every time."""

from __future__ import annotations

from pathlib import Path
from typing import IO

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from gateway.recordings.parquet import ROW_GROUP_ROWS, schema_for
from tests.recordings import thrift
from tests.recordings.thrift import I64, Field, Raw

MAGIC = b"PAR1"
# Parquet's FileMetaData, RowGroup, ColumnChunk and ColumnMetaData field ids (parquet.thrift)
_FMD_NUM_ROWS, _FMD_ROW_GROUPS = 3, 4
_RG_COLUMNS, _RG_FILE_OFFSET, _RG_ORDINAL = 1, 5, 7
_CC_FILE_OFFSET, _CC_META = 2, 3
_CC_INDEX_OFFSETS = (4, 6)  # offset / column index: not written (write_page_index=False)
_CMD_OFFSETS = (9, 10, 11)  # data page, index page, dictionary page
_CMD_BLOOM = 14


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


class FooterRewritingWriter:
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
