"""The shipped geometry (config/default.yaml) holds the paper's experiment.

The eq. 20 path (two layers, z0 = 1.2 m, mass falling 40 -> 21 kg) and a +-0.08 m /
+-4 degree cyclic grid in all six DOF must be wrench-feasible within the configured
tension limits, and the structure matrix must have full rank (the uncrossed variant of
the same frame does not: that is why the cables are crossed).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from gateway.core.config import load_config
from gateway.model.kinematics import structure_matrix
from gateway.model.statics import distribute_tensions, gravity_wrench

CFG = load_config()
A_FRAME = np.asarray(CFG.geometry.frame_anchors_m)
B_PLAT = np.asarray(CFG.geometry.platform_anchors_m)
LO, HI = CFG.tension.min_n, CFG.tension.max_n


def feasible_tensions(pose: np.ndarray, mass: float) -> np.ndarray:
    a = structure_matrix(A_FRAME, B_PLAT, pose)
    w = gravity_wrench(mass, CFG.geometry.gravity_m_s2, pose, np.zeros(3))
    return distribute_tensions(a, w, LO, HI)


def test_full_rank_at_home_and_uncrossed_variant_is_singular() -> None:
    home = np.asarray(CFG.geometry.home_pose)
    assert np.linalg.matrix_rank(structure_matrix(A_FRAME, B_PLAT, home)) == 6
    uncrossed = A_FRAME * np.array([0.1, 0.1, 0.0])  # platform corners under frame corners
    uncrossed[:4, 2], uncrossed[4:, 2] = 0.1, -0.1
    assert np.linalg.matrix_rank(structure_matrix(A_FRAME, uncrossed, home), tol=1e-9) == 5


def test_paper_path_is_feasible_within_sensor_range() -> None:
    u = np.linspace(0.0, 30.0, 200)
    mass = np.linspace(CFG.geometry.platform_mass_kg, CFG.geometry.platform_mass_kg - 19.2, 400)
    tensions = []
    for layer, z_layer in enumerate((0.0, 0.3)):
        for k, uk in enumerate(u):
            pose = np.array([0.2 * np.sin(5 - uk), 0.015 * (15 - uk), 1.2 + 0.01 * uk + z_layer])
            tensions.append(feasible_tensions(np.r_[pose, 0, 0, 0], mass[layer * 200 + k]))
    tensions = np.asarray(tensions)
    assert tensions.min() >= LO - 1e-9 and tensions.max() <= HI + 1e-9
    assert tensions.max() < CFG.sensor.range_n


@pytest.mark.parametrize("mass", [40.0, 21.0])
def test_cyclic_six_dof_grid_is_feasible(mass: float) -> None:
    home = np.asarray(CFG.geometry.home_pose)
    step = np.array([0.08, 0.08, 0.08, *np.radians([4.0, 4.0, 4.0])])
    for signs in itertools.product((-1, 0, 1), repeat=6):
        feasible_tensions(home + np.asarray(signs) * step, mass)  # raises if infeasible
