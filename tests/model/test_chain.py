"""The sensor chain both ways (simulate / compensate) against references."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from numpy.testing import assert_allclose

from gateway.core.config import load_config
from gateway.model.chain_runs import BATCH_ROWS, ChainStepper, new_state, run, travel
from gateway.model.chain_schema import ChainParams, coulomb_coefficients
from gateway.model.effects import displacement
from tests.model_reference import coulomb_gain

WRAPS = np.radians([90.0, 60.0, 30.0])


def params(model: str = "dahl", cables: int = 2, **kw: object) -> ChainParams:
    return ChainParams.build(model, cables, WRAPS, 0.015, **kw)  # type: ignore[arg-type]


def steady(v: float, n: int = 4000, cables: int = 2, tension: float = 300.0):
    t = np.arange(n) * 1e-3
    return t, np.full((n, cables), tension), np.full((n, cables), v)


@pytest.mark.parametrize("v", [0.05, -0.05])
def test_coulomb_chain_equals_exact_gain(v: float) -> None:
    t, tp, vel = steady(v, n=10)
    ts = run(params("coulomb"), "simulate", tp, vel, t)
    gain = coulomb_gain(np.full(3, 0.015), WRAPS, v)
    assert_allclose(tp[1:] / ts[1:], gain, rtol=1e-12)
    # paying out the sensor reads less than the platform tension, reeling in more
    assert (ts[1:] < tp[1:]).all() if v > 0 else (ts[1:] > tp[1:]).all()


@pytest.mark.parametrize("v", [0.04, -0.04])
def test_dahl_steady_state_equals_coulomb(v: float) -> None:
    t, tp, vel = steady(v, n=10_000)  # 0.4 m of travel: >> 30 F_R / sigma for every pulley
    dahl = run(params("dahl"), "simulate", tp, vel, t)
    coul = run(params("coulomb"), "simulate", tp, vel, t)
    assert_allclose(dahl[-1], coul[-1], rtol=1e-10)
    assert abs(dahl[1, 0] - tp[1, 0]) < abs(coul[1, 0] - tp[1, 0])  # pre-sliding starts small


def test_reversal_hysteresis_width() -> None:
    """Triangle motion: at the same position the two directions differ by the Coulomb band."""
    n, v = 8000, 0.05  # 0.2 m per stroke, >> F_R / sigma ~ 10 mm
    t = np.arange(2 * n) * 1e-3
    vel = np.concatenate([np.full(n, v), np.full(n, -v)])[:, None]
    tp = np.full((2 * n, 1), 300.0)
    ts = run(params("dahl", cables=1), "simulate", tp, vel, t)
    width = ts[n + n // 2, 0] - ts[n // 2, 0]  # same position, reeling in minus paying out
    gains = [coulomb_gain(np.full(3, 0.015), WRAPS, s) for s in (1.0, -1.0)]
    expected = 300.0 / gains[1] - 300.0 / gains[0]
    assert width == pytest.approx(expected, rel=1e-6)  # transient left: e^-(0.2 m sigma / F_R)
    # just after the reversal the Dahl state has not crossed the band yet (pre-sliding)
    assert ts[n + 5, 0] < ts[n // 2, 0] + 0.5 * expected


def test_viscous_f0_and_stribeck_signs() -> None:
    t, tp, vel = steady(0.02, n=5, cables=1)
    ts = run(params("none", cables=1, viscous_ns_m=40.0), "simulate", tp, vel, t)
    assert_allclose(ts, tp - 40.0 * 0.02)
    base = run(params("coulomb", cables=1), "simulate", tp, vel, t)
    with_f0 = run(params("coulomb", cables=1, f0_n=3.0), "simulate", tp, vel, t)
    # paying out, sensor side: T_{j-1} = (1 - lam_j) T_j - f0 / n, pulley n first
    lam_pos, _ = coulomb_coefficients(params("coulomb", cables=1))
    expected = 300.0
    for lam in lam_pos[0][::-1]:
        expected = (1.0 - lam) * expected - 3.0 / 3
    assert_allclose(with_f0, expected, rtol=1e-12)  # the sample's own v: from k = 0 on
    assert 2.9 < float(base[1, 0] - with_f0[1, 0]) < 3.0  # about f0, less the lambda coupling
    strib = run(
        params("coulomb", cables=1, stribeck_k=0.5, stribeck_v_m_s=0.02), "simulate", tp, vel, t
    )
    factor = 1 + 0.5 * np.exp(-1.0)  # v = v_s
    expected = 300.0 * np.prod(1.0 - factor * lam_pos[0])
    assert_allclose(strib, expected, rtol=1e-12)


def jittered(n: int = 3000, rate: float = 200.0, jitter: float = 0.8e-3, seed: int = 4):
    """Sample times of a logger at ``rate`` with +-``jitter`` on every stamp."""
    rng = np.random.default_rng(seed)
    return np.arange(n) / rate + rng.uniform(-jitter, jitter, n)


def test_travel_is_the_trapezoid_over_the_actual_time_stamps() -> None:
    t = jittered(200)
    vel = np.column_stack([0.1 - 0.3 * t, 0.05 + 0.0 * t])  # linear: the trapezoid is exact
    dx = travel(t, vel)
    exact = np.diff(np.column_stack([0.1 * t - 0.15 * t**2, 0.05 * t]), axis=0)
    assert_allclose(dx[0], 0.0, atol=0)  # no travel before the first sample
    assert_allclose(dx[1:], exact, rtol=0, atol=1e-15)
    mid = 0.5 * (vel[1:3, 0] + vel[:2, 0])  # a constant period: the same definition
    want = [[0.0, 0.0], [1e-3 * mid[0], 5e-5], [1e-3 * mid[1], 5e-5]]
    assert_allclose(travel(1e-3, vel[:3]), want, rtol=0, atol=1e-18)


@pytest.mark.parametrize("forward", [True, False])
def test_stepper_matches_batch_on_jittered_samples(forward: bool) -> None:
    """The per-cycle form carries the previous velocity: stepped with the actual spacing
    it equals the batch form's trapezoid travel to 1e-9 N through reversals."""
    t = jittered()
    rng = np.random.default_rng(5)
    vel = 0.2 * np.sin(2 * np.pi * 0.4 * t[:, None] + rng.uniform(0, 6, 3))
    tp = 250 + 80 * np.sin(0.7 * t[:, None]) + rng.normal(0, 1, (t.size, 3))
    p = params("dahl", cables=3, f0_n=1.0, stribeck_k=0.3, viscous_ns_m=20.0)
    batch = run(p, "compensate" if forward else "simulate", tp, vel, t)
    stepper = ChainStepper(p, 5e-3, forward=forward, tol_n=1e-10, max_iter=20)
    out = np.zeros(3)
    for k in range(t.size):
        stepper.step(tp[k], vel[k], out, t[k] - t[k - 1] if k else 0.0)
        assert_allclose(out, batch[k], rtol=0, atol=1e-9, err_msg=f"sample {k}")


