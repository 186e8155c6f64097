"""The soft PLC's cyclic task: the plant stepped in real time, or as fast as asked.

``PlcRuntime(plant, image).start()`` runs a thread that calls ``plant.step(image)`` once
per period against absolute deadlines (``next += period``). When the thread falls
behind (a slow step, the OS preempting it) it catches up by stepping back to back, up to
``max_catch_up`` periods; deadlines further behind are counted as missed and skipped (the
plant's time then lags the wall clock; it never jumps). ``stop()`` ends the thread and
is safe to call twice. ``step(n)`` advances ``n`` cycles at once without a clock (tests).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Protocol

from sim_plc.image import ProcessImage


class Steppable(Protocol):
    def step(self, image: ProcessImage | None = None) -> None: ...


@dataclass
class RuntimeStats:
    """Counters of the cyclic task (read them while it runs; ints are atomic enough)."""

    cycles: int = 0
    late: int = 0  # cycles that started a whole period or more behind their deadline
    missed: int = 0  # deadlines skipped (more than ``max_catch_up`` periods behind)
    max_step_s: float = 0.0  # longest plant step seen
    last_step_s: float = 0.0


class PlcRuntime:
    """Steps ``plant`` into ``image`` every ``period_s`` seconds on a daemon thread."""

    def __init__(
        self,
        plant: Steppable,
        image: ProcessImage,
        period_s: float = 0.001,
        clock=time.perf_counter,
        sleep=time.sleep,
        max_catch_up: int = 5,
    ) -> None:
        if period_s <= 0:
            raise ValueError("period_s must be > 0")
        self.plant, self.image, self.period_s = plant, image, float(period_s)
        self.stats = RuntimeStats()
        self.max_catch_up = int(max_catch_up)
        self._clock, self._sleep = clock, sleep
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def error(self) -> BaseException | None:
        """The exception that ended the thread, if one did."""
        return self._error

    def step(self, n: int = 1) -> None:
        """Advance ``n`` cycles immediately (fast stepped mode); not while running."""
        if self.running:
            raise RuntimeError("PlcRuntime.step() while the real-time thread runs")
        for _ in range(int(n)):
            self._one()

    def _one(self) -> None:
        t0 = self._clock()
        self.plant.step(self.image)
        took = self._clock() - t0
        self.stats.cycles += 1
        self.stats.last_step_s = took
        if took > self.stats.max_step_s:
            self.stats.max_step_s = took

    def start(self) -> None:
        """Start the real-time thread (no-op if it already runs)."""
        if self.running:
            return
        self._stop.clear()
        self._error = None
        self._thread = threading.Thread(target=self._run, name="sim-plc-cycle", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        period = self.period_s
        deadline = self._clock()
        try:
            while not self._stop.is_set():
                self._one()
                deadline += period
                behind = int((self._clock() - deadline) // period)
                if behind > 0:  # late: catch up back to back, skip beyond max_catch_up
                    self.stats.late += 1
                    if behind > self.max_catch_up:
                        skip = behind - self.max_catch_up
                        self.stats.missed += skip
                        deadline += skip * period
                wait = deadline - self._clock()
                if wait > 0:
                    self._sleep(wait)
        except BaseException as exc:  # kept for the caller; the thread ends
            self._error = exc

    def stop(self, timeout_s: float = 2.0) -> None:
        """Stop the thread and wait for it; safe to call twice or before ``start``."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout_s)

    def __enter__(self) -> PlcRuntime:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
