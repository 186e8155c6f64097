"""Statics and tension distribution (paper eq. 5, 18, 19; physics.md sec. 1).

Pure numpy/scipy, SI units: tensions in N, forces in N, moments in N m, world frame.
``A`` is the (6, m) structure matrix of ``kinematics.structure_matrix``; ``w`` the (6,)
external wrench on the platform (force, then moment about the platform reference point),
and equilibrium is ``A @ tau + w = 0`` (eq. 5).

Tension distribution (eq. 18, 19): among all ``tau = -A^+ w + (I - A^+ A) h`` with
``tau_min <= tau <= tau_max`` pick the one minimising ``sum (tau_i - tau_avg_i)^2``,
``tau_avg = (tau_min + tau_max) / 2``: the Euclidean projection of ``tau_avg`` onto
``{tau : A tau = -w}`` intersected with the box. It is solved exactly:

1. SVD of ``A`` gives an orthonormal null-space basis ``N`` (m, m - 6) and the optimum
   ``t*`` without limits. With ``tau = t* + N x`` the cost is ``const + |x|^2``, so the
   problem is a least-distance program (LDP) in the null-space coordinates ``x``:
   ``min |x|`` s.t. ``lo - t* <= N x <= hi - t*``.
2. The LDP is solved by Lawson & Hanson's finite method (Solving Least Squares Problems,
   ch. 23): one non-negative least-squares problem (``scipy.optimize.nnls``), which also
   proves infeasibility (zero residual) when the box and the equality do not meet.
3. The active set found is re-solved as an equality-constrained problem (``min |x|`` with
   the active rows of ``N x`` at their bounds), so active tensions sit exactly on their
   limits and ``A tau + w = 0`` holds to rounding; the result is then checked against
   the limits with a tolerance of ``TOL_REL`` times the tension scale.

A pose with no feasible ``tau`` raises ``InfeasiblePoseError``: a clipped vector is never
returned. A rank-deficient ``A`` (``m < 6`` or a singular pose) raises it as well, because
``-A^+ w`` then no longer balances every wrench.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from gateway.errors import InfeasiblePoseError
from gateway.model.kinematics import rotation_matrices

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

RANK_RTOL = 1e-10
"""``A`` counts as rank-deficient when its smallest singular value is below this times
its largest."""

TOL_REL = 1e-9
"""Limit violations up to this times ``max(1, |tau_min|, |tau_max|, |w|)`` (N) are rounding."""


def gravity_wrench_batch(
    mass_kg: ArrayLike,
    g: float,
    poses: ArrayLike,
    center_of_mass_platform: ArrayLike = (0.0, 0.0, 0.0),
) -> FloatArray:
    """Gravity wrenches (N, 6) for poses (N, 6) and masses (scalar or (N,), kg).

    ``g`` in m/s^2 (positive, acting along -z); see ``gravity_wrench``.
    """
    p = np.asarray(poses, dtype=float)
    if p.ndim != 2 or p.shape[1] != 6:
        raise ValueError(f"poses must have shape (N, 6); got {p.shape}")
    com = np.asarray(center_of_mass_platform, dtype=float)
    if com.shape != (3,):
        raise ValueError(f"center_of_mass_platform must have shape (3,); got {com.shape}")
    mass = np.broadcast_to(np.asarray(mass_kg, dtype=float), (p.shape[0],))
    force = np.zeros((p.shape[0], 3))
    force[:, 2] = -mass * g
    lever = rotation_matrices(p[:, 3:]) @ com
    return np.concatenate([force, np.cross(lever, force)], axis=1)


def gravity_wrench(
    mass_kg: float,
    g: float,
    pose: ArrayLike,
    center_of_mass_platform: ArrayLike = (0.0, 0.0, 0.0),
) -> FloatArray:
    """Gravity wrench on the platform, shape (6,): ``[F ; (R com) x F]``, ``F = (0, 0, -m g)``.

    ``mass_kg`` in kg, ``g`` in m/s^2 (positive), ``pose`` (6,), ``center_of_mass_platform``
    (3,) in m in the platform frame, relative to the platform reference point. Force in N,
    moment in N m about the platform reference point, world frame.
    """
    p = np.asarray(pose, dtype=float)
    if p.shape != (6,):
        raise ValueError(f"pose must have shape (6,); got {p.shape}")
    return gravity_wrench_batch(mass_kg, g, p[None, :], center_of_mass_platform)[0]


def inertial_wrench(mass_kg: ArrayLike, accel_m_s2: ArrayLike) -> FloatArray:
    """d'Alembert wrench ``[-m a ; 0]`` of the translating platform, (6,) or (N, 6).

    ``mass_kg`` scalar or (N,), ``accel_m_s2`` (3,) or (N, 3) in m/s^2, world frame.
    Rotational inertia, gyroscopic terms and the moment of ``-m a`` about an off-centre
    centre of mass are neglected: at the printing speeds of the paper (0.04 m/s) they are
    far below the tension resolution.
    """
    acc = np.asarray(accel_m_s2, dtype=float)
    if acc.shape[-1:] != (3,) or acc.ndim > 2:
        raise ValueError(f"accel_m_s2 must have shape (3,) or (N, 3); got {acc.shape}")
    mass = np.asarray(mass_kg, dtype=float)
    force = -(mass[..., None] if mass.ndim else mass) * acc
    return np.concatenate([force, np.zeros_like(force)], axis=-1)


def external_wrench_batch(
    mass_kg: ArrayLike, poses: ArrayLike, accel_m_s2: ArrayLike, geometry: Any
) -> FloatArray:
    """External wrench (N, 6) on the platform: gravity plus d'Alembert ``-m a``.

    ``geometry``: has ``gravity_m_s2`` and ``center_of_mass_m`` (a ``GeometryConfig``);
    ``mass_kg`` scalar or (N,), ``poses`` (N, 6), ``accel_m_s2`` (N, 3). The one external
    wrench of the plant and of the diagnosis.
    """
    w = gravity_wrench_batch(mass_kg, geometry.gravity_m_s2, poses, geometry.center_of_mass_m)
    return w + inertial_wrench(mass_kg, accel_m_s2)


@njit(cache=True)
def wrench_into(frame_anchors, platform_anchors, pose, tension, out):
    """Per-cycle forward statics ``w = -A(pose) @ tension`` into ``out`` (6,), no allocation.

    ``frame_anchors``, ``platform_anchors``: (m, 3) m; ``pose``: (6,) x, y, z m and
    rx, ry, rz rad with ``R = Rz Ry Rx``; ``tension``: (m,) N. Column i of ``A`` is
    ``[u_i; (R b_i) x u_i]`` (eq. 4) with ``u_i`` the unit vector platform -> frame anchor.
    Tested against :func:`wrench_from_tensions` with :func:`kinematics.structure_matrix`.
    """
    ca, sa = math.cos(pose[3]), math.sin(pose[3])
    cb, sb = math.cos(pose[4]), math.sin(pose[4])
    cg, sg = math.cos(pose[5]), math.sin(pose[5])
    r00, r01, r02 = cg * cb, cg * sb * sa - sg * ca, cg * sb * ca + sg * sa
    r10, r11, r12 = sg * cb, sg * sb * sa + cg * ca, sg * sb * ca - cg * sa
    r20, r21, r22 = -sb, cb * sa, cb * ca
    for k in range(6):
        out[k] = 0.0
    for i in range(tension.size):
        bx, by, bz = platform_anchors[i, 0], platform_anchors[i, 1], platform_anchors[i, 2]
        px = r00 * bx + r01 * by + r02 * bz
        py = r10 * bx + r11 * by + r12 * bz
        pz = r20 * bx + r21 * by + r22 * bz
        lx = frame_anchors[i, 0] - pose[0] - px
        ly = frame_anchors[i, 1] - pose[1] - py
        lz = frame_anchors[i, 2] - pose[2] - pz
        norm = math.sqrt(lx * lx + ly * ly + lz * lz)
        ux, uy, uz = lx / norm, ly / norm, lz / norm
        t = tension[i]
        out[0] -= ux * t
        out[1] -= uy * t
        out[2] -= uz * t
        out[3] -= (py * uz - pz * uy) * t
        out[4] -= (pz * ux - px * uz) * t
        out[5] -= (px * uy - py * ux) * t


def wrench_from_tensions(a_mat: ArrayLike, tau: ArrayLike) -> FloatArray:
    """Forward statics ``w_hat = -A @ tau`` (A (6, m), tau (m,) in N). Returns (6,)."""
    return -(np.asarray(a_mat, dtype=float) @ np.asarray(tau, dtype=float))


def wrench_from_tensions_batch(a_mats: ArrayLike, taus: ArrayLike) -> FloatArray:
    """Forward statics for many poses: A (N, 6, m), tau (N, m) in N. Returns (N, 6)."""
    return -np.einsum("nim,nm->ni", np.asarray(a_mats, float), np.asarray(taus, float))


def _check_args(
    a_mat: ArrayLike, w: ArrayLike, tau_min: ArrayLike, tau_max: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    a = np.asarray(a_mat, dtype=float)
    wr = np.asarray(w, dtype=float)
    if a.ndim != 2 or a.shape[0] != 6 or wr.shape != (6,):
        raise ValueError(f"A must be (6, m) and w (6,); got {a.shape}, {wr.shape}")
    m = a.shape[1]
    lo = np.broadcast_to(np.asarray(tau_min, dtype=float), (m,))
    hi = np.broadcast_to(np.asarray(tau_max, dtype=float), (m,))
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(wr))):
        raise ValueError("A and w must be finite")
    if not np.all(lo <= hi):
        raise ValueError("tau_min must not exceed tau_max (and neither may be NaN)")
    return a, wr, lo, hi


def null_space_split(a: FloatArray, w: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Minimum-norm ``-A^+ w`` (m,) and an orthonormal null-space basis of A (m, m - 6)."""
    m = a.shape[1]
    if m < 6:
        raise InfeasiblePoseError(f"structure matrix has {m} < 6 columns: rank-deficient")
    u, s, vt = np.linalg.svd(a)
    if not s[-1] > RANK_RTOL * s[0]:
        raise InfeasiblePoseError(
            f"structure matrix is rank-deficient (singular values {s[0]:.3g} .. {s[-1]:.3g}):"
            " singular pose"
        )
    tau_part = -(vt[:6].T @ ((u.T @ w) / s))
    return tau_part, vt[6:].T


