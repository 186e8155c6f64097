"""The gateway records what it saw: a shared-memory ring filled by the cycle, drained by a
writer process.

The cycle calls :meth:`Recorder.push` once: it copies this cycle's inputs and outputs into
a preallocated staging row and that row into the next free slot of a fixed-size float64
ring (``record.buffer_rows`` rows) in shared memory, then publishes the new head. Nothing
else happens in the cycle: no formatting, no I/O, no system call, no lock, no array
allocation. When the ring is full (the disk is slower than the loop) the sample is
dropped and counted (:attr:`Recorder.dropped`, exported as
``cdpr_gateway_record_dropped_total``); the cycle never waits.

A writer *process* (:mod:`gateway.service.recorder_proc`: a fresh interpreter, SCHED_OTHER at
nice 10 even under a SCHED_FIFO gateway) wakes every ``record.batch_s``, formats the
filled slots as whole CSV rows and frees them. It is a process, not a thread, because
formatting in the gateway's process held the GIL: the cycle thread waited for it on
wake-up and overruns went from 0.08 % to 0.46 % of cycles (``python -m bench record``).
Files rotate at whole-row boundaries after ``record.rotate_bytes`` bytes or
``record.rotate_s`` seconds; with rotation every file is numbered (``out-0000.csv.gz``,
``out-0001.csv.gz``, ...) and each one is a complete recording (metadata, header, rows).
A ``.parquet`` path writes Parquet (an Arrow IPC stream, a record batch per drain, that a
kill cuts at most by the batch being written, converted at close into row groups of
:data:`ROW_GROUP_S`; pyarrow is imported by the writer process only, never by the gateway's);
``record.layout: hive`` writes ``path/robot=R/date=YYYY-MM-DD/part-N.parquet``.
A write that fails (a full disk: ``ENOSPC``) is logged once, the recorder stops (every
later sample, and what was still in the ring, is counted as dropped), a plain CSV is cut
back to its last whole row and the file is closed. :meth:`Recorder.close` (after SIGTERM
ends the loop) lets the writer drain what is left and close the file, writing the gzip
trailer; if the gateway dies, the writer sees its pipe close and does the same.

Columns (docs/recording-format.md): ``t`` (s, the loop's clock, 0 at the first sample),
per cable ``velocity_i``, ``tension_sensor_i``, ``length_i``, the pose ``x y z rx ry rz``,
``mass`` (only when the register map provides ``platform_mass``), then the gateway's own
``tension_corrected_i`` and ``status_i``. ``record.columns`` picks kinds among
:data:`RECORD_KINDS` (``t`` is always written).
"""

from __future__ import annotations

import contextlib
import datetime
import json
import logging
import mmap
import os
import socket
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import IO, Any

import numpy as np

from gateway.core.config import RECORD_KINDS, RecordConfig
from gateway.recordings.reader import POSE_COLUMNS
from gateway.runtime import realtime
from gateway.service.recorder_proc import DROPPED, HEAD, RING_OFFSET, STOP, TAIL, WRITTEN

__all__ = ["RECORD_KINDS", "RecordConfig", "Recorder", "ring_columns"]

log = logging.getLogger("cdpr_gateway.recorder")

PACKAGE_ROOT = str(Path(__file__).resolve().parents[2])  # where ``gateway`` is found
ROW_GROUP_S = 5.0  # a Parquet recording's row groups (converted at close from its stream)


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


def _shared_fd(nbytes: int) -> int:
    """A descriptor of ``nbytes`` of shared memory without a name (nothing to leak)."""
    try:
        fd = os.memfd_create("cdpr-gateway-record", os.MFD_CLOEXEC)
    except (AttributeError, OSError):  # not Linux, or a seccomp filter without memfd
        shm = "/dev/shm" if os.path.isdir("/dev/shm") else None
        with tempfile.TemporaryFile(dir=shm) as tmp:  # already unlinked
            fd = os.dup(tmp.fileno())
    os.ftruncate(fd, nbytes)
    return fd


