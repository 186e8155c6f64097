"""Parquet recordings (docs/recording-format.md, "Parquet"): written as an append-only Arrow
IPC stream while recording and converted to Parquet at close; read by column through the
CSV reader's checks.

Writing (:class:`ParquetRecordingWriter`, the interface of
:class:`gateway.recordings.writer.RecordingWriter`): every column float64, the recording's
metadata in the schema's key-value metadata and each column's unit in its field metadata
(``unit``). Each :meth:`~ParquetRecordingWriter.write_rows` appends one record batch to
``NAME.parquet.arrows`` (:func:`stream_path`) and flushes it: a writer killed at any moment
(SIGKILL, inside a write or not) leaves every batch before the one it was writing.
:meth:`~ParquetRecordingWriter.close` converts the stream to ``NAME.parquet`` (zstd, row
groups of ``row_group_rows``, one row group in memory at a time; written under a temporary
name and renamed, so a Parquet file on disk is always whole) and removes the stream. A
stream left by a killed writer is converted the same way the next time the recording is
opened (:func:`recover`, from :func:`open_checked`: ``diagnose``, ``export``), its cut last
batch dropped with one warning. Chosen by measurement over rewriting the footer after every
row group with a hand-written Thrift codec, as before (``python -m bench parquet_kill``,
docs/recording-format.md: 0 rows lost to a SIGKILL against up to 1 s with 1-s row groups,
11.4 against 22.1 us of CPU per row over a 600-s file, and no footer growing by 5.7 kB per
row group, rewritten whole after each).

Reading (:func:`read_parquet`): the footer is checked before anything is allocated (its
size, the number of rows and columns, every column a number), then each row group is read
column by column straight into the arrays of :class:`gateway.recordings.reader.Recording`
through the same checks and limits as a CSV (time steps, magnitudes, missing values).
Errors name the file, the row (1-based) and the column, like the CSV reader's.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import IO

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from gateway.errors import RecordingError

log = logging.getLogger("cdpr_gateway.recordings")
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


def unit_of(name: str) -> str | None:
    """The unit of a recording column (docs/recording-format.md), None if not known."""
    return next((unit for pattern, unit in _UNITS if pattern.match(name)), None)


def schema_for(columns: list[str], metadata: dict[str, str]) -> pa.Schema:
    fields = []
    for name in columns:
        unit = unit_of(name)
        fields.append(pa.field(name, pa.float64(), metadata={"unit": unit} if unit else None))
    return pa.schema(fields, metadata={str(k): str(v) for k, v in metadata.items()})


STREAM_SUFFIX = ".arrows"  # the Arrow IPC stream of a recording being written
END_OF_STREAM = b"\xff\xff\xff\xff\x00\x00\x00\x00"  # IPC: continuation, length 0


def stream_path(path: Path) -> Path:
    """Where the recording ``path`` is written until it is closed."""
    return path.with_name(path.name + STREAM_SUFFIX)


class ParquetRecordingWriter:
    """A Parquet recording: an Arrow IPC stream (the schema's message, then one record
    batch's message per :meth:`write_rows`, each in one ``write``, then the end-of-stream
    marker), converted to ``path`` at :meth:`close`.

    ``path``, ``columns``, ``rows``, ``rows_on_disk``, ``bytes`` (the stream's size),
    :meth:`write_rows` and :meth:`close` as :class:`gateway.recordings.writer.RecordingWriter`;
    ``fileobj`` replaces the stream's file opened from ``path`` (tests: a full disk).
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
        self.rows_on_disk = 0  # rows in complete batches of the stream
        self.row_group_rows = max(1, row_group_rows)
        self.schema = schema_for(self.columns, metadata or {})
        self.stream = stream_path(self.path)
        self._raw: IO[bytes] = fileobj if fileobj is not None else open(self.stream, "wb")  # noqa: SIM115
        self._raw.write(self.schema.serialize().to_pybytes())  # the stream's first message
        self._raw.flush()
        self.bytes = self._raw.tell()

    def write_rows(self, table: np.ndarray) -> None:
        """Append ``table`` (rows, len(columns)) as one record batch, in one ``write``."""
        if table.shape[0] == 0:
            return
        cols = np.ascontiguousarray(np.asarray(table, dtype=np.float64).T)
        batch = pa.RecordBatch.from_arrays([pa.array(c) for c in cols], schema=self.schema)
        self.rows += table.shape[0]
        self._raw.write(batch.serialize().to_pybytes())
        self._raw.flush()
        self.rows_on_disk = self.rows
        self.bytes = self._raw.tell()

    def close(self) -> None:
        """End the stream and convert it to ``path`` (nothing is lost if that fails: the
        stream stays, and :func:`recover` converts it when the recording is opened)."""
        try:
            self._raw.write(END_OF_STREAM)
            self._raw.flush()
        finally:
            self._raw.close()
        if self.stream.exists():  # not a test's file object
            convert(self.stream, self.path, self.row_group_rows)


def _parquet_writer(sink: str | Path, schema: pa.Schema) -> pq.ParquetWriter:
    """zstd; the measurements (noise on every value) split into byte streams (the exponents
    together, ...), which zstd takes ~15 % more off, no dictionary (pyarrow would try one
    first and give up on it, at 3x the time); the status columns (three values) keep it."""
    status = [n for n in schema.names if n.startswith("status_")]
    return pq.ParquetWriter(
        str(sink),
        schema,
        compression="zstd",
        use_dictionary=status,
        use_byte_stream_split=[n for n in schema.names if n not in status],
        write_statistics=True,
        store_schema=True,
    )


def convert(stream: Path, path: Path, row_group_rows: int = ROW_GROUP_ROWS) -> tuple[int, bool]:
    """The IPC ``stream`` written as the Parquet file ``path`` (under ``path.tmp``, then
    renamed), the stream removed; (rows, whether a cut last batch was dropped). Every
    complete batch is kept; one cut short by a kill ends the stream. Raises
    :class:`RecordingError` for a file that is no stream."""
    tmp = path.with_name(path.name + ".tmp")
    rows, cut, pending, held = 0, False, [], 0
    try:
        with pa.OSFile(str(stream), "rb") as src:
            try:
                reader = pa.ipc.open_stream(src)
            except (pa.ArrowInvalid, OSError) as exc:
                raise RecordingError(f"{stream}: not an Arrow stream: {_one_line(exc)}") from exc
            with _parquet_writer(tmp, reader.schema) as out:
                while True:
                    try:
                        batch = reader.read_next_batch()
                    except StopIteration:
                        break
                    except (pa.ArrowInvalid, OSError):  # cut by a kill: the end
                        cut = True
                        break
                    pending.append(batch)
                    held += batch.num_rows
                    if held >= row_group_rows:  # whole row groups out, the rest held
                        table = pa.Table.from_batches(pending).combine_chunks()  # a page
                        n = held - held % row_group_rows  # per column, not one per batch
                        out.write_table(table.slice(0, n), row_group_rows)
                        rest = table.slice(n)
                        rows, pending, held = rows + n, rest.to_batches(), rest.num_rows
                if held or rows == 0:
                    last = pa.Table.from_batches(pending, reader.schema).combine_chunks()
                    out.write_table(last, row_group_rows)
                    rows += held
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    stream.unlink()
    return rows, cut


def recover(path: Path) -> None:
    """The stream of a writer killed before it closed ``path``, converted to ``path``, with
    one warning (nothing when ``path`` exists or there is no stream)."""
    stream = stream_path(path)
    if path.exists() or not stream.exists():
        return
    try:
        rows, cut = convert(stream, path)
    except OSError as exc:
        raise RecordingError(
            f"{path}: cannot convert the stream {stream.name} left by an unclean stop: "
            f"{exc.strerror or exc}"
        ) from exc
    last = ""
    if rows and "t" in pq.read_schema(path).names:
        t = pq.read_table(path, columns=["t"]).column(0)
        last = f" to t = {t[-1].as_py():.3f} s"
    log.warning(
        "%s: ends after an unclean stop: %d rows%s recovered from %s%s",
        path,
        rows,
        last,
        stream.name,
        ", the last partial batch dropped" if cut else "",
    )


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
    """The file and its column names, the footer, its counts and the schema checked; a
    recording whose writer was killed is converted from its stream first (:func:`recover`)."""
    recover(path)
    pf = _open(path)
    names = check_schema(path, pf, max_columns)
    try:
        check_counts(path, pf)
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    return pf, names
