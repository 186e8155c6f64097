"""Recordings in and out: plain CSV (or .csv.gz), spec/recording.md.

A recording is refused whole with :class:`RecordingError` naming file, line and column when
it is malformed (no ``t``, ``t`` not strictly increasing, a cable with only some of its
required columns, text in a number field). A row with a missing required value is skipped
and counted (``Recording.skipped_rows``), never filled in; a missing optional value is NaN.
"""

from __future__ import annotations

import gzip
import io
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gateway.errors import RecordingError

POSE_COLUMNS = ("x", "y", "z", "rx", "ry", "rz")
_CABLE_COLUMN = re.compile(r"^(velocity|tension_sensor|tension_platform|length)_(\d+)$")
_REQUIRED_KINDS = ("velocity", "tension_sensor")


@dataclass
class Recording:
    """Arrays of one recording; ``m`` cables, ``N`` kept samples.

    ``t`` (N,) s; ``velocity``, ``tension_sensor`` (N, m); ``tension_platform`` and
    ``length`` (N, m) or None; ``pose`` (N, 6) or None; ``mass`` (N,) or None.
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


def _open_text(path: Path) -> io.TextIOWrapper:
    if path.suffix == ".gz":
        return io.TextIOWrapper(gzip.open(path, "rb"), encoding="utf-8-sig")
    return open(path, encoding="utf-8-sig")  # utf-8-sig: spreadsheets write a BOM


def _split_header(path: Path, lines: list[str]) -> tuple[dict[str, str], int, list[str]]:
    """Metadata, 0-based index of the header line, column names."""
    meta: dict[str, str] = {}
    i = 0
    while i < len(lines) and lines[i].startswith("#"):
        body = lines[i][1:].strip()
        if ":" in body:
            key, value = body.split(":", 1)
            meta[key.strip()] = value.strip()
        i += 1
    while i < len(lines) and not lines[i].strip():
        i += 1
    if i >= len(lines):
        raise RecordingError(f"{path}: no header row")
    # spreadsheets may quote every header name: "t","velocity_1",...
    names = [c.strip().strip('"').strip() for c in lines[i].rstrip("\r\n").split(",")]
    seen: set[str] = set()
    for col, name in enumerate(names, start=1):
        if not name:
            raise RecordingError(f"{path}:{i + 1}: column {col} has no name")
        if name in seen:
            raise RecordingError(f"{path}:{i + 1}: column {name!r} appears twice")
        seen.add(name)
    return meta, i, names


def _layout(path: Path, line: int, names: list[str]) -> tuple[int, dict[str, list[int]]]:
    """Number of cables and, per kind, the column index of cables 1..m (-1: absent)."""
    if "t" not in names:
        raise RecordingError(f"{path}:{line}: no 't' column")
    found: dict[str, dict[int, int]] = {}
    for col, name in enumerate(names):
        match = _CABLE_COLUMN.match(name)
        if match:
            found.setdefault(match.group(1), {})[int(match.group(2))] = col
    cables = max((max(d) for d in found.values()), default=0)
    if cables == 0:
        raise RecordingError(f"{path}:{line}: no cable columns (velocity_1, tension_sensor_1, ...)")
    kinds = ("velocity", "tension_sensor", "tension_platform", "length")
    cols = {k: [found.get(k, {}).get(i, -1) for i in range(1, cables + 1)] for k in kinds}
    for i in range(cables):
        for kind in _REQUIRED_KINDS:
            if cols[kind][i] < 0:
                raise RecordingError(
                    f"{path}:{line}: cable {i + 1} has no column '{kind}_{i + 1}' "
                    f"(each cable needs velocity_i and tension_sensor_i)"
                )
    has_platform = [c >= 0 for c in cols["tension_platform"]]
    if any(has_platform) and not all(has_platform):
        missing = has_platform.index(False) + 1
        raise RecordingError(f"{path}:{line}: column 'tension_platform_{missing}' is missing")
    if not any(has_platform) and not all(n in names for n in (*POSE_COLUMNS, "mass")):
        raise RecordingError(
            f"{path}:{line}: no tension_platform_i columns and no pose and mass columns "
            "(x, y, z, rx, ry, rz, mass) to compute them from"
        )
    return cables, cols


def _parse_rows(path: Path, body: list[str], first_line: int, names: list[str]) -> np.ndarray:
    """(rows, columns) float array; NaN for empty fields; errors name line and column."""
    try:
        return np.loadtxt(body, delimiter=",", dtype=float, ndmin=2).reshape(-1, len(names))
    except ValueError:
        pass  # empty fields or bad text: the careful parser below says where
    data = np.full((len(body), len(names)), np.nan)
    for r, text in enumerate(body):
        fields = text.rstrip("\r\n").split(",")
        if len(fields) != len(names):
            raise RecordingError(
                f"{path}:{first_line + r}: {len(fields)} fields, header has {len(names)}"
            )
        for c, value in enumerate(fields):
            value = value.strip()
            if value:
                try:
                    data[r, c] = float(value)
                except ValueError:
                    raise RecordingError(
                        f"{path}:{first_line + r}: column {names[c]!r}: {value!r} is not a number"
                    ) from None
    return data


def read_recording(path: str | Path) -> Recording:
    """Read and validate a recording (spec/recording.md)."""
    path = Path(path)
    try:
        with _open_text(path) as fh:
            lines = fh.readlines()
    except (OSError, EOFError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{path}: cannot read: {exc}") from exc
    meta, head, names = _split_header(path, lines)
    cables, cols = _layout(path, head + 1, names)
    body_idx = [i for i in range(head + 1, len(lines)) if lines[i].strip()]
    body = [lines[i] for i in body_idx]
    if not body:
        raise RecordingError(f"{path}: no data rows")
    data = _parse_rows(path, body, head + 2, names)
    if len(body_idx) != body_idx[-1] - head:  # blank lines inside: map rows back to lines
        line_of = np.asarray(body_idx) + 1
    else:
        line_of = np.arange(head + 2, head + 2 + len(body))
    bad = ~np.isfinite(data) & ~np.isnan(data)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise RecordingError(f"{path}:{line_of[r]}: column {names[c]!r}: value is not finite")
    return _assemble(path, meta, names, cables, cols, data, line_of)


def _assemble(path, meta, names, cables, cols, data, line_of) -> Recording:
    index = {n: i for i, n in enumerate(names)}
    t_all = data[:, index["t"]]
    required = [index["t"], *cols["velocity"], *cols["tension_sensor"]]
    if cols["tension_platform"][0] >= 0:
        required += cols["tension_platform"]
    else:
        required += [index[n] for n in (*POSE_COLUMNS, "mass")]
    keep = ~np.isnan(data[:, required]).any(axis=1)
    t = t_all[keep]
    if t.size == 0:
        raise RecordingError(f"{path}: every row misses a required value")
    steps = np.diff(t)
    if np.any(steps <= 0):
        r = int(np.nonzero(steps <= 0)[0][0]) + 1
        line = line_of[np.nonzero(keep)[0][r]]
        raise RecordingError(
            f"{path}:{line}: column 't': {float(t[r])!r} does not increase "
            f"(previous {float(t[r - 1])!r})"
        )

    def block(kind: str) -> np.ndarray | None:
        if cols[kind][0] < 0 and all(c < 0 for c in cols[kind]):
            return None
        out = np.full((t.size, cables), np.nan)
        for i, c in enumerate(cols[kind]):
            if c >= 0:
                out[:, i] = data[keep, c]
        return out

    has_pose = all(n in index for n in POSE_COLUMNS)
    known = {"t", "mass", *POSE_COLUMNS}
    extra = {
        n: data[keep, i] for n, i in index.items() if n not in known and not _CABLE_COLUMN.match(n)
    }
    return Recording(
        t=t,
        velocity=block("velocity"),  # type: ignore[arg-type]
        tension_sensor=block("tension_sensor"),  # type: ignore[arg-type]
        tension_platform=block("tension_platform"),
        length=block("length"),
        pose=data[keep][:, [index[n] for n in POSE_COLUMNS]] if has_pose else None,
        mass=data[keep, index["mass"]] if "mass" in index else None,
        metadata=meta,
        extra=extra,
        skipped_rows=int((~keep).sum()),
        source=str(path),
    )


def write_recording(path: str | Path, rec: Recording, metadata: dict[str, str] | None = None):
    """Write ``rec`` as CSV (gzip when the name ends in .gz); NaN becomes an empty field."""
    path = Path(path)
    m = rec.cables
    columns: list[tuple[str, np.ndarray]] = [("t", rec.t)]
    for i in range(m):
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
    table = np.column_stack([c for _, c in columns])
    buf = io.StringIO()
    for key, value in {**rec.metadata, **(metadata or {})}.items():
        buf.write(f"# {key}: {value}\n")
    buf.write(",".join(n for n, _ in columns) + "\n")
    np.savetxt(buf, table, delimiter=",", fmt="%.10g")
    text = buf.getvalue()
    if np.isnan(table).any():
        text = re.sub(r"(?<=,)nan(?=,|\n)|^nan(?=,)", "", text, flags=re.MULTILINE)
    if path.suffix == ".gz":
        with gzip.open(path, "wt", encoding="utf-8") as fh:
            fh.write(text)
    else:
        path.write_text(text, encoding="utf-8")
