"""Soft PLC plant: per-cycle step cost (median, p99, max) and batch recording throughput."""

from __future__ import annotations

import time

import numpy as np

from gateway.config import load_config
from sim_plc.image import ProcessImage
from sim_plc.plant import Plant, make_recording


def run() -> None:
    cfg = load_config()
    plant, image = Plant(cfg), ProcessImage(cfg.cables)
    for _ in range(200):  # compile and warm up
        plant.step(image)
    cycles = 5000
    took = np.empty(cycles)
    for k in range(cycles):
        t0 = time.perf_counter()
        plant.step(image)
        took[k] = time.perf_counter() - t0
    med, p95, p99 = np.percentile(took, [50, 95, 99]) * 1e6
    print(f"   Plant.step (8 cables, Dahl, paper path): median {med:.0f} us, p95 {p95:.0f} us, "
          f"p99 {p99:.0f} us, max {took.max() * 1e6:.0f} us of the 1000 us period")  # fmt: skip
    seconds = 10.0
    t0 = time.perf_counter()
    rec = make_recording(cfg, None, seconds)
    dt = time.perf_counter() - t0
    print(f"   make_recording: {rec.samples} samples in {dt:.2f} s "
          f"({rec.samples / dt:,.0f} samples/s, {seconds / dt:.1f}x real time)")  # fmt: skip
