"""The last ``size`` values of a series, written in the cycle without allocating, read at
scrape time (percentiles): the loop's timings and the driver's round trips."""

from __future__ import annotations

import math

import numpy as np


class Ring:
    """The last ``size`` values; :meth:`add` in the cycle, :meth:`recent` / :meth:`percentile`
    outside it."""

    def __init__(self, size: int) -> None:
        self.values = np.zeros(size)
        self.size = size
        self.count = 0

    def add(self, value: float) -> None:
        n = self.count
        self.values[n % self.size] = value
        self.count = n + 1

    def last(self) -> float:
        """The value added last (NaN before the first)."""
        if self.count == 0:
            return math.nan
        return float(self.values[(self.count - 1) % self.size])

    def recent(self) -> np.ndarray:
        return self.values[: min(self.count, self.size)]

    def percentile(self, q: float) -> float:
        data = self.recent()
        return float(np.percentile(data, q)) if data.size else math.nan
