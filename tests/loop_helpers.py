"""Shared helpers for the loop, compensator, metrics and demo tests."""

from __future__ import annotations

import dataclasses
import gc
import socket
from typing import Any

import numpy as np

from drivers.base import Driver, Outputs
from gateway.core.config import Config, load_config
from sim_plc.image import ProcessImage


class FakeClock:
    """A clock that moves only when slept on, plus ``tick`` per reading (so spins end)."""

    def __init__(self, start: float = 100.0, tick: float = 1e-7) -> None:
        self.now = start
        self.tick = tick
        self.slept = 0.0

    def __call__(self) -> float:
        self.now += self.tick
        return self.now

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self.now += seconds
            self.slept += seconds

    def advance(self, seconds: float) -> None:
        self.now += seconds


def run_frozen(svc: Any, cycles: int) -> Any:
    """``svc.run(cycles=cycles)`` with the test process's heap frozen first.

    The loop's start-up collects the whole heap before freezing it (gateway/runtime/loop.py):
    a daemon's heap is small, a test process's (pytest, hypothesis, every module a test
    imported) made each ``run`` take 0.2-0.9 s of a full collection under load, the most of
    a property's examples (tests/runtime/test_output_invariant.py and
    test_pacing_outage.py: 55 s of the 68 s those three tests took in one `make test`).
    Frozen, the collection sees only what the test allocated since; the loop runs as it
    does (its own collect, freeze and unfreeze), and the heap is unfrozen after."""
    gc.freeze()
    try:
        return svc.run(cycles=cycles)
    finally:
        gc.unfreeze()


def config(**loop: Any) -> Config:
    """The default config with ``loop`` fields replaced and the virtual driver."""
    cfg = load_config()
    cfg = dataclasses.replace(cfg, loop=dataclasses.replace(cfg.loop, **loop))
    return dataclasses.replace(cfg, bus=dataclasses.replace(cfg.bus, driver="virtual"))


def live_image(cfg: Config, tension_n: float = 200.0) -> ProcessImage:
    """An image with every channel at ``tension_n`` (S7 counts) and cables moving."""
    img = ProcessImage(cfg.cables)
    counts = round(tension_n / cfg.sensor.range_n * cfg.sensor.adc_full_scale)
    img.raw_counts[:] = counts
    img.true_tension_n[:] = tension_n
    img.velocity_m_s[:] = 0.05
    img.pose[:] = cfg.geometry.home_pose
    return img


class Wobble:
    """Stepped-mode stand-in: raw counts change every read (so nothing looks stuck)."""

    def __init__(self, img: ProcessImage, amplitude: int = 3) -> None:
        self.img = img
        self.k = 0
        self.base = img.raw_counts.copy()
        self.amplitude = amplitude

    def __call__(self) -> None:
        self.k += 1
        self.img.raw_counts[:] = self.base + (self.k % (2 * self.amplitude)) - self.amplitude
        self.img.plc_heartbeat = (self.img.plc_heartbeat + 1) & 0xFFFF


def free_port() -> int:
    """A TCP port that was free a moment ago on 127.0.0.1."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def fresh(out: Outputs, driver: Driver) -> Outputs:
    """``out`` stamped as computed now from fresh data with a live PLC heartbeat, for a
    test that drives a driver without the loop (the output gate needs both times)."""
    now = driver.clock()
    return out.stamp(now, now)


def finite(a: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(a)))
