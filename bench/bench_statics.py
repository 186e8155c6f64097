"""Benchmark: microseconds per pose of ``statics.distribute_tensions`` (8 cables).

Random wrench-feasible workspace poses of the default geometry (4.0 x 3.0 x 3.0 m frame,
0.4 x 0.3 x 0.2 m platform, 50 kg, limits 20..1000 N); each call is timed on its own
with ``time.perf_counter_ns``. Prints one line; asserts nothing about time.
"""

from __future__ import annotations

import time

import numpy as np
from numpy.typing import NDArray

from gateway.core.config import load_config
from gateway.model import kinematics, statics

_CFG = load_config()  # the shipped geometry, mass and tension limits
FRAME_ANCHORS = np.asarray(_CFG.geometry.frame_anchors_m)
PLATFORM_ANCHORS = np.asarray(_CFG.geometry.platform_anchors_m)
HOME = np.asarray(_CFG.geometry.home_pose)
SPAN = np.array([0.3, 0.3, 0.3, *np.radians([5.0, 5.0, 5.0])])
MASS_KG, G = _CFG.geometry.platform_mass_kg, _CFG.geometry.gravity_m_s2
TAU_MIN, TAU_MAX = _CFG.tension.min_n, _CFG.tension.max_n


def feasible_cases(
    n: int, platform_anchors: NDArray[np.float64], seed: int = 0
) -> list[tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """``n`` pairs (A (6, 8), w (6,)) at random wrench-feasible poses around home."""
    rng = np.random.default_rng(seed)
    cases: list[tuple[NDArray[np.float64], NDArray[np.float64]]] = []
    for _ in range(1000 * n):
        pose = HOME + rng.uniform(-1.0, 1.0, 6) * SPAN
        a_mat = kinematics.structure_matrix(FRAME_ANCHORS, platform_anchors, pose)
        w = statics.gravity_wrench(MASS_KG, G, pose)
        if statics.is_wrench_feasible(a_mat, w, TAU_MIN, TAU_MAX):
            cases.append((a_mat, w))
            if len(cases) == n:
                return cases
    raise RuntimeError(f"found only {len(cases)} feasible poses out of {1000 * n}")


def run(n: int = 500, platform_anchors: NDArray[np.float64] = PLATFORM_ANCHORS) -> None:
    """Print median and p99 microseconds per ``distribute_tensions`` call over ``n`` poses."""
    cases = feasible_cases(n, platform_anchors)
    for a_mat, w in cases[:20]:  # warm-up
        statics.distribute_tensions(a_mat, w, TAU_MIN, TAU_MAX)
    times_us = np.empty(len(cases))
    for k, (a_mat, w) in enumerate(cases):
        start = time.perf_counter_ns()
        statics.distribute_tensions(a_mat, w, TAU_MIN, TAU_MAX)
        times_us[k] = (time.perf_counter_ns() - start) / 1000.0
    median, p99 = np.percentile(times_us, [50, 99])
    print(
        f"statics.distribute_tensions  median {median:.1f} us  p99 {p99:.1f} us  (n={len(cases)})"
    )


if __name__ == "__main__":
    run()
