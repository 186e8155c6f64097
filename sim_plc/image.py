"""The soft PLC's process image: the variables its buses serve.

The plant writes the PLC's inputs (raw ADC counts, setpoints, heartbeat, truth for
scoring); bus servers (Modbus TCP, CANopen) read them and write what the gateway sends
into the gateway's outputs. One lock guards the image; hold it only to copy.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np


@dataclass
class ProcessImage:
    cables: int
    # written by the plant (PLC inputs as a real PLC holds them)
    raw_counts: np.ndarray = field(init=False)  # (m,) int16, S7 analog 0..27648 (32767 overflow)
    velocity_m_s: np.ndarray = field(init=False)  # (m,) setpoint cable velocity
    length_m: np.ndarray = field(init=False)  # (m,) setpoint cable length
    pose: np.ndarray = field(init=False)  # (6,) pose setpoint
    plc_heartbeat: int = 0  # uint16, +1 every PLC cycle
    true_tension_n: np.ndarray = field(init=False)  # (m,) platform tension (simulation only)
    time_s: float = 0.0  # plant time of the last step
    platform_mass_kg: float = 0.0  # current platform mass (falls while printing)
    # written by the gateway
    corrected_n: np.ndarray = field(init=False)  # (m,)
    channel_status: np.ndarray = field(init=False)  # (m,) uint16
    gateway_heartbeat: int = 0
    gateway_state: int = 0
    wrench: np.ndarray = field(init=False)  # (6,)
    gateway_writes: int = 0  # count of accepted writes from the gateway
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def __post_init__(self) -> None:
        m = self.cables
        self.raw_counts = np.zeros(m, dtype=np.int16)
        self.velocity_m_s = np.zeros(m)
        self.length_m = np.zeros(m)
        self.pose = np.zeros(6)
        self.true_tension_n = np.zeros(m)
        # nothing written by a gateway yet: every channel invalid, as the gateway writes it
        self.corrected_n = np.full(m, np.nan)
        self.channel_status = np.full(m, 2, dtype=np.uint16)
        self.wrench = np.full(6, np.nan)