def least_distance(null_basis: FloatArray, lower: FloatArray, upper: FloatArray) -> FloatArray:
    """``min |x|`` s.t. ``lower <= N x <= upper`` by Lawson-Hanson LDP via NNLS.

    ``N`` (m, r), bounds (m,). Raises InfeasiblePoseError when the constraints are
    incompatible. Constraints are written ``G x >= h`` with ``G = [N; -N]``,
    ``h = [lower; -upper]``, scaled so that ``max |h| = 1``.
    """
    g_mat = np.concatenate([null_basis, -null_basis])
    h = np.concatenate([lower, -upper])
    scale = float(np.max(np.abs(h))) or 1.0
    e_mat = np.vstack([g_mat.T, h[None, :] / scale])
    f = np.zeros(e_mat.shape[0])
    f[-1] = 1.0
    from scipy.optimize import nnls  # here: the daemon's wrench needs no scipy (47 MB RSS)

    u, _ = nnls(e_mat, f)
    res = e_mat @ u - f
    if not res[-1] < -1e-12:
        raise InfeasiblePoseError("no tension distribution within the limits")
    return -res[:-1] / res[-1] * scale


def _polish(
    null_basis: FloatArray, x: FloatArray, lower: FloatArray, upper: FloatArray, tol: float
) -> tuple[FloatArray, BoolArray, BoolArray]:
    """Re-solve ``min |x|`` with the active limits of the LDP solution as equalities.

    ``null_basis`` (m, r), ``x`` (r,), bounds (m,) relative to ``t*``. Returns
    ``(x, at_lower, at_upper)`` with the masks (m,) of the limits met. Keeps the LDP
    solution when the active rows are dependent or the re-solve leaves the box.
    """
    nx = null_basis @ x
    at_lower = nx <= lower + tol
    at_upper = (nx >= upper - tol) & ~at_lower
    active = at_lower | at_upper
    if not np.any(active):
        return x, at_lower, at_upper
    rows = null_basis[active]
    target = np.where(at_lower, lower, upper)[active]
    solution, _, rank, _ = np.linalg.lstsq(rows, target, rcond=None)
    x_eq = np.asarray(solution, dtype=np.float64)
    nx_eq = null_basis @ x_eq
    if rank < rows.shape[0] or np.any(nx_eq < lower - tol) or np.any(nx_eq > upper + tol):
        return x, at_lower, at_upper
    return x_eq, at_lower, at_upper


