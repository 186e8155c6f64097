"""The recorder's writer process: drains the shared ring, writes whole rows (CSV, or Parquet
through an Arrow IPC stream: :func:`gateway.recordings.writer.open_writer` by the file
name), rotates.

Started by :class:`gateway.service.recorder.Recorder` as ``python -m
gateway.service.recorder_proc`` (a fresh interpreter: fork+exec, never a fork of the
threaded gateway), below the cycle (SCHED_OTHER, nice 10, even when the gateway runs
SCHED_FIFO). Formatting ~100 rows x ~57 columns every 0.1 s in the gateway's own process
held the GIL long enough to make the 1 ms cycle wait for it on wake-up (overruns 0.08 % ->
0.46 %, ``python -m bench record``); a process of its own has its own GIL.

The protocol (one producer, one consumer, no locks):

* Shared memory (a ``memfd``, passed as a descriptor: it has no name, so nothing is left
  in ``/dev/shm`` whatever ends the processes) holds a control block of int64 slots
  (:data:`HEAD` ... :data:`DROPPED`, head and tail on separate cache lines) and the ring
  of float64 rows at :data:`RING_OFFSET`.
* The gateway writes a row into slot ``head % rows``, then publishes ``head + 1``; it
  writes nothing else the writer reads but :data:`DROPPED`. The writer reads ``head``,
  copies the rows ``tail .. head`` out, writes them, then publishes ``tail``. Memory
  ordering: this relies on x86-64's total store order (stores are seen in program order,
  loads are not reordered with other loads) and on aligned 8-byte loads and stores being
  atomic; a weakly ordered CPU (aarch64) would need barriers that Python cannot express.
* stdin: the first line is the job (JSON); then the gateway closes it. EOF -- a close, or
  the gateway's death, which closes its end too -- means: drain to ``head``, close the file
  (the gzip trailer) and exit. The parent pid is checked as well. SIGINT and SIGTERM are
  ignored (a terminal's Ctrl-C and systemd's stop reach every process of the group; the
  gateway, which gets them too, stops its loop and then closes this writer).
* stdout: events as JSON lines (``file``, ``ready``, ``error``, ``failed``, ``log``,
  ``done``), which the gateway logs and keeps.

A failed write (ENOSPC) is logged once, :data:`STOP` is set (the gateway then drops and
counts every later sample), a plain CSV is cut back to its last whole row, and the
writer exits.
"""

from __future__ import annotations

import contextlib
import json
import logging
import mmap
import os
import re
import select
import signal
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from gateway.recordings.writer import RowWriter, open_writer
from gateway.runtime import realtime

# control block: int64 slot indices; HEAD on its own cache line, the writer's on another
HEAD = 0  # rows pushed (written by the gateway only)
TAIL = 8  # rows consumed (written by the writer only)
WRITTEN = 9  # rows written to files (writer)
STOP = 10  # 1: the writer failed and stopped (writer; the gateway's push drops)
DROPPED = 16  # samples the gateway's push dropped (gateway)
RING_OFFSET = 4096  # the ring starts on its own page

LOG_INTERVAL_S = 10.0  # dropped samples are logged at most this often
MAX_BATCH_ROWS = 4096  # rows formatted per write


