"""Statics and the exact tension distribution (gateway.model.statics)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose
from scipy.optimize import linprog, minimize

from gateway.errors import InfeasiblePoseError
from gateway.model import kinematics as kin
from gateway.model import statics
from tests.geometry_helpers import BOX, CROSSED, FRAME, HOME

MASS_KG, G = 50.0, 9.81
LO, HI = 20.0, 1000.0

offset = st.floats(-0.4, 0.4, allow_nan=False)
tilt = st.floats(-0.3, 0.3, allow_nan=False)
load = st.floats(-300.0, 300.0, allow_nan=False)


def assert_optimal(a_mat: np.ndarray, w: np.ndarray, tau: np.ndarray, lo, hi) -> None:
    """Equilibrium, limits and the KKT conditions of min |tau - mid|^2."""
    lo = np.broadcast_to(lo, tau.shape)
    hi = np.broadcast_to(hi, tau.shape)
    assert_allclose(a_mat @ tau, -w, rtol=0, atol=1e-9)
    assert np.all(tau >= lo) and np.all(tau <= hi)
    grad = tau - 0.5 * (lo + hi)
    at_lo, at_hi = tau == lo, tau == hi
    free = ~(at_lo | at_hi)
    nu = np.linalg.lstsq(a_mat[:, free].T, -grad[free], rcond=None)[0]
    stationarity = grad + a_mat.T @ nu
    # the KKT residual is known to the rounding of tau amplified by A's conditioning: a
    # near-singular pose (cond 1e9, accepted above RANK_RTOL) leaves ~1e-5 N of it
    tol = 1e-7 + 100 * np.finfo(float).eps * np.linalg.cond(a_mat) * np.max(np.abs(tau))
    assert_allclose(stationarity[free], 0.0, rtol=0, atol=tol)
    assert np.all(stationarity[at_lo] >= -tol)  # multiplier of tau >= lo
    assert np.all(stationarity[at_hi] <= tol)  # multiplier of tau <= hi


def lp_feasible(a_mat: np.ndarray, w: np.ndarray, lo: float, hi: float) -> bool:
    res = linprog(np.zeros(a_mat.shape[1]), A_eq=a_mat, b_eq=-w, bounds=[(lo, hi)] * a_mat.shape[1])
    return bool(res.status == 0)


def random_case(rng: np.random.Generator, anchors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pose = HOME + rng.uniform(-1, 1, 6) * [0.4, 0.4, 0.4, 0.2, 0.2, 0.2]
    a_mat = kin.structure_matrix(FRAME, anchors, pose)
    w = statics.gravity_wrench(MASS_KG, G, pose) + rng.normal(0.0, 60.0, 6)
    return a_mat, w


def test_gravity_wrench_centred_and_off_centre() -> None:
    assert_allclose(statics.gravity_wrench(50.0, 9.81, HOME), [0, 0, -490.5, 0, 0, 0], atol=0)
    level = statics.gravity_wrench(50.0, 9.81, HOME, (0.1, 0.0, 0.0))
    assert_allclose(level, [0, 0, -490.5, 0, 49.05, 0], rtol=1e-15, atol=1e-13)
    turned = statics.gravity_wrench(
        50.0, 9.81, HOME + np.array([0, 0, 0, 0, 0, np.pi / 2]), (0.1, 0, 0)
    )
    assert_allclose(turned, [0, 0, -490.5, -49.05, 0, 0], rtol=1e-15, atol=1e-13)
    batch = statics.gravity_wrench_batch([50.0, 30.0], 9.81, np.stack([HOME, HOME]), (0.1, 0, 0))
    assert_allclose(batch[1], [0, 0, -294.3, 0, 29.43, 0], rtol=1e-15, atol=1e-13)


def test_inertial_wrench() -> None:
    assert_allclose(statics.inertial_wrench(50.0, [0.1, 0, -0.2]), [-5, 0, 10, 0, 0, 0], atol=0)
    batch = statics.inertial_wrench(np.array([1.0, 2.0]), np.ones((2, 3)))
    assert_allclose(batch, [[-1, -1, -1, 0, 0, 0], [-2, -2, -2, 0, 0, 0]], atol=0)


def test_symmetric_pose_gives_symmetric_tensions() -> None:
    a_mat = kin.structure_matrix(FRAME, CROSSED, HOME)
    w = statics.gravity_wrench(MASS_KG, G, HOME)
    tau = statics.distribute_tensions(a_mat, w, LO, HI)
    assert_allclose(tau[:4], tau[0], rtol=1e-12)  # the four upper cables
    assert_allclose(tau[4:], tau[4], rtol=1e-12)  # the four lower cables
    assert tau[0] > tau[4]
    # vertical balance: upper l = (2.2, 1.35, 1.4), lower l = (1.8, 1.65, -1.4)
    uz_up = 1.4 / np.linalg.norm([2.2, 1.35, 1.4])
    uz_low = 1.4 / np.linalg.norm([1.8, 1.65, 1.4])
    assert_allclose(4 * (uz_up * tau[0] - uz_low * tau[4]), MASS_KG * G, rtol=1e-12)
    assert_optimal(a_mat, w, tau, LO, HI)


def test_uncrossed_box_is_singular_at_home() -> None:
    # a_i and b_i have proportional x, y: every cable line meets the z axis, no moment about z
    a_mat = kin.structure_matrix(FRAME, BOX, HOME)
    assert np.linalg.matrix_rank(a_mat) == 5
    with pytest.raises(InfeasiblePoseError, match="rank-deficient"):
        statics.distribute_tensions(a_mat, statics.gravity_wrench(MASS_KG, G, HOME), LO, HI)


@settings(max_examples=150, deadline=None)
@given(
    st.lists(offset, min_size=3, max_size=3),
    st.lists(tilt, min_size=3, max_size=3),
    st.lists(load, min_size=6, max_size=6),
    st.sampled_from([BOX, CROSSED]),
)
def test_distribution_is_exact_or_refused(
    shift: list[float], angles: list[float], extra: list[float], anchors: np.ndarray
) -> None:
    pose = HOME + np.array(shift + angles)
    a_mat = kin.structure_matrix(FRAME, anchors, pose)
    w = statics.gravity_wrench(MASS_KG, G, pose) + np.array(extra)
    sv = np.linalg.svd(a_mat, compute_uv=False)
    if sv[-1] <= statics.RANK_RTOL * sv[0]:  # singular pose: refused even if w is balanced
        with pytest.raises(InfeasiblePoseError, match="rank-deficient"):
            statics.distribute_tensions(a_mat, w, LO, HI)
        return
    try:
        tau = statics.distribute_tensions(a_mat, w, LO, HI)
    except InfeasiblePoseError:
        # refused only when even slightly tighter limits admit no solution; near-singular
        # poses are skipped: there HiGHS' 1e-7 equality tolerance admits false solutions
        if sv[-1] > 1e-6 * sv[0]:
            assert not lp_feasible(a_mat, w, LO + 1e-6, HI - 1e-6)
        return
    assert_optimal(a_mat, w, tau, LO, HI)
    assert_allclose(statics.wrench_from_tensions(a_mat, tau), w, rtol=0, atol=1e-9)


def test_matches_slsqp_on_random_feasible_cases() -> None:
    rng = np.random.default_rng(7)
    checked = 0
    while checked < 15:
        a_mat, w = random_case(rng, CROSSED)
        if not statics.is_wrench_feasible(a_mat, w, LO, HI):
            continue
        tau = statics.distribute_tensions(a_mat, w, LO, HI)
        start = linprog(np.zeros(8), A_eq=a_mat, b_eq=-w, bounds=[(LO, HI)] * 8).x / HI
        ref = minimize(
            lambda x: np.sum((x - 0.51) ** 2),
            start,
            jac=lambda x: 2.0 * (x - 0.51),
            constraints=[
                {
                    "type": "eq",
                    "fun": lambda x, a=a_mat, b=w / HI: a @ x + b,
                    "jac": lambda x, a=a_mat: a,
                }
            ],
            bounds=[(LO / HI, 1.0)] * 8,
            method="SLSQP",
            options={"ftol": 1e-15, "maxiter": 500},
        )
        assert ref.success
        assert_allclose(tau / HI, ref.x, rtol=0, atol=1e-6)
        checked += 1


@pytest.mark.parametrize("anchors", [BOX, CROSSED], ids=["box", "crossed"])
def test_feasibility_agrees_with_linprog(anchors: np.ndarray) -> None:
    rng = np.random.default_rng(3)
    for _ in range(60):
        a_mat, w = random_case(rng, anchors)
        assert statics.is_wrench_feasible(a_mat, w, LO, HI) == lp_feasible(a_mat, w, LO, HI)


def test_active_limits_are_met_exactly() -> None:
    rng = np.random.default_rng(11)
    n_active = 0
    for _ in range(100):
        a_mat, w = random_case(rng, CROSSED)
        if statics.is_wrench_feasible(a_mat, w, LO, HI):
            tau = statics.distribute_tensions(a_mat, w, LO, HI)
            n_active += int(np.sum((tau == LO) | (tau == HI)))
            assert_optimal(a_mat, w, tau, LO, HI)
    assert n_active > 0


def test_huge_wrench_is_refused() -> None:
    a_mat = kin.structure_matrix(FRAME, CROSSED, HOME)
    w = np.array([0.0, 0.0, -1e5, 0.0, 0.0, 0.0])
    with pytest.raises(InfeasiblePoseError, match="not feasible"):
        statics.distribute_tensions(a_mat, w, LO, HI)
    assert not statics.is_wrench_feasible(a_mat, w, LO, HI)


def test_too_low_upper_limit_is_refused() -> None:
    a_mat = kin.structure_matrix(FRAME, CROSSED, HOME)
    w = statics.gravity_wrench(MASS_KG, G, HOME)
    with pytest.raises(InfeasiblePoseError):
        statics.distribute_tensions(a_mat, w, LO, 100.0)
    assert statics.is_wrench_feasible(a_mat, w, LO, 300.0)


def test_per_cable_limits() -> None:
    a_mat = kin.structure_matrix(
        FRAME, CROSSED, HOME + np.array([0.1, -0.05, 0.1, 0.02, 0.0, 0.03])
    )
    w = statics.gravity_wrench(MASS_KG, G, HOME)
    lo = np.array([20.0, 30, 40, 50, 20, 20, 20, 20])
    hi = np.array([600.0, 700, 800, 900, 1000, 300, 300, 300])
    assert_optimal(a_mat, w, statics.distribute_tensions(a_mat, w, lo, hi), lo, hi)
    with pytest.raises(ValueError, match="tau_min"):
        statics.distribute_tensions(a_mat, w, 500.0, 400.0)


def test_square_system_has_the_unique_solution() -> None:
    rng = np.random.default_rng(5)
    a_mat = rng.normal(size=(6, 6))
    tau_true = rng.uniform(100.0, 900.0, 6)
    w = -a_mat @ tau_true
    assert_allclose(statics.distribute_tensions(a_mat, w, LO, HI), tau_true, rtol=1e-10)
    with pytest.raises(InfeasiblePoseError):
        statics.distribute_tensions(a_mat, w, LO, 500.0)


@pytest.mark.parametrize("m", [7, 8, 12])
def test_any_number_of_cables_above_six(m: int) -> None:
    rng = np.random.default_rng(m)
    for _ in range(10):
        a_mat = rng.normal(size=(6, m))
        w = -a_mat @ rng.uniform(LO, HI, m)  # feasible by construction
        assert_optimal(a_mat, w, statics.distribute_tensions(a_mat, w, LO, HI), LO, HI)


def test_rank_deficient_matrix_is_refused() -> None:
    rng = np.random.default_rng(2)
    a_mat = rng.normal(size=(6, 8))
    a_mat[5] = a_mat[4]
    with pytest.raises(InfeasiblePoseError, match="rank-deficient"):
        statics.distribute_tensions(a_mat, np.zeros(6), LO, HI)
    with pytest.raises(InfeasiblePoseError, match="rank-deficient"):
        statics.distribute_tensions(rng.normal(size=(6, 5)), np.zeros(6), LO, HI)
    with pytest.raises(ValueError):
        statics.distribute_tensions(rng.normal(size=(5, 8)), np.zeros(6), LO, HI)


def test_batch_matches_single_and_names_the_infeasible_index() -> None:
    poses = np.stack(
        [HOME, HOME + np.array([0.1, 0.1, 0.1, 0, 0, 0.05]), HOME + np.array([0, 0, -0.2, 0, 0, 0])]
    )
    a_mats = kin.structure_matrix_batch(FRAME, CROSSED, poses)
    wrenches = statics.gravity_wrench_batch(MASS_KG, G, poses)
    taus = statics.distribute_tensions_batch(a_mats, wrenches, LO, HI)
    for k in range(3):
        assert_allclose(taus[k], statics.distribute_tensions(a_mats[k], wrenches[k], LO, HI))
    assert_allclose(statics.wrench_from_tensions_batch(a_mats, taus), wrenches, atol=1e-9)
    wrenches[1, 2] = -1e5
    with pytest.raises(InfeasiblePoseError, match="pose index 1"):
        statics.distribute_tensions_batch(a_mats, wrenches, LO, HI)


def test_per_cycle_wrench_equals_the_batch_forward_statics() -> None:
    """``wrench_into`` (the cycle's allocation-free form) against ``-A tau`` in batch."""
    rng = np.random.default_rng(3)
    poses = np.column_stack(
        [rng.uniform(-0.3, 0.3, (20, 2)), np.full(20, 1.5), rng.uniform(-0.2, 0.2, (20, 3))]
    )
    taus = rng.uniform(20, 500, (20, 8))
    a_mats = kin.structure_matrix_batch(FRAME, CROSSED, poses)
    expected = statics.wrench_from_tensions_batch(a_mats, taus)
    out = np.zeros(6)
    a, b = np.ascontiguousarray(FRAME, dtype=float), np.ascontiguousarray(CROSSED, dtype=float)
    for k in range(20):
        statics.wrench_into(a, b, poses[k], taus[k], out)
        assert_allclose(out, expected[k], rtol=1e-12, atol=1e-9)


def test_external_wrench_is_gravity_plus_dalembert() -> None:
    class Geo:
        gravity_m_s2 = 9.81
        center_of_mass_m = (0.0, 0.0, 0.0)

    poses = np.zeros((2, 6))
    acc = np.array([[0.0, 0.0, 0.0], [1.0, -2.0, 0.5]])
    w = statics.external_wrench_batch(np.array([10.0, 10.0]), poses, acc, Geo())
    assert_allclose(w[0], [0, 0, -98.1, 0, 0, 0], atol=1e-12)
    assert_allclose(w[1], [-10.0, 20.0, -98.1 - 5.0, 0, 0, 0], atol=1e-12)