def test_jittered_samples_match_a_fine_grid() -> None:
    """The same smooth motion sampled at 1 kHz and at 100 Hz +-2 ms: the Dahl chain on the
    coarse, jittered samples stays at the fine one: 0.004 N RMS (stepped with ``v_k dt_k``:
    0.18 N)."""
    fine = np.arange(0.0, 10.0, 1e-4)
    coarse = np.sort(jittered(1000, rate=100.0, jitter=2e-3)[1:-1])

    def motion(tt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        v = 0.15 * np.sin(2 * np.pi * 0.3 * tt) + 0.05 * np.sin(2 * np.pi * 1.1 * tt)
        return np.full((tt.size, 1), 300.0), v[:, None]

    p = params("dahl", cables=1, sigma_n_m=800.0)
    ref = np.interp(coarse, fine, run(p, "simulate", *motion(fine), fine)[:, 0])
    got = run(p, "simulate", *motion(coarse), coarse)[:, 0]
    late = coarse > 1.0
    assert np.sqrt(np.mean((got - ref)[late] ** 2)) < 0.01


def test_push_forces_mirror_pull_forces() -> None:
    t, tp, vel = steady(0.03, n=300, cables=1)
    pull = run(params("dahl", cables=1), "simulate", tp, vel, t)
    push = run(params("dahl", cables=1), "simulate", -tp, vel, t)
    # friction opposes the motion whatever the sign of the force: the same direction, and
    # the same size to first order (|T| shrinks towards the sensor pulling, grows pushing)
    f_pull, f_push = tp - pull, (-tp) - push
    assert (f_pull[1:] > 0).all() and (f_push[1:] > 0).all()
    assert_allclose(f_push, f_pull, rtol=0.05)
    assert (f_push[-1] > f_pull[-1]).all()


@settings(max_examples=30, deadline=None)
@given(
    tp=arrays(np.float64, (200, 3), elements=st.floats(-800, 800)),
    vel=arrays(np.float64, (200, 3), elements=st.floats(-0.5, 0.5)),
    model=st.sampled_from(["coulomb", "dahl"]),
    viscous=st.floats(0, 50),
)
def test_compensate_inverts_simulate(tp, vel, model, viscous) -> None:
    p = params(model, cables=3, viscous_ns_m=viscous, f0_n=1.0, stribeck_k=0.3)
    t = np.cumsum(np.full(200, 1e-3))
    ts = run(p, "simulate", tp, vel, t)
    assert_allclose(run(p, "compensate", ts, vel, t), tp, rtol=0, atol=1e-9)


def test_compensate_inverts_simulate_where_the_tension_crosses_zero() -> None:
    """Found by the property above: a platform tension of -1.2e-7 N between 17 N samples
    was returned 1.1e-9 N off. |T| has its kink at 0, where Newton's curvature bound
    (one small step confirms convergence) does not hold; a step across 0 is not final."""
    tp = np.full((200, 3), 17.0)
    tp[5, 0] = -1.1920929e-07
    vel = np.full((200, 3), 0.5)
    p = params("dahl", cables=3, viscous_ns_m=0.0, f0_n=1.0, stribeck_k=0.3)
    t = np.cumsum(np.full(200, 1e-3))
    assert_allclose(
        run(p, "compensate", run(p, "simulate", tp, vel, t), vel, t), tp, rtol=0, atol=1e-12
    )


def test_stepper_matches_batch_and_converges_in_two_passes() -> None:
    cfg = load_config()
    p = ChainParams.from_friction(cfg.friction, cfg.cables)
    n = 3000
    t = np.arange(n) * 1e-3
    rng = np.random.default_rng(3)
    vel = 0.3 * np.sin(2 * np.pi * 0.5 * t[:, None] + rng.uniform(0, 6, cfg.cables))
    tp = 200 + 100 * np.sin(t[:, None]) + rng.normal(0, 1, (n, cfg.cables))
    ts = run(p, "simulate", tp, vel, t)
    stepper = ChainStepper(p, 1e-3, tol_n=1e-9)
    out = np.zeros(cfg.cables)
    got = np.empty_like(ts)
    passes = []
    stepper.step(ts[0], vel[0], out, 0.0)  # the batch form takes no travel at k = 0
    got[0] = out
    for k in range(1, n):
        passes.append(stepper.step(ts[k], vel[k], out))
        got[k] = out
    assert_allclose(got, tp, atol=1e-8)
    assert max(passes) <= 2


def test_shape_errors_are_clear() -> None:
    with pytest.raises(ValueError, match=r"shape \(N, 2\)"):
        run(params(), "simulate", np.zeros((5, 3)), np.zeros((5, 3)), 1e-3)
    with pytest.raises(ValueError, match="model must be one of"):
        ChainParams.build("lugre", 1, WRAPS, 0.01)  # type: ignore[arg-type]


# ---- the presliding state's variants: Maxwell-slip elements, stretch, backlash ----------

ONE = np.radians([90.0])


def one_pulley(model: str = "dahl", **kw: object) -> ChainParams:
    return ChainParams.build(model, 1, ONE, 0.02, **kw)  # type: ignore[arg-type]


def reversal(n: int = 4000, v: float = 0.05, tension: float = 200.0):
    """Out for n samples at 1 kHz, then in: the friction force F = T_p - T_s of the second
    half and the travel since the reversal (trapezoid, as the chain steps)."""
    t = np.arange(2 * n) * 1e-3
    vel = np.where(np.arange(2 * n) < n, v, -v)[:, None]
    return t, np.full((2 * n, 1), tension), vel


def levels(p: ChainParams, tension: float) -> tuple[float, float]:
    lam_pos, lam_neg = (float(c[0, 0]) for c in coulomb_coefficients(p))
    return lam_pos * tension, lam_neg * tension


@settings(max_examples=30, deadline=None)
@given(
    sigma=st.floats(50.0, 1e5),
    sigma2=st.floats(10.0, 1e4),
    beta=st.sampled_from([1.0, 0.6, 1.5]),
)
def test_maxwell_slip_with_one_element_is_dahl(sigma, sigma2, beta) -> None:
    t = np.arange(3000) * 1e-3
    vel = 0.1 * np.sin(2 * np.pi * 0.8 * t)[:, None] * np.ones((1, 2))
    tp = 250 + 40 * np.sin(t)[:, None] * np.ones((1, 2))
    dahl = run(params("dahl", sigma_n_m=sigma, beta=beta), "simulate", tp, vel, t)
    slip = params(
        "maxwell_slip",
        sigma_n_m=sigma,
        beta=beta,
        slip_w=np.array([1.0, 0.0]),
        slip_sigma=np.array([sigma, sigma2]),
    )
    assert_allclose(run(slip, "simulate", tp, vel, t), dahl, rtol=0, atol=1e-12)


def test_maxwell_slip_relaxes_as_two_exponentials_after_a_reversal() -> None:
    """Element q holds w_q of the level L and relaxes over L / sigma_q: after a reversal
    ``F(x) = sum_q (-w_q L + (F_q0 + w_q L) exp(-sigma_q x / L))``."""
    w, s1, s2, n = 0.3, 20000.0, 1500.0, 4000
    p = one_pulley("maxwell_slip", slip_w=np.array([w, 1 - w]), slip_sigma=np.array([s1, s2]))
    t, tp, vel = reversal(n)
    force = tp[:, 0] - run(p, "simulate", tp, vel, t)[:, 0]
    out, back = levels(p, 200.0)
    assert force[n - 1] == pytest.approx(out, abs=1e-9)  # both elements saturated
    x = np.abs(displacement(t, vel[:, 0])[n:] - displacement(t, vel[:, 0])[n - 1])
    want = sum(
        -wq * back + (wq * out + wq * back) * np.exp(-sq * x / back)
        for wq, sq in ((w, s1), (1 - w, s2))
    )
    assert_allclose(force[n:], want, rtol=0, atol=1e-9)
    dahl = one_pulley("dahl", sigma_n_m=s2)
    assert np.max(np.abs(force - (tp[:, 0] - run(dahl, "simulate", tp, vel, t)[:, 0]))) > 1.0


def test_backlash_holds_the_friction_for_its_width_after_a_reversal() -> None:
    """The drive stands in the dead zone until the setpoint has travelled the width back;
    then the Dahl state relaxes over the travel beyond it."""
    width, sigma, n = 0.004, 800.0, 4000
    p = one_pulley("dahl", sigma_n_m=sigma, backlash_m=width)
    t, tp, vel = reversal(n)
    force = tp[:, 0] - run(p, "simulate", tp, vel, t)[:, 0]
    back = levels(p, 200.0)[1]
    x = np.abs(displacement(t, vel[:, 0])[n:] - displacement(t, vel[:, 0])[n - 1])
    held = x <= width
    assert held.sum() > 70 and np.all(force[n:][held] == force[n - 1])
    f0 = force[n - 1]
    want = -back + (f0 + back) * np.exp(-sigma * (x - width) / back)
    assert_allclose(force[n:][~held], want[~held], rtol=0, atol=1e-9)
    # the first motion from the centred start needs half the width
    x0 = displacement(t, vel[:, 0])[:n]
    assert np.all(force[:n][x0 <= width / 2] == 0.0) and force[n - 1] > 0


def test_cable_stretch_puts_the_cable_in_series_with_the_presliding_state() -> None:
    """The drive is the setpoint travel minus ``(F - F_0) c``: the force after a reversal
    is the Dahl curve of that drive (checked sample by sample), softer than without
    stretch."""
    sigma, k, n = 800.0, 400.0, 4000
    p = one_pulley("dahl", sigma_n_m=sigma, stretch_c=1.0 / k)
    t, tp, vel = reversal(n)
    force = tp[:, 0] - run(p, "simulate", tp, vel, t)[:, 0]
    out, back = levels(p, 200.0)
    assert force[n - 1] == pytest.approx(out, abs=1e-8)
    x = np.abs(displacement(t, vel[:, 0])[n:] - displacement(t, vel[:, 0])[n - 1])
    drive = x - (force[n - 1] - force[n:]) / k  # the reversal lowers F: the drive lags
    want = -back + (force[n - 1] + back) * np.exp(-sigma * drive / back)
    assert_allclose(force[n:], want, rtol=0, atol=1e-8)
    rigid = tp[:, 0] - run(one_pulley("dahl", sigma_n_m=sigma), "simulate", tp, vel, t)[:, 0]
    assert np.all(force[n + 1 : n + 200] > rigid[n + 1 : n + 200])  # softer: F falls later


def test_the_stretch_takes_no_difference_of_the_readings() -> None:
    """Compensating noisy readings through a stretching chain: the drive comes from the
    model's friction, not from differences of the readings, so sensor noise of 0.5 N at
    1 kHz (0.07 mm per step at k = 1e4 N/m were it differenced, against 0.03 mm of
    setpoint travel) leaves the estimate as unbiased as on a rigid chain."""
    n, m = 20000, 2
    t = np.arange(n) * 1e-3
    vel = 0.03 * np.sign(np.sin(2 * np.pi * 0.2 * t))[:, None] * np.ones((1, m))
    tp = np.full((n, m), 250.0)
    noise = np.random.default_rng(9).normal(0.0, 0.5, (n, m))
    for c in (0.0, 1e-4):
        p = params("dahl", cables=m, stretch_c=c)
        ts = run(p, "simulate", tp, vel, t)
        err = run(p, "compensate", ts + noise, vel, t) - tp
        assert abs(float(np.mean(err))) < 0.02, c


@settings(max_examples=30, deadline=None)
@given(
    tp=arrays(np.float64, (200, 3), elements=st.floats(-800, 800)),
    vel=arrays(np.float64, (200, 3), elements=st.floats(-0.5, 0.5)),
    model=st.sampled_from(["dahl", "maxwell_slip"]),
    k=st.one_of(st.just(np.inf), st.floats(100.0, 1e6)),
    width=st.one_of(st.just(0.0), st.floats(1e-5, 0.02)),
    w=st.floats(0.0, 1.0),
)
def test_compensate_inverts_simulate_with_elements_stretch_and_backlash(
    tp, vel, model, k, width, w
) -> None:
    p = params(
        model,
        cables=3,
        f0_n=1.0,
        stribeck_k=0.3,
        viscous_ns_m=5.0,
        slip_w=np.array([w, 1 - w]),
        slip_sigma=np.array([5000.0, 500.0]),
        stretch_c=1.0 / k,
        backlash_m=width,
    )
    t = np.cumsum(np.full(200, 1e-3))
    ts = run(p, "simulate", tp, vel, t)
    assert_allclose(run(p, "compensate", ts, vel, t), tp, rtol=0, atol=1e-8)


@pytest.mark.parametrize("model", ["dahl", "maxwell_slip"])
def test_the_general_step_inverts_simulate_where_the_tension_crosses_zero(model: str) -> None:
    """The per-cable step with elements and stretch (``_through``) keeps the plain path's
    guard: a Newton step across T = 0 (the kink of |T|) is not final. Without it a soft
    cable (k = 500 N/m) at 0.05 m/s was returned 2-3e-9 N off at the -1.2e-7 N samples;
    with it the stretch solve's own precision (< 2e-12 N) is left."""
    tp = np.full((200, 3), 17.0)
    tp[5, 0] = tp[50, 1] = tp[120, 2] = -1.19e-07
    vel = np.full((200, 3), 0.05)
    p = params(
        model,
        cables=3,
        viscous_ns_m=0.0,
        f0_n=1.0,
        slip_w=np.array([0.5, 0.5]),
        slip_sigma=np.array([5000.0, 500.0]),
        stretch_c=1.0 / 500.0,
    )
    t = np.cumsum(np.full(200, 1e-3))
    assert_allclose(
        run(p, "compensate", run(p, "simulate", tp, vel, t), vel, t), tp, rtol=0, atol=1e-10
    )


@pytest.mark.parametrize("forward", [True, False])
def test_stepper_matches_batch_with_elements_stretch_and_backlash(forward: bool) -> None:
    t = jittered()
    rng = np.random.default_rng(6)
    vel = 0.2 * np.sin(2 * np.pi * 0.4 * t[:, None] + rng.uniform(0, 6, 3))
    tp = 250 + 80 * np.sin(0.7 * t[:, None]) + rng.normal(0, 1, (t.size, 3))
    p = params(
        "maxwell_slip",
        cables=3,
        slip_w=np.array([0.4, 0.6]),
        slip_sigma=np.array([8000.0, 800.0]),
        stretch_c=[1e-4, 0.0, 5e-4],
        backlash_m=[0.002, 0.001, 0.0],
    )
    batch = run(p, "compensate" if forward else "simulate", tp, vel, t)
    stepper = ChainStepper(p, 5e-3, forward=forward, tol_n=1e-10, max_iter=20)
    out = np.zeros(3)
    for k in range(t.size):
        stepper.step(tp[k], vel[k], out, t[k] - t[k - 1] if k else 0.0)
        assert_allclose(out, batch[k], rtol=0, atol=1e-9, err_msg=f"sample {k}")
    assert stepper.state.shape == (3, 3)  # per pulley: the sum of its elements


@settings(max_examples=20, deadline=None)
@given(w=st.floats(-0.5, 1.5), s1=st.floats(100.0, 1e5), s2=st.floats(10.0, 1e4))
def test_maxwell_slip_force_is_linear_in_the_fractions(w, s1, s2) -> None:
    """The elements are carried per unit fraction: the force is ``w F(1) + (1 - w) F(0)``
    for any ``w`` (the fit's finite differences may step past [0, 1])."""
    t = np.arange(2000) * 1e-3
    vel = 0.08 * np.sin(2 * np.pi * 1.1 * t)[:, None]
    tp = 200 + 30 * np.sin(2 * t)[:, None]

    def force(frac: float) -> np.ndarray:
        p = one_pulley(
            "maxwell_slip", slip_w=np.array([frac, 1 - frac]), slip_sigma=np.array([s1, s2])
        )
        return tp[:, 0] - run(p, "simulate", tp, vel, t)[:, 0]

    assert_allclose(force(w), w * force(1.0) + (1 - w) * force(0.0), rtol=0, atol=1e-9)


@pytest.mark.parametrize("direction", ["compensate", "simulate"])
@pytest.mark.parametrize("model", ["dahl", "coulomb"])
def test_every_way_of_keeping_a_run_is_the_whole_run(model: str, direction: str) -> None:
    """:func:`run`'s options keep the whole run's values bit for bit: ``rows`` (in every
    batch, at batch edges, at both ends, none), ``pieces`` in the rolling buffer and into
    ``out``, and ``out``."""
    n = 2 * BATCH_ROWS + 123
    t = np.arange(n) * 1e-3
    v = 0.2 * np.sin(2 * np.pi * 0.5 * t)[:, None] * np.ones((1, 2))
    ts = 300.0 + 20.0 * np.cos(2 * np.pi * 0.2 * t)[:, None] * np.ones((1, 2))
    p = params(model, sigma_n_m=2000.0) if model == "dahl" else params(model)
    whole = run(p, direction, ts, v, t)
    for rows in (
        np.arange(0, n, 7),
        np.array([0, BATCH_ROWS - 1, BATCH_ROWS, 2 * BATCH_ROWS, n - 1]),
        np.array([], dtype=int),
    ):
        np.testing.assert_array_equal(run(p, direction, ts, v, t, rows=rows), whole[rows])
    with pytest.raises(ValueError, match="increasing"):
        run(p, direction, ts, v, t, rows=np.array([5, 3]))
    pieces = [(a, b, part.copy()) for a, b, part in run(p, direction, ts, v, t, pieces=True)]
    edges = [(0, BATCH_ROWS), (BATCH_ROWS, 2 * BATCH_ROWS), (2 * BATCH_ROWS, n)]
    assert [(a, b) for a, b, _ in pieces] == edges
    np.testing.assert_array_equal(np.concatenate([part for *_, part in pieces]), whole)
    out = np.full_like(ts, np.nan)
    for a, b, part in run(p, direction, ts, v, t, out=out, pieces=True):
        assert np.shares_memory(part, out) and not np.isnan(out[:b]).any()
        np.testing.assert_array_equal(part, whole[a:b])  # final when yielded
    np.testing.assert_array_equal(out, whole)
    into = np.empty_like(ts)
    assert run(p, direction, ts, v, t, out=into) is into
    np.testing.assert_array_equal(into, whole)
    with pytest.raises(ValueError, match="rows and pieces"):
        run(p, direction, ts, v, t, rows=np.arange(3), pieces=True)  # type: ignore[call-overload]
    with pytest.raises(ValueError, match="direction"):
        run(p, "forward", ts, v, t)  # type: ignore[call-overload]


@settings(max_examples=25, deadline=None)
@given(
    st.sampled_from(["coulomb", "dahl", "maxwell_slip"]),
    st.sampled_from(["compensate", "simulate"]),
    st.booleans(),
    st.lists(st.integers(1, 60), min_size=1, max_size=5),
    st.integers(0, 2**32 - 1),
)
def test_a_run_continued_block_by_block_is_the_whole_run(
    model: str, direction: str, constant_period: bool, blocks: list[int], seed: int
) -> None:
    """Blocks run one after another with the state and the previous sample carried
    (``previous``) give the whole run's values bit for bit, on irregular sample times or a
    constant period, stretching cables with play included (the general path)."""
    rng = np.random.default_rng(seed)
    n = sum(blocks)
    t_all = np.cumsum(rng.uniform(0.0008, 0.0012, n))
    t = 1e-3 if constant_period else t_all
    v = np.cumsum(rng.normal(0.0, 0.01, (n, 2)), axis=0)
    ts = 300.0 + np.cumsum(rng.normal(0.0, 2.0, (n, 2)), axis=0)
    extra = {"slip_w": (0.3, 0.7), "slip_sigma": (800.0, 5000.0)} if model == "maxwell_slip" else {}
    p = params(model, sigma_n_m=2000.0, stretch_c=1e-5, backlash_m=2e-4, **extra)
    whole = run(p, direction, ts, v, t)
    state = new_state(p)
    previous = None
    got = []
    a = 0
    for size in blocks:
        b = a + size
        t_blk = t if constant_period else t_all[a:b]
        got.append(run(p, direction, ts[a:b], v[a:b], t_blk, state=state, previous=previous))
        previous = (float(t_all[b - 1]), v[b - 1].copy())
        a = b
    np.testing.assert_array_equal(np.concatenate(got), whole)


@settings(max_examples=30, deadline=None)
@given(st.integers(1, 4), st.integers(0, 2**32 - 1))
def test_every_declared_column_reaches_the_kernels_where_they_read_it(cables, seed) -> None:
    """:data:`COLUMNS` is the one declaration: a chain built from it (directly, or as the
    effects' draft) holds every column at its shape, and the kernels' ``cable`` array holds
    each ``cable`` column where the kernels read it (:data:`F0` .. :data:`PLAY`)."""
    from gateway.model import chain_schema as chain

    rng = np.random.default_rng(seed)
    values = {c: rng.uniform(0.01, 0.1, cables) for c in chain.CABLE_COLUMNS}
    p = params("dahl", cables, **values)
    draft = chain.ChainDraft("dahl", WRAPS, 1.0, dict(p.columns))
    for built in (p, draft.params()):
        assert list(built.columns) == [c.name for c in chain.COLUMNS]
        for c in chain.COLUMNS:
            want = {"cable": (cables,), "pulley": (cables, WRAPS.size), "element": (cables, 1)}
            assert built.columns[c.name].shape == want[c.shape], c.name
    kp = chain.kernel_params(p)
    assert kp.cable.shape == (cables, len(chain.CABLE_COLUMNS))
    read_at = dict(
        zip(
            ("f0_n", "stribeck_k", "stribeck_v_m_s", "viscous_ns_m", "sigma_n_m", "stretch_c"),
            (chain.F0, chain.STRIB_K, chain.STRIB_V, chain.VISCOUS, chain.SIGMA, chain.STRETCH),
            strict=True,
        ),
        backlash_m=chain.PLAY,
    )
    assert len(set(read_at.values())) == len(read_at)
    for name, col in read_at.items():
        assert chain.CABLE_COLUMNS[col] == name
        assert_allclose(kp.cable[:, col], values[name], rtol=0, atol=0)
    # the coefficient's growth with the load: per pulley 2 sin(wrap / 2) mu_load
    growth = values["mu_load"][:, None] * 2.0 * np.sin(WRAPS / 2.0)
    assert_allclose(kp.lam[:, :, chain.LOAD], growth, rtol=1e-15, atol=0)


def test_a_column_follows_the_one_it_defaults_to_until_set() -> None:
    """``slip_sigma`` defaults to ``sigma_n_m`` and ``mu_in`` to ``mu`` in the builder and
    in the draft (a changed stiffness carries its elements along), unless set."""
    from gateway.model import chain_schema as chain

    p = params("dahl", 2, sigma_n_m=300.0)
    assert_allclose(p.slip_sigma, 300.0)
    assert_allclose(p.mu_in, p.mu)
    draft = chain.ChainDraft("dahl", WRAPS, 1.0, dict(p.columns))
    draft.sigma_n_m = np.array([100.0, 200.0])
    assert_allclose(draft.params().slip_sigma[:, 0], [100.0, 200.0])
    draft.slip_sigma = np.array([[7.0], [8.0]])
    draft.sigma_n_m = np.array([1.0, 2.0])
    assert_allclose(draft.params().slip_sigma[:, 0], [7.0, 8.0])
    with pytest.raises(ValueError, match="unknown chain parameter"):
        params("dahl", 2, stretch=1.0)
    with pytest.raises(ValueError, match="backlash_m must be >= 0"):
        params("dahl", 2, backlash_m=-1.0)