class Sink:
    """The files of one recording: whole-row batches, rotation, a failed disk."""

    def __init__(self, job: dict[str, Any], ring: np.ndarray, ctl: memoryview) -> None:
        self.job = job
        self.ring = ring
        self.ctl = ctl
        self.select = np.array(job["select"], dtype=np.intp)
        self.writer: RowWriter | None = None
        self.done_rows = 0  # rows in files closed already
        self.files = 0
        self.opened_at = 0.0
        self.good_bytes = 0
        self.failed = False
        self.logged_dropped = 0
        self.log_at = 0.0

    def drain(self) -> None:
        """Write every filled slot as whole rows, in batches, rotating between batches."""
        size, ctl = self.ring.shape[0], self.ctl
        while not self.failed:
            head, tail = ctl[HEAD], ctl[TAIL]
            if head == tail:
                return
            start = tail % size
            count = min(head - tail, size - start, MAX_BATCH_ROWS)
            block = self.ring[start : start + count][:, self.select]  # a copy
            try:
                self.maybe_rotate()
                assert self.writer is not None
                self.writer.write_rows(block)
                self.good_bytes = self.writer.bytes
            except OSError as exc:
                self.fail(exc)
                return
            # on disk (a writer may hold rows back: a .gz member being gathered)
            ctl[WRITTEN] = self.done_rows + self.writer.rows_on_disk
            ctl[TAIL] = tail + count  # after the copy: the slots are free again

    def maybe_rotate(self) -> None:
        w, job = self.writer, self.job
        assert w is not None
        due = (job["rotate_bytes"] is not None and w.bytes >= job["rotate_bytes"]) or (
            job["rotate_s"] is not None and time.monotonic() - self.opened_at >= job["rotate_s"]
        )
        if due and w.rows > 0:  # a file holds rows (a Parquet footer alone may be 4 kB)
            self.close_file()
            self.open_next()

    def path(self, part: int) -> Path:
        """The file of part ``part``: ``path`` itself, ``STEM-NNNN.SUFFIX`` when files
        rotate, or in the Hive layout ``path/robot=R/date=YYYY-MM-DD/part-N.parquet``
        (N the next number free in that folder, so a restart adds files)."""
        path, job = Path(self.job["path"]), self.job
        if job.get("layout") == "hive":
            day = time.strftime("%Y-%m-%d", time.gmtime())
            folder = path / f"robot={job['robot']}" / f"date={day}"
            folder.mkdir(parents=True, exist_ok=True)
            taken = [  # a stream a killed writer left (not converted yet) takes its number
                int(m.group(1))
                for p in folder.glob("part-*")
                if (m := re.fullmatch(r"part-(\d+)\.parquet(?:\.arrows|\.tmp)?", p.name))
            ]
            return folder / f"part-{max(taken, default=-1) + 1:04d}.parquet"
        if job["rotate_bytes"] is None and job["rotate_s"] is None:
            return path
        stem, dot, suffix = path.name.partition(".")
        return path.with_name(f"{stem}-{part:04d}{dot}{suffix}")

    def open_next(self) -> None:
        path = self.path(self.files)
        meta = dict(self.job["metadata"])
        if path != Path(self.job["path"]):
            meta["part"] = str(self.files)
        self.writer = open_writer(
            path,
            self.job["columns"],
            meta,
            compresslevel=1,
            row_group_rows=self.job.get("row_group_rows"),
        )
        self.good_bytes = self.writer.bytes
        self.opened_at = time.monotonic()
        self.files += 1
        emit(file=str(path))

    def close_file(self) -> None:
        w, self.writer = self.writer, None
        if w is None:
            return
        try:
            w.close()
        except OSError as exc:
            if not self.failed:
                self.writer = w
                self.fail(exc)
            return
        self.done_rows += w.rows_on_disk
        self.ctl[WRITTEN] = self.done_rows

    def fail(self, exc: OSError) -> None:
        """A write failed (disk full): stop, tell the gateway, keep whole rows on disk."""
        self.failed = True
        self.ctl[STOP] = 1
        why = f"{exc.strerror or exc}"
        w, self.writer = self.writer, None
        path = w.path if w is not None else self.path(max(self.files - 1, 0))
        emit(failed=why)
        emit_log(
            logging.ERROR,
            f"recording stopped: writing {path} failed: {why} ({self.ctl[WRITTEN]} rows "
            "written; later samples are dropped and counted)",
        )
        if w is not None:
            self.abandon(w)

    def abandon(self, w: RowWriter) -> None:
        """Close after a failed write; a plain CSV is cut back to its last whole row (a
        Parquet writer's stream keeps its complete batches: converted when it is read)."""
        with contextlib.suppress(OSError, ValueError):
            w._raw.close()  # type: ignore[attr-defined]  # may still flush part of a row
        with contextlib.suppress(OSError):
            path = w.path
            plain = path.suffix not in (".gz", ".parquet")
            if plain and path.is_file() and path.stat().st_size > self.good_bytes:
                os.truncate(path, self.good_bytes)

    def log_dropped(self, force: bool = False) -> None:
        now, dropped = time.monotonic(), self.ctl[DROPPED]
        if dropped == self.logged_dropped or (not force and now < self.log_at):
            return
        emit_log(
            logging.WARNING,
            f"recording: {dropped} samples dropped ({dropped - self.logged_dropped} since "
            "the last report): the writer is behind",
        )
        self.logged_dropped = dropped
        self.log_at = now + LOG_INTERVAL_S


def emit(**event: Any) -> None:
    """One event line to the gateway (gone: nothing to tell)."""
    with contextlib.suppress(OSError, ValueError):
        sys.stdout.write(json.dumps(event) + "\n")
        sys.stdout.flush()


def emit_log(level: int, message: str) -> None:
    emit(log=[level, message])


def wait_for_end(timeout_s: float, parent: int) -> bool:
    """Sleep up to ``timeout_s`` on stdin; True once it is closed or the parent is gone."""
    ready, _, _ = select.select([0], [], [], timeout_s)
    if ready and not os.read(0, 4096):
        return True
    return os.getppid() != parent


def map_ring(job: dict[str, Any]) -> tuple[mmap.mmap, memoryview, np.ndarray]:
    mm = mmap.mmap(job["fd"], RING_OFFSET + job["rows"] * job["width"] * 8)
    os.close(job["fd"])  # the mapping keeps the memory
    ctl = memoryview(mm)[:RING_OFFSET].cast("q")
    ring = np.ndarray((job["rows"], job["width"]), np.float64, buffer=mm, offset=RING_OFFSET)
    return mm, ctl, ring


def main() -> int:
    realtime.below_the_cycle()  # never compete with a real-time cycle for the CPU
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    parent = os.getppid()
    line = b""
    while not line.endswith(b"\n"):  # the job line; unbuffered, so select() sees the rest
        chunk = os.read(0, 65536)
        if not chunk:
            return 1
        line += chunk
    job = json.loads(line)
    _mm, ctl, ring = map_ring(job)
    sink = Sink(job, ring, ctl)
    try:
        sink.open_next()
    except OSError as exc:
        emit(error=[exc.errno or 0, exc.strerror or str(exc)])
        return 1
    emit(ready=True)
    while True:
        ending = wait_for_end(job["batch_s"], parent)
        sink.drain()
        sink.log_dropped()
        if ending or sink.failed:
            break
    sink.close_file()
    emit(done=int(ctl[WRITTEN]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
