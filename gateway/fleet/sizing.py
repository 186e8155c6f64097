"""How much memory a recording's diagnosis needs, told from its header and size before it
is loaded: a fleet task that cannot fit its worker is refused in one line, never sent to a
worker it would kill (a 16 MB CSV.gz needing ~2 GB killed four workers in turn).

Rows x columns x 8 bytes is the recording as float64 columns; the diagnosis holds about
:data:`COPIES` times that at its peak, on top of :data:`TASK_BASE_BYTES` (the libraries it
loads): 10 min x 1 kHz x 8 cables (600 000 x 33) is 158 MB of columns, estimated 403 MB,
measured 373-422 MB (docs/performance.md). Parquet states its rows and columns in the
footer; a CSV's rows are estimated from its size and its first MiB of text (a ``.gz``'s
compression ratio from the same sample). Several recordings of one robot diagnosed as one
task (``fleet --per-robot``) are joined into one series first: their rows add up, the
columns are one recording's (:func:`joined`).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from pathlib import Path

COPIES = 1.6
TASK_BASE_BYTES = 150 << 20
SAMPLE_BYTES = 1 << 20


@dataclass(frozen=True)
class Size:
    rows: int
    columns: int
    exact: bool  # rows from the file's own count (Parquet), not estimated

    @property
    def need_bytes(self) -> int:
        return int(TASK_BASE_BYTES + COPIES * self.rows * self.columns * 8)

    def describe(self) -> str:
        rows = f"{self.rows}" if self.exact else f"about {self.rows}"
        return (
            f"{rows} rows x {self.columns} columns: about {self.need_bytes >> 20} MiB to diagnose"
        )


def estimate(path: Path) -> Size | None:
    """The recording's rows and columns, from its header and size; None when the file
    cannot tell (unreadable: the task itself then says why)."""
    try:
        if path.suffix == ".parquet":
            import pyarrow.parquet as pq

            md = pq.ParquetFile(path).metadata
            return Size(max(md.num_rows, 0), md.num_columns, True)
        return _csv(path)
    except Exception:  # any damage: the diagnosis reads it and refuses it in its own words
        return None


def _csv(path: Path) -> Size | None:
    size = path.stat().st_size
    with open(path, "rb") as fh:
        raw = fh.read(SAMPLE_BYTES)
    if path.suffix == ".gz":
        d = zlib.decompressobj(wbits=31)
        text = d.decompress(raw, 16 * SAMPLE_BYTES)
        used = len(raw) - len(d.unconsumed_tail)
        ratio = len(text) / max(used, 1)
    else:
        text, ratio = raw, 1.0
    lines = [ln for ln in text.split(b"\n")[:-1] if ln and not ln.startswith(b"#")]
    if len(lines) < 2:
        return None
    columns = max(lines[0].count(d) for d in (b",", b";", b"\t")) + 1  # the reader's rule
    per_row = sum(len(ln) + 1 for ln in lines[1:]) / (len(lines) - 1)
    return Size(int(size * ratio / per_row), columns, False)


def joined(paths: list[Path]) -> Size | None:
    """The size of several recordings diagnosed as one (:mod:`gateway.diagnose.sessions`
    joins them into one series): the sum of their rows, the most columns of any; None when
    one of them cannot tell."""
    sizes = [estimate(p) for p in paths]
    if not sizes or any(s is None for s in sizes):
        return None
    known = [s for s in sizes if s is not None]
    return Size(
        sum(s.rows for s in known), max(s.columns for s in known), all(s.exact for s in known)
    )


def refusal(path: Path | list[Path], budget_bytes: int) -> str | None:
    """One line when the recording's diagnosis (a list: the recordings' joined diagnosis)
    would not fit ``budget_bytes``, else None."""
    if isinstance(path, list):
        found = joined(path)
        what = f"{len(path)} recordings joined ({path[0]}, ...)" if len(path) > 1 else path[0]
    else:
        found, what = estimate(path), path
    if found is None or found.need_bytes <= budget_bytes:
        return None
    return (
        f"{what}: not sent to a worker: {found.describe()}, over the {budget_bytes >> 20} MiB "
        "a worker has for one task (diagnose it alone, or split it)"
    )
