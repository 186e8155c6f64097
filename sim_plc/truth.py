"""The demo's scoring: the gateway's raw and corrected tensions against the plant's truth.

* :class:`TruthScorer`: a loop observer that reads the truth in the cycle (in process and
  single-threaded only: ``demo --offline``, where the truth is of the very plant step read).
* :class:`CycleRing` + :class:`TruthMatcher`: against a running soft PLC. The observer only
  copies (heartbeat, raw, corrected, status) into a preallocated ring -- no allocation, no
  I/O, no logging in the cycle; a thread of its own reads the truth (the side channel,
  :class:`TruthChannel`) and scores the cycle that read the same plant step.
* :class:`TruthChannel`: the demo's own Modbus connection to the soft PLC's side channel
  (:data:`sim_plc.modbus_server.TRUTH_ADDRESS`: the true tensions and the PLC heartbeat of
  one plant step, in no gateway register map).
"""

from __future__ import annotations

import math
import os
import socket
import struct
import threading
import time
from collections.abc import Callable

import numpy as np

from drivers.base import Inputs
from gateway.runtime.compensator import Compensator
from sim_plc.modbus_server import TRUTH_ADDRESS

SCORE_AFTER_S = 0.5  # scoring skips the model's warm-up
TRUTH_EVERY_CYCLES = 10  # the in-cycle scorer (TruthScorer) samples the truth this seldom
TRUTH_INTERVAL_S = 0.01  # the off-cycle matcher (TruthMatcher) reads the truth this often
RING_SIZE = 1024  # cycles the demo's observer keeps for matching (~1 s at 1 kHz)
MATCH_WINDOW_S = 0.25  # a ring slot older than this is an old lap of the 16-bit heartbeat
WAIT_FOR_CYCLE_S = 0.005  # how long a truth sample waits for the gateway to read its step
TruthSource = Callable[[np.ndarray], "int | None"]  # fills truth, returns its heartbeat


class TruthScore:
    """Sums of squared error of raw and corrected tensions against the plant's truth."""

    def __init__(self, cables: int) -> None:
        self.raw_sq = np.zeros(cables)
        self.corrected_sq = np.zeros(cables)
        self.samples = np.zeros(cables, dtype=np.int64)

    def add(self, truth: np.ndarray, raw: np.ndarray, corrected: np.ndarray,
            status: np.ndarray) -> None:  # fmt: skip
        """Add the squared errors of the good channels (status 0, finite) against ``truth``."""
        good = (status == 0) & np.isfinite(corrected) & np.isfinite(truth)
        self.raw_sq[good] += (raw[good] - truth[good]) ** 2
        self.corrected_sq[good] += (corrected[good] - truth[good]) ** 2
        self.samples[good] += 1

    def rmse(self) -> tuple[np.ndarray, np.ndarray]:
        n = np.maximum(self.samples, 1)
        return np.sqrt(self.raw_sq / n), np.sqrt(self.corrected_sq / n)


class TruthScorer:
    """A loop observer: every ``every`` cycles (after ``SCORE_AFTER_S``) it asks ``source``
    for the plant's truth and scores the gateway's raw and corrected tensions against it.

    ``source(truth)`` fills ``truth`` and returns the PLC heartbeat of that plant step
    (None: unknown, score anyway); a heartbeat other than the gateway's reading means
    the plant has stepped since: that sample is skipped (``mismatched``) and the next
    cycle tries again.
    """

    def __init__(self, cables: int, source: TruthSource, every: int = 1) -> None:
        self.score = TruthScore(cables)
        self.source = source
        self.every = every
        self.truth = np.zeros(cables)
        self.mismatched = 0
        self.failed = 0
        self._countdown = 1
        self._started: float | None = None

    def __call__(self, inputs: Inputs, comp: Compensator, now: float) -> None:
        if self._started is None:
            self._started = now
        if now - self._started < SCORE_AFTER_S:
            return
        self._countdown -= 1
        if self._countdown > 0:
            return
        self._countdown = self.every
        try:
            heartbeat = self.source(self.truth)
        except OSError:
            self.failed += 1
            return
        if heartbeat is not None and heartbeat != inputs.plc_heartbeat:
            self.mismatched += 1
            self._countdown = 1  # the plant stepped in between: try again next cycle
            return
        self.score.add(self.truth, comp.raw_n, comp.corrected_n, comp.status)