def distribute_tensions(
    a_mat: ArrayLike, w: ArrayLike, tau_min: ArrayLike, tau_max: ArrayLike
) -> FloatArray:
    """Tension distribution closest to the mid-range (eq. 18, 19), solved exactly.

    ``a_mat`` (6, m) structure matrix with rank 6 (m >= 6), ``w`` (6,) external wrench
    (N, N m), ``tau_min``/``tau_max`` scalars or (m,) in N. Returns ``tau`` (m,) in N with
    ``A tau + w = 0`` and ``tau_min <= tau <= tau_max`` minimising
    ``sum (tau - (tau_min + tau_max) / 2)^2``.

    Raises ``InfeasiblePoseError`` when no such ``tau`` exists or ``A`` is rank-deficient.
    """
    a, wr, lo, hi = _check_args(a_mat, w, tau_min, tau_max)
    scale = max(1.0, float(np.max(np.abs(lo))), float(np.max(np.abs(hi))))
    tol = TOL_REL * max(scale, float(np.max(np.abs(wr))))
    tau_part, null_basis = null_space_split(a, wr)
    t_star = tau_part + null_basis @ (null_basis.T @ (0.5 * (lo + hi)))
    lower, upper = lo - t_star, hi - t_star
    if np.all(lower <= tol) and np.all(upper >= -tol):
        return np.clip(t_star, lo, hi)
    if null_basis.shape[1] == 0:
        raise _infeasible(t_star, lo, hi)
    try:
        x = least_distance(null_basis, lower, upper)
    except InfeasiblePoseError:
        raise _infeasible(t_star, lo, hi) from None
    x, at_lower, at_upper = _polish(null_basis, x, lower, upper, tol)
    tau = t_star + null_basis @ x
    if np.any(tau < lo - tol) or np.any(tau > hi + tol):
        raise _infeasible(tau, lo, hi)
    tau = np.clip(tau, lo, hi)
    tau[at_lower] = lo[at_lower]
    tau[at_upper] = hi[at_upper]
    return tau


