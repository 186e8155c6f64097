"""The Modbus holding-register map of the ``bus.modbus_tcp.registers`` config section.

Where each block of values the gateway reads from or writes to the PLC sits, and in which
type, word order and scaling. Also importable from :mod:`gateway.core.config`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

from gateway.core.configtypes import Ranged, require

RegisterType = Literal["int16", "uint16", "int32", "uint32", "float32"]


@dataclass(frozen=True)
class RegisterField(Ranged):
    """A block of ``count`` values of one type starting at holding register ``address``.

    ``word_order`` applies to 32-bit types; ``format: s7_analog`` maps 0..adc_full_scale
    to 0..sensor range; otherwise value = raw * scale. ``invalid``: for integer outputs,
    the raw value written for "no value" (default: the type's minimum if signed, its
    maximum if unsigned); float32 writes NaN.
    """

    address: int  # the block's first holding register (0-based)
    count: int = 1  # how many values
    type: RegisterType = "uint16"  # each value's register type
    # 32-bit types: which 16-bit word comes first
    word_order: Literal["high_first", "low_first"] = "high_first"
    scale: float = 1.0  # value = raw x scale (format plain)
    # s7_analog: 0..adc_full_scale is 0..sensor range
    format: Literal["plain", "s7_analog"] = "plain"
    invalid: int | None = None  # integer outputs: the raw value written for no value
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "address": (0, 65535),
        "count": (1, 125),
        "scale": (-1e9, 1e9),
        "invalid": (-(2**31), 2**32 - 1),
    }

    def __post_init__(self) -> None:
        super().__post_init__()  # RANGES; a scale near 0 is refused here, as in the file
        require(abs(self.scale) >= 1e-9, "scale must be +-1e-9..1e9")

    @property
    def words(self) -> int:
        per = 2 if self.type in ("int32", "uint32", "float32") else 1
        return self.count * per

    @property
    def end(self) -> int:
        """One past the last register of the block."""
        return self.address + self.words


@dataclass(frozen=True)
class RegisterMap:
    """Holding-register map (0-based). Inputs are read from the PLC, outputs written."""

    # read: the force channels
    raw_tensions: RegisterField = RegisterField(0, 8, "int16", format="s7_analog")
    # read: setpoint cable speeds (m/s)
    setpoint_velocities: RegisterField = RegisterField(8, 8, "float32")
    # read: setpoint cable lengths (m)
    setpoint_lengths: RegisterField = RegisterField(24, 8, "float32")
    pose: RegisterField = RegisterField(40, 6, "float32")  # read: the pose setpoint (m, rad)
    # read: the PLC's heartbeat (loop.heartbeat says its kind)
    plc_heartbeat: RegisterField = RegisterField(52, 1, "uint16")
    # written: the compensated platform tensions (N)
    corrected_tensions: RegisterField = RegisterField(100, 8, "float32")
    # written: 0 good, 1 substituted, 2 invalid, per cable
    channel_status: RegisterField = RegisterField(116, 8, "uint16")
    # written: +1 every written cycle (the PLC's watchdog)
    gateway_heartbeat: RegisterField = RegisterField(124, 1, "uint16")
    # written: 0 stopped, 1 connected, 2 active, 3 fault
    gateway_state: RegisterField = RegisterField(125, 1, "uint16")
    # written: the estimated platform wrench (N, N m)
    wrench: RegisterField = RegisterField(126, 6, "float32")
    platform_mass: RegisterField | None = None  # optional: the platform mass (kg), count 1

    def inputs(self) -> dict[str, RegisterField]:
        names = ("raw_tensions", "setpoint_velocities", "setpoint_lengths", "pose", "plc_heartbeat")
        found = {n: getattr(self, n) for n in names}
        if self.platform_mass is not None:
            found["platform_mass"] = self.platform_mass
        return found

    def outputs(self) -> dict[str, RegisterField]:
        names = (
            "corrected_tensions",
            "channel_status",
            "gateway_heartbeat",
            "gateway_state",
            "wrench",
        )
        return {n: getattr(self, n) for n in names}
