"""The cable path between force sensor and platform, both ways (physics.md sec. 2, 3).

``m`` cables, each passing ``n`` pulleys numbered from the sensor towards the platform.
Per pulley ``T_j = T_{j-1} + F_j`` where ``F_j`` is

* ``coulomb``: ``sgn(v) F_Rj`` (eq. 8, 11, 12),
* ``dahl``: the pre-sliding state stepped with :func:`friction.dahl_step` over the
  cable travel of each step (eq. 14), carried between calls,
* ``maxwell_slip``: ``K`` Dahl elements in parallel (generalised Maxwell-slip): element
  ``q`` holds the fraction ``w_q`` of the Coulomb level and has the stiffness
  ``w_q sigma_q``, each stepped like the Dahl state; ``F_j`` is their sum (one element
  with ``w = 1`` is ``dahl``). An element is carried per unit fraction, ``G_q`` with the
  whole level ``F_R`` and the stiffness ``sigma_q`` (``F_q = w_q G_q`` exactly: the Dahl
  step is homogeneous in level and stiffness), so ``F_j`` is linear in the fractions,
* ``none``: 0,

with the Coulomb level ``F_Rj = ((lambda_ij(s) + g_j mu1_i |T_j|) |T_j| + f0_i / n) S_i(v)``
(:func:`_level`; ``g_j mu1_i``: the coefficient's growth with the load, ``coulomb_load``;
physics.md:
``F_Rj = lambda_j T_j``, the level the Dahl state tends to): ``lambda_ij(s)`` is taken at
the exact per-direction Coulomb ratio ``n_j(s)`` (eq. 11, 12 solved as a quadratic, see
:func:`gateway.model.chain_schema.coulomb_coefficients`), so at steady sliding Dahl equals
Coulomb exactly; ``f0`` is a load-independent part (seals, preload; split evenly over the
pulleys) and
``S = 1 + k exp(-(v / v_s)^2)`` the Stribeck factor. Viscous friction ``c_i v`` is added
at the platform end: ``T_p = T_n + c v``. ``|T|`` makes the law hold for push forces too
(a single-axis test rig).

Cable travel (the one definition every form uses): the setpoint travel
(:func:`travel_into`), the trapezoid over the actual sample times,
``dx_k = (v_{k-1} + v_k) / 2 (t_k - t_{k-1})``, ``dx_0 = 0``; then, per cable, in the
kernels (:func:`_step_cable`): minus the stretch change ``(F_k - F_{k-1}) c`` of the cable
between winch and pulleys (compliance ``c = 1 / k``; ``F = sum_j F_j`` the tension the
pulleys hold back, so the stretch the friction itself causes), then through the play
operator of width ``b`` (:func:`_play`, backlash: the drive stands still until the
setpoint has travelled ``b`` back across the gap). The Dahl and Maxwell-slip states
advance by that travel and take their direction from it, while the Coulomb sign, the
Stribeck factor and the viscous term take the sample's own ``v_k``.
(Stepping with ``v_k dt_k`` instead makes an error of the order ``a dt^2 / 2`` per step
that sampling jitter turns into noise: 0.13 N RMS on a noise-free 100 Hz +-2 ms recording.)

Simulation (platform -> sensor) is explicit: ``F_Rj`` follows from the known platform-side
tension, so each pulley is one exact Dahl step. Compensation (sensor -> platform) is
implicit in ``T_j``: Newton's iteration seeded with the previous cycle (``T_{j-1} +
F_old``) converges to 1e-9 N in one or two passes at 1 kHz (tests check it), stopping at
``tol_n`` or after ``max_iter`` passes. With a stretching cable the travel depends on the
friction the step produces: both directions solve for the drive per sample by a bracketed
secant (:func:`_step_cable`), and both read the same drive, so each inverts the other.

The two directions' compiled kernels (:func:`compensate_kernel`, :func:`simulate_kernel`;
run by :func:`gateway.model.chain_runs.run` and
:class:`gateway.model.chain_runs.ChainStepper`) share the pulley step and read their
parameters from one :class:`gateway.model.chain_schema.KernelParams` and their state from
one :class:`gateway.model.chain_schema.ChainState`; compensating a simulated reading
returns the tension simulated from. The parameters' schema (names, units, defaults) is
:mod:`gateway.model.chain_schema`.
"""

