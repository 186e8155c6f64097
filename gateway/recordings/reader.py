"""Recordings in and out: plain CSV (or .csv.gz), docs/recording-format.md.

A recording is refused whole with :class:`RecordingError` naming file, line and column when
it is malformed (no ``t``, ``t`` not strictly increasing, a cable with only some of its
required columns, text in a number field). A row with a missing required value is skipped
and counted (``Recording.skipped_rows``), never filled in; a missing optional value is NaN.

Hostile input is bounded before anything is allocated for it: cable indices must be
contiguous ``1..m`` with ``m <= MAX_CABLES``, written in ASCII digits without leading
zeros (``velocity_01``, ``velocity_١`` are refused, not read as cable 1); a line longer
than ``MAX_LINE_CHARS``, more than ``MAX_COLUMNS`` columns, ``MAX_METADATA_LINES``
metadata lines or ``MAX_METADATA_CHARS`` characters of metadata in all, a time step below
``MIN_STEP_S``, a value beyond ``MAX_ABS_VALUE`` (``MAX_ABS_TIME_S`` for ``t``), a
non-finite value, fewer than ``min_samples`` kept rows or more than ``max_samples`` rows
are refused. The body is parsed in chunks of ``CHUNK_ROWS`` lines, each straight into
the result arrays (grown in place, :class:`_Columns`), so the peak memory is the result,
8 bytes x columns per sample, plus a constant for one chunk (~10 MB): 8 MB per column per
million samples, e.g. 410 MB for a million samples of a gateway recording of 8 cables
(51 columns), 190 MB for a 10-min sim_plc recording (600 000 samples x 40 columns).

Files from other loggers (docs/recording-format.md, "Recordings from other loggers"): the
fields are split by the header's delimiter (comma, semicolon or tab; with the latter two a
comma in a number is the decimal comma), ``read_recording(columns=...)`` renames the
file's columns first (:mod:`gateway.recordings.columns`, ``--columns``), an error about a
missing column lists the columns found and expected, and a last line without its line end
(a writer stopped mid-line) is dropped with one warning, as :class:`GzipMembers` drops a
cut gzip member.

Writing streams too (:class:`RecordingWriter`, :func:`write_recording`): rows are
formatted and written ``CHUNK_ROWS`` at a time, never the whole file as one string.
"""

from __future__ import annotations

import io
import logging
import re
import zlib
from collections.abc import Collection, Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import IO, Any

import numpy as np

from gateway.core.heap import return_large_frees
from gateway.errors import RecordingError
from gateway.recordings.columns import MAX_CABLES, found_and_expected, rename
from gateway.recordings.writer import (
    open_writer,
)

log = logging.getLogger("cdpr_gateway.recordings")

POSE_COLUMNS = ("x", "y", "z", "rx", "ry", "rz")
CABLE_KINDS = ("velocity", "tension_sensor", "tension_platform", "length")
_CABLE_COLUMN = re.compile(r"^(velocity|tension_sensor|tension_platform|length)_(.+)$")
_CABLE_INDEX = re.compile(r"^[1-9][0-9]*$", re.ASCII)
_REQUIRED_KINDS = ("velocity", "tension_sensor")

MAX_COLUMNS = 8192
MAX_LINE_CHARS = 1 << 20  # 1 MiB per line (header included)
MAX_METADATA_LINES = 1000
MAX_METADATA_CHARS = 1 << 20  # all metadata lines together
MIN_SAMPLES = 10  # fewer kept rows than this: "too short"
DEFAULT_MAX_SAMPLES = 20_000_000  # 5.5 h at 1 kHz; read_recording(max_samples=...) to change
MAX_VALUES = 250_000_000  # samples x columns: 8 bytes each = 2 GB at most
MIN_STEP_S = 1e-6  # consecutive time stamps closer than this are refused (1 MHz at most)
MAX_ABS_TIME_S = 1e12  # Unix time stamps (~1.7e9 s) are fine
MAX_ABS_VALUE = 1e9  # any other column: N, m, m/s, rad, kg
CHUNK_ROWS = 8192
FIRST_ROW_ONLY = ("length", "pose", "mass", "tension_platform")
READ_BLOCK_CHARS = 1 << 22
_TOO_LONG = f"line longer than {MAX_LINE_CHARS} characters"
RECORDING_SUFFIXES = (".csv", ".csv.gz", ".parquet")  # what a recording is written as
DELIMITERS = (",", ";", "\t")  # the header's most frequent one separates the fields
_DELIMITER_NAMES = {",": "comma", ";": "semicolon", "\t": "tab"}


