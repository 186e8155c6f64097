"""Writing recording files in whole rows: :class:`RecordingWriter`, :func:`format_rows` and
:func:`open_writer` (CSV, or Parquet by :mod:`gateway.recordings.parquet` for ``.parquet``).

The CSV (or ``.csv.gz``) layout is docs/recording-format.md's: ``# key: value`` metadata
lines, the header, then rows; NaN and +-inf are written as empty fields. Used by
:func:`gateway.recordings.reader.write_recording` and by the gateway's recorder; also importable
from :mod:`gateway.recordings.reader`.
"""

from __future__ import annotations

import gzip
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


class RecordingWriter:
    """A recording file written in whole rows: metadata and header, then row batches.

    Every :meth:`write_rows` call writes complete lines in one ``write``; :meth:`close`
    ends the file (the gzip trailer for ``.gz``). ``fileobj`` replaces the file opened
    from ``path`` (tests: a slow or full disk). ``compresslevel`` 1 is 5x faster than 6
    for 17 % more bytes (the gateway's recorder uses 1).
    """

    def __init__(
        self,
        path: str | Path,
        columns: list[str],
        metadata: dict[str, str] | None = None,
        fileobj: IO[bytes] | None = None,
        compresslevel: int = 6,
    ) -> None:
        self.path = Path(path)
        self.columns = list(columns)
        self.rows = 0
        self.bytes = 0
        raw: IO[bytes] = fileobj if fileobj is not None else open(self.path, "wb")  # noqa: SIM115
        self._raw = raw
        self._fh: IO[bytes] | gzip.GzipFile = raw
        if self.path.suffix == ".gz":
            self._fh = gzip.GzipFile(
                filename=self.path.name, mode="wb", fileobj=raw, compresslevel=compresslevel
            )
        head = "".join(f"# {k}: {v}\n" for k, v in (metadata or {}).items())
        self._write(head + ",".join(self.columns) + "\n")

    def _write(self, text: str) -> None:
        data = text.encode("utf-8")
        self._fh.write(data)
        self.bytes += len(data)

    @property
    def rows_on_disk(self) -> int:
        """Rows written to the file (all of them: a row is never held back)."""
        return self.rows

    def write_rows(self, table: np.ndarray) -> None:
        """Write ``table`` (rows, len(columns)) as whole rows."""
        if table.shape[0]:
            self._write(format_rows(table))
            self.rows += table.shape[0]
            if self._fh is self._raw:  # plain CSV: the rows are on disk or the write failed
                self._fh.flush()

    def close(self) -> None:
        try:
            if self._fh is not self._raw:
                self._fh.close()
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
