"""The cable path between force sensor and platform, both ways (physics.md sec. 2, 3).

``m`` cables, each passing ``n`` pulleys numbered from the sensor towards the platform.
Per pulley ``T_j = T_{j-1} + F_j`` where ``F_j`` is

* ``coulomb``: ``sgn(v) F_Rj`` (eq. 8, 11, 12),
* ``dahl``: the pre-sliding state stepped with :func:`friction.dahl_step` over the
  cable travel of each step (eq. 14), carried between calls,
* ``none``: 0,

with the Coulomb level ``F_Rj = (lambda_ij(s) |T_j| + f0_i / n) S_i(v)`` (physics.md:
``F_Rj = lambda_j T_j``, the level the Dahl state tends to): ``lambda_ij(s)`` is taken at
the exact per-direction Coulomb ratio ``n_j(s)`` (eq. 11, 12 solved as a quadratic, see
:func:`coulomb_coefficients`), so at steady sliding Dahl equals Coulomb exactly; ``f0`` is
a load-independent part (seals, preload; split evenly over the pulleys) and
``S = 1 + k exp(-(v / v_s)^2)`` the Stribeck factor. Viscous friction ``c_i v`` is added
at the platform end: ``T_p = T_n + c v``. ``|T|`` makes the law hold for push forces too
(a single-axis test rig).

Cable travel (:func:`travel_into`, the one definition every form uses): the trapezoid over
the actual sample times, ``dx_k = (v_{k-1} + v_k) / 2 (t_k - t_{k-1})``, ``dx_0 = 0``; the
Dahl state advances by ``dx_k`` and takes its direction from it, while the Coulomb sign,
the Stribeck factor and the viscous term take the sample's own ``v_k``. (Stepping with
``v_k dt_k`` instead makes an error of the order ``a dt^2 / 2`` per step that sampling
jitter turns into noise: 0.13 N RMS on a noise-free 100 Hz +-2 ms recording.)

Simulation (platform -> sensor) is explicit: ``F_Rj`` follows from the known platform-side
tension, so each pulley is one exact Dahl step. Compensation (sensor -> platform) is
implicit in ``T_j``: Newton's iteration seeded with the previous cycle (``T_{j-1} +
F_old``) converges to 1e-9 N in one or two passes at 1 kHz (tests check it), stopping at
``tol_n`` or after ``max_iter`` passes.

* :func:`compensate` / :class:`ChainStepper`: sensor reading ``T_s`` and setpoint velocity
  -> platform tension ``T_p`` (what the gateway does each cycle).
* :func:`simulate`: platform tension and velocity -> the sensor reading ``T_s`` (the plant).

Two compiled kernels (:func:`compensate_kernel`, :func:`simulate_kernel`) share the pulley
step and read their parameters from one :class:`KernelParams`; ``compensate(simulate(T))``
returns ``T``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Literal, NamedTuple

import numpy as np
from numba import njit

from gateway.model.fastcall import entry_point
from gateway.model.friction import FR_FLOOR_N, coulomb_ratio_exact, dahl_step, dahl_step_slope

LAWS = {"none": 0, "coulomb": 1, "dahl": 2}
"""The law table: a friction law's name -> its code in the compiled pulley step
(:func:`_pulley` dispatches on it). A new chain-side law is one row here and its branch
there; the effects that switch a chain to it say so in their module."""
LAW_NONE, LAW_COULOMB, LAW_DAHL = LAWS["none"], LAWS["coulomb"], LAWS["dahl"]
ModelName = Literal["none", "coulomb", "dahl"]


def _per_cable(value: float | np.ndarray, cables: int, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        return np.full(cables, float(arr))
    if arr.shape != (cables,):
        raise ValueError(f"{name}: expected a scalar or shape ({cables},), got {arr.shape}")
    return arr.copy()


@dataclass(frozen=True, eq=False)
class ChainParams:
    """Friction parameters of ``m`` cable chains of ``n`` pulleys each.

    ``model``: the friction law (a key of :data:`LAWS`). Arrays: ``wrap_rad`` (n,);
    ``mu`` (m, n) the bearing coefficient paying out (v > 0), ``mu_in`` (m, n) hauling in
    (v < 0; the same as ``mu`` unless a direction-dependent effect sets it);
    ``sigma_n_m``, ``f0_n``, ``stribeck_k``, ``stribeck_v_m_s``, ``viscous_ns_m`` (m,).
    ``beta``: Dahl shape exponent.
    """

    model: ModelName
    wrap_rad: np.ndarray
    mu: np.ndarray
    sigma_n_m: np.ndarray
    beta: float = 1.0
    f0_n: np.ndarray = field(default_factory=lambda: np.zeros(0))
    stribeck_k: np.ndarray = field(default_factory=lambda: np.zeros(0))
    stribeck_v_m_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    viscous_ns_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    mu_in: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @staticmethod
    def build(
        model: ModelName,
        cables: int,
        wrap_rad: np.ndarray | tuple[float, ...],
        mu: float | np.ndarray | tuple[float, ...],
        *,
        mu_in: float | np.ndarray | tuple[float, ...] | None = None,
        sigma_n_m: float | np.ndarray = 500.0,
        beta: float = 1.0,
        f0_n: float | np.ndarray = 0.0,
        stribeck_k: float | np.ndarray = 0.0,
        stribeck_v_m_s: float | np.ndarray = 0.01,
        viscous_ns_m: float | np.ndarray = 0.0,
    ) -> ChainParams:
        """Broadcast scalars and per-pulley (n,) or per-cable-per-pulley (m, n) ``mu``
        (``mu_in`` None: the same as ``mu``)."""
        if model not in LAWS:
            raise ValueError(f"model must be one of {sorted(LAWS)}, got {model!r}")
        wrap = np.asarray(wrap_rad, dtype=float).reshape(-1)
        shape = (cables, wrap.size)
        mu_arr = np.broadcast_to(np.asarray(mu, dtype=float), shape).copy()
        mu_in_arr = (
            mu_arr.copy()
            if mu_in is None
            else np.broadcast_to(np.asarray(mu_in, dtype=float), shape).copy()
        )
        vs = _per_cable(stribeck_v_m_s, cables, "stribeck_v_m_s")
        if np.any(vs <= 0):
            raise ValueError("stribeck_v_m_s must be > 0")
        return ChainParams(
            model=model,
            wrap_rad=wrap,
            mu=mu_arr,
            mu_in=mu_in_arr,
            sigma_n_m=_per_cable(sigma_n_m, cables, "sigma_n_m"),
            beta=float(beta),
            f0_n=_per_cable(f0_n, cables, "f0_n"),
            stribeck_k=_per_cable(stribeck_k, cables, "stribeck_k"),
            stribeck_v_m_s=vs,
            viscous_ns_m=_per_cable(viscous_ns_m, cables, "viscous_ns_m"),
        )

    @staticmethod
    def from_friction(friction: object, cables: int) -> ChainParams:
        """The nominal chain of a :class:`gateway.core.config.FrictionConfig` (same for every
        cable), without its fitted ``effects``: for those use
        :func:`gateway.model.effects.chain_params`."""
        return ChainParams.build(
            model=friction.model,  # type: ignore[attr-defined]
            cables=cables,
            wrap_rad=np.asarray(friction.wrap_rad),  # type: ignore[attr-defined]
            mu=np.asarray(friction.mu),  # type: ignore[attr-defined]
            sigma_n_m=friction.sigma_n_m,  # type: ignore[attr-defined]
            beta=friction.beta,  # type: ignore[attr-defined]
            viscous_ns_m=friction.viscous_ns_m,  # type: ignore[attr-defined]
        )

    def with_model(self, model: ModelName) -> ChainParams:
        return replace(self, model=model)

    @property
    def cables(self) -> int:
        return int(self.mu.shape[0])

    @property
    def pulleys(self) -> int:
        return int(self.wrap_rad.size)


_NEWTON_CURVATURE = 1.0
"""Bound, in 1/N, on |g''/(2 g')| for the pulley equation g(T) = T - T_a - F(T): F depends on
T only through F_R = lambda S |T| (+ f0), so g'' carries (lambda S)^2 ~ 1e-3 times the
Dahl step's curvature in F_R, far below 1/N for any tension that carries friction.
Newton's next correction is at most this times step^2, so a pass whose correction has
step^2 * bound <= tol leaves an error below tol: no confirming pass is needed."""


class KernelParams(NamedTuple):
    """What the compiled kernels read, as one numba-compatible structure.

    ``lam_pos``, ``lam_neg`` (m, n): Coulomb coefficients for v > 0 and v < 0;
    ``f0``, ``strib_k``, ``strib_v``, ``viscous``, ``sigma`` (m,); ``beta``; ``law``
    (:data:`LAWS`); Newton's ``tol`` (N^2 on the squared step) and ``max_iter``.
    """

    lam_pos: np.ndarray
    lam_neg: np.ndarray
    f0: np.ndarray
    strib_k: np.ndarray
    strib_v: np.ndarray
    viscous: np.ndarray
    sigma: np.ndarray
    beta: float
    law: int
    tol: float
    max_iter: int


def kernel_params(params: ChainParams, tol_n: float = 1e-10, max_iter: int = 20) -> KernelParams:
    """The kernels' view of ``params`` (Coulomb coefficients solved once here)."""
    lam_pos, lam_neg = coulomb_coefficients(params)
    return KernelParams(
        lam_pos=lam_pos,
        lam_neg=lam_neg,
        f0=params.f0_n,
        strib_k=params.stribeck_k,
        strib_v=params.stribeck_v_m_s,
        viscous=params.viscous_ns_m,
        sigma=params.sigma_n_m,
        beta=float(params.beta),
        law=LAWS[params.model],
        tol=float(tol_n),
        max_iter=int(max_iter),
    )


@njit(cache=True, inline="always")
def _pulley(p, i, j, t_b, f_old, dx, strib):
    """Friction force of pulley ``j`` of cable ``i`` whose platform-side tension is
    ``t_b``, and dF/dt_b, by the chain's law (:data:`LAWS`).

    ``dx``: the step's cable travel (Dahl) or, for Coulomb, anything with the sign of
    the sample's velocity (only its sign is read); ``strib``: the Stribeck factor."""
    law = p.law
    if dx == 0.0:
        return (0.0 if law == LAW_COULOMB else f_old), 0.0
    s = 1.0 if dx > 0.0 else -1.0
    lam = p.lam_pos[i, j] if dx > 0.0 else p.lam_neg[i, j]
    fr = (lam * abs(t_b) + p.f0[i] / p.lam_pos.shape[1]) * strib
    dfr = lam * strib * (1.0 if t_b >= 0.0 else -1.0)
    if law == LAW_COULOMB:
        return s * fr, s * dfr
    # LAW_DAHL
    if fr <= FR_FLOOR_N:
        return 0.0, 0.0
    sigma = p.sigma[i]
    if p.beta == 1.0:
        f_new, slope = dahl_step_slope(f_old, fr, dx, sigma)
        return f_new, slope * dfr
    f_new = dahl_step(f_old, fr, dx, sigma, p.beta)
    return f_new, s * (1.0 - math.exp(-sigma * abs(dx) / fr)) * dfr  # quasi-Newton slope


@njit(cache=True, inline="always")
def _stribeck(p, i, v):
    if p.strib_k[i] == 0.0:
        return 1.0
    return 1.0 + p.strib_k[i] * math.exp(-((v / p.strib_v[i]) ** 2))


@njit(cache=True)
def travel_into(vel, dt, v_prev, dx):
    """Cable travel of each step (m), the trapezoid over the actual sample spacing:
    ``dx[k, i] = (v_prev[i] + vel[k, i]) / 2 * dt[k]`` with ``v_prev`` the velocity of the
    step before, updated in place (so a per-cycle caller carries it). ``vel``, ``dx``
    (N, m); ``dt`` (N,); ``v_prev`` (m,)."""
    for k in range(vel.shape[0]):
        for i in range(vel.shape[1]):
            dx[k, i] = 0.5 * (v_prev[i] + vel[k, i]) * dt[k]
            v_prev[i] = vel[k, i]


@njit(cache=True, inline="always")
def _direction(law, v, dx):
    """What sets the pulley's direction: the velocity for Coulomb, the travel for Dahl."""
    return v if law == LAW_COULOMB else dx


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def compensate_kernel(p, t_in, vel, dx_all, f_state, out):
    """Sensor -> platform for (N, m) ``t_in``, ``vel``, travel ``dx_all`` (:func:`travel_into`)
    and ``out``; ``f_state`` (m, n) in/out. Each pulley's implicit equation by Newton, seeded
    with the previous cycle's force. Returns the largest number of Newton passes any pulley
    needed."""
    n_samples, m = t_in.shape
    n = p.lam_pos.shape[1]
    worst = 0
    for k in range(n_samples):
        for i in range(m):
            v = vel[k, i]
            dx = _direction(p.law, v, dx_all[k, i])
            t_a = t_in[k, i]
            if p.law != LAW_NONE:
                strib = _stribeck(p, i, v)
                for j in range(n):
                    f_old = f_state[i, j]
                    t_b = t_a + f_old
                    it = 0
                    while it < p.max_iter:
                        it += 1
                        f_new, d_b = _pulley(p, i, j, t_b, f_old, dx, strib)
                        step = (t_b - t_a - f_new) / (1.0 - d_b)
                        t_prev = t_b
                        t_b -= step
                        # the curvature bound holds on one side of T = 0 (|T| has its kink
                        # there): a step that crossed it or landed on it is not confirmed
                        if step * step * _NEWTON_CURVATURE <= p.tol and t_prev * t_b > 0.0:
                            break
                    f_state[i, j] = t_b - t_a
                    worst = max(worst, it)
                    t_a = t_b
            out[k, i] = t_a + p.viscous[i] * v
    return worst


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def simulate_kernel(p, t_in, vel, dx_all, f_state, out):
    """Platform -> sensor, same arguments as :func:`compensate_kernel`; explicit (each
    pulley's Coulomb level follows from its known platform-side tension)."""
    n_samples, m = t_in.shape
    n = p.lam_pos.shape[1]
    for k in range(n_samples):
        for i in range(m):
            v = vel[k, i]
            dx = _direction(p.law, v, dx_all[k, i])
            t_b = t_in[k, i] - p.viscous[i] * v
            if p.law != LAW_NONE:
                strib = _stribeck(p, i, v)
                for j in range(n - 1, -1, -1):
                    f_new, _ = _pulley(p, i, j, t_b, f_state[i, j], dx, strib)
                    f_state[i, j] = f_new
                    t_b -= f_new
            out[k, i] = t_b
    return 0


def coulomb_coefficients(params: ChainParams) -> tuple[np.ndarray, np.ndarray]:
    """``lambda_ij`` (m, n) for paying out and for reeling in, from the exact ratio.

    At sliding, ``T_j - T_{j-1} = s lambda_j T_j`` with ``n_j = 1 - s lambda_j`` the exact
    root of the Coulomb quadratic (:func:`friction.coulomb_ratio_exact`), so
    ``lambda = 1 - n(+)`` paying out (with ``mu``) and ``n(-) - 1`` reeling in (with
    ``mu_in``).
    """
    mu_in = params.mu_in if params.mu_in.shape == params.mu.shape else params.mu
    lam_pos = np.empty_like(params.mu)
    lam_neg = np.empty_like(params.mu)
    for (i, j), mu in np.ndenumerate(params.mu):
        wrap = float(params.wrap_rad[j])
        lam_pos[i, j] = 1.0 - coulomb_ratio_exact(float(mu), wrap, 1.0)
        lam_neg[i, j] = coulomb_ratio_exact(float(mu_in[i, j]), wrap, -1.0) - 1.0
    return lam_pos, lam_neg


BATCH_ROWS = 32768  # rows per kernel call in the batch forms (bounds the travel array)


def _time_steps(t: np.ndarray | float, n_samples: int) -> np.ndarray:
    """``dt_k = t_k - t_{k-1}`` with ``dt_0 = 0`` (no travel before the first sample)."""
    if np.ndim(t) == 0:
        dt = np.full(n_samples, float(t))
        dt[0] = 0.0
        return dt
    t_arr = np.asarray(t, dtype=float)
    if t_arr.shape != (n_samples,):
        raise ValueError(f"t: expected shape ({n_samples},), got {t_arr.shape}")
    return np.concatenate(([0.0], np.diff(t_arr)))


def travel(t: np.ndarray | float, velocity: np.ndarray) -> np.ndarray:
    """Cable travel (N, m) of each step, m, for velocity (N, m) at times ``t`` (N,) or a
    constant period: :func:`travel_into` with no travel at the first sample."""
    vel = np.ascontiguousarray(velocity, dtype=float)
    dx = np.empty_like(vel)
    if vel.shape[0]:
        travel_into(vel, _time_steps(t, vel.shape[0]), vel[0].copy(), dx)
    return dx


def new_state(params: ChainParams) -> np.ndarray:
    """Friction state (m, n), N: relaxed (every pulley force zero)."""
    return np.zeros((params.cables, params.pulleys))


def _run_batch(
    params: ChainParams,
    forward: bool,
    tension: np.ndarray,
    velocity: np.ndarray,
    t: np.ndarray | float,
    state: np.ndarray | None,
    tol_n: float,
    max_iter: int,
) -> np.ndarray:
    t_in = np.ascontiguousarray(tension, dtype=float)
    vel = np.ascontiguousarray(velocity, dtype=float)
    if t_in.ndim != 2 or t_in.shape[1] != params.cables or vel.shape != t_in.shape:
        raise ValueError(
            f"tension and velocity must both have shape (N, {params.cables}); "
            f"got {t_in.shape} and {vel.shape}"
        )
    f_state = new_state(params) if state is None else state
    out = np.empty_like(t_in)
    kernel = compensate_kernel if forward else simulate_kernel
    p = kernel_params(params, tol_n, max_iter)
    n = t_in.shape[0]
    if n == 0:
        return out
    dt = _time_steps(t, n)
    # the travel in row blocks (the friction state and the previous velocity carried
    # across): a 10-min, 8-cable run would otherwise hold a 38 MB travel array
    dx = np.empty((min(n, BATCH_ROWS), t_in.shape[1]))
    v_prev = vel[0].copy()
    for a in range(0, n, BATCH_ROWS):
        b = min(a + BATCH_ROWS, n)
        travel_into(vel[a:b], dt[a:b], v_prev, dx[: b - a])
        kernel(p, t_in[a:b], vel[a:b], dx[: b - a], f_state, out[a:b])
    return out


def simulate(
    params: ChainParams,
    tension_platform: np.ndarray,
    velocity: np.ndarray,
    t: np.ndarray | float,
    state: np.ndarray | None = None,
    tol_n: float = 1e-10,
    max_iter: int = 20,
) -> np.ndarray:
    """Sensor reading (N, m) from platform tension and cable velocity, both (N, m).

    ``t``: sample times (N,) in s, or a constant period. ``state`` (m, n): friction
    state carried in and updated in place (relaxed if None).
    """
    return _run_batch(params, False, tension_platform, velocity, t, state, tol_n, max_iter)


def compensate(
    params: ChainParams,
    tension_sensor: np.ndarray,
    velocity: np.ndarray,
    t: np.ndarray | float,
    state: np.ndarray | None = None,
    tol_n: float = 1e-10,
    max_iter: int = 20,
) -> np.ndarray:
    """Platform tension (N, m) from the sensor reading and the setpoint velocity."""
    return _run_batch(params, True, tension_sensor, velocity, t, state, tol_n, max_iter)


class ChainStepper:
    """Per-cycle form: one sample for every cable on preallocated buffers.

    The friction state and the previous step's velocity (for the travel,
    :func:`travel_into`) are carried between calls. ``step`` allocates nothing. The first
    step after construction or :meth:`reset` has no previous velocity: it takes its own
    (``dx = v dt``; the batch form takes no travel at its first sample, ``dt = 0``).
    """

    def __init__(
        self,
        params: ChainParams,
        period_s: float,
        forward: bool = True,
        tol_n: float = 1e-9,
        max_iter: int = 8,
    ) -> None:
        m = params.cables
        self.params = params
        self.forward = forward
        self.period_s = float(period_s)
        self.state = new_state(params)
        self.iterations = 0
        self._in = np.zeros((1, m))
        self._vel = np.zeros((1, m))
        self._out = np.zeros((1, m))
        self._dx = np.zeros((1, m))
        self._v_prev = np.zeros(m)
        self._primed = False
        self._dt = np.array([self.period_s])
        self._p = kernel_params(params, tol_n, max_iter)
        self._travel = entry_point(travel_into, self._vel, self._dt, self._v_prev, self._dx)
        self._kernel = entry_point(
            compensate_kernel if forward else simulate_kernel,
            self._p,
            self._in,
            self._vel,
            self._dx,
            self.state,
            self._out,
        )

    def reset(self) -> None:
        """Relax every pulley (e.g. after a long outage when the real state is unknown);
        the next step has no previous velocity."""
        self.state[:] = 0.0
        self._primed = False

    def step(
        self, tension: np.ndarray, velocity: np.ndarray, out: np.ndarray, dt: float = -1.0
    ) -> int:
        """Advance by ``dt`` (s; negative: the period); write the result (m,) into ``out``;
        return the Newton passes (0 when simulating)."""
        self._in[0] = tension
        self._vel[0] = velocity
        if not self._primed:
            self._v_prev[:] = self._vel[0]
            self._primed = True
        self._dt[0] = self.period_s if dt < 0.0 else dt  # own buffers: types fixed
        self._travel(self._vel, self._dt, self._v_prev, self._dx)
        self.iterations = self._kernel(
            self._p, self._in, self._vel, self._dx, self.state, self._out
        )
        out[:] = self._out[0]
        return self.iterations