@dataclass
class Recording:
    """Arrays of one recording; ``m`` cables, ``N`` kept samples.

    ``t`` (N,) s; ``velocity``, ``tension_sensor`` (N, m); ``tension_platform`` and
    ``length`` (N, m) or None; ``pose`` (N, 6) or None; ``mass`` (N,) or None; an optional
    array read with ``read_recording(first_row_only=...)`` holds its first row only.
    """

    t: np.ndarray
    velocity: np.ndarray
    tension_sensor: np.ndarray
    tension_platform: np.ndarray | None = None
    length: np.ndarray | None = None
    pose: np.ndarray | None = None
    mass: np.ndarray | None = None
    metadata: dict[str, str] = field(default_factory=dict)
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    skipped_rows: int = 0
    source: str = ""

    @property
    def cables(self) -> int:
        return int(self.velocity.shape[1])

    @property
    def samples(self) -> int:
        return int(self.t.shape[0])

    def take(self, rows: np.ndarray) -> Recording:
        """This recording at ``rows`` only (a bool mask or indices) in every per-sample
        array; metadata, source and ``skipped_rows`` as they are."""

        def sub(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[rows]

        return replace(
            self,
            t=self.t[rows],
            velocity=self.velocity[rows],
            tension_sensor=self.tension_sensor[rows],
            tension_platform=sub(self.tension_platform),
            length=sub(self.length),
            pose=sub(self.pose),
            mass=sub(self.mass),
            extra={k: v[rows] for k, v in (self.extra or {}).items()},
        )


# --- reading ------------------------------------------------------------------------------


def _why(exc: BaseException) -> str:
    """An error's own words: ``Is a directory``, not ``[Errno 21] Is a directory: 'x'``."""
    return (exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)) or repr(exc)


HELD_MEMBER_BYTES = 64 << 20  # a gzip member's text held back until its end is seen


class GzipMembers(io.RawIOBase):
    """The text of a ``.gz`` file's complete gzip members, streamed.

    The recorder writes a gzip member at least every second (:class:`RecordingWriter`), so
    a writer killed mid-way leaves complete members and one cut short. Each member's text
    is held back until its end (its CRC and length checked) has been read; at the end of
    the file a member without its end is dropped, ``cut_bytes`` says how much of the file
    that was. Damage before the end (a bad CRC, bad deflate data, bytes that are no gzip
    member) is an error: the file is refused, never half-read. A member larger than
    ``HELD_MEMBER_BYTES`` of text (one written by another tool) streams as it comes; cut
    short, it cannot be dropped and is refused."""

    def __init__(self, path: Path) -> None:
        self._f = open(path, "rb")  # noqa: SIM115 - closed by close()
        self._ready = bytearray()  # text of complete members, not read yet
        self._held = bytearray()  # text of the current member
        self._d: Any = None  # the current member's decompressor
        self._member_in = 0  # compressed bytes of the current member so far
        self._streamed = False  # the current member's text went out before its end
        self._eof = False
        self._members = 0  # complete members read
        self.cut_bytes = 0

    def readable(self) -> bool:
        return True

    def close(self) -> None:
        self._f.close()
        super().close()

    def readinto(self, b: Any) -> int:
        while not self._ready and not self._eof:
            self._fill()
        n = min(len(b), len(self._ready))
        b[:n] = self._ready[:n]
        del self._ready[:n]
        return n

    def _fill(self) -> None:
        data = self._f.read(1 << 16)
        if not data:
            self._eof = True
            if self._d is not None and (self._member_in or self._held):
                if self._streamed:
                    raise EOFError("cut inside a gzip member too large to drop")
                if not self._members:
                    raise EOFError("cut short before its first complete gzip block")
                self.cut_bytes = self._member_in
                self._held.clear()
            return
        while data:
            if self._d is None:
                self._d = zlib.decompressobj(wbits=31)  # one gzip member
                self._member_in, self._streamed = 0, False
            out = self._d.decompress(data, HELD_MEMBER_BYTES)
            used = len(data) - len(self._d.unused_data) - len(self._d.unconsumed_tail)
            self._member_in += used
            self._held += out
            if self._d.eof:  # the member's end: CRC and length checked by zlib
                self._members += 1
                self._ready += self._held
                self._held.clear()
                data = self._d.unused_data
                self._d = None
            else:
                data = self._d.unconsumed_tail
            if len(self._held) > HELD_MEMBER_BYTES:
                self._ready += self._held
                self._held.clear()
                self._streamed = True
            if self._ready and len(self._ready) >= HELD_MEMBER_BYTES:
                return


