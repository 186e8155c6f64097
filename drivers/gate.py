"""The output gate: the one function every frame to the PLC passes, last before encoding.

A PLC trusts a channel whose status word says good (0) or substituted (1). The gate is
the contract that trust relies on, enforced once at the boundary: :class:`drivers.base.Driver`
calls its :class:`Gate` in :meth:`~drivers.base.Driver.exchange` and
:meth:`~drivers.base.Driver.write_from`, with the driver's clock read at that moment, right
before the driver's hook encodes and sends the frame. A channel keeps a status other than
invalid only if, at the moment of sending,

* ``heartbeat``: the PLC heartbeat has been seen changing, and its last change is no older
  than ``loop.heartbeat_timeout_s`` (the watchdog is armed and not expired);
* ``age``: the frame was computed from PLC data no older than ``loop.max_input_age_s``
  (the data's time is when it was requested, or the SYNC it belongs to: an upper bound of
  its age);
* ``non_finite``: its value is finite;
* ``range``: its value lies in what the register type and scale can carry without
  clipping or colliding with the sentinel (:func:`drivers.registers.value_band`; CANopen:
  the PDO's +-655.32 N).

Any other channel is written invalid (status 2) with NaN, which the codec writes as the
register's "no value" (NaN for float32, the integer sentinel otherwise). The wrench is
written only when every channel is good or substituted and each component is finite and
in range; else every component is NaN. Each channel stopped (and each wrench stopped on
its own) is counted once, under the first reason in :data:`REASONS` that applies:
``cdpr_gateway_gated_total{reason}``.

What no gate in the sending process can close: the process held (SIGSTOP, a VM pause, a
long page fault) between the last look and the send system call. The frame then leaves
late with the status it was given; it is one frame per hold (the next cycle's look
writes it invalid), and the PLC's own watchdog on the gateway's heartbeat is what covers
that window (docs/operation.md). ``tests/system/test_hostile_plc_invariant.py`` allows
exactly that frame and no other.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from drivers.codes import DATA_AT, HEARTBEAT_AT, NOW, REASONS
from gateway.fastcall import entry_point


class GateLimits(NamedTuple):
    """What a good value must satisfy: the register bands and the two time limits."""

    tension_lo: float
    tension_hi: float
    wrench_lo: float
    wrench_hi: float
    max_input_age_s: float
    heartbeat_timeout_s: float


class Gate:
    """The gate of one driver: its limits, counts and a compiled entry (no per-call type
    dispatch, :mod:`gateway.fastcall`; ~1 us a frame)."""

    def __init__(self, lim: GateLimits, cables: int) -> None:
        self.limits = lim
        self.counts = np.zeros(len(REASONS), dtype=np.int64)
        self._stamp = np.zeros(3)
        self._checked: tuple[object, ...] = (None, None, None)  # arrays found to fit the entry
        tension, status = np.zeros(cables), np.zeros(cables, dtype=np.uint16)
        from drivers.kernels import gate  # numba loads with the first gate, not at import

        self._kernel = gate
        self._entry = entry_point(gate, lim, self._stamp, tension, status, np.zeros(6), self.counts)

    def __call__(
        self,
        now: float,
        data_at: float,
        heartbeat_at: float,
        tension: np.ndarray,
        status: np.ndarray,
        wrench: np.ndarray,
    ) -> int:
        """Invalidate, in place, every value of the frame that breaks the contract
        (module doc) at time ``now``; count what was stopped by reason; return how many
        values were stopped."""
        stamp = self._stamp
        stamp[NOW], stamp[DATA_AT], stamp[HEARTBEAT_AT] = now, data_at, heartbeat_at
        c = self._checked
        same = tension is c[0] and status is c[1] and wrench is c[2]
        if not same and not self._fits(tension, status, wrench):
            return int(self._kernel(self.limits, stamp, tension, status, wrench, self.counts))
        return int(self._entry(self.limits, stamp, tension, status, wrench, self.counts))

    def _fits(self, tension: np.ndarray, status: np.ndarray, wrench: np.ndarray) -> bool:
        """True (and remembered) when the arrays have the compiled entry's types."""
        usual = status.dtype == np.uint16 and tension.dtype == wrench.dtype == np.float64
        contiguous = tension.flags.c_contiguous and status.flags.c_contiguous
        if usual and contiguous and wrench.flags.c_contiguous:
            self._checked = (tension, status, wrench)
            return True
        return False


def limits(
    tension_band: tuple[float, float],
    wrench_band: tuple[float, float],
    max_input_age_s: float,
    heartbeat_timeout_s: float,
) -> GateLimits:
    return GateLimits(
        float(tension_band[0]),
        float(tension_band[1]),
        float(wrench_band[0]),
        float(wrench_band[1]),
        float(max_input_age_s),
        float(heartbeat_timeout_s),
    )
