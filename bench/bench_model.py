"""Physics core: one compensation step (8 cables x 3 pulleys, Dahl) and batch throughput.

``model.compensate_step``: the chain alone (``ChainStepper.step``).
``model.compensator_step``: the gateway's whole per-cycle step (``Compensator.step``:
validation, the fitted effects' inverse, the chain, the wrench), nominal model and with
every online effect fitted, side by side; plus the heap it leaves behind (tracemalloc).
"""

from __future__ import annotations

import time
import tracemalloc
from dataclasses import replace

import numpy as np

from drivers.base import Inputs, Outputs
from gateway.core.config import Config, EffectParams, load_config
from gateway.model import chain_runs
from gateway.model.chain_runs import ChainStepper
from gateway.model.chain_schema import ChainParams
from gateway.model.effects.registry import ONLINE_EFFECTS
from gateway.runtime.compensator import Compensator


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
    ts = chain_runs.run(params, "simulate", tp, v, t)
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
    chain_runs.run(params, "simulate", tp[:10], v[:10], t[:10])
    chain_runs.run(params, "compensate", tp[:10], v[:10], t[:10])
    for name in ("simulate", "compensate"):
        runs = []
        for _ in range(3):
            t0 = time.perf_counter()
            chain_runs.run(params, name, tp, v, t)  # type: ignore[arg-type]
            runs.append(time.perf_counter() - t0)
        rate = n * params.cables / float(np.median(runs))
        print(
            f"model.batch_{name:<10} {n} samples x {params.cables} cables: "
            f"median {np.median(runs) * 1e3:.0f} ms -> {rate / 1e6:.1f} M cable-samples/s (1 core)"
        )


ALL_ONLINE: dict[str, EffectParams] = {
    "coulomb": {"f0_n": 0.5, "mu": 0.02},
    "presliding": {"sigma_n_m": 400.0},
    "viscous": {"c_ns_m": 3.0},
    "stribeck": {"k": 0.3, "v_s_m_s": 0.005},
    "inertia": {"m_eff_kg": 1.5},
    "gain": {"g": 0.004},
    "offset": {"c_n": (-0.7, 0.1, 0.2, 0.3, 0.0, 0.0, 0.1, 0.2)},
    "eccentricity": {"a_n": 0.4, "r_m": 0.03, "phi_rad": 0.7},
    "coulomb_directional": {"mu_out": 0.018, "mu_in": 0.022, "f0_n": 0.5},
    "coulomb_load": {"mu1_per_n": 2e-5},
    "maxwell_slip": {"sigma_n_m": 4000.0, "w": 0.7},
    "cable_stretch": {"k_n_m": 3000.0},
    "backlash": {"width_m": 0.002},
    "sensor_creep": {"c": 0.03, "tau_s": 0.5},
    "spring": {"k_n_m": 5.0, "l0_m": 0.0},
}
"""Every effect the gateway compensates online (``registry.ONLINE_EFFECTS``, checked in
:func:`_compensator_figures`), at a size the suites hide."""


def _compensator_median(cfg: Config, cycles: int, trace: bool) -> tuple[float, float, int]:
    """Median and p99 of ``Compensator.step`` (us) and, with ``trace``, the heap retained
    over the second half of the run (tracemalloc slows every step: not timed then)."""
    m = cfg.cables
    t, v, tp = _signals(cycles, m)
    comp = Compensator(cfg)
    inp, out = Inputs.allocate(m), Outputs.allocate(m)
    inp.pose[:] = cfg.geometry.home_pose
    inp.length_m[:] = 2.0
    times = np.empty(cycles)
    before = 0
    for k in range(cycles):
        inp.tension_raw_n[:] = tp[k]
        inp.velocity_m_s[:] = v[k]
        inp.length_m += v[k] * 1e-3
        inp.read_time_s = t[k]
        if trace and k == cycles // 2:
            tracemalloc.start()
            before, _ = tracemalloc.get_traced_memory()
        t0 = time.perf_counter_ns()
        comp.step(inp, t[k], out)
        times[k] = time.perf_counter_ns() - t0
    leaked = 0
    if trace:
        after, _ = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        leaked = after - before
    steady = times[100:]
    return float(np.median(steady)) / 1e3, float(np.percentile(steady, 99)) / 1e3, leaked


def _compensator_figures(cfg: Config) -> None:
    cycles = 20000
    missing = set(ONLINE_EFFECTS) ^ set(ALL_ONLINE)
    if missing:
        raise SystemExit(f"bench_model: ALL_ONLINE and ONLINE_EFFECTS differ in {sorted(missing)}")
    fitted = replace(cfg, friction=replace(cfg.friction, effects=ALL_ONLINE))
    rows = [("nominal", cfg), ("all online effects", fitted)]
    res = []
    for name, c in rows:
        med, p99, _ = _compensator_median(c, cycles, trace=False)
        res.append((name, med, p99, _compensator_median(c, 4000, trace=True)[2]))
    for name, med, p99, leaked in res:
        print(
            f"model.compensator_step {name:<19} median {med:.2f} us  p99 {p99:.2f} us  "
            f"(n={cycles}; heap retained over 2000 cycles: {leaked} B)"
        )
    print(f"model.compensator_step ratio fitted/nominal: {res[1][1] / res[0][1]:.2f}")


def run() -> None:
    cfg = load_config()
    params = ChainParams.from_friction(cfg.friction, cfg.cables)
    _step_figures(params)
    _compensator_figures(cfg)
    _batch_figures(params)