from __future__ import annotations

import math

from numba import njit

from gateway.model.chain_schema import (
    F0,
    LAW_COULOMB,
    LAW_DAHL,
    LAW_NONE,
    LAW_SLIP,
    LOAD,
    NEG,
    PLAY,
    POS,
    SIGMA,
    STRETCH,
    STRIB_K,
    STRIB_V,
    VISCOUS,
)
from gateway.model.friction import FR_FLOOR_N, dahl_step_power, dahl_step_slope

_NEWTON_CURVATURE = 1.0
"""Bound, in 1/N, on |g''/(2 g')| for the pulley equation g(T) = T - T_a - F(T): F depends on
T only through F_R = lambda S |T| (+ f0), so g'' carries (lambda S)^2 ~ 1e-3 times the
Dahl step's curvature in F_R, far below 1/N for any tension that carries friction.
Newton's next correction is at most this times step^2, so a pass whose correction has
step^2 * bound <= tol leaves an error below tol: no confirming pass is needed."""


@njit(cache=True, inline="always")
def _level(p, i, j, t_b, dx, strib):
    """The Coulomb level ``F_R`` of pulley ``j`` of cable ``i`` whose platform-side tension
    is ``t_b``, moving in the direction of ``dx`` (not 0), and ``dF_R / dt_b``: the chain's
    law of the level, written once (module docstring)."""
    lam = p.lam[i, j, POS] if dx > 0.0 else p.lam[i, j, NEG]
    growth = p.lam[i, j, LOAD] * abs(t_b)  # coulomb_load: mu + mu1 |T|, to first order
    fr = ((lam + growth) * abs(t_b) + p.cable[i, F0] / p.lam.shape[1]) * strib
    return fr, (lam + 2.0 * growth) * strib * (1.0 if t_b >= 0.0 else -1.0)


@njit(cache=True, inline="always")
def _pulley(p, i, j, t_b, f_old, dx, strib):
    """Friction force of pulley ``j`` of cable ``i`` whose platform-side tension is
    ``t_b``, and dF/dt_b, by the chain's law (:data:`LAWS`; ``maxwell_slip``:
    :func:`_slip`).

    ``dx``: the step's cable travel (Dahl) or, for Coulomb, anything with the sign of
    the sample's velocity (only its sign is read); ``strib``: the Stribeck factor."""
    law = p.law
    if dx == 0.0:
        return (0.0 if law == LAW_COULOMB else f_old), 0.0
    s = 1.0 if dx > 0.0 else -1.0
    fr, dfr = _level(p, i, j, t_b, dx, strib)
    if law == LAW_COULOMB:
        return s * fr, s * dfr
    # LAW_DAHL
    if fr <= FR_FLOOR_N:
        return 0.0, 0.0
    sigma = p.cable[i, SIGMA]
    if p.beta == 1.0:
        f_new, slope = dahl_step_slope(f_old, fr, dx, sigma)
        return f_new, slope * dfr
    f_new = dahl_step_power(f_old, fr, dx, sigma, p.beta)
    return f_new, s * (1.0 - math.exp(-sigma * abs(dx) / fr)) * dfr  # quasi-Newton slope


