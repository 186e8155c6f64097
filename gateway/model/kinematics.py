"""Inverse kinematics of a cable-driven parallel robot (paper eq. 1-4, physics.md sec. 1).

Pure numpy: arrays in, arrays out, SI units (m, rad, s). Conventions:

- ``frame_anchors`` ``a_i``: shape (m, 3), world frame B, in m.
- ``platform_anchors`` ``b_i``: shape (m, 3), platform frame E, in m.
- ``pose = (x, y, z, rx, ry, rz)``: shape (6,), position of the platform reference point
  in m and orientation angles in rad, ``R = Rz(rz) @ Ry(ry) @ Rx(rx)`` (eq. 2).
- ``twist = (vx, vy, vz, wx, wy, wz)``: shape (6,), linear velocity of the platform
  reference point in m/s and angular velocity in rad/s, both in the world frame.

Every function has a ``*_batch`` twin taking poses of shape (N, 6) and returning arrays
with a leading axis N.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def _as_anchors(frame_anchors: ArrayLike, platform_anchors: ArrayLike) -> tuple[FloatArray, ...]:
    a = np.asarray(frame_anchors, dtype=float)
    b = np.asarray(platform_anchors, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape != b.shape:
        raise ValueError(
            f"anchors must both have shape (m, 3); got frame {a.shape}, platform {b.shape}"
        )
    return a, b


def _as_poses(poses: ArrayLike) -> FloatArray:
    p = np.asarray(poses, dtype=float)
    if p.ndim != 2 or p.shape[1] != 6:
        raise ValueError(f"poses must have shape (N, 6); got {p.shape}")
    return p


def _as_pose(pose: ArrayLike) -> FloatArray:
    p = np.asarray(pose, dtype=float)
    if p.shape != (6,):
        raise ValueError(f"pose must have shape (6,); got {p.shape}")
    return p


def rotation_matrices(angles: ArrayLike) -> FloatArray:
    """Rotation matrices ``R = Rz(rz) @ Ry(ry) @ Rx(rx)`` (eq. 2) for many orientations.

    ``angles``: (N, 3) rows ``(rx, ry, rz)`` in rad. Returns (N, 3, 3); ``R`` maps
    platform-frame vectors to the world frame.
    """
    ang = np.asarray(angles, dtype=float)
    if ang.ndim != 2 or ang.shape[1] != 3:
        raise ValueError(f"angles must have shape (N, 3); got {ang.shape}")
    cx, cy, cz = np.cos(ang).T
    sx, sy, sz = np.sin(ang).T
    rot = np.empty((ang.shape[0], 3, 3))
    rot[:, 0, 0] = cz * cy
    rot[:, 0, 1] = cz * sy * sx - sz * cx
    rot[:, 0, 2] = cz * sy * cx + sz * sx
    rot[:, 1, 0] = sz * cy
    rot[:, 1, 1] = sz * sy * sx + cz * cx
    rot[:, 1, 2] = sz * sy * cx - cz * sx
    rot[:, 2, 0] = -sy
    rot[:, 2, 1] = cy * sx
    rot[:, 2, 2] = cy * cx
    return rot


def rotation_matrix(rx: float, ry: float, rz: float) -> FloatArray:
    """Rotation matrix ``R = Rz(rz) @ Ry(ry) @ Rx(rx)`` (eq. 2), angles in rad. Returns (3, 3)."""
    return rotation_matrices(np.array([[rx, ry, rz]], dtype=float))[0]


def cable_vectors_batch(
    frame_anchors: ArrayLike, platform_anchors: ArrayLike, poses: ArrayLike
) -> FloatArray:
    """Cable vectors ``l_i = a_i - r - R b_i`` (eq. 1) for poses (N, 6). Returns (N, m, 3) in m."""
    return _rotated_anchors_and_vectors(frame_anchors, platform_anchors, poses)[1]


def _rotated_anchors_and_vectors(
    frame_anchors: ArrayLike, platform_anchors: ArrayLike, poses: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """``R b_i`` (the moment arms) and ``l_i = a_i - r - R b_i``, both (N, m, 3) in m."""
    a, b = _as_anchors(frame_anchors, platform_anchors)
    p = _as_poses(poses)
    rb = np.einsum("nij,mj->nmi", rotation_matrices(p[:, 3:]), b)
    return rb, a[None, :, :] - p[:, None, :3] - rb


def cable_vectors(
    frame_anchors: ArrayLike, platform_anchors: ArrayLike, pose: ArrayLike
) -> FloatArray:
    """Cable vectors ``l_i = a_i - r - R b_i`` (eq. 1), platform towards frame.

    ``frame_anchors`` (m, 3), ``platform_anchors`` (m, 3), ``pose`` (6,). Returns (m, 3) in m.
    """
    return cable_vectors_batch(frame_anchors, platform_anchors, _as_pose(pose)[None, :])[0]


def cable_lengths_batch(
    frame_anchors: ArrayLike, platform_anchors: ArrayLike, poses: ArrayLike
) -> FloatArray:
    """Cable lengths ``L_i = |l_i|`` for poses (N, 6). Returns (N, m) in m."""
    return np.linalg.norm(cable_vectors_batch(frame_anchors, platform_anchors, poses), axis=-1)


def cable_lengths(
    frame_anchors: ArrayLike, platform_anchors: ArrayLike, pose: ArrayLike
) -> FloatArray:
    """Cable lengths ``L_i = |l_i|`` for one pose (6,). Returns (m,) in m."""
    return np.linalg.norm(cable_vectors(frame_anchors, platform_anchors, pose), axis=-1)


def unit_vectors_batch(
    frame_anchors: ArrayLike, platform_anchors: ArrayLike, poses: ArrayLike
) -> FloatArray:
    """Unit cable directions ``u_i = l_i / L_i`` (platform towards frame), (N, m, 3)."""
    vec = cable_vectors_batch(frame_anchors, platform_anchors, poses)
    return vec / np.linalg.norm(vec, axis=-1, keepdims=True)


def unit_vectors(
    frame_anchors: ArrayLike, platform_anchors: ArrayLike, pose: ArrayLike
) -> FloatArray:
    """Unit cable directions ``u_i = l_i / L_i`` (platform towards frame) for one pose, (m, 3)."""
    return unit_vectors_batch(frame_anchors, platform_anchors, _as_pose(pose)[None, :])[0]


def structure_matrix_batch(
    frame_anchors: ArrayLike, platform_anchors: ArrayLike, poses: ArrayLike
) -> FloatArray:
    """Structure matrices for poses (N, 6). Returns (N, 6, m); see ``structure_matrix``."""
    rb, vec = _rotated_anchors_and_vectors(frame_anchors, platform_anchors, poses)
    u = vec / np.linalg.norm(vec, axis=-1, keepdims=True)
    moment = np.cross(rb, u)
    return np.concatenate([u, moment], axis=-1).transpose(0, 2, 1)


def structure_matrix(
    frame_anchors: ArrayLike, platform_anchors: ArrayLike, pose: ArrayLike
) -> FloatArray:
    """Structure matrix ``A`` (eq. 4): column i is ``[u_i ; (R b_i) x u_i]``. Returns (6, m).

    ``A @ tau`` (tau in N, shape (m,)) is the wrench the cables exert on the platform,
    force in N and moment in N m about the platform reference point, world frame.
    """
    return structure_matrix_batch(frame_anchors, platform_anchors, _as_pose(pose)[None, :])[0]


def cable_velocities_batch(
    frame_anchors: ArrayLike, platform_anchors: ArrayLike, poses: ArrayLike, twists: ArrayLike
) -> FloatArray:
    """Cable velocities ``dL/dt = -A^T @ twist`` for poses (N, 6) and twists (N, 6).

    Returns (N, m) in m/s; positive pays the cable out (it gets longer).
    """
    tw = np.asarray(twists, dtype=float)
    if tw.ndim != 2 or tw.shape[1] != 6:
        raise ValueError(f"twists must have shape (N, 6); got {tw.shape}")
    a_mat = structure_matrix_batch(frame_anchors, platform_anchors, poses)
    return cable_velocities_from_structure(a_mat, tw)


def cable_velocities_from_structure(a_mats: ArrayLike, twists: ArrayLike) -> FloatArray:
    """``dL/dt = -A^T @ twist`` from structure matrices (N, 6, m) already computed."""
    return -np.einsum(
        "nim,ni->nm", np.asarray(a_mats, dtype=float), np.asarray(twists, dtype=float)
    )


def cable_velocities(
    frame_anchors: ArrayLike, platform_anchors: ArrayLike, pose: ArrayLike, twist: ArrayLike
) -> FloatArray:
    """Cable velocities ``dL_i/dt`` from the platform twist (6,). Returns (m,) in m/s.

    ``dL_i/dt = u_i . dl_i/dt = -u_i . (v + omega x R b_i) = -(A^T twist)_i``;
    positive pays the cable out. ``twist`` = (v in m/s, omega in rad/s), world frame.
    """
    tw = np.asarray(twist, dtype=float)
    if tw.shape != (6,):
        raise ValueError(f"twist must have shape (6,); got {tw.shape}")
    return -structure_matrix(frame_anchors, platform_anchors, pose).T @ tw


def angular_velocity_from_euler_rates(angles: ArrayLike, rates: ArrayLike) -> FloatArray:
    """World-frame angular velocity for ``R = Rz(rz) Ry(ry) Rx(rx)`` and angle rates.

    ``omega = drz e_z + dry Rz e_y + drx Rz Ry e_x``. ``angles`` (rad) and ``rates``
    (rad/s) have shape (3,) or (N, 3); returns the same shape in rad/s.
    """
    ang = np.asarray(angles, dtype=float)
    rate = np.asarray(rates, dtype=float)
    if ang.shape != rate.shape or ang.shape[-1] != 3 or ang.ndim > 2:
        raise ValueError(f"angles and rates must have equal shape (3,) or (N, 3); got {ang.shape}")
    ry, rz = ang[..., 1], ang[..., 2]
    drx, dry, drz = rate[..., 0], rate[..., 1], rate[..., 2]
    cy, sy, cz, sz = np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    wx = cz * cy * drx - sz * dry
    wy = sz * cy * drx + cz * dry
    wz = -sy * drx + drz
    return np.stack([wx, wy, wz], axis=-1)


def twists_from_poses(poses: ArrayLike, t_s: ArrayLike) -> FloatArray:
    """Platform twists (N, 6) of a sampled trajectory by finite differences.

    ``poses`` (N, 6), ``t_s`` (N,) increasing sample times in s (N >= 2). Pose rates by
    ``numpy.gradient`` (second order inside, first order at the ends), angle rates turned
    into a world-frame angular velocity with ``angular_velocity_from_euler_rates``.
    """
    p = _as_poses(poses)
    rates = np.gradient(p, np.asarray(t_s, dtype=float), axis=0)
    omega = angular_velocity_from_euler_rates(p[:, 3:], rates[:, 3:])
    return np.concatenate([rates[:, :3], omega], axis=1)


def cable_velocities_fd(lengths: ArrayLike, t_s: ArrayLike) -> FloatArray:
    """Cable velocities (N, m) in m/s from sampled lengths (N, m) in m and times (N,) in s.

    ``numpy.gradient`` along time: second order inside, first order at the two ends.
    """
    lengths_arr = np.asarray(lengths, dtype=float)
    t_arr = np.asarray(t_s, dtype=float)
    if lengths_arr.ndim != 2 or t_arr.shape != (lengths_arr.shape[0],):
        raise ValueError(
            f"lengths must be (N, m) and t_s (N,); got {lengths_arr.shape}, {t_arr.shape}"
        )
    return np.gradient(lengths_arr, t_arr, axis=0)
