"""The gateway records what it saw: a ring buffer filled by the cycle, drained by a thread.

The cycle calls :meth:`Recorder.push` once: it copies this cycle's inputs and outputs into
a preallocated staging row and that row into the next free slot of a fixed-size float64
ring (``record.buffer_rows`` rows). Nothing else happens in the cycle: no formatting, no
I/O, no lock, no array allocation. When the ring is full (the disk is slower than the
loop) the sample is dropped and counted (:attr:`Recorder.dropped`, exported as
``cdpr_gateway_record_dropped_total``); the cycle never waits.

A writer thread wakes every ``record.batch_s``, formats the filled slots as whole CSV rows
(:class:`gateway.recording.RecordingWriter`) and frees them. Files rotate at whole-row
boundaries after ``record.rotate_bytes`` bytes of text or ``record.rotate_s`` seconds;
with rotation every file is numbered (``out-0000.csv.gz``, ``out-0001.csv.gz``, ...) and
each one is a complete recording (metadata, header, rows). A write that fails (a full
disk: ``ENOSPC``) is logged once, the recorder stops (every later sample is counted as
dropped), a plain CSV is cut back to its last whole row and the file is closed.
:meth:`Recorder.close` (after SIGTERM ends the loop) drains what is left and closes the
file, writing the gzip trailer.

Columns (docs/recording-format.md): ``t`` (s, the loop's clock, 0 at the first sample),
per cable ``velocity_i``, ``tension_sensor_i``, ``length_i``, the pose ``x y z rx ry rz``,
``mass`` (only when the register map provides ``platform_mass``), then the gateway's own
``tension_corrected_i`` and ``status_i``. ``record.columns`` picks kinds among
:data:`RECORD_KINDS` (``t`` is always written).
"""

from __future__ import annotations

import contextlib
import datetime
import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import numpy as np

from gateway.config import RecordConfig
from gateway.recording import POSE_COLUMNS, RecordingWriter

log = logging.getLogger("cdpr_gateway.recorder")

LOG_INTERVAL_S = 10.0  # dropped samples are logged at most this often
MAX_BATCH_ROWS = 4096  # rows formatted per write


def ring_columns(cables: int, with_mass: bool) -> list[tuple[str, str]]:
    """(kind, column name) of every ring column, in ring order."""
    cols = [("t", "t")]
    for kind in ("velocity", "tension_sensor", "length"):
        cols += [(kind, f"{kind}_{i + 1}") for i in range(cables)]
    cols += [("pose", p) for p in POSE_COLUMNS]
    if with_mass:
        cols.append(("mass", "mass"))
    for kind in ("tension_corrected", "status"):
        cols += [(kind, f"{kind}_{i + 1}") for i in range(cables)]
    return cols


Opener = Callable[[Path], IO[bytes]]


