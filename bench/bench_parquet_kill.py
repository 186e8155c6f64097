"""Parquet recordings that survive a kill (issue 30 item 3): the footer rewritten after every
row group (bench/parquet_footer.py with the hand-written Thrift codec,
tests/recordings/thrift.py: the recorder's writer until then) against an append-only Arrow
IPC stream converted to Parquet at close (gateway/recordings/parquet.py now). ``python -m
bench parquet_kill``: for each, the CPU per row of a 1 kHz x 57-column recording written 100
rows at a time (as the recorder's writer drains its ring), the footer's growth, and the rows
a SIGKILL at a random moment loses (a child writing in real time, killed 2-4 s in, the file
read back)."""

from __future__ import annotations

import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from bench.parquet_footer import FooterRewritingWriter
from gateway.recordings.parquet import ParquetRecordingWriter, stream_path

ROOT = Path(__file__).resolve().parents[1]
COLUMNS = ["t"] + [f"c{i}_{k}" for i in range(1, 9) for k in range(7)]  # 57, as a recorder
BATCH = 100  # rows per write (0.1 s at 1 kHz)


def block(first: int, n: int) -> np.ndarray:
    rng = np.random.default_rng(first)
    out = 100 + rng.standard_normal((n, len(COLUMNS)))
    out[:, 0] = np.arange(first, first + n) * 1e-3
    return out


def read_ipc_rows(path: Path) -> int:
    """Rows of every complete batch of a cut stream."""
    rows = 0
    try:
        with pa.ipc.open_stream(str(path)) as reader:
            for batch in reader:
                rows += batch.num_rows
    except (pa.ArrowInvalid, OSError):
        pass
    return rows


def cpu(make, seconds: int) -> tuple[float, float, int]:
    """(us of CPU per row overall, in the last tenth, the file's bytes)."""
    with tempfile.TemporaryDirectory() as d:
        w = make(Path(d) / "r.parquet")
        n, total, last = seconds * 1000, 0.0, 0.0
        for first in range(0, n, BATCH):
            data = block(first, BATCH)
            t0 = time.process_time()
            w.write_rows(data)
            dt = time.process_time() - t0
            total += dt
            last += dt if first >= 0.9 * n else 0.0
        t0 = time.process_time()
        w.close()
        total += time.process_time() - t0
        size = (Path(d) / "r.parquet").stat().st_size
    return total / n * 1e6, last / (0.1 * n) * 1e6, size


CHILD = textwrap.dedent(
    """
    import sys, time
    sys.path.insert(0, {root!r})
    from bench.bench_parquet_kill import COLUMNS, block, BATCH
    from bench.parquet_footer import FooterRewritingWriter
    from gateway.recordings.parquet import ParquetRecordingWriter
    if {kind!r} == "footer":
        w = FooterRewritingWriter({path!r}, COLUMNS, {{"robot": "r"}}, row_group_rows=1000)
    else:
        w = ParquetRecordingWriter({path!r}, COLUMNS, {{"robot": "r"}})
    first = 0
    while True:
        w.write_rows(block(first, BATCH))
        first += BATCH
        print(first, flush=True)
        time.sleep(0.1)
    """
)


def kill_loss(kind: str, after_rows: int) -> tuple[int, int]:
    """(rows written before the SIGKILL, rows read back)."""
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "k.parquet"
        code = CHILD.format(root=str(ROOT), kind=kind, path=str(path))
        proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
        assert proc.stdout is not None
        written, deadline = 0, time.monotonic() + 60
        while written < after_rows and time.monotonic() < deadline:
            written = int(proc.stdout.readline().split()[0])
        time.sleep(np.random.default_rng(after_rows).uniform(0, 0.1))  # inside a write, or not
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        proc.stdout.close()
        if kind == "footer":
            return written, pq.read_table(path).num_rows  # the whole file, read
        return written, read_ipc_rows(stream_path(path))


def run() -> None:
    rng = np.random.default_rng(7)
    moments = sorted(int(x) * 100 for x in rng.integers(20, 40, 5))
    for kind in ("footer", "ipc"):
        lost = [w - r for w, r in (kill_loss(kind, m) for m in moments)]
        print(f"   {kind}: rows lost per SIGKILL at 1 kHz (kills after {moments} rows): {lost}")
    for seconds in (60, 600):
        cases = {
            "footer, 5-s row groups": lambda p: FooterRewritingWriter(p, COLUMNS, {}),
            "footer, 1-s row groups": lambda p: FooterRewritingWriter(
                p, COLUMNS, {}, row_group_rows=1000
            ),
            "ipc, a batch per write (0.1 s) + conversion": lambda p: ParquetRecordingWriter(
                p, COLUMNS, {}
            ),
        }
        for name, make in cases.items():
            per_row, last, size = cpu(make, seconds)
            print(
                f"   {seconds:4d} s, {name}: {per_row:.2f} us CPU/row overall, "
                f"{last:.2f} in the last tenth, {size / 1e6:.1f} MB"
            )
    w = FooterRewritingWriter(
        Path(tempfile.mkdtemp()) / "f.parquet", COLUMNS, {}, row_group_rows=1000
    )
    for first in range(0, 60_000, 1000):
        w.write_rows(block(first, 1000))
    per = len(w._tail) / 60
    print(
        f"   footer: {per / 1e3:.1f} kB per row group, rewritten whole after each: with 1-s "
        f"groups the reader's 64 MiB footer limit is reached after {(64 << 20) / per / 3600:.1f} h"
    )
    w.close()
    files = [
        "gateway/recordings/parquet.py",
        "bench/parquet_footer.py",
        "tests/recordings/thrift.py",
    ]
    lines = {f: len((ROOT / f).read_text().splitlines()) for f in files}
    print(f"   code (lines): {lines}")


if __name__ == "__main__":
    run()
