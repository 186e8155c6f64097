"""A recording's time base, as the diagnosis cuts it: interleaved time blocks (even ones
fit, odd ones held out) and the gaps where rows are missing (trials joined into one
recording, a logger's pauses). Functions of the time stamps alone, below every stage that
uses them (:mod:`.prepare`, :mod:`.sessions`, :mod:`.reference`, :mod:`.wrench`)."""

from __future__ import annotations

import numpy as np

GAP_SPACINGS = 10.0
"""A step longer than this many median sample spacings is a gap (rows missing): how the
cable moved in it is unknown, so the friction state after it is too, as at the start."""


def time_blocks(t: np.ndarray) -> tuple[np.ndarray, int]:
    """Block index (N,) of interleaved time blocks; even blocks train, odd ones are held out.

    About one block per second of recording, between 10 and 40 blocks (an even number).
    """
    span = float(t[-1] - t[0]) if t.size > 1 else 0.0
    nb = int(np.clip(round(span / 1.0), 10, 40))
    nb += nb % 2
    edges = t[0] + span * np.arange(1, nb) / nb
    return np.searchsorted(edges, t, side="right").astype(np.int64), nb


def gap_starts(t: np.ndarray) -> np.ndarray:
    """Indices of the samples that follow a gap (a step longer than ``GAP_SPACINGS``
    median spacings), ascending."""
    if t.size < 2:
        return np.zeros(0, np.int64)
    dt = np.diff(t)
    return np.nonzero(dt > GAP_SPACINGS * float(np.median(dt)))[0] + 1


def gap_segments(t: np.ndarray) -> np.ndarray:
    """(N,) index of the piece of recording each sample lies in: a new piece after every
    gap (:func:`gap_starts`; trials joined into one recording)."""
    seg = np.zeros(t.size, np.int64)
    seg[gap_starts(t)] = 1
    return np.cumsum(seg)