def _open_text(path: Path) -> IO[str]:
    if path.suffix == ".gz":
        members = GzipMembers(path)
        text = io.TextIOWrapper(io.BufferedReader(members), encoding="utf-8-sig")
        text.members = members  # type: ignore[attr-defined]  # cut_bytes, read after
        return text
    return open(path, encoding="utf-8-sig")  # utf-8-sig: spreadsheets write a BOM


def _lines(path: Path, fh: IO[str], partial: list[int] | None = None) -> Iterator[tuple[int, str]]:
    """(1-based line number, text without the newline), read in blocks of 4 MiB; a line
    longer than ``MAX_LINE_CHARS`` is refused before more of it is read.

    A last line without its line end is not yielded: a writer stopped in the middle of a
    line (killed, a full disk) leaves one, whose last value may be cut short (``12.5`` of
    ``12.53``); its number is appended to ``partial`` (blanks alone are no line)."""
    number = 0
    carry = ""
    while True:
        data = fh.read(READ_BLOCK_CHARS)
        if not data:
            if carry.strip() and partial is not None:
                partial.append(number + 1)
            return
        data = carry + data
        cut = data.rfind("\n")
        carry = data[cut + 1 :]
        if len(carry) > MAX_LINE_CHARS:
            raise RecordingError(f"{path}:{number + data.count(chr(10)) + 1}: {_TOO_LONG}")
        lines = data[:cut].split("\n") if cut >= 0 else []
        if lines and max(map(len, lines)) > MAX_LINE_CHARS:
            at = next(i for i, x in enumerate(lines) if len(x) > MAX_LINE_CHARS)
            raise RecordingError(f"{path}:{number + at + 1}: {_TOO_LONG}")
        for text in lines:
            number += 1
            yield number, text


def _split_header(
    path: Path, lines: Iterator[tuple[int, str]]
) -> tuple[dict[str, str], int, list[str], str]:
    """Metadata, 1-based line number of the header line, column names, the delimiter."""
    meta: dict[str, str] = {}
    count = chars = 0
    for number, text in lines:
        if text.startswith("#"):
            count += 1
            chars += len(text)
            if count > MAX_METADATA_LINES:
                raise RecordingError(
                    f"{path}:{number}: more than {MAX_METADATA_LINES} metadata lines"
                )
            if chars > MAX_METADATA_CHARS:
                raise RecordingError(
                    f"{path}:{number}: metadata of more than {MAX_METADATA_CHARS} characters"
                )
            body = text[1:].strip()
            if ":" in body:
                key, value = body.split(":", 1)
                meta[key.strip()] = value.strip()
            continue
        if not text.strip():
            continue
        delimiter = detect_delimiter(text)
        return meta, number, _names(path, number, text, delimiter), delimiter
    raise RecordingError(f"{path}: no header row")


def detect_delimiter(header: str) -> str:
    """The delimiter of a header line: the most frequent of comma, semicolon and tab (a
    comma when none is there or on a tie: column names hold none of them)."""
    counts = [header.count(d) for d in DELIMITERS]
    return DELIMITERS[counts.index(max(counts))]


def _names(path: Path, number: int, text: str, delimiter: str = ",") -> list[str]:
    if text.count(delimiter) >= MAX_COLUMNS:
        raise RecordingError(f"{path}:{number}: more than {MAX_COLUMNS} columns")
    # spreadsheets may quote every header name: "t","velocity_1",...
    names = [c.strip().strip('"').strip() for c in text.rstrip("\r\n").split(delimiter)]
    seen: set[str] = set()
    for col, name in enumerate(names, start=1):
        if not name:
            raise RecordingError(f"{path}:{number}: column {col} has no name")
        if name in seen:
            raise RecordingError(f"{path}:{number}: column {name!r} appears twice")
        seen.add(name)
    return names


