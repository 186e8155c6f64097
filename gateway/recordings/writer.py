"""Writing recording files in whole rows: :class:`RecordingWriter`, :func:`format_rows` and
:func:`open_writer` (CSV, or Parquet by :mod:`gateway.recordings.parquet` for ``.parquet``).

The CSV (or ``.csv.gz``) layout is docs/recording-format.md's: ``# key: value`` metadata
lines, the header, then rows; NaN and +-inf are written as empty fields. Used by
:func:`gateway.recordings.reader.write_recording` and by the gateway's recorder; also importable
from :mod:`gateway.recordings.reader`.
"""

from __future__ import annotations

import gzip
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Protocol

import numpy as np


def format_rows(table: np.ndarray, fmt: str = "%.10g") -> str:
    """Whole CSV rows (each ending in a newline); NaN and +-inf become empty fields."""
    if table.shape[0] == 0:
        return ""
    row = ",".join([fmt] * table.shape[1]) + "\n"
    text = "".join([row % tuple(r) for r in table.tolist()])
    if "n" in text:  # 'nan', 'inf' (digits and 'e' are all a number can hold otherwise)
        text = text.replace("-inf", "").replace("inf", "").replace("nan", "")
    return text


class RowWriter(Protocol):
    """What the recorder and :func:`gateway.recordings.reader.write_recording` write with."""

    path: Path
    columns: list[str]
    rows: int  # rows handed to write_rows
    bytes: int  # the file's size so far

    @property
    def rows_on_disk(self) -> int: ...

    def write_rows(self, table: np.ndarray) -> None: ...

    def close(self) -> None: ...


MEMBER_S = 1.0  # a .gz recording is a series of gzip members: one closed at least this often
MEMBER_BYTES = 4 << 20  # ... or when this much text is waiting


class RecordingWriter:
    """A recording file written in whole rows: metadata and header, then row batches.

    Plain CSV: every :meth:`write_rows` call writes complete lines in one ``write``. ``.gz``:
    a series of complete gzip members (concatenated members are plain gzip: ``zcat``, any
    reader), one closed at least every ``MEMBER_S`` of writing (or ``MEMBER_BYTES`` of
    text) and at :meth:`close`, each holding whole rows; a writer killed at any moment
    leaves every member before the one it was writing, so the reader
    (:class:`gateway.recordings.reader.GzipMembers`) loses at most the last second. One
    gzip stream closed only at the end, before, lost the whole file to a kill.
    ``fileobj`` replaces the file opened from ``path`` (tests: a slow or full disk).
    ``compresslevel`` 1 is 5x faster than 6 for 17 % more bytes (the gateway's recorder
    uses 1).
    """

    def __init__(
        self,
        path: str | Path,
        columns: list[str],
        metadata: dict[str, str] | None = None,
        fileobj: IO[bytes] | None = None,
        compresslevel: int = 6,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.path = Path(path)
        self.columns = list(columns)
        self.rows = 0
        self.bytes = 0
        raw: IO[bytes] = fileobj if fileobj is not None else open(self.path, "wb")  # noqa: SIM115
        self._raw = raw
        self._gz = self.path.suffix == ".gz"
        self._level = compresslevel
        self._clock = clock
        self._held: list[bytes] = []  # text of the member being gathered
        self._held_bytes = 0
        self._held_rows = 0
        self._member_at = clock()
        head = "".join(f"# {k}: {v}\n" for k, v in (metadata or {}).items())
        self._write(head + ",".join(self.columns) + "\n")

    def _write(self, text: str) -> None:
        data = text.encode("utf-8")
        self.bytes += len(data)
        if not self._gz:
            self._raw.write(data)
            return
        self._held.append(data)
        self._held_bytes += len(data)

    def _member(self) -> None:
        """Close the member being gathered: compressed whole, written in one ``write``."""
        if self._held:
            self._raw.write(gzip.compress(b"".join(self._held), self._level, mtime=0))
            self._raw.flush()
        self._held, self._held_bytes, self._held_rows = [], 0, 0
        self._member_at = self._clock()

    @property
    def rows_on_disk(self) -> int:
        """Rows written to the file (``.gz``: in closed members)."""
        return self.rows - self._held_rows

    def write_rows(self, table: np.ndarray) -> None:
        """Write ``table`` (rows, len(columns)) as whole rows."""
        if table.shape[0]:
            self._write(format_rows(table))
            self.rows += table.shape[0]
            if not self._gz:  # plain CSV: the rows are on disk or the write failed
                self._raw.flush()
                return
            self._held_rows += table.shape[0]
            due = self._clock() - self._member_at >= MEMBER_S
            if due or self._held_bytes >= MEMBER_BYTES:
                self._member()

    def close(self) -> None:
        try:
            if self._gz:
                self._member()
        finally:
            self._raw.close()


def open_writer(
    path: str | Path,
    columns: list[str],
    metadata: dict[str, str] | None = None,
    *,
    compresslevel: int = 6,
    row_group_rows: int | None = None,
) -> RowWriter:
    """The writer the file name asks for: Parquet for ``.parquet`` (pyarrow, imported only
    then; ``row_group_rows``), else CSV (gzip for ``.gz``; ``compresslevel``)."""
    if Path(path).suffix == ".parquet":
        from gateway.recordings.parquet import ROW_GROUP_ROWS, ParquetRecordingWriter

        rows = ROW_GROUP_ROWS if row_group_rows is None else row_group_rows
        return ParquetRecordingWriter(path, columns, metadata, row_group_rows=rows)
    return RecordingWriter(path, columns, metadata, compresslevel=compresslevel)
