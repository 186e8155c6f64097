"""The demo's scoring: the gateway's raw and corrected tensions against the plant's truth.

* :class:`TruthScorer`: a loop observer that reads the truth in the cycle (in process and
  single-threaded only: ``demo --offline``, where the truth is of the very plant step read).
* :class:`CycleRing` + :class:`TruthMatcher`: against a running soft PLC. The observer only
  copies (heartbeat, raw, corrected, status) into a preallocated ring -- no allocation, no
  I/O, no logging in the cycle; a thread of its own reads the truth (the side channel,
  :class:`TruthChannel`) and scores the cycle that read the same plant step.
* :class:`TruthChannel`: the demo's own Modbus connection to the soft PLC's side channel
  (:data:`sim_plc.modbus_image.TRUTH_ADDRESS`: the true tensions and the PLC heartbeat of
  one plant step, in no gateway register map).
* :class:`ChainWarmup`: which cables' friction state has forgotten its relaxed start, so
  that a score measures the model, not where the plant happened to be when the gateway
  joined it.
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
from gateway.core.config import Config
from gateway.model import effects as fx
from gateway.model.chain_schema import coulomb_coefficients
from gateway.runtime.compensator import Compensator
from sim_plc.modbus_image import TRUTH_ADDRESS

SCORE_AFTER_S = 0.5  # scoring skips the loop's start, and each cable's chain warm-up
WARMUP_LENGTHS = 4.0
"""Relaxation lengths ``F_R / sigma`` of cable travel before a cable is scored. The soft PLC's
plant has run (and its pulleys' pre-sliding state developed) before the gateway connects,
whose chain starts relaxed; the difference decays as ``exp(-sigma |x| / F_R)`` over the
travel ``x``, 2 % after four lengths: the diagnosis leaves out the same warm-up
(``gateway.diagnose.engine.WARMUP_LENGTHS``). Measured on replays of a live read pattern,
the first seconds otherwise decided a 30-s score: 0.500 N from 2 s on, 0.50-0.56 N from
0.5 s (nominal friction) and 0.51-0.78 N (mu 0.025), by where the plant was at the
gateway's start."""
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

    def add(
        self,
        truth: np.ndarray,
        raw: np.ndarray,
        corrected: np.ndarray,
        status: np.ndarray,
        warm: np.ndarray | None = None,
    ) -> None:
        """Add the squared errors of the good channels (status 0, finite, ``warm`` where
        given) against ``truth``."""
        good = (status == 0) & np.isfinite(corrected) & np.isfinite(truth)
        if warm is not None:
            good &= warm
        self.raw_sq[good] += (raw[good] - truth[good]) ** 2
        self.corrected_sq[good] += (corrected[good] - truth[good]) ** 2
        self.samples[good] += 1

    def rmse(self) -> tuple[np.ndarray, np.ndarray]:
        n = np.maximum(self.samples, 1)
        return np.sqrt(self.raw_sq / n), np.sqrt(self.corrected_sq / n)


class ChainWarmup:
    """Per cable, whether the gateway's chain has travelled ``WARMUP_LENGTHS`` relaxation
    lengths since its first cycle (True from the start for a chain without pre-sliding
    state: Coulomb or none). ``F_R`` is the cable's largest pulley level at its corrected
    tension of the cycle; ``sigma`` its Dahl stiffness, from ``cfg``'s model and fitted
    effects. :meth:`update` allocates nothing (it runs in the cycle's observers)."""

    def __init__(self, cfg: Config) -> None:
        m = cfg.cables
        params = fx.chain_params(cfg.friction, cfg.friction.effect_values(m), m)
        dahl = params.model == "dahl" and params.pulleys > 0
        self.lam = np.zeros(m)
        self.f0 = np.zeros(m)
        if dahl:
            lam_pos, lam_neg = coulomb_coefficients(params)
            self.lam = np.max(np.maximum(lam_pos, lam_neg), axis=1)
            self.f0 = params.f0_n / params.pulleys
        self.per_sigma = WARMUP_LENGTHS / np.maximum(params.sigma_n_m, 1e-12)
        self.travel = np.zeros(m)
        self.warm = np.full(m, not dahl)
        self.all_warm = not dahl
        self._at = math.nan
        self._step = np.zeros(m)
        self._need = np.zeros(m)
        self._reached = np.zeros(m, bool)

    def update(self, velocity: np.ndarray, tension: np.ndarray, now: float) -> np.ndarray:
        """Add the travel since the previous call (|v| times the time between calls) and
        return the (m,) warm mask (a cable stays warm once it is)."""
        if self.all_warm:
            return self.warm
        dt = now - self._at if self._at == self._at else 0.0
        self._at = now
        np.abs(velocity, out=self._step)
        self._step *= max(dt, 0.0)
        self.travel += self._step
        np.abs(tension, out=self._need)
        self._need *= self.lam
        self._need += self.f0
        self._need *= self.per_sigma
        np.greater_equal(self.travel, self._need, out=self._reached)
        self.warm |= self._reached
        self.all_warm = bool(self.warm.all())
        return self.warm


class TruthScorer:
    """A loop observer: every ``every`` cycles (after ``SCORE_AFTER_S``) it asks ``source``
    for the plant's truth and scores the gateway's raw and corrected tensions against it.

    ``source(truth)`` fills ``truth`` and returns the PLC heartbeat of that plant step
    (None: unknown, score anyway); a heartbeat other than the gateway's reading means
    the plant has stepped since: that sample is skipped (``mismatched``) and the next
    cycle tries again. With ``warmup`` a cable is scored once its chain has warmed up.
    """

    def __init__(
        self, cables: int, source: TruthSource, every: int = 1, warmup: ChainWarmup | None = None
    ) -> None:
        self.score = TruthScore(cables)
        self.source = source
        self.every = every
        self.warmup = warmup
        self.truth = np.zeros(cables)
        self.mismatched = 0
        self.failed = 0
        self._countdown = 1
        self._started: float | None = None

    def __call__(self, inputs: Inputs, comp: Compensator, now: float) -> None:
        if self._started is None:
            self._started = now
        warm = None
        if self.warmup is not None:
            warm = self.warmup.update(comp.velocity_m_s, comp.corrected_n, now)
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
        self.score.add(self.truth, comp.raw_n, comp.corrected_n, comp.status, warm)


class CycleRing:
    """A loop observer that only copies: each cycle's PLC heartbeat, raw and corrected
    tensions and channel status go into slot ``heartbeat % size`` of preallocated arrays
    (after ``SCORE_AFTER_S``). It allocates nothing, logs nothing and does no I/O, so the
    scoring costs the cycle a few copies; :class:`TruthMatcher` reads the ring off the cycle.

    A slot's ``stamp`` is -1 while it is written (a reader that sees the same heartbeat
    before and after its copy has a whole sample); ``when`` is the cycle's time. With
    ``warmup`` each slot also holds which cables had warmed up (else all count).
    """

    def __init__(
        self, cables: int, size: int = RING_SIZE, warmup: ChainWarmup | None = None
    ) -> None:
        if size & (size - 1) or not 0 < size <= 0x10000:
            raise ValueError("ring size must be a power of two <= 65536")
        self.mask = size - 1
        self.stamp = np.full(size, -1, dtype=np.int64)
        self.when = np.full(size, -math.inf)
        self.raw = np.zeros((size, cables))
        self.corrected = np.zeros((size, cables))
        self.status = np.zeros((size, cables), dtype=np.uint16)
        self.warm = np.ones((size, cables), dtype=bool)
        self.warmup = warmup
        self._rows = [
            (self.raw[i], self.corrected[i], self.status[i], self.warm[i]) for i in range(size)
        ]
        self.latest = -1  # slot of the last cycle copied
        self.copied = 0  # cycles copied
        self._started = math.nan

    def __call__(self, inputs: Inputs, comp: Compensator, now: float) -> None:
        if self._started != self._started:
            self._started = now
        warm_now = None
        if self.warmup is not None:
            warm_now = self.warmup.update(comp.velocity_m_s, comp.corrected_n, now)
        if now - self._started < SCORE_AFTER_S:
            return
        hb = inputs.plc_heartbeat
        slot = int(hb) & self.mask
        raw, corrected, status, warm = self._rows[slot]
        self.stamp[slot] = -1
        np.copyto(raw, comp.raw_n)
        np.copyto(corrected, comp.corrected_n)
        np.copyto(status, comp.status)
        if warm_now is not None:
            np.copyto(warm, warm_now)
        self.when[slot] = now
        self.stamp[slot] = hb
        self.latest = slot
        self.copied += 1

    def take(self, heartbeat: int | None, near: float, into: tuple[np.ndarray, ...]) -> bool:
        """Copy the cycle that read ``heartbeat`` (None: the latest cycle) into ``into``
        (raw, corrected, status, warm) if the ring holds it from within ``MATCH_WINDOW_S`` of
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

    def __init__(
        self,
        ring: CycleRing,
        source: TruthSource,
        cables: int,
        interval_s: float = TRUTH_INTERVAL_S,
    ) -> None:
        self.ring, self.source, self.interval_s = ring, source, interval_s
        self.score = TruthScore(cables)
        self.truth = np.zeros(cables)
        self._sample = (
            np.zeros(cables),
            np.zeros(cables),
            np.zeros(cables, dtype=np.uint16),
            np.ones(cables, dtype=bool),
        )
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
        raw, corrected, status, warm = self._sample
        self.score.add(self.truth, raw, corrected, status, warm)
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
        request = struct.pack(
            ">HHHBBHH", self._tid, 0, 6, self.unit_id, 3, TRUTH_ADDRESS, self.words
        )
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