def _cable_indices(path: Path, line: int, names: list[str]) -> dict[str, dict[int, int]]:
    """Per kind, cable index -> column; indices bounded before any per-cable list exists."""
    found: dict[str, dict[int, int]] = {}
    for col, name in enumerate(names):
        match = _CABLE_COLUMN.match(name)
        if not match:
            continue
        digits = match.group(2)
        if not _CABLE_INDEX.match(digits):
            raise RecordingError(
                f"{path}:{line}: column {name!r}: cable indices must be contiguous 1..m with "
                f"m <= {MAX_CABLES}, in ASCII digits without leading zeros"
            )
        index = int(digits) if len(digits) <= 6 else MAX_CABLES + 1
        if not 1 <= index <= MAX_CABLES:
            raise RecordingError(
                f"{path}:{line}: column {name!r}: cable indices must be contiguous 1..m "
                f"with m <= {MAX_CABLES}"
            )
        found.setdefault(match.group(1), {})[index] = col
    return found


def _layout(path: Path, line: int, names: list[str]) -> tuple[int, dict[str, list[int]]]:
    """Number of cables and, per kind, the column index of cables 1..m (-1: absent)."""
    if "t" not in names:
        raise RecordingError(f"{path}:{line}: no 't' column{found_and_expected(names)}")
    found = _cable_indices(path, line, names)
    cables = max((max(d) for d in found.values()), default=0)
    if cables == 0:
        raise RecordingError(
            f"{path}:{line}: no cable columns (velocity_1, tension_sensor_1, ...)"
            f"{found_and_expected(names)}"
        )
    cols = {k: [found.get(k, {}).get(i, -1) for i in range(1, cables + 1)] for k in CABLE_KINDS}
    for i in range(cables):
        for kind in _REQUIRED_KINDS:
            if cols[kind][i] < 0:
                raise RecordingError(
                    f"{path}:{line}: cable {i + 1} has no column '{kind}_{i + 1}' "
                    f"(each cable needs velocity_i and tension_sensor_i; cable indices must be "
                    f"contiguous 1..m){found_and_expected(names)}"
                )
    has_platform = [c >= 0 for c in cols["tension_platform"]]
    if any(has_platform) and not all(has_platform):
        missing = has_platform.index(False) + 1
        raise RecordingError(
            f"{path}:{line}: column 'tension_platform_{missing}' is missing"
            f"{found_and_expected(names)}"
        )
    if not any(has_platform) and not all(n in names for n in (*POSE_COLUMNS, "mass")):
        raise RecordingError(
            f"{path}:{line}: no tension_platform_i columns and no pose and mass columns "
            f"(x, y, z, rx, ry, rz, mass) to compute them from{found_and_expected(names)}"
        )
    return cables, cols


def _parse_careful(
    path: Path, body: list[str], line_of: list[int], names: list[str], delimiter: str = ","
) -> np.ndarray:
    """The slow parser that names the line and column of what is wrong."""
    data = np.full((len(body), len(names)), np.nan)
    for r, text in enumerate(body):
        fields = text.rstrip("\r\n").split(delimiter)
        if len(fields) != len(names):
            sep = "" if delimiter == "," else f" ({_DELIMITER_NAMES[delimiter]}-separated)"
            raise RecordingError(
                f"{path}:{line_of[r]}: {len(fields)} fields, header has {len(names)}{sep}"
            )
        for c, value in enumerate(fields):
            value = value.strip()
            if value:
                try:
                    data[r, c] = float(value if delimiter == "," else value.replace(",", "."))
                except ValueError:
                    raise RecordingError(
                        f"{path}:{line_of[r]}: column {names[c]!r}: {value!r} is not a number"
                    ) from None
    return data


def _fill_empty(text: str, d: str = ",") -> str:
    """Empty fields become ``nan`` (str.replace: C speed; a regex was 4x the parse)."""
    if d + d in text:
        text = text.replace(d + d, d + "nan" + d).replace(d + d, d + "nan" + d)  # ',,,' runs
    if d + "\n" in text:
        text = text.replace(d + "\n", d + "nan\n")
    if "\n" + d in text:
        text = text.replace("\n" + d, "\nnan" + d)
    return "nan" + text if text.startswith(d) else text