def _infeasible(tau: FloatArray, lo: FloatArray, hi: FloatArray) -> InfeasiblePoseError:
    viol = np.maximum(lo - tau, tau - hi)
    worst = int(np.argmax(viol))
    return InfeasiblePoseError(
        f"wrench not feasible: no tensions within [{lo.min():g}, {hi.max():g}] N balance it"
        f" (best candidate puts cable {worst + 1} at {tau[worst]:.6g} N)"
    )


def is_wrench_feasible(
    a_mat: ArrayLike, w: ArrayLike, tau_min: ArrayLike, tau_max: ArrayLike
) -> bool:
    """True when ``distribute_tensions`` finds tensions within the limits balancing ``w``.

    Same arguments as ``distribute_tensions``. A rank-deficient ``A`` counts as infeasible
    (the controller cannot distribute there), as does a violation above the rounding
    tolerance ``TOL_REL``.
    """
    try:
        distribute_tensions(a_mat, w, tau_min, tau_max)
    except InfeasiblePoseError:
        return False
    return True


def distribute_tensions_batch(
    a_mats: ArrayLike, wrenches: ArrayLike, tau_min: ArrayLike, tau_max: ArrayLike
) -> FloatArray:
    """``distribute_tensions`` for A (N, 6, m) and w (N, 6). Returns (N, m) in N.

    Raises ``InfeasiblePoseError`` naming the first infeasible index.
    """
    a = np.asarray(a_mats, dtype=float)
    wr = np.asarray(wrenches, dtype=float)
    if a.ndim != 3 or wr.ndim != 2 or a.shape[0] != wr.shape[0]:
        raise ValueError(f"A must be (N, 6, m) and w (N, 6); got {a.shape}, {wr.shape}")
    out = np.empty((a.shape[0], a.shape[2]))
    for k in range(a.shape[0]):
        try:
            out[k] = distribute_tensions(a[k], wr[k], tau_min, tau_max)
        except InfeasiblePoseError as err:
            raise InfeasiblePoseError(f"pose index {k}: {err}") from err
    return out