@njit(cache=True, inline="always")
def _elements(p, i, j, t_b, f, dx, strib, store):
    """The presliding laws (Dahl, Maxwell-slip) of pulley ``j`` of cable ``i`` whose
    platform-side tension is ``t_b``, for the drive ``dx``: its elements ``f[i, j]`` (per
    unit fraction; Dahl: one with ``w = 1``) stepped, and stored back into ``f[i, j]``
    when ``store`` (a commit; else a trial, which stores nothing). Returns the force
    ``sum_q w_q G_q``, its derivative in ``t_b`` and in ``dx`` (at fixed ``t_b``). Element
    ``q`` per unit fraction is a Dahl state with the whole level ``F_R`` and the stiffness
    ``sigma_q`` (its relaxation length ``F_R / sigma_q``).

    ``store`` is a constant at every call site, so the compiler keeps only one branch. A
    trial that wrote its states into a scratch array cost three times a committed step:
    the compiler cannot tell the scratch from the parameters and states it reads, and
    reloads them after every store (measured, ``simulate`` of 150 000 samples of one
    stretching 3-pulley Dahl cable, k = 10^4 N/m, 2.9 trials a sample: 152 ms with scratch
    trials, 96 ms without; 6 ms for a rigid cable). The trial and the commit are compiled
    as two functions (:func:`_trial`, :func:`_commit`): inlined into the kernels they ran
    in 83 ms but took 2.8 GB and 65 s to compile, against 0.58 GB and 48 s.

    numba inlines at its own IR level and types every inlined copy again, so each copy
    costs compile time: the sample that needs no solve commits through :func:`_commit`
    (not a third inlined :func:`_through`), and the ``beta != 1`` step is
    :func:`friction.dahl_step_power`, without the checks and the ``beta = 1`` step that a
    whole :func:`friction.dahl_step` carried into every copy. Measured side by side (CPU
    seconds, a cold cache, the batch plant's kernels with the four test chains of
    ``simulate``): 146 s before, 102 s after; 150 000 x 8 samples of a stretching Dahl
    chain 910-1055 ms before, 977-1084 ms after, Maxwell-slip with play 1404-1466 and
    1182-1468 ms (five runs each, interleaved, machine shared). Keeping the inlining but
    calling ``dahl_step_power`` out of line compiled in 66 s but ran 20 % slower, although
    the stretching Dahl chain never takes that branch: a call in the loop costs more than
    its execution."""
    k_el = f.shape[2]
    total = 0.0
    if dx == 0.0:
        for q in range(k_el):
            total += p.slip[i, q, 0] * f[i, j, q]
        return total, 0.0, 0.0
    s = 1.0 if dx > 0.0 else -1.0
    fr, dfr = _level(p, i, j, t_b, dx, strib)
    if fr <= FR_FLOOR_N:
        if store:
            for q in range(k_el):
                f[i, j, q] = 0.0
        return 0.0, 0.0, 0.0
    slope = 0.0
    ddx = 0.0
    for q in range(k_el):
        w = p.slip[i, q, 0]
        sigma = p.slip[i, q, 1]
        g = f[i, j, q]
        e = math.exp(-sigma * abs(dx) / fr)
        if p.beta == 1.0:
            rest = g - s * fr
            g_new = s * fr + rest * e
            sl = s * (1.0 - e) + rest * e * sigma * abs(dx) / (fr * fr)
            ddx += w * sigma * (1.0 - s * g / fr) * e
        else:
            g_new = dahl_step_power(g, fr, dx, sigma, p.beta)
            sl = s * (1.0 - e)  # quasi-Newton slopes
            ddx += w * sigma * e
        if store:
            f[i, j, q] = g_new
        total += w * g_new
        slope += w * sl
    return total, slope * dfr, ddx


@njit(cache=True, inline="always")
def _stribeck(p, i, v):
    if p.cable[i, STRIB_K] == 0.0:
        return 1.0
    return 1.0 + p.cable[i, STRIB_K] * math.exp(-((v / p.cable[i, STRIB_V]) ** 2))


@njit(cache=True)
def travel_into(vel, dt, v_prev, dx):
    """Setpoint travel of each step (m), the trapezoid over the actual sample spacing:
    ``dx[k, i] = (v_prev[i] + vel[k, i]) / 2 * dt[k]`` with ``v_prev`` the velocity of the
    step before, updated in place (so a per-cycle caller carries it). ``vel``, ``dx``
    (N, m); ``dt`` (N,); ``v_prev`` (m,). The kernels drive the friction state with it
    through :func:`_step_cable` (stretch, backlash)."""
    for k in range(vel.shape[0]):
        for i in range(vel.shape[1]):
            dx[k, i] = 0.5 * (v_prev[i] + vel[k, i]) * dt[k]
            v_prev[i] = vel[k, i]