class CycleRing:
    """A loop observer that only copies: each cycle's PLC heartbeat, raw and corrected
    tensions and channel status go into slot ``heartbeat % size`` of preallocated arrays
    (after ``SCORE_AFTER_S``). It allocates nothing, logs nothing and does no I/O, so the
    scoring costs the cycle a few copies; :class:`TruthMatcher` reads the ring off the cycle.

    A slot's ``stamp`` is -1 while it is written (a reader that sees the same heartbeat
    before and after its copy has a whole sample); ``when`` is the cycle's time.
    """

    def __init__(self, cables: int, size: int = RING_SIZE) -> None:
        if size & (size - 1) or not 0 < size <= 0x10000:
            raise ValueError("ring size must be a power of two <= 65536")
        self.mask = size - 1
        self.stamp = np.full(size, -1, dtype=np.int64)
        self.when = np.full(size, -math.inf)
        self.raw = np.zeros((size, cables))
        self.corrected = np.zeros((size, cables))
        self.status = np.zeros((size, cables), dtype=np.uint16)
        self._rows = [(self.raw[i], self.corrected[i], self.status[i]) for i in range(size)]
        self.latest = -1  # slot of the last cycle copied
        self.copied = 0  # cycles copied
        self._started = math.nan

    def __call__(self, inputs: Inputs, comp: Compensator, now: float) -> None:
        if self._started != self._started:
            self._started = now
        if now - self._started < SCORE_AFTER_S:
            return
        hb = inputs.plc_heartbeat
        slot = int(hb) & self.mask
        raw, corrected, status = self._rows[slot]
        self.stamp[slot] = -1
        np.copyto(raw, comp.raw_n)
        np.copyto(corrected, comp.corrected_n)
        np.copyto(status, comp.status)
        self.when[slot] = now
        self.stamp[slot] = hb
        self.latest = slot
        self.copied += 1

    def take(self, heartbeat: int | None, near: float, into: tuple[np.ndarray, ...]) -> bool:
        """Copy the cycle that read ``heartbeat`` (None: the latest cycle) into ``into``
        (raw, corrected, status) if the ring holds it from within ``MATCH_WINDOW_S`` of
        ``near`` (not an old lap of the 16-bit heartbeat); False if it does not."""
        slot = self.latest if heartbeat is None else heartbeat & self.mask
        if slot < 0:
            return False
        stamp = int(self.stamp[slot])
        if stamp < 0 or (heartbeat is not None and stamp != heartbeat):
            return False
        if abs(float(self.when[slot]) - near) > MATCH_WINDOW_S:
            return False
        for dst, src in zip(into, self._rows[slot], strict=True):
            np.copyto(dst, src)
        return int(self.stamp[slot]) == stamp  # not rewritten while copied


