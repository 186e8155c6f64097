"""The one S7 analog codec: Siemens S7 analog value counts <-> newtons.

Every place that turns sensor counts into newtons or back uses :class:`S7Analog`: the
Modbus register codec (:mod:`drivers.registers`), the CANopen and virtual drivers, the
soft PLC's A/D converter and the demo's stand-in plant.

The S7 format of a unipolar measuring range (Siemens, *S7-300/S7-400 Module Data*,
"Representation of analog values", table "Unipolar input ranges"), int16 counts::

    32767            overflow (>= 118.515 %; also wire break / parameter error)
    27649 .. 32511   overrange (the top, 32511, is 117.589 %)
        0 .. 27648   nominal range (27648 = 100 %)
       -1 .. -4864   underrange (-4864 = -17.593 %)
   -32768            underflow

A module delivers nothing between the end of the overrange and the overflow code, nor
between the end of the underrange and the underflow code. The one reading here is
therefore a *window*: counts inside ``min_counts .. max_counts`` (over- and underrange
included) decode to ``counts * range_n / full_scale``; everything outside it (the two
codes, and the values no S7 module sends, e.g. 32600 or -5000) decodes to NaN, which the
gateway flags invalid. With ``full_scale`` other than 27648 the window scales the same
way (``floor(full_scale * 32511 / 27648)``, ``-floor(full_scale * 4864 / 27648)``),
bounded by +-32766 so the codes stay codes.

Encoding rounds ``newtons / newtons_per_count`` to the nearest count; values above the
window (and NaN) become the overflow code, values below it the underflow code.

The reading and the encoding are written once, as the compiled scalar functions
:func:`drivers.kernels.s7_decode_count` and :func:`drivers.kernels.s7_encode_count`
(compiled, so they live with the drivers' other kernels, imported when first used):
:class:`S7Analog` (arrays and single counts, the soft PLC's A/D converter) and the
register codec's kernel (:mod:`drivers.registers`) call them.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from drivers.codes import S7_OVERFLOW, S7_UNDERFLOW

S7_NOMINAL = 27648
S7_OVERRANGE_MAX = 32511  # 117.589 % of nominal
S7_UNDERRANGE_MIN = -4864  # -17.593 % of nominal


def window(full_scale: int) -> tuple[int, int]:
    """(smallest underrange count, largest overrange count) for a nominal ``full_scale``."""
    hi = math.floor(full_scale * S7_OVERRANGE_MAX / S7_NOMINAL)
    lo = -math.floor(full_scale * -S7_UNDERRANGE_MIN / S7_NOMINAL)
    return max(lo, S7_UNDERFLOW + 1), min(hi, S7_OVERFLOW - 1)


_TABLES: dict[tuple[float, int], np.ndarray] = {}


@dataclass(frozen=True)
class S7Analog:
    """S7 analog counts of a sensor with ``range_n`` newtons at ``full_scale`` counts."""

    range_n: float
    full_scale: int = S7_NOMINAL
    newtons_per_count: float = field(init=False)
    min_counts: int = field(init=False)
    max_counts: int = field(init=False)

    def __post_init__(self) -> None:
        lo, hi = window(self.full_scale)
        object.__setattr__(self, "newtons_per_count", self.range_n / self.full_scale)
        object.__setattr__(self, "min_counts", lo)
        object.__setattr__(self, "max_counts", hi)

    @staticmethod
    def from_sensor(sensor: Any) -> S7Analog:
        """From a :class:`gateway.core.config.SensorConfig` (``range_n``, ``adc_full_scale``)."""
        return s7_codec(float(sensor.range_n), int(sensor.adc_full_scale))

    # --- decode ----------------------------------------------------------------------
    @property
    def table(self) -> np.ndarray:
        """Newtons for each 16-bit word (index = the word as unsigned; read-only)."""
        key = (self.range_n, self.full_scale)
        table = _TABLES.get(key)
        if table is None:
            counts = np.arange(65536, dtype=np.uint16).view(np.int16).astype(np.int64)
            table = np.empty(65536)
            from drivers.kernels import s7_decode_all

            s7_decode_all(counts, self.newtons_per_count, self.min_counts, self.max_counts, table)
            table.flags.writeable = False
            _TABLES[key] = table
        return table

    def decode(self, counts: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Counts (any integer array, int16 or the raw 16-bit words) -> newtons, NaN outside
        the window. ``out`` (float64, same shape) is filled without allocating."""
        words = np.asarray(counts)
        if words.dtype == np.int16:
            words = words.view(np.uint16)
        elif words.dtype != np.uint16:
            words = words.astype(np.int16).view(np.uint16)
        if out is None:
            return np.take(self.table, words)
        return np.take(self.table, words, out=out)

    def decode_count(self, count: int) -> float:
        """One count -> newtons (NaN outside the window)."""
        from drivers.kernels import s7_decode_count

        return float(
            s7_decode_count(int(count), self.newtons_per_count, self.min_counts, self.max_counts)
        )

    def valid(self, count: int) -> bool:
        return self.min_counts <= count <= self.max_counts

    # --- encode ----------------------------------------------------------------------
    def encode(self, newtons: np.ndarray | float) -> np.ndarray:
        """Newtons -> int16 counts: rounded, the codes beyond the window and for NaN."""
        x = np.asarray(newtons, dtype=float)
        flat = np.ascontiguousarray(x).reshape(-1)
        f = np.empty(flat.size)
        from drivers.kernels import s7_encode_all

        s7_encode_all(flat, self.newtons_per_count, self.min_counts, self.max_counts, f)
        return f.reshape(x.shape).astype(np.int16)


@functools.lru_cache(maxsize=16)
def s7_codec(range_n: float, full_scale: int = S7_NOMINAL) -> S7Analog:
    """The (cached) codec for one sensor range and full scale."""
    return S7Analog(float(range_n), int(full_scale))