@njit(cache=True, inline="always")
def _play(gap, d, width):
    """The play operator: the drive's position in the dead zone ``gap`` moved by ``d``;
    returns (the drive's travel, the new gap). Inside ``[-width/2, width/2]`` nothing
    moves; at an edge the drive follows."""
    g = gap + d
    half = 0.5 * width
    if g > half:
        return g - half, half
    if g < -half:
        return g + half, -half
    return 0.0, g


@njit(cache=True, inline="always")
def _direction(law, v, dx):
    """What sets the pulley's direction: the velocity for Coulomb, the travel for Dahl
    and Maxwell-slip."""
    return v if law == LAW_COULOMB else dx


@njit(cache=True, inline="always")
def _chain_force(p, f, i):
    """Cable ``i``'s pulleys' friction, ``sum_j F_j``, from the element states ``f``."""
    total = 0.0
    for j in range(f.shape[1]):
        for q in range(f.shape[2]):
            total += p.slip[i, q, 0] * f[i, j, q]
    return total


@njit(cache=True, inline="always")
def _through(p, st, i, forward, t_known, v, strib, d_raw, store):
    """Cable ``i`` through its pulleys for one sample whose drive before the dead zone is
    ``d_raw``: from the sensor side (``forward``: ``t_known`` the sensor-side tension,
    Newton per pulley) or from the platform side (``t_known`` the platform tension,
    explicit). The element states come from ``st.f`` and, when ``store`` (a commit; else a
    trial), go back there (:func:`_elements`). Returns the other end's tension, the
    pulleys' friction ``F = sum_j F_j``, ``dF / d(d_raw)`` at fixed tensions, and the most
    Newton passes."""
    n = p.lam.shape[1]
    d = d_raw
    moving = 1.0
    if p.cable[i, PLAY] != 0.0:
        d = _play(st.gap[i], d_raw, p.cable[i, PLAY])[0]
        moving = 1.0 if d != 0.0 else 0.0
    coulomb = p.law == LAW_COULOMB
    dx = v if coulomb else d
    worst = 0
    force = 0.0
    slope_d = 0.0
    if p.law == LAW_NONE:
        out = t_known + p.cable[i, VISCOUS] * v if forward else t_known - p.cable[i, VISCOUS] * v
        return out, 0.0, 0.0, 0
    if forward:
        t_a = t_known
        for j in range(n):
            f_old = _chain_force_pulley(p, st.f, i, j)
            t_b = t_a + f_old
            it = 0
            while it < p.max_iter:
                it += 1
                if coulomb:
                    f_new, d_b = _pulley(p, i, j, t_b, f_old, dx, strib)
                else:
                    f_new, d_b, _ = _elements(p, i, j, t_b, st.f, dx, strib, False)
                step = (t_b - t_a - f_new) / (1.0 - d_b)
                t_prev = t_b
                t_b -= step
                # as in _compensate_plain: a step that crossed or landed on T = 0 (the kink
                # of |T|) is not confirmed by the curvature bound
                if step * step * _NEWTON_CURVATURE <= p.tol and t_prev * t_b > 0.0:
                    break
            if coulomb:
                if store:
                    st.f[i, j, 0] = t_b - t_a
            else:
                f_new, _, dd = _elements(p, i, j, t_b, st.f, dx, strib, store)
                slope_d += dd
            worst = max(worst, it)
            t_a = t_b
        force = t_a - t_known
        return t_a + p.cable[i, VISCOUS] * v, force, slope_d * moving, worst
    t_b = t_known - p.cable[i, VISCOUS] * v
    for j in range(n - 1, -1, -1):
        if coulomb:
            f_new, _ = _pulley(p, i, j, t_b, st.f[i, j, 0], dx, strib)
            if store:
                st.f[i, j, 0] = f_new
        else:
            f_new, _, dd = _elements(p, i, j, t_b, st.f, dx, strib, store)
            slope_d += dd
        t_b -= f_new
        force += f_new
    return t_b, force, slope_d * moving, 0