def lowest_realtime() -> bool:
    """SCHED_FIFO priority 1 for the calling thread where permitted; False if refused."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except (OSError, AttributeError):
        return False
    return True


class TruthMatcher:
    """Scores the gateway against the plant's truth off the cycle, on its own thread.

    Every ``interval_s`` it asks ``source`` for the truth (the side channel: one Modbus
    transaction on its own connection) and looks up, in the :class:`CycleRing`, the cycle
    that read the same plant step (PLC heartbeat); a step the gateway has not read yet is
    looked up again for up to ``WAIT_FOR_CYCLE_S``. Counts: ``read`` truth samples
    received, ``matched`` scored, ``unmatched`` (the gateway never read that plant step:
    an overrun, or two plant steps between two of its reads),
    ``failed`` (the side channel failed). The thread shares the GIL (held for a few
    numpy operations at a time) and the soft PLC's server (one request per ``interval_s``)
    with the cycle; :meth:`set_realtime` keeps it from being preempted while it holds the
    GIL (the loop would wait behind it).
    """

    def __init__(self, ring: CycleRing, source: TruthSource, cables: int,
                 interval_s: float = TRUTH_INTERVAL_S) -> None:  # fmt: skip
        self.ring, self.source, self.interval_s = ring, source, interval_s
        self.score = TruthScore(cables)
        self.truth = np.zeros(cables)
        self._sample = (np.zeros(cables), np.zeros(cables), np.zeros(cables, dtype=np.uint16))
        self.read = self.matched = self.unmatched = self.failed = 0
        self.by_heartbeat = True  # False once the source gave no heartbeat
        self.priority: int | None = None  # set_realtime(): SCHED_FIFO 1 for this thread
        self.priority_applied = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="demo-truth", daemon=True)

    def set_realtime(self) -> None:
        """Run the thread at SCHED_FIFO priority 1 (below the loop's): a thread that takes
        the GIL must not be preempted by every normal process while it holds it, or the
        loop waits for the GIL behind it (priority inversion)."""
        self.priority = 1

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=10)

    def _run(self) -> None:
        if self.priority is not None:
            self.priority_applied = lowest_realtime()
        rng = np.random.default_rng()
        # a random gap (0.5..1.5 intervals): samples not phase-locked to the plant's steps
        while not self._stop.wait(self.interval_s * (0.5 + rng.random())):
            if self.ring.copied == 0:
                continue  # the gateway is not scoring yet (warm-up)
            self.poll()

    def poll(self) -> None:
        """One truth sample: read it, find the gateway's cycle of that plant step, score."""
        try:
            heartbeat = self.source(self.truth)
        except OSError:
            self.failed += 1
            return
        self.read += 1
        self.by_heartbeat = heartbeat is not None
        give_up = time.monotonic() + WAIT_FOR_CYCLE_S
        while not self.ring.take(heartbeat, time.monotonic(), self._sample):
            if time.monotonic() >= give_up or self._stop.wait(0.001):
                self.unmatched += 1
                return
        raw, corrected, status = self._sample
        self.score.add(self.truth, raw, corrected, status)
        self.matched += 1


class TruthChannel:
    """The demo's own Modbus connection to the soft PLC's side channel (function 3).

    Reads the true tensions and the PLC heartbeat of one plant step in one transaction;
    a failed connection is retried at most once per second.
    """

    def __init__(self, host: str, port: int, unit_id: int, cables: int) -> None:
        self.address = (host, port)
        self.unit_id = unit_id
        self.words = 2 * cables + 1
        self.reply_len = 9 + 2 * self.words
        self._sock: socket.socket | None = None
        self._tid = 0
        self._retry_at = 0.0

    def __call__(self, truth: np.ndarray) -> int:
        sock = self._connect()
        self._tid = (self._tid + 1) & 0xFFFF
        request = struct.pack(">HHHBBHH", self._tid, 0, 6, self.unit_id, 3, TRUTH_ADDRESS,
                              self.words)  # fmt: skip
        try:
            sock.sendall(request)
            reply = b""
            while len(reply) < self.reply_len:
                chunk = sock.recv(self.reply_len - len(reply))
                if not chunk:
                    raise OSError("side channel closed")
                reply += chunk
                if len(reply) >= 9 and reply[7] & 0x80:
                    raise OSError(f"side channel: exception {reply[8]}")
        except OSError:
            self.close()
            raise
        if struct.unpack_from(">H", reply)[0] != self._tid:
            self.close()
            raise OSError("side channel: wrong transaction id")
        truth[:] = np.frombuffer(reply, ">f4", count=truth.size, offset=9)
        return int(struct.unpack_from(">H", reply, 9 + 4 * truth.size)[0])

    def _connect(self) -> socket.socket:
        if self._sock is not None:
            return self._sock
        if time.monotonic() < self._retry_at:
            raise OSError("side channel: waiting to reconnect")
        self._retry_at = time.monotonic() + 1.0
        sock = socket.create_connection(self.address, timeout=0.05)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = sock
        return sock

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
