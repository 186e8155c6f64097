"""The numbers the drivers' Python side and their compiled kernels (:mod:`drivers.kernels`)
share: the gate's reasons and stamp slots, the codec's modes, the S7 sentinels.

Stated here once, below both sides, so that the kernels take nothing from the modules
that run them (:mod:`drivers.gate`, :mod:`drivers.registers`, :mod:`drivers.s7`) and no
import runs in a circle. This module imports nothing but the standard library.
"""

from __future__ import annotations

# --- the output gate (drivers.gate) -------------------------------------------------------
REASONS = ("heartbeat", "age", "non_finite", "range")  # cdpr_gateway_gated_total{reason}
HEARTBEAT, AGE, NON_FINITE, RANGE = range(4)  # their indices, in that order
INVALID = 2  # drivers.base.ChannelStatus.INVALID (base imports the gate)
NOW, DATA_AT, HEARTBEAT_AT = range(3)  # the stamp: the frame's three times (driver clock)

# --- the register codec (drivers.registers) -----------------------------------------------
MODE_SCALED, MODE_RAW, MODE_WRAP = 0, 1, 2  # a field's value: scaled, as is (clipped), modulo

# --- the S7 analog count (drivers.s7) -----------------------------------------------------
S7_OVERFLOW = 32767
S7_UNDERFLOW = -32768