class Recorder:
    """Single producer (the cycle's :meth:`push`), single consumer (the writer thread)."""

    def __init__(
        self,
        cfg: RecordConfig,
        cables: int,
        *,
        with_mass: bool = False,
        metadata: dict[str, str] | None = None,
        opener: Opener | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if cfg.path is None:
            raise ValueError("record.path is not set")
        self.cfg = cfg
        self.cables = cables
        cols = ring_columns(cables, with_mass)
        keep = {"t", *cfg.columns}
        self._select = np.array([i for i, (k, _) in enumerate(cols) if k in keep])
        self.columns = [cols[i][1] for i in self._select]
        self._ring = np.full((cfg.buffer_rows, len(cols)), np.nan)
        self._row = np.full(len(cols), np.nan)
        m = cables
        self._views = {
            "velocity": self._row[1 : 1 + m],
            "tension_sensor": self._row[1 + m : 1 + 2 * m],
            "length": self._row[1 + 2 * m : 1 + 3 * m],
            "pose": self._row[1 + 3 * m : 7 + 3 * m],
        }
        base = 7 + 3 * m + (1 if with_mass else 0)
        self._mass_col = 7 + 3 * m if with_mass else -1
        self._corrected = self._row[base : base + m]
        self._status = self._row[base + m : base + 2 * m]
        self._head = 0  # written by push only
        self._tail = 0  # written by the writer thread only
        self._t0: float | None = None
        self._accepting = True
        self.dropped = 0
        self.rows_written = 0
        self.files: list[Path] = []
        self.failed: str | None = None
        self.metadata = {
            "source": "cdpr-gateway run --record",
            "clock": "t is the loop's monotonic clock in s, 0 at the first sample",
            "started": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            **(metadata or {}),
        }
        self._opener = opener
        self._clock = clock
        self._writer: RecordingWriter | None = None
        self._opened_at = 0.0
        self._good_bytes = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._logged_dropped = 0
        self._log_at = 0.0

    # --- the cycle's side ----------------------------------------------------------------
    def push(self, now: float, inputs: Any, outputs: Any) -> None:
        """Copy one cycle into the ring (no I/O, no lock); a full ring drops and counts."""
        head = self._head
        if not self._accepting or head - self._tail >= self._ring.shape[0]:
            self.dropped += 1
            return
        if self._t0 is None:
            self._t0 = now
        row, v = self._row, self._views
        row[0] = now - self._t0
        np.copyto(v["velocity"], inputs.velocity_m_s)
        np.copyto(v["tension_sensor"], inputs.tension_raw_n)
        np.copyto(v["length"], inputs.length_m)
        np.copyto(v["pose"], inputs.pose)
        if self._mass_col >= 0:
            row[self._mass_col] = getattr(inputs, "platform_mass_kg", np.nan)
        np.copyto(self._corrected, outputs.tension_corrected_n)
        np.copyto(self._status, outputs.channel_status, casting="unsafe")
        self._ring[head % self._ring.shape[0]] = row
        self._head = head + 1

    # --- lifecycle -----------------------------------------------------------------------
    def start(self) -> None:
        """Open the first file (errors raise here, before the loop runs) and the thread."""
        self._open_next()
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()

    def close(self, timeout_s: float = 30.0) -> None:
        """Stop accepting, drain what is in the ring, close the file (gzip trailer)."""
        self._accepting = False
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.error("recording: the writer did not finish within %.0f s", timeout_s)
        else:
            self._close_file()
        self._log_dropped(force=True)

    # --- the writer thread ---------------------------------------------------------------
    def _run(self) -> None:
        try:
            while True:
                stopping = self._stop.wait(self.cfg.batch_s)
                self._drain()
                self._log_dropped()
                if stopping or self.failed:
                    break
        finally:
            self._close_file()

    def _drain(self) -> None:
        """Write every filled slot as whole rows, in batches, rotating between batches."""
        size = self._ring.shape[0]
        while not self.failed:
            head, tail = self._head, self._tail
            if head == tail:
                return
            start = tail % size
            count = min(head - tail, size - start, MAX_BATCH_ROWS)
            block = self._ring[start : start + count][:, self._select]
            try:
                self._maybe_rotate()
                assert self._writer is not None
                self._writer.write_rows(block)
                self._good_bytes = self._writer.bytes
            except OSError as exc:
                self._fail(exc)
                return
            self.rows_written += count
            self._tail = tail + count

    def _maybe_rotate(self) -> None:
        w, cfg = self._writer, self.cfg
        assert w is not None
        due = (cfg.rotate_bytes is not None and w.bytes >= cfg.rotate_bytes) or (
            cfg.rotate_s is not None and self._clock() - self._opened_at >= cfg.rotate_s
        )
        if due:
            self._close_file()
            self._open_next()

    def _path(self, part: int) -> Path:
        path = Path(str(self.cfg.path))
        if self.cfg.rotate_bytes is None and self.cfg.rotate_s is None:
            return path
        name = path.name
        stem, dot, suffix = name.partition(".")
        return path.with_name(f"{stem}-{part:04d}{dot}{suffix}")

    def _open_next(self) -> None:
        path = self._path(len(self.files))
        raw = self._opener(path) if self._opener is not None else open(path, "wb")  # noqa: SIM115
        meta = dict(self.metadata)
        if path != Path(str(self.cfg.path)):
            meta["part"] = str(len(self.files))
        self._writer = RecordingWriter(path, self.columns, meta, fileobj=raw, compresslevel=1)
        self._good_bytes = self._writer.bytes
        self._opened_at = self._clock()
        self.files.append(path)

    def _close_file(self) -> None:
        w, self._writer = self._writer, None
        if w is None:
            return
        try:
            w.close()
        except OSError as exc:
            if not self.failed:
                self._fail(exc)

    def _fail(self, exc: OSError) -> None:
        """A write failed (disk full): stop recording, count what is lost, keep the cycle."""
        self.failed = f"{exc.strerror or exc}"
        self._accepting = False
        self.dropped += self._head - self._tail
        self._tail = self._head
        w, self._writer = self._writer, None
        path = self.files[-1] if self.files else self.cfg.path
        log.error(
            "recording stopped: writing %s failed: %s (%d rows written; later samples are "
            "dropped and counted)", path, self.failed, self.rows_written,
        )  # fmt: skip
        if w is not None:
            self._abandon(w)

    def _abandon(self, w: RecordingWriter) -> None:
        """Close after a failed write; a plain CSV is cut back to its last whole row."""
        with contextlib.suppress(OSError, ValueError):
            w._raw.close()  # a buffered file may still flush part of a row here
        with contextlib.suppress(OSError):
            if w.path.suffix != ".gz" and w.path.stat().st_size > self._good_bytes:
                os.truncate(w.path, self._good_bytes)

    def _log_dropped(self, force: bool = False) -> None:
        now = self._clock()
        if self.dropped == self._logged_dropped or (not force and now < self._log_at):
            return
        log.warning(
            "recording: %d samples dropped (%d since the last report): the writer is behind",
            self.dropped, self.dropped - self._logged_dropped,
        )  # fmt: skip
        self._logged_dropped = self.dropped
        self._log_at = now + LOG_INTERVAL_S
