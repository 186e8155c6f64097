"""Physics core: one compensation step (8 cables x 3 pulleys, Dahl) and batch throughput."""

from __future__ import annotations

import time

import numpy as np

from gateway.config import load_config
from gateway.model.chain import ChainParams, ChainStepper, compensate, simulate


def _signals(n: int, m: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 1e-3
    phase = rng.uniform(0, 2 * np.pi, m)
    v = 0.04 * np.sin(2 * np.pi * 0.2 * t[:, None] + phase)
    tp = 250 + 80 * np.sin(2 * np.pi * 0.05 * t[:, None] + phase) + rng.normal(0, 0.5, (n, m))
    return t, v, tp


def _step_figures(params: ChainParams) -> None:
    cycles = 20000
    t, v, tp = _signals(cycles, params.cables)
    ts = simulate(params, tp, v, t)
    stepper = ChainStepper(params, 1e-3)
    out = np.zeros(params.cables)
    stepper.step(ts[0], v[0], out)  # compile before timing
    times = np.empty(cycles)
    passes = np.empty(cycles, dtype=int)
    for k in range(cycles):
        t0 = time.perf_counter_ns()
        passes[k] = stepper.step(ts[k], v[k], out)
        times[k] = time.perf_counter_ns() - t0
    print(
        f"model.compensate_step  {params.cables} cables x {params.pulleys} pulleys, dahl: "
        f"median {np.median(times) / 1e3:.2f} us  p99 {np.percentile(times, 99) / 1e3:.2f} us  "
        f"(n={cycles}; Newton passes max {passes[1:].max()}, mean {passes[1:].mean():.2f})"
    )


def _batch_figures(params: ChainParams) -> None:
    n = 600_000  # 10 minutes at 1 kHz
    t, v, tp = _signals(n, params.cables)
    simulate(params, tp[:10], v[:10], t[:10])
    compensate(params, tp[:10], v[:10], t[:10])
    for name, fn in (("simulate", simulate), ("compensate", compensate)):
        runs = []
        for _ in range(3):
            t0 = time.perf_counter()
            fn(params, tp, v, t)
            runs.append(time.perf_counter() - t0)
        rate = n * params.cables / float(np.median(runs))
        print(
            f"model.batch_{name:<10} {n} samples x {params.cables} cables: "
            f"median {np.median(runs) * 1e3:.0f} ms -> {rate / 1e6:.1f} M cable-samples/s (1 core)"
        )


def run() -> None:
    cfg = load_config()
    params = ChainParams.from_friction(cfg.friction, cfg.cables)
    _step_figures(params)
    _batch_figures(params)