@njit(cache=True, inline="always")
def _chain_force_pulley(p, f, i, j):
    """Pulley ``j`` of cable ``i``'s friction force from its elements."""
    total = 0.0
    for q in range(f.shape[2]):
        total += p.slip[i, q, 0] * f[i, j, q]
    return total


@njit(cache=True)
def _trial(p, st, i, forward, t_known, v, strib, d):
    """:func:`_through` storing nothing: the pulleys' friction and its slope in ``d``."""
    return _through(p, st, i, forward, t_known, v, strib, d, False)[1:3]


@njit(cache=True)
def _commit(p, st, i, forward, t_known, v, strib, d):
    """:func:`_through` storing the states."""
    return _through(p, st, i, forward, t_known, v, strib, d, True)


@njit(cache=True)
def _step_cable(p, st, i, forward, t_known, v, strib, dx_set):
    """One sample of cable ``i`` (general path): with a stretching cable the drive ``d``
    solves ``g(d) = d - dx_set + (F(d) - F_old) c = 0`` (``F`` the pulleys' friction after
    the step, ``F_old`` before it) by Newton's iteration from ``dx_set`` with the slope
    ``1 + c dF/dd``, kept inside the bracket its own steps find (bisection where a step
    leaves it: ``g`` has kinks where the drive changes sign or meets the dead zone's edge).
    ``g`` rises with slope >= 1 wherever the friction grows with its travel, so the root
    is unique. Once a step is below 1e-9 of the drive it is taken without another trial
    (Newton's error after it is about (1e-9)^2 of the drive). The trials store nothing;
    the root is evaluated once more to commit its states, and the dead zone moved. Returns
    the other end's tension and the most Newton passes."""
    c = p.cable[i, STRETCH]
    if c == 0.0 or p.law == LAW_NONE or p.law == LAW_COULOMB:
        out, _, _, worst = _commit(p, st, i, forward, t_known, v, strib, dx_set)
        if p.cable[i, PLAY] != 0.0:
            st.gap[i] = _play(st.gap[i], dx_set, p.cable[i, PLAY])[1]
        return out, worst
    f_old = _chain_force(p, st.f, i)
    lo, hi = -math.inf, math.inf
    d = dx_set
    passes = 4 * p.max_iter + 20
    for it in range(passes):
        force, slope = _trial(p, st, i, forward, t_known, v, strib, d)
        g = d - dx_set + c * (force - f_old)
        if g == 0.0:
            break
        if g > 0.0:
            hi = min(hi, d)
        else:
            lo = max(lo, d)
        gp = 1.0 + c * slope
        nxt = d - g / (gp if gp > 0.5 else 1.0)
        if not lo < nxt < hi and math.isfinite(lo) and math.isfinite(hi):
            nxt = 0.5 * (lo + hi)
        if abs(nxt - d) <= 1e-18 + 1e-9 * abs(nxt):
            d = nxt  # Newton's error after a step of 1e-9 d: about (1e-9)^2 d
            break
        if it == passes - 1:
            break  # out of passes: commit the last d evaluated
        d = nxt
    out, _, _, worst = _commit(p, st, i, forward, t_known, v, strib, d)
    if p.cable[i, PLAY] != 0.0:
        st.gap[i] = _play(st.gap[i], d, p.cable[i, PLAY])[1]
    return out, worst


