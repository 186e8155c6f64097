"""Inverse kinematics (gateway.model.kinematics) against analytic references and properties."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from gateway.model import kinematics as kin
from tests.geometry_helpers import BOX as PLATFORM
from tests.geometry_helpers import FRAME, HOME

angle = st.floats(-np.pi, np.pi, allow_nan=False)
small_angle = st.floats(-0.5, 0.5, allow_nan=False)
offset = st.floats(-0.5, 0.5, allow_nan=False)
rate = st.floats(-1.0, 1.0, allow_nan=False)


def workspace_pose(d: list[float]) -> np.ndarray:
    """A pose near home from six offsets (m, rad)."""
    return HOME + np.asarray(d)


poses = st.lists(offset, min_size=3, max_size=3).flatmap(
    lambda p: st.lists(small_angle, min_size=3, max_size=3).map(lambda r: workspace_pose(p + r))
)


def elementary(axis: int, angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    i, j = (axis + 1) % 3, (axis + 2) % 3
    rot = np.eye(3)
    rot[i, i], rot[i, j], rot[j, i], rot[j, j] = c, -s, s, c
    return rot


@given(angle, angle, angle)
def test_rotation_is_orthonormal_with_det_one(rx: float, ry: float, rz: float) -> None:
    rot = kin.rotation_matrix(rx, ry, rz)
    assert_allclose(rot @ rot.T, np.eye(3), rtol=0, atol=1e-14)
    assert_allclose(np.linalg.det(rot), 1.0, rtol=0, atol=1e-14)


@given(angle, angle, angle)
def test_rotation_order_is_rz_ry_rx(rx: float, ry: float, rz: float) -> None:
    expected = elementary(2, rz) @ elementary(1, ry) @ elementary(0, rx)
    assert_allclose(kin.rotation_matrix(rx, ry, rz), expected, rtol=0, atol=1e-14)


def test_rotation_about_z_maps_x_to_y() -> None:
    assert_allclose(kin.rotation_matrix(0, 0, np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-15)


def test_rotation_batch_matches_single() -> None:
    rng = np.random.default_rng(1)
    angles = rng.uniform(-3, 3, (5, 3))
    batch = kin.rotation_matrices(angles)
    for k in range(5):
        assert_allclose(batch[k], kin.rotation_matrix(*angles[k]), rtol=0, atol=0)


def test_cable_vectors_at_home_are_analytic() -> None:
    vec = kin.cable_vectors(FRAME, PLATFORM, HOME)
    assert_allclose(vec[0], [1.8, 1.35, 1.4], rtol=0, atol=1e-15)
    assert_allclose(vec[6], [-1.8, -1.35, -1.4], rtol=0, atol=1e-15)
    assert_allclose(kin.cable_lengths(FRAME, PLATFORM, HOME), np.hypot(2.25, 1.4), rtol=1e-15)


def test_rotated_platform_moves_the_anchors() -> None:
    pose = np.array([0.1, -0.2, 1.0, 0.0, 0.0, np.pi])
    vec = kin.cable_vectors(FRAME, PLATFORM, pose)
    # rz = pi maps b = (0.2, 0.15, 0.1) to (-0.2, -0.15, 0.1)
    assert_allclose(vec[0], FRAME[0] - pose[:3] - [-0.2, -0.15, 0.1], rtol=0, atol=1e-14)


def test_mirror_symmetric_cables_have_equal_lengths_at_home() -> None:
    lengths = kin.cable_lengths(FRAME, PLATFORM, HOME)
    assert_allclose(lengths, lengths[0], rtol=1e-15)


@settings(max_examples=50, deadline=None)
@given(poses)
def test_batch_functions_match_single_pose(pose: np.ndarray) -> None:
    batch = np.stack([pose, HOME])
    assert_allclose(
        kin.cable_vectors_batch(FRAME, PLATFORM, batch)[0],
        kin.cable_vectors(FRAME, PLATFORM, pose),
        rtol=0,
        atol=1e-15,
    )
    assert_allclose(
        kin.cable_lengths_batch(FRAME, PLATFORM, batch)[0],
        kin.cable_lengths(FRAME, PLATFORM, pose),
        rtol=1e-15,
    )
    assert_allclose(
        kin.unit_vectors_batch(FRAME, PLATFORM, batch)[0],
        kin.unit_vectors(FRAME, PLATFORM, pose),
        rtol=0,
        atol=1e-15,
    )
    assert_allclose(
        kin.structure_matrix_batch(FRAME, PLATFORM, batch)[0],
        kin.structure_matrix(FRAME, PLATFORM, pose),
        rtol=0,
        atol=1e-15,
    )


@settings(max_examples=50, deadline=None)
@given(poses)
def test_structure_matrix_columns(pose: np.ndarray) -> None:
    a_mat = kin.structure_matrix(FRAME, PLATFORM, pose)
    assert a_mat.shape == (6, 8)
    assert_allclose(np.linalg.norm(a_mat[:3], axis=0), 1.0, rtol=1e-14)
    rb = PLATFORM @ kin.rotation_matrix(*pose[3:]).T
    assert_allclose(a_mat[3:].T, np.cross(rb, a_mat[:3].T), rtol=0, atol=1e-15)
    assert_allclose(np.sum(a_mat[:3] * a_mat[3:], axis=0), 0.0, rtol=0, atol=1e-14)
    unit = kin.unit_vectors(FRAME, PLATFORM, pose)
    assert_allclose(a_mat[:3].T, unit, rtol=0, atol=0)
    # unit vectors point from the platform anchor towards the frame anchor
    anchors = pose[:3] + rb
    assert np.all(np.sum(unit * (FRAME - anchors), axis=1) > 0)


@settings(max_examples=50, deadline=None)
@given(poses, st.lists(rate, min_size=6, max_size=6))
def test_cable_velocity_matches_finite_differences(pose: np.ndarray, rates: list[float]) -> None:
    pose_rate = np.asarray(rates)
    omega = kin.angular_velocity_from_euler_rates(pose[3:], pose_rate[3:])
    twist = np.concatenate([pose_rate[:3], omega])
    dt = 1e-6
    ahead = kin.cable_lengths(FRAME, PLATFORM, pose + dt * pose_rate)
    behind = kin.cable_lengths(FRAME, PLATFORM, pose - dt * pose_rate)
    expected = (ahead - behind) / (2 * dt)
    assert_allclose(kin.cable_velocities(FRAME, PLATFORM, pose, twist), expected, atol=1e-8)


def test_moving_up_shortens_upper_cables() -> None:
    vel = kin.cable_velocities(FRAME, PLATFORM, HOME, [0, 0, 0.1, 0, 0, 0])
    assert np.all(vel[:4] < 0) and np.all(vel[4:] > 0)
    assert_allclose(vel[:4], -0.1 * 1.4 / np.hypot(2.25, 1.4), rtol=1e-14)


@settings(max_examples=50, deadline=None)
@given(st.lists(angle, min_size=3, max_size=3), st.lists(rate, min_size=3, max_size=3))
def test_angular_velocity_is_the_axial_vector_of_rdot_rt(
    angles: list[float], rates: list[float]
) -> None:
    ang, rat = np.asarray(angles), np.asarray(rates)
    dt = 1e-6
    r_dot = (kin.rotation_matrix(*(ang + dt * rat)) - kin.rotation_matrix(*(ang - dt * rat))) / (
        2 * dt
    )
    skew = r_dot @ kin.rotation_matrix(*ang).T
    omega = kin.angular_velocity_from_euler_rates(ang, rat)
    assert_allclose([skew[2, 1], skew[0, 2], skew[1, 0]], omega, atol=1e-8)
    batch = kin.angular_velocity_from_euler_rates(ang[None, :], rat[None, :])
    assert_allclose(batch[0], omega, rtol=0, atol=0)


def test_trajectory_velocities_twist_and_fd_agree() -> None:
    t = np.linspace(0.0, 2.0, 2001)
    traj = HOME + np.column_stack(
        [0.1 * np.sin(t), 0.05 * t, 0.1 * np.cos(2 * t), 0.05 * np.sin(t), 0.03 * t, -0.02 * t]
    )
    twists = kin.twists_from_poses(traj, t)
    from_twists = kin.cable_velocities_batch(FRAME, PLATFORM, traj, twists)
    from_lengths = kin.cable_velocities_fd(kin.cable_lengths_batch(FRAME, PLATFORM, traj), t)
    assert from_twists.shape == (2001, 8)
    assert_allclose(from_twists[1:-1], from_lengths[1:-1], rtol=0, atol=1e-6)


def test_cable_velocities_fd_is_exact_for_linear_lengths() -> None:
    t = np.array([0.0, 0.1, 0.3, 0.4])
    lengths = 2.0 + np.outer(t, [0.5, -0.25])
    assert_allclose(kin.cable_velocities_fd(lengths, t), [[0.5, -0.25]] * 4, rtol=1e-12)


def test_bad_shapes_raise() -> None:
    with pytest.raises(ValueError, match="anchors"):
        kin.cable_vectors(FRAME, PLATFORM[:7], HOME)
    with pytest.raises(ValueError, match="pose"):
        kin.cable_lengths(FRAME, PLATFORM, HOME[:5])
    with pytest.raises(ValueError, match="twist"):
        kin.cable_velocities(FRAME, PLATFORM, HOME, np.zeros(3))
    with pytest.raises(ValueError, match="lengths"):
        kin.cable_velocities_fd(np.zeros((4, 8)), np.zeros(3))


def test_any_number_of_cables() -> None:
    a_mat = kin.structure_matrix(FRAME[:1], PLATFORM[:1], HOME)
    assert a_mat.shape == (6, 1)
    assert_allclose(np.linalg.norm(a_mat[:3, 0]), 1.0, rtol=1e-15)