def _parse_chunk(
    path: Path, body: list[str], line_of: list[int], names: list[str], delimiter: str = ","
) -> np.ndarray:
    """(rows, columns) float array; NaN for empty fields; errors name line and column.
    Separated by semicolons or tabs, a comma in a number is the decimal comma."""
    text = "\n".join(body) + "\n"
    if "\r" in text:
        text = text.replace("\r", "")
    if delimiter != "," and "," in text:
        text = text.replace(",", ".")
    text = _fill_empty(text, delimiter)
    try:
        data = np.loadtxt(io.StringIO(text), delimiter=delimiter, dtype=float, ndmin=2)
        if data.shape == (len(body), len(names)):
            return data
    except ValueError:
        pass  # bad text or a wrong field count: the careful parser says where
    return _parse_careful(path, body, line_of, names, delimiter)


class _Reader:
    """Chunk by chunk checks that need the previous chunk (time steps, counts)."""

    def __init__(
        self,
        path: Path,
        names: list[str],
        required: list[int],
        max_samples: int,
        sink: _Columns,
        where: str = "{path}:{line}",
        delimiter: str = ",",
    ):
        self.path, self.names, self.required = path, names, required
        self.delimiter = delimiter
        self.where = where  # the place of an error: file and line (CSV), or row (Parquet)
        self.t_col = names.index("t")
        self.max_samples = min(max_samples, MAX_VALUES // len(names))
        self.sink = sink
        self.kept = 0
        self.skipped = 0
        self.last_t: float | None = None
        limits = np.full(len(names), MAX_ABS_VALUE)
        limits[self.t_col] = MAX_ABS_TIME_S
        self.limits = limits

    def add(self, body: list[str], line_of: list[int]) -> None:
        self.add_rows(_parse_chunk(self.path, body, line_of, self.names, self.delimiter), line_of)

    def at(self, line: int) -> str:
        return self.where.format(path=self.path, line=line)

    def add_rows(self, data: np.ndarray, line_of: list[int]) -> None:
        """Check and keep parsed rows (rows, columns); ``line_of`` their line numbers."""
        self._check_values(data, line_of)
        keep = ~np.isnan(data[:, self.required]).any(axis=1)
        rows = np.nonzero(keep)[0]
        self.skipped += len(data) - rows.size
        if rows.size == 0:
            return
        kept = data[rows] if rows.size != len(data) else data
        self._check_time(kept[:, self.t_col], [line_of[r] for r in rows])
        self.kept += rows.size
        if self.kept > self.max_samples:
            raise RecordingError(
                f"{self.at(line_of[rows[-1]])}: more than {self.max_samples} samples "
                f"of {len(self.names)} columns (the reader's limits: max_samples, and "
                f"{MAX_VALUES:.1e} values = {8 * MAX_VALUES / 1e9:.0f} GB to read)"
            )
        self.sink.append(kept)

    def _check_values(self, data: np.ndarray, line_of: list[int]) -> None:
        with np.errstate(invalid="ignore"):
            bad = np.isinf(data) | (np.abs(data) > self.limits)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            value = float(data[r, c])
            why = (
                "value is not finite"
                if not np.isfinite(value)
                else (f"{value!r} exceeds the limit {self.limits[c]:g}")
            )
            raise RecordingError(f"{self.at(line_of[r])}: column {self.names[c]!r}: {why}")

    def _check_time(self, t: np.ndarray, lines: list[int]) -> None:
        prev = np.concatenate(([self.last_t], t[:-1])) if self.last_t is not None else t[:-1]
        cur = t if self.last_t is not None else t[1:]
        lines = lines if self.last_t is not None else lines[1:]
        steps = cur - prev
        bad = np.nonzero(steps < MIN_STEP_S)[0]
        if bad.size:
            r = int(bad[0])
            if steps[r] <= 0:
                raise RecordingError(
                    f"{self.at(lines[r])}: column 't': {float(cur[r])!r} does not increase "
                    f"(previous {float(prev[r])!r})"
                )
            raise RecordingError(
                f"{self.at(lines[r])}: column 't': time step {float(steps[r]):.3g} s is "
                f"below the minimum {MIN_STEP_S:g} s"
            )
        self.last_t = float(t[-1])


def _required_columns(names: list[str], cols: dict[str, list[int]]) -> list[int]:
    index = {n: i for i, n in enumerate(names)}
    required = [index["t"], *cols["velocity"], *cols["tension_sensor"]]
    if cols["tension_platform"][0] >= 0:
        return required + cols["tension_platform"]
    return required + [index[n] for n in (*POSE_COLUMNS, "mass")]


def read_recording(
    path: str | Path,
    *,
    min_samples: int = MIN_SAMPLES,
    max_samples: int = DEFAULT_MAX_SAMPLES,
    first_row_only: Collection[str] = (),
    columns: Mapping[str, str] | None = None,
) -> Recording:
    """Read and validate a recording (docs/recording-format.md), streaming the body.

    ``first_row_only``: names of optional arrays (``length``, ``pose``, ``mass``,
    ``tension_platform``) of which only the first kept row is stored, shape (1, k) (``mass``
    (1,)), for a caller that reads no more of them (memory: 8 bytes per value and sample
    not held). Their values are parsed and checked as any other: the same refusals.
    ``columns``: format name -> the file's column (``--columns``,
    :mod:`gateway.recordings.columns`), applied to the header before anything else.

    A CSV's fields are separated by the header's delimiter (comma, semicolon or tab); a
    last line without its line end is dropped with a warning, as a ``.csv.gz``'s last
    member cut short is."""
    path = Path(path)
    if not set(first_row_only) <= set(FIRST_ROW_ONLY):
        raise ValueError(f"first_row_only: only {FIRST_ROW_ONLY}, not {first_row_only!r}")
    return_large_frees()  # the result arrays grow by realloc: mremap, not copies
    if path.suffix == ".parquet":
        return _read_parquet(path, min_samples, max_samples, first_row_only, columns)
    partial: list[int] = []
    try:
        with _open_text(path) as fh:
            lines = _lines(path, fh, partial)
            meta, head, names, delimiter = _split_header(path, lines)
            names = rename(f"{path}:{head}", names, columns)
            cables, cols = _layout(path, head, names)
            sink = _Columns(_targets(names, cables, cols), first_row_only)
            required = _required_columns(names, cols)
            reader = _Reader(path, names, required, max_samples, sink, delimiter=delimiter)
            body: list[str] = []
            line_of: list[int] = []
            for number, text in lines:
                if text.strip():
                    body.append(text)
                    line_of.append(number)
                    if len(body) >= CHUNK_ROWS:
                        reader.add(body, line_of)
                        body, line_of = [], []
            if body:
                reader.add(body, line_of)
            cut = getattr(getattr(fh, "members", None), "cut_bytes", 0)
    except (OSError, EOFError, UnicodeDecodeError, zlib.error) as exc:
        raise RecordingError(f"{path}: cannot read: {_why(exc)}") from exc
    rec = _finish(path, meta, sink, reader, min_samples)
    if cut:
        log.warning(
            "%s: ends after an unclean stop: %d rows to t = %.3f s, the last partial block "
            "(%d bytes) dropped",
            path,
            rec.t.size,
            rec.t[-1],
            cut,
        )
    if partial:
        log.warning(
            "%s: ends after an unclean stop: %d rows to t = %.3f s, the last partial line "
            "(line %d) dropped",
            path,
            rec.t.size,
            rec.t[-1],
            partial[0],
        )
    return rec


def _finish(path: Path, meta: dict[str, str], sink: _Columns, reader: _Reader, min_samples: int):
    if reader.kept == 0:
        raise RecordingError(
            f"{path}: no data rows"
            if reader.skipped == 0
            else f"{path}: every row misses a required value"
        )
    if reader.kept < min_samples:
        raise RecordingError(
            f"{path}: too short: {reader.kept} samples, at least {min_samples} are needed"
        )
    return _assemble(path, meta, sink.finish(), reader.skipped)


def _read_parquet(
    path: Path,
    min_samples: int,
    max_samples: int,
    first_row_only: Collection[str],
    columns: Mapping[str, str] | None = None,
) -> Recording:
    """A Parquet recording (:mod:`gateway.recordings.parquet`, imported only here: the
    gateway's cycle process never loads pyarrow): the same layout rules, checks and limits
    as a CSV, the schema standing for the header and rows numbered from 1."""
    try:
        return _read_parquet_text_checked(path, min_samples, max_samples, first_row_only, columns)
    except UnicodeDecodeError as exc:  # pyarrow decodes names, paths and metadata lazily
        raise RecordingError(
            f"{path}: not a readable Parquet file: text in its footer is not UTF-8 "
            f"(byte {exc.object[exc.start : exc.start + 1]!r})"
        ) from exc


def _read_parquet_text_checked(
    path: Path,
    min_samples: int,
    max_samples: int,
    first_row_only: Collection[str],
    columns: Mapping[str, str] | None,
) -> Recording:
    from gateway.recordings import parquet

    pf, stored = parquet.open_checked(path, MAX_COLUMNS)
    names = rename(f"{path}: schema", stored, columns)
    max_rows = min(max_samples, MAX_VALUES // max(len(names), 1))
    if pf.metadata.num_rows > max_rows:
        raise RecordingError(
            f"{path}: {pf.metadata.num_rows} rows of {len(names)} columns "
            f"exceed the reader's limit of {max_rows} samples"
        )
    meta = parquet.parquet_metadata(path, pf, MAX_METADATA_LINES, MAX_LINE_CHARS)
    try:
        cables, cols = _layout(path, 0, names)
    except RecordingError as exc:  # the schema is no line of text
        raise RecordingError(str(exc).replace(f"{path}:0:", f"{path}: schema:", 1)) from None
    sink = _Columns(_targets(names, cables, cols), first_row_only)
    where = "{path}: row {line}"
    reader = _Reader(path, names, _required_columns(names, cols), max_samples, sink, where)
    for first, block in parquet.iter_row_groups(path, pf, stored):
        for start in range(0, block.shape[0], 8 * CHUNK_ROWS):
            part = block[start : start + 8 * CHUNK_ROWS]
            reader.add_rows(part, list(range(first + start, first + start + len(part))))
    return _finish(path, meta, sink, reader, min_samples)


class _Columns:
    """The result arrays, filled chunk by chunk from the parsed rows: ``targets`` maps a
    name to the source column of each of its columns (-1: absent, NaN). The capacity grows
    by 1/8 at a time with ``ndarray.resize`` (``realloc``; glibc moves the pages of a large
    array with ``mremap`` instead of copying them; numpy zero-fills the new rows, so the
    spare capacity, at most 1/8, is resident): the peak is the arrays themselves, 8 bytes
    per value, plus at most 1/8 of them and one chunk."""

    FIRST_ROWS = 1 << 16

    def __init__(self, targets: dict[str, list[int]], first_row_only: Collection[str] = ()) -> None:
        self.rows = 0
        self.capacity = 0
        self.sources = {k: np.asarray(c, dtype=np.intp) for k, c in targets.items()}
        self.arrays = {k: np.empty((0, len(c))) for k, c in targets.items()}
        self.heads = {k: self.arrays.pop(k) for k in first_row_only if k in self.arrays}

    def append(self, block: np.ndarray) -> None:
        stop = self.rows + block.shape[0]
        if self.rows == 0:  # the first kept row of the arrays read no further
            for name, arr in self.heads.items():
                arr.resize((1, arr.shape[1]), refcheck=False)
                _fill(arr, block[:1], self.sources[name])
        if stop > self.capacity:  # resize zero-fills the new rows: they are resident
            self.capacity = max(stop, self.capacity * 9 // 8, self.FIRST_ROWS)
            for arr in self.arrays.values():
                arr.resize((self.capacity, arr.shape[1]), refcheck=False)
        for name, arr in self.arrays.items():
            _fill(arr[self.rows : stop], block, self.sources[name])
        self.rows = stop

    def finish(self) -> dict[str, np.ndarray]:
        """The arrays, cut to the rows read (``t``, ``mass`` and extras as (N,)); those
        read for their first row only as (1, k) ((1,))."""
        out = {}
        for name, arr in [*self.arrays.items(), *self.heads.items()]:
            if name not in self.heads:
                arr.resize((self.rows, arr.shape[1]), refcheck=False)
            flat = name in ("t", "mass") or name.startswith("extra:")
            out[name] = arr.reshape(arr.shape[0]) if flat else arr
        self.arrays, self.heads = {}, {}
        return out


def _fill(rows: np.ndarray, block: np.ndarray, src: np.ndarray) -> None:
    """``rows`` from the parsed ``block``'s columns ``src`` (-1: absent, NaN)."""
    if np.all(src >= 0):
        rows[:] = block[:, src]
    else:
        rows[:] = np.nan
        present = np.nonzero(src >= 0)[0]
        rows[:, present] = block[:, src[present]]


def _targets(names: list[str], cables: int, cols: dict[str, list[int]]) -> dict[str, list[int]]:
    """Result array name -> source column per result column (-1: absent): ``t``, each
    cable kind present, ``pose`` (all six or none), ``mass`` and ``extra:NAME`` columns."""
    index = {name: i for i, name in enumerate(names)}
    out = {"t": [index["t"]]}
    for kind in CABLE_KINDS:
        if any(c >= 0 for c in cols[kind]):
            out[kind] = list(cols[kind])
    if all(p in index for p in POSE_COLUMNS):
        out["pose"] = [index[p] for p in POSE_COLUMNS]
    if "mass" in index:
        out["mass"] = [index["mass"]]
    known = {"t", "mass", *POSE_COLUMNS}
    for x in names:
        if x not in known and not _CABLE_COLUMN.match(x):
            out[f"extra:{x}"] = [index[x]]
    return out


def _assemble(path: Path, meta: dict[str, str], out: dict[str, np.ndarray], skipped: int):
    extras = {k[len("extra:") :]: v for k, v in out.items() if k.startswith("extra:")}
    return Recording(
        t=out["t"],
        velocity=out["velocity"],
        tension_sensor=out["tension_sensor"],
        tension_platform=out.get("tension_platform"),
        length=out.get("length"),
        pose=out.get("pose"),
        mass=out.get("mass"),
        metadata=meta,
        extra=extras,
        skipped_rows=skipped,
        source=str(path),
    )


def read_metadata(path: str | Path) -> dict[str, str]:
    """The metadata of a recording alone: the ``# key: value`` lines of a CSV (read up to
    the header) or the key-value metadata of a Parquet file's footer."""
    path = Path(path)
    try:
        if path.suffix == ".parquet":
            from gateway.recordings import parquet

            pf, _ = parquet.open_checked(path, MAX_COLUMNS)
            return parquet.parquet_metadata(path, pf, MAX_METADATA_LINES, MAX_LINE_CHARS)
        with _open_text(path) as fh:
            return _split_header(path, _lines(path, fh))[0]
    except (OSError, EOFError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{path}: cannot read: {_why(exc)}") from exc


# --- writing ------------------------------------------------------------------------------
def check_recording_name(path: str | Path, option: str) -> None:
    """Refuse (:class:`RecordingError`, naming ``option``) a file to write whose name is no
    recording format's: the extension chooses the format, never silently CSV."""
    if not Path(path).name.endswith(RECORDING_SUFFIXES):
        raise RecordingError(
            f"{option} {path}: not a recording format (the name must end in "
            f"{', '.join(RECORDING_SUFFIXES)})"
        )


def recording_columns(rec: Recording) -> list[tuple[str, np.ndarray]]:
    """(name, column array) of ``rec`` in the order written."""
    columns: list[tuple[str, np.ndarray]] = [("t", rec.t)]
    for i in range(rec.cables):
        columns.append((f"velocity_{i + 1}", rec.velocity[:, i]))
        columns.append((f"tension_sensor_{i + 1}", rec.tension_sensor[:, i]))
        if rec.tension_platform is not None:
            columns.append((f"tension_platform_{i + 1}", rec.tension_platform[:, i]))
        if rec.length is not None:
            columns.append((f"length_{i + 1}", rec.length[:, i]))
    if rec.pose is not None:
        columns += [(n, rec.pose[:, k]) for k, n in enumerate(POSE_COLUMNS)]
    if rec.mass is not None:
        columns.append(("mass", rec.mass))
    columns += list(rec.extra.items())
    return columns


def write_recording(path: str | Path, rec: Recording, metadata: dict[str, str] | None = None):
    """Write ``rec`` as CSV (gzip when the name ends in .gz) or Parquet (``.parquet``),
    ``CHUNK_ROWS`` rows at a time."""
    columns = recording_columns(rec)
    writer = open_writer(path, [n for n, _ in columns], {**rec.metadata, **(metadata or {})})
    try:
        chunk = np.empty((min(CHUNK_ROWS, rec.samples), len(columns)))
        for start in range(0, rec.samples, CHUNK_ROWS):
            stop = min(start + CHUNK_ROWS, rec.samples)
            block = chunk[: stop - start]
            for c, (_, values) in enumerate(columns):
                block[:, c] = values[start:stop]
            writer.write_rows(block)
    finally:
        writer.close()