@njit(cache=True, inline="always")
def _rigid(p):
    """True when the chain has a presliding state and no cable stretches: its drive is
    explicit (the setpoint travel, through a dead zone where there is one)."""
    if p.law != LAW_DAHL and p.law != LAW_SLIP:
        return False
    for i in range(p.cable.shape[0]):  # noqa: SIM110 (numba: a plain loop)
        if p.cable[i, STRETCH] != 0.0:
            return False
    return True


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def _simulate_rigid(p, t_in, vel, dx_all, st, out):
    """:func:`simulate_kernel` for a :func:`_rigid` chain (the general path's explicit
    case, without its per-sample solve)."""
    n_samples, m = t_in.shape
    n = p.lam.shape[1]
    f_state = st.f
    for k in range(n_samples):
        for i in range(m):
            v = vel[k, i]
            dx = dx_all[k, i]
            width = p.cable[i, PLAY]
            if width != 0.0:
                dx, st.gap[i] = _play(st.gap[i], dx, width)
            t_b = t_in[k, i] - p.cable[i, VISCOUS] * v
            strib = _stribeck(p, i, v)
            for j in range(n - 1, -1, -1):
                t_b -= _elements(p, i, j, t_b, f_state, dx, strib, True)[0]
            out[k, i] = t_b
    return 0


@njit(cache=True, inline="always")
def _plain(p):
    """True when the chain is one-element (not Maxwell-slip) and every cable's travel is
    the setpoint's (no stretch, no dead zone): the kernels' fast path."""
    if p.law == LAW_SLIP:
        return False
    for i in range(p.cable.shape[0]):
        if p.cable[i, STRETCH] != 0.0 or p.cable[i, PLAY] != 0.0:
            return False
    return True


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def _compensate_plain(p, t_in, vel, dx_all, f_state, out):
    """:func:`compensate_kernel` for a :func:`_plain` chain, ``f_state`` (m, n)."""
    n_samples, m = t_in.shape
    n = p.lam.shape[1]
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
            out[k, i] = t_a + p.cable[i, VISCOUS] * v
    return worst


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def compensate_kernel(p, t_in, vel, dx_all, st, out):
    """Sensor -> platform for (N, m) ``t_in``, ``vel``, setpoint travel ``dx_all``
    (:func:`travel_into`) and ``out``; ``st`` (:class:`ChainState`) in/out. Each pulley's
    implicit equation by Newton, seeded with the previous cycle's force. Returns the largest
    number of Newton passes any pulley needed."""
    n_samples, m = t_in.shape
    if _plain(p):
        f_state = st.f
        return _compensate_plain(p, t_in, vel, dx_all, f_state.reshape((m, f_state.shape[1])), out)
    worst = 0
    for k in range(n_samples):
        for i in range(m):
            v = vel[k, i]
            strib = _stribeck(p, i, v)
            out[k, i], it = _step_cable(p, st, i, True, t_in[k, i], v, strib, dx_all[k, i])
            worst = max(worst, it)
    return worst


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def _simulate_plain(p, t_in, vel, dx_all, f_state, out):
    """:func:`simulate_kernel` for a :func:`_plain` chain, ``f_state`` (m, n)."""
    n_samples, m = t_in.shape
    n = p.lam.shape[1]
    for k in range(n_samples):
        for i in range(m):
            v = vel[k, i]
            dx = _direction(p.law, v, dx_all[k, i])
            t_b = t_in[k, i] - p.cable[i, VISCOUS] * v
            if p.law != LAW_NONE:
                strib = _stribeck(p, i, v)
                for j in range(n - 1, -1, -1):
                    f_new, _ = _pulley(p, i, j, t_b, f_state[i, j], dx, strib)
                    f_state[i, j] = f_new
                    t_b -= f_new
            out[k, i] = t_b
    return 0


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def simulate_kernel(p, t_in, vel, dx_all, st, out):
    """Platform -> sensor, same arguments as :func:`compensate_kernel`; explicit (each
    pulley's Coulomb level follows from its known platform-side tension) but for a
    stretching cable (:func:`_step_cable`)."""
    n_samples, m = t_in.shape
    if _plain(p):
        f_state = st.f
        return _simulate_plain(p, t_in, vel, dx_all, f_state.reshape((m, f_state.shape[1])), out)
    if _rigid(p):
        return _simulate_rigid(p, t_in, vel, dx_all, st, out)
    for k in range(n_samples):
        for i in range(m):
            v = vel[k, i]
            strib = _stribeck(p, i, v)
            out[k, i] = _step_cable(p, st, i, False, t_in[k, i], v, strib, dx_all[k, i])[0]
    return 0
