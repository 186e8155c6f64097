"""What the cyclic service measures: histograms, rings and counters, allocated once.

The loop writes into :class:`LoopStats` during the cycle (no allocation: bucket counters
and fixed-size ring buffers); the metrics collector and the demo read it at scrape or
report time. The driver's own round-trip ring (:class:`gateway.core.ring.Ring`) is
merged in by :meth:`LoopStats.add_roundtrip_from`, once per successful read.
"""

from __future__ import annotations

import math
from bisect import bisect_left
from typing import Protocol

import numpy as np

from gateway.core.ring import Ring

CYCLE_BUCKETS_S = (50e-6, 100e-6, 200e-6, 300e-6, 500e-6, 750e-6, 1e-3, 2e-3, 5e-3)
JITTER_BUCKETS_S = (10e-6, 20e-6, 50e-6, 100e-6, 200e-6, 500e-6, 1e-3, 2e-3, 5e-3)
ROUNDTRIP_BUCKETS_S = (50e-6, 100e-6, 200e-6, 300e-6, 500e-6, 750e-6, 1e-3, 2e-3, 5e-3, 0.05)
ERROR_KINDS = (
    "timeout",
    "io",
    "connect",
    "write",
    "invalid_value",
    "heartbeat",
    "implausible",
    "clock",  # reads the sample clock could not vouch for: the chain resynchronised
)


class Histogram:
    """Prometheus-style histogram: per-bucket counts (not cumulative), sum and count."""

    def __init__(self, bounds: tuple[float, ...]) -> None:
        self.bounds = bounds
        self.counts = [0] * (len(bounds) + 1)  # last: above every bound (+Inf only)
        self.sum = 0.0
        self.count = 0

    def add(self, value: float) -> None:
        self.counts[bisect_left(self.bounds, value)] += 1
        self.sum += value
        self.count += 1

    def cumulative(self) -> list[tuple[str, int]]:
        """``[(le, cumulative count), ..., ('+Inf', count)]`` for the exposition."""
        out, total = [], 0
        for bound, n in zip((*self.bounds, math.inf), self.counts, strict=True):
            total += n
            out.append(("+Inf" if bound == math.inf else repr(bound), total))
        return out


class _DriverRing(Protocol):
    values: np.ndarray
    count: int


class LoopStats:
    """Everything the loop measures, preallocated; read at scrape time."""

    def __init__(self, history: int = 1 << 16) -> None:
        self.cycle = Histogram(CYCLE_BUCKETS_S)
        self.jitter = Histogram(JITTER_BUCKETS_S)
        self.roundtrip = Histogram(ROUNDTRIP_BUCKETS_S)
        self.cycle_ring = Ring(history)
        self.jitter_ring = Ring(history)
        self.roundtrip_ring = Ring(history)
        self.read_ring = Ring(history)
        self.compensate_ring = Ring(history)
        self.write_ring = Ring(history)
        self.cycles = 0  # cycles executed
        self.written = 0  # cycles whose outputs were written
        self.overruns = 0  # cycles that ended after the next deadline
        self.skipped = 0  # deadlines skipped because of overruns
        self.reconnects = 0  # successful reconnections after a loss
        self.errors = dict.fromkeys(ERROR_KINDS, 0)

    def add_jitter(self, seconds: float) -> None:
        _book(self.jitter, self.jitter_ring, seconds)

    def add_cycle(self, seconds: float) -> None:
        _book(self.cycle, self.cycle_ring, seconds)

    def add_phases(self, read_s: float, compensate_s: float, write_s: float) -> None:
        """One successful cycle's phases (the three rings stay aligned, one index)."""
        ring = self.read_ring
        n = ring.count
        i = n % ring.size
        ring.values[i] = read_s
        ring.count = n + 1
        ring = self.compensate_ring
        ring.values[i] = compensate_s
        ring.count = n + 1
        ring = self.write_ring
        ring.values[i] = write_s
        ring.count = n + 1

    def add_overrun(self, missed: int) -> None:
        """One cycle that ended late; ``missed`` deadlines (or SYNCs) were skipped."""
        self.overruns += 1
        self.skipped += missed

    def add_roundtrip_from(self, ring: _DriverRing) -> None:
        """Merge the last transaction of the driver's round-trip ring."""
        n = ring.count
        if n == 0:
            return
        values = ring.values
        last = values.item((n - 1) % values.size)  # a Python float
        _book(self.roundtrip, self.roundtrip_ring, last)


def _book(hist: Histogram, ring: Ring, value: float) -> None:
    """``hist.add(value)`` and ``ring.add(value)`` in one call (per cycle, 3 times)."""
    hist.counts[bisect_left(hist.bounds, value)] += 1
    hist.sum += value
    hist.count += 1
    n = ring.count
    ring.values[n % ring.size] = value
    ring.count = n + 1