class Recorder:
    """Single producer (the cycle's :meth:`push`), single consumer (the writer process)."""

    def __init__(
        self,
        cfg: RecordConfig,
        cables: int,
        *,
        with_mass: bool = False,
        metadata: dict[str, str] | None = None,
        period_s: float = 0.001,
    ) -> None:
        if cfg.path is None:
            raise ValueError("record.path is not set")
        self.cfg = cfg
        self.robot = cfg.robot or socket.gethostname()
        self.row_group_rows = max(1, round(ROW_GROUP_S / period_s))
        self.cables = cables
        cols = ring_columns(cables, with_mass)
        keep = {"t", *cfg.columns}
        self._select = [i for i, (k, _) in enumerate(cols) if k in keep]
        self.columns = [cols[i][1] for i in self._select]
        self._width, self._size = len(cols), cfg.buffer_rows
        self._fd = _shared_fd(RING_OFFSET + self._size * self._width * 8)
        self._mm: mmap.mmap | None = mmap.mmap(self._fd, RING_OFFSET + self._size * self._width * 8)
        self._ctl = memoryview(self._mm)[:RING_OFFSET].cast("q")
        self._ring = np.ndarray((self._size, self._width), np.float64, self._mm, RING_OFFSET)
        self._ring.fill(np.nan)  # every page touched now, never first in a cycle
        self._row = np.full(self._width, np.nan)
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
        self._head = 0  # the cycle's copy of HEAD
        self._t0: float | None = None
        self._accepting = True
        self._dropped = 0  # samples push dropped
        self._final: tuple[int, bool] | None = None  # (rows written, stopped) once closed
        self.files: list[Path] = []
        self.failed: str | None = None
        self.metadata = {
            "source": "cdpr-gateway run --record",
            "clock": "t is the loop's monotonic clock in s, 0 at the first sample",
            "started": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "robot": self.robot,
            **(metadata or {}),
        }
        self._proc: subprocess.Popen[str] | None = None
        self._events: threading.Thread | None = None
        self._done = False

    # --- the cycle's side ----------------------------------------------------------------
    def push(self, now: float, inputs: Any, outputs: Any) -> None:
        """Copy one cycle into the ring (no I/O, no lock); a full ring drops and counts."""
        if not self._accepting:
            self._dropped += 1
            return
        head, ctl = self._head, self._ctl
        if ctl[STOP] or head - ctl[TAIL] >= self._size:
            self._dropped += 1
            ctl[DROPPED] = self._dropped
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
        self._ring[head % self._size] = row
        self._head = head + 1
        ctl[HEAD] = head + 1  # publish after the row (x86-64 keeps stores in order)

    # --- what the parent sees ------------------------------------------------------------
    @property
    def rows_written(self) -> int:
        return self._final[0] if self._final is not None else self._ctl[WRITTEN]

    @property
    def dropped(self) -> int:
        """Samples not recorded: a full ring, and once the writer stopped (failed, ended)
        every sample it had not written."""
        written, stopped = (
            self._final if self._final is not None else (self._ctl[WRITTEN], bool(self._ctl[STOP]))
        )
        return self._dropped + (self._head - written if stopped else 0)

    @property
    def pid(self) -> int | None:
        """The writer process's pid (benchmarks read its CPU time)."""
        return self._proc.pid if self._proc is not None else None

    # --- lifecycle -----------------------------------------------------------------------
    def start(self) -> None:
        """Start the writer; it opens the first file (errors raise here, before the loop)."""
        if self._proc is not None:
            raise RuntimeError("the recorder was started already")
        self._proc = self._spawn()
        assert self._proc.stdin is not None and self._proc.stdout is not None
        job = {
            "fd": self._fd,
            "rows": self._size,
            "width": self._width,
            "select": self._select,
            "columns": self.columns,
            "metadata": self.metadata,
            "path": str(self.cfg.path),
            "rotate_bytes": self.cfg.rotate_bytes,
            "rotate_s": self.cfg.rotate_s,
            "batch_s": self.cfg.batch_s,
            "layout": self.cfg.layout,
            "robot": self.robot,
            "row_group_rows": self.row_group_rows,
        }
        try:
            self._proc.stdin.write(json.dumps(job) + "\n")
            self._proc.stdin.flush()
        except OSError:
            pass  # the writer died at start: its status is reported below
        finally:
            os.close(self._fd)  # the writer has its own copy
            self._fd = -1
        while True:
            event = self._next_event(self._proc.stdout)
            if event is None or "error" in event:
                self._proc.wait()
                with contextlib.suppress(OSError):
                    self._proc.stdin.close()
                self._proc.stdout.close()
                self._release()
                code, why = (event or {}).get("error") or (0, "")
                why = why or f"the writer process ended (exit status {self._proc.returncode})"
                raise OSError(code, why)
            self._handle(event)
            if event.get("ready"):
                break
        self._events = threading.Thread(target=self._read_events, name="recorder", daemon=True)
        self._events.start()

    def _spawn(self) -> subprocess.Popen[str]:
        """``python -m gateway.service.recorder_proc``, started from a thread lowered below the
        cycle, so the writer never runs a moment real-time (a child inherits the policy and
        nice of the thread that forks it)."""
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (PACKAGE_ROOT, env.get("PYTHONPATH")) if p)
        result: list[Any] = []

        def spawn() -> None:
            realtime.below_the_cycle()
            try:
                result.append(
                    subprocess.Popen(
                        [sys.executable, "-m", "gateway.service.recorder_proc"],
                        stdin=subprocess.PIPE,
                        stdout=subprocess.PIPE,
                        pass_fds=(self._fd,),
                        env=env,
                        text=True,
                    )
                )
            except OSError as exc:
                result.append(exc)

        starter = threading.Thread(target=spawn, name="recorder-start")
        starter.start()
        starter.join()
        if isinstance(result[0], OSError):
            self._release()
            raise result[0]
        proc: subprocess.Popen[str] = result[0]
        return proc

    @staticmethod
    def _next_event(stream: IO[str]) -> dict[str, Any] | None:
        line = stream.readline()
        return json.loads(line) if line else None

    def _handle(self, event: dict[str, Any]) -> None:
        if "file" in event:
            self.files.append(Path(event["file"]))
        if "failed" in event:
            self.failed = event["failed"]
        if "log" in event:
            log.log(*event["log"])
        if "done" in event:
            self._done = True

    def _read_events(self) -> None:
        """The writer's events: files opened, failures, log lines; its unexpected end."""
        realtime.below_the_cycle()
        assert self._proc is not None and self._proc.stdout is not None
        while (event := self._next_event(self._proc.stdout)) is not None:
            self._handle(event)
        if not self._done and self.failed is None:  # killed, crashed: stop recording
            code = self._proc.wait()
            self.failed = f"the writer process ended (exit status {code})"
            log.error("recording stopped: %s; later samples are dropped and counted", self.failed)
        if not self._done:
            self._ctl[STOP] = 1

    def close(self, timeout_s: float = 30.0) -> None:
        """Stop accepting, let the writer drain the ring and close the file (gzip trailer)."""
        if self._final is not None:
            return
        self._accepting = False
        proc = self._proc
        if proc is not None:
            assert proc.stdin is not None
            with contextlib.suppress(OSError):
                proc.stdin.close()  # EOF: drain, close the file, exit
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                log.error("recording: the writer did not finish within %.0f s", timeout_s)
                proc.kill()
                proc.wait()
            if self._events is not None:
                self._events.join()
            assert proc.stdout is not None
            proc.stdout.close()
        self._release()
        if self.dropped:
            log.warning("recording: %d samples dropped in all", self.dropped)

    def _release(self) -> None:
        """Keep the final counters, unmap the ring."""
        if self._final is None:  # the writer has ended: what it has not written is lost
            self._final = (self._ctl[WRITTEN], True)
        self._accepting = False
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
        del self._ring
        self._ctl.release()
        if self._mm is not None:
            self._mm.close()
            self._mm = None
