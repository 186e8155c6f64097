"""The effects of the catalogue: forms against closed forms, the registry, the gateway's
per-cycle inverse against the batch forms, the plant's per-sample forms."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from gateway.model.effects import SeriesData, acceleration, displacement, effect_values
from gateway.model.effects import forward as apply_forward
from gateway.model.effects.forms import LowpassStepper, delay, lowpass


def series(t: np.ndarray, v: np.ndarray, x: np.ndarray | None = None) -> SeriesData:
    """The plant's view: ``x`` the cable length (default the travel), ``a`` look-ahead."""
    return SeriesData(t, v, displacement(t, v) if x is None else x, acceleration(t, v), t[0])


def test_displacement_and_acceleration() -> None:
    t = np.linspace(0, 2, 2001)
    v = 0.1 * np.sin(t)
    assert_allclose(displacement(t, v), 0.1 * (1 - np.cos(t)), atol=1e-7)
    assert_allclose(acceleration(t, v)[1:-1], 0.1 * np.cos(t)[1:-1], atol=1e-6)


def _whole_displacement(t: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The one-cumsum form :func:`displacement` computes piece by piece."""
    steps = 0.5 * (v[1:] + v[:-1]) * np.diff(t).reshape((-1,) + (1,) * (v.ndim - 1))
    return np.concatenate([np.zeros_like(v[:1]), np.cumsum(steps, axis=0)])


def test_piecewise_displacement_and_acceleration_equal_the_whole_bit_for_bit() -> None:
    """Computed CHUNK rows at a time (memory), the values are the whole-array formulas'
    (numpy's gradient, one cumsum), on even, uneven and gapped time bases."""
    from gateway.model.effects.forms import CHUNK

    rng = np.random.default_rng(3)
    for n in (2, 3, 5, CHUNK, CHUNK + 1, CHUNK + 2, 2 * CHUNK + 7):
        bases = {
            "even": np.arange(n) * 1e-3,
            "linspace": np.linspace(0.0, 1.0, n),
            "uneven": np.cumsum(rng.uniform(0.5e-3, 1.5e-3, n)),
            "gap": np.arange(n) * 1e-3 + np.where(np.arange(n) >= n // 2, 1.0, 0.0),
        }
        for t in bases.values():
            for v in (rng.normal(size=n), rng.normal(size=(n, 3))):
                np.testing.assert_array_equal(acceleration(t, v), np.gradient(v, t, axis=0))
                np.testing.assert_array_equal(displacement(t, v), _whole_displacement(t, v))


def test_delay_of_a_ramp_on_uneven_samples() -> None:
    t = np.sort(np.random.default_rng(1).uniform(0, 1, 500))
    y = 3.0 * t
    out = delay(t, y, 0.05)
    late = t > t[0] + 0.05
    assert_allclose(out[late], 3.0 * (t[late] - 0.05), atol=1e-12)


def test_lowpass_step_and_ramp_responses_are_exact() -> None:
    t = np.sort(np.concatenate([[0.0], np.random.default_rng(2).uniform(0, 0.5, 300)]))
    tau = 0.02
    ramp = lowpass(t, 10.0 * t, tau)  # exact for a ramp: 10 (t - tau (1 - e^-t/tau))
    assert_allclose(ramp, 10.0 * (t - tau * (1 - np.exp(-t / tau))), atol=1e-12)
    const = lowpass(t, np.full_like(t, 4.0), tau)
    assert_allclose(const, 4.0)


@settings(max_examples=60, deadline=None)
@given(
    steps=st.lists(
        st.sampled_from([0.0, 1e-3, 1e-3 + 2e-19, 0.9e-3, 2.5e-3]), min_size=1, max_size=300
    ),
    fresh=st.integers(0, 80),
    tau=st.lists(st.sampled_from([0.0, 1e-3, 0.02, 0.3]), min_size=1, max_size=3),
    seed=st.integers(0, 2**16),
)
def test_lowpass_batch_is_the_per_sample_step_bit_for_bit(steps, fresh, tau, seed) -> None:
    """The batch filter remembers the factors of recent steps (forms.LOWPASS_MEMO): the
    same bits as the per-sample form on time bases with repeated, zero and more distinct
    steps than it remembers."""
    rng = np.random.default_rng(seed)
    dts = np.concatenate([steps, rng.uniform(1e-4, 3e-3, fresh)])
    rng.shuffle(dts)
    t = np.concatenate([[0.0], np.cumsum(dts)])
    y = rng.normal(100.0, 5.0, (t.size, len(tau)))
    taus = np.array(tau)
    batch = lowpass(t, y, taus)
    stepper = LowpassStepper(taus)
    per = np.array([stepper.step(k, t[k], y[k]).copy() for k in range(t.size)])
    np.testing.assert_array_equal(batch, per)


def test_sensor_and_path_effect_signs() -> None:
    t = np.arange(1000) * 1e-3
    ts = np.full((1000, 2), 100.0)
    eff = effect_values(
        {"gain": {"g": [0.01, 0.0]}, "offset": {"c_n": 2.0}, "drift": {"k_n_s": 0.5}}, 2
    )
    out = apply_forward(series(t, np.zeros((1000, 2))), ts, eff)
    assert_allclose(out[:, 0], 101.0 + 2.0 + 0.5 * t)
    assert_allclose(out[:, 1], 100.0 + 2.0 + 0.5 * t)
    v = np.outer(t, [1.0, 1.0])  # a = 1 m/s^2
    path = apply_forward(series(t, v), ts, effect_values({"inertia": {"m_eff_kg": 0.3}}, 2))
    assert_allclose(path, 100.0 - 0.3, atol=1e-9)  # the sensor reads T_p - m_eff a
    ecc = apply_forward(
        series(t, np.full((1000, 2), 0.1)),
        ts,
        effect_values({"eccentricity": {"a_n": 1.5, "r_m": 0.05}}, 2),
    )
    assert_allclose(ecc[:, 0], 100.0 + 1.5 * np.sin(0.1 * t / 0.05), atol=1e-9)


# --- the registry -------------------------------------------------------------------------

import dataclasses  # noqa: E402
import math  # noqa: E402

import pytest  # noqa: E402
import yaml  # noqa: E402

from drivers.base import Inputs, Outputs  # noqa: E402
from gateway.core.config import FrictionConfig, PulleyConfig, load_config, load_friction  # noqa: E402
from gateway.diagnose import forward  # noqa: E402
from gateway.model import effects as fx  # noqa: E402
from gateway.model.chain_runs import run  # noqa: E402
from gateway.model.chain_schema import ChainParams, coulomb_coefficients  # noqa: E402
from gateway.model.effects.eccentricity import phase_at_length  # noqa: E402
from gateway.runtime.compensator import Compensator  # noqa: E402

REPORT_NAMES = {
    "coulomb": {"mu": "1", "f0_n": "N"},
    "coulomb_directional": {"mu_out": "1", "mu_in": "1", "f0_n": "N"},
    "coulomb_load": {"mu1_per_n": "1/N"},
    "presliding": {"sigma_n_m": "N/m"},
    "viscous": {"c_ns_m": "N s/m"},
    "stribeck": {"k": "1", "v_s_m_s": "m/s"},
    "inertia": {"m_eff_kg": "kg"},
    "delay": {"d_s": "s"},
    "lowpass": {"tau_s": "s"},
    "gain": {"g": "1"},
    "offset": {"c_n": "N"},
    "drift": {"k_n_s": "N/s"},
    "eccentricity": {"a_n": "N", "r_m": "m", "phi_rad": "rad"},
    "mass_change": {"q_kg_s": "kg/s"},
    "maxwell_slip": {"sigma_n_m": "N/m", "w": "1"},
    "cable_stretch": {"k_n_m": "N/m"},
    "backlash": {"width_m": "m"},
    "sensor_creep": {"c": "1", "tau_s": "s"},
    "spring": {"k_n_m": "N/m", "l0_m": "m"},
}


def test_registry_holds_the_catalogue_with_report_names_and_units() -> None:
    assert list(fx.REGISTRY) == list(REPORT_NAMES)
    for name, params in REPORT_NAMES.items():
        assert {p.name: p.unit for p in fx.REGISTRY[name].params} == params
    assert set(fx.ONLINE_EFFECTS) == {
        "coulomb",
        "coulomb_directional",
        "coulomb_load",
        "presliding",
        "viscous",
        "stribeck",
        "inertia",
        "gain",
        "offset",
        "eccentricity",
        "maxwell_slip",
        "cable_stretch",
        "backlash",
        "sensor_creep",
        "spring",
    }


@pytest.mark.parametrize(
    ("raw", "match"),
    [
        ({"viscos": {}}, r"^effects\.viscos: unknown effect"),
        ({"viscous": {"c": 1.0}}, r"^effects\.viscous\.c: unknown parameter"),
        ({"offset": {"c_n": [1.0, 2.0, 3.0]}}, r"^effects\.offset\.c_n: expected a scalar or 2"),
        ({"presliding": {"sigma_n_m": 0.0}}, r"^effects\.presliding\.sigma_n_m: must be > 0"),
        ({"gain": {"g": "big"}}, r"^effects\.gain\.g: expected a number"),
    ],
)
def test_effect_values_errors_name_the_key(raw, match) -> None:
    with pytest.raises(ValueError, match=match):
        fx.effect_values(raw, 2)


def test_effect_values_broadcast_and_default() -> None:
    eff = fx.effect_values({"offset": {"c_n": [0.3, -0.2]}, "eccentricity": {"a_n": 1.0}}, 2, 0.04)
    assert_allclose(eff["offset"]["c_n"], [0.3, -0.2])
    assert_allclose(eff["eccentricity"]["r_m"], [0.04, 0.04])  # the pulley radius
    assert_allclose(eff["eccentricity"]["phi_rad"], [0.0, 0.0])
    assert fx.to_mapping(eff) == {
        "offset": {"c_n": [0.3, -0.2]},
        "eccentricity": {"a_n": 1.0, "r_m": 0.04, "phi_rad": 0.0},
    }


UNEVEN = FrictionConfig(
    model="dahl",
    pulleys=(PulleyConfig(90.0, 0.01), PulleyConfig(60.0, 0.02), PulleyConfig(30.0, 0.03)),
)


def test_coulomb_mu_is_absolute_per_pulley_for_every_user() -> None:
    """Plant, scenarios, diagnosis and gateway read coulomb mu the same way: the
    coefficient of every pulley of the cable, not a scale of the nominal mean."""
    from evaluation import scenarios
    from sim_plc.config import load_sim_config
    from sim_plc.plant import chain_params as plant_chain

    cfg = load_config()
    cfg = dataclasses.replace(cfg, friction=UNEVEN)
    eff = {"coulomb": {"mu": 0.05, "f0_n": 0.2}}
    users = {}
    users["registry"] = fx.chain_params(UNEVEN, fx.effect_values(eff, 8), 8)
    sim_cfg = dataclasses.replace(cfg, sim_plc={"effects": eff})
    users["plant"] = plant_chain(load_sim_config(sim_cfg), 8)
    gw = dataclasses.replace(cfg, friction=dataclasses.replace(UNEVEN, effects=eff))
    users["gateway"] = Compensator(gw).params
    nom = forward.Nominal(
        "dahl", np.asarray(UNEVEN.wrap_rad), np.asarray(UNEVEN.mu), 500.0, 1.0, 0.0, 0.05
    )
    users["diagnosis"] = forward.chain_params(nom, {"coulomb": np.array([0.05, 0.2])})
    sc = dataclasses.replace(scenarios.Scenario("x", eff), nominal_model="dahl")
    sc_nominal = dataclasses.replace(sc.nominal(), pulleys=UNEVEN.pulleys)
    users["scenarios"] = fx.chain_params(sc_nominal, scenarios._effects(sc, 2), 2)
    for name, p in users.items():
        assert_allclose(p.mu, 0.05, rtol=0, atol=0, err_msg=name)
        assert_allclose(p.f0_n, 0.2, err_msg=name)
    # without coulomb.mu the nominal per-pulley values stay
    kept = fx.chain_params(UNEVEN, fx.effect_values({"coulomb": {"f0_n": 1.0}}, 8), 8)
    assert_allclose(kept.mu, np.broadcast_to([0.01, 0.02, 0.03], (8, 3)))


def test_f0_adds_to_the_coulomb_level_under_dahl() -> None:
    """Under Dahl the state tends to F_R = lambda T + f0 and relaxes to it with the
    pre-sliding dynamics: after a reversal ``F(x) = -L + (F_0 + L) exp(-sigma |x| / L)``."""
    sigma, f0, tp = 2000.0, 2.0, 200.0
    fr = FrictionConfig(model="dahl", pulleys=(PulleyConfig(90.0, 0.02),), sigma_n_m=sigma)
    params = fx.chain_params(fr, fx.effect_values({"coulomb": {"f0_n": f0}}, 1), 1)
    lam_pos, lam_neg = (float(c[0, 0]) for c in coulomb_coefficients(params))
    n, dt = 4000, 1e-3
    v = np.where(np.arange(n) < n // 2, 0.05, -0.05)[:, None]
    ts = run(params, "simulate", np.full((n, 1), tp), v, dt)[:, 0]
    force = tp - ts  # the pulley's friction force F (T_p = T_s + F)
    level_out, level_in = lam_pos * tp + f0, lam_neg * tp + f0
    assert force[n // 2 - 1] == pytest.approx(level_out, abs=1e-9)  # relaxed paying out
    # |x| since the reversal: the travel of the trapezoid between the samples (the step
    # across the reversal has none: (0.05 - 0.05) / 2 dt)
    x = displacement(dt * np.arange(n), v[:, 0])
    x = np.abs(x[n // 2 :] - x[n // 2 - 1])
    expected = -level_in + (force[n // 2 - 1] + level_in) * np.exp(-sigma * x / level_in)
    assert_allclose(force[n // 2 :], expected, rtol=0, atol=1e-9)


def test_f0_splits_over_the_pulleys_under_dahl() -> None:
    """At steady sliding each of the n pulleys tends to lambda_j T_j + f0 / n, T_j its own
    platform-side tension (worked out here pulley by pulley, platform to sensor)."""
    sigma, f0, tp = 800.0, 3.0, 300.0
    pulleys = (PulleyConfig(90.0, 0.02), PulleyConfig(45.0, 0.03))  # j = 1 (sensor), 2
    fr = FrictionConfig(model="dahl", pulleys=pulleys, sigma_n_m=sigma)
    params = fx.chain_params(fr, fx.effect_values({"coulomb": {"f0_n": f0}}, 1), 1)
    lam_pos, lam_neg = (c[0] for c in coulomb_coefficients(params))
    n, dt = 3000, 1e-3
    for speed, lam in ((0.2, lam_pos), (-0.2, lam_neg)):  # 0.6 m: ~40 relaxation lengths
        s = math.copysign(1.0, speed)
        ts = run(params, "simulate", np.full((n, 1), tp), np.full((n, 1), speed), dt)[-1, 0]
        t2 = tp
        t1 = t2 - s * (lam[1] * t2 + f0 / 2)
        want = t1 - s * (lam[0] * t1 + f0 / 2)
        assert ts == pytest.approx(want, abs=1e-9), speed


def test_dahl_level_falls_over_travel_not_at_once() -> None:
    """No clamp |F| <= F_R: when the tension (so the level lambda T + f0) drops at
    standstill the state stays; moving again it relaxes over travel to the new level."""
    sigma, f0, dt = 800.0, 2.0, 1e-3
    fr = FrictionConfig(model="dahl", pulleys=(PulleyConfig(90.0, 0.02),), sigma_n_m=sigma)
    params = fx.chain_params(fr, fx.effect_values({"coulomb": {"f0_n": f0}}, 1), 1)
    lam = float(coulomb_coefficients(params)[0][0, 0])
    k1, k2, k3 = 3000, 3500, 5000  # slide at 300 N, stand at 100 N, slide at 100 N
    tp = np.where(np.arange(k3) < k1, 300.0, 100.0)[:, None]
    k = np.arange(k3)
    v = np.where(k < k1, 0.2, np.where(k >= k2, 0.05, 0.0))[:, None]
    force = tp[:, 0] - run(params, "simulate", tp, v, dt)[:, 0]
    high, low = lam * 300.0 + f0, lam * 100.0 + f0
    assert force[k1 - 1] == pytest.approx(high, abs=1e-9)
    # the stop's own step still travels (0.2 + 0) / 2 dt = 0.1 mm at the new level: F moves
    # by ~2 % of the gap, then stands while v = 0 (far above the level, not snapped to it)
    assert low + 0.95 * (high - low) < force[k1] < high
    assert_allclose(force[k1:k2], force[k1], rtol=0, atol=1e-12)  # standstill
    x = displacement(dt * k, v[:, 0])  # travel (trapezoid) since the level fell
    x = x[k1:] - x[k1 - 1]
    assert_allclose(force[k1:], low + (high - low) * np.exp(-sigma * x / low), rtol=0, atol=1e-9)


def test_coulomb_load_grows_the_coefficient_with_the_tension() -> None:
    """``coulomb_load``: at steady sliding the level is ``(lambda + 2 sin(a/2) mu1 T) T``
    (docs/physics.md sec. 3), the same to first order as ``coulomb`` with the coefficient
    ``mu + mu1 T`` at that tension, and the excess over the nominal grows with ``T^2``."""
    mu, mu1, wrap = 0.02, 1e-4, 90.0
    fr = FrictionConfig(model="coulomb", pulleys=(PulleyConfig(wrap, mu),))
    load = fx.chain_params(fr, fx.effect_values({"coulomb_load": {"mu1_per_n": mu1}}, 1), 1)
    nominal = fx.chain_params(fr, {}, 1)
    lam_pos, lam_neg = (float(c[0, 0]) for c in coulomb_coefficients(load))
    g = 2.0 * math.sin(math.radians(wrap) / 2.0)
    excess = []
    for tp in (100.0, 200.0, 300.0):
        for v, lam in ((0.1, lam_pos), (-0.1, lam_neg)):
            args = (np.full((50, 1), tp), np.full((50, 1), v), 1e-3)
            force = tp - run(load, "simulate", *args)[-1, 0]
            assert force == pytest.approx(math.copysign((lam + g * mu1 * tp) * tp, v), abs=1e-9)
            plain = tp - run(nominal, "simulate", *args)[-1, 0]
            moved = fx.effect_values({"coulomb": {"mu": mu + mu1 * tp}}, 1)
            first_order = tp - run(fx.chain_params(fr, moved, 1), "simulate", *args)[-1, 0]
            assert abs(force - first_order) < 0.05 * abs(first_order - plain), (tp, v)
            if v > 0:
                excess.append(force - plain)
    assert excess[2] / excess[0] == pytest.approx(9.0, rel=1e-9)  # T^2


def test_coulomb_load_compensation_inverts_the_plant() -> None:
    """Under Dahl, a reversing motion and a varying load: the gateway's chain undoes the
    plant's (compensate(simulate(T)) = T) with the coefficient growing with the load."""
    from gateway.model.chain_runs import run

    fr = FrictionConfig(model="dahl", pulleys=(PulleyConfig(90.0, 0.02), PulleyConfig(45.0, 0.03)))
    params = fx.chain_params(fr, fx.effect_values({"coulomb_load": {"mu1_per_n": 2e-4}}, 2), 2)
    t = np.arange(6000) * 1e-3
    v = 0.05 * np.sin(2 * np.pi * 0.7 * t)[:, None] * np.array([1.0, -1.0])
    tp = 200.0 + 80.0 * np.sin(2 * np.pi * 0.3 * t)[:, None] * np.ones(2)
    ts = run(params, "simulate", tp, v, t)
    assert np.max(np.abs(tp - ts)) > 1.0  # the friction is there
    assert_allclose(run(params, "compensate", ts, v, t), tp, rtol=0, atol=1e-6)


def test_eccentricity_phase_from_travel_to_length() -> None:
    r, l0, phi = 0.03, 2.345, 0.7
    length = l0 + np.linspace(0, 0.5, 50)
    phi_abs = phase_at_length(phi, r, l0)
    assert_allclose(np.sin(length / r + phi_abs), np.sin((length - l0) / r + phi), atol=1e-12)


# --- online compensation: per-cycle against batch -------------------------------------------

ONLINE_CASES = {
    "coulomb": {"coulomb": {"mu": [0.02, 0.01, 0.03, 0.02, 0.015, 0.02, 0.025, 0.01], "f0_n": 0.8}},
    "coulomb_directional": {"coulomb_directional": {"mu_out": 0.025, "mu_in": 0.01, "f0_n": 0.3}},
    "presliding": {"presliding": {"sigma_n_m": 300.0}},
    "viscous": {"viscous": {"c_ns_m": [6.0, 2.0, 0.0, 1.0, 3.0, 4.0, 5.0, 0.5]}},
    "stribeck": {"stribeck": {"k": 0.5, "v_s_m_s": 0.004}},
    "inertia": {"inertia": {"m_eff_kg": 2.0}},
    "gain": {"gain": {"g": [0.002, -0.01, 0.0, 0.01, 0.0, 0.0, 0.03, 0.0]}},
    "offset": {"offset": {"c_n": [0.3, -0.2, 0.0, 1.0, 0.0, 0.0, 0.0, -1.5]}},
    "eccentricity": {"eccentricity": {"a_n": 0.4, "r_m": 0.03, "phi_rad": 0.7}},
    "maxwell_slip": {
        "maxwell_slip": {
            "sigma_n_m": [5000.0, 3000.0, 8000.0, 5000.0, 2000.0, 5000.0, 5000.0, 4000.0],
            "w": 0.4,
        }
    },
    "cable_stretch": {"cable_stretch": {"k_n_m": [5e3, 1e4, 2e3, 5e4, 1e4, 5e3, 3e3, 1e4]}},
    "backlash": {"backlash": {"width_m": [0.003, 0.001, 0.0, 0.002, 0.003, 0.004, 0.0, 0.01]}},
    "sensor_creep": {
        "sensor_creep": {"c": [0.05, 0.1, 0.0, -0.05, 0.3, 0.05, 0.05, 0.02], "tau_s": 0.3}
    },
    "spring": {"spring": {"k_n_m": [20.0, -5.0, 0.0, 40.0, 20.0, 10.0, 1.0, 30.0], "l0_m": 2.01}},
    "all": {
        "coulomb": {"f0_n": 0.5},
        "viscous": {"c_ns_m": 3.0},
        "stribeck": {"k": 0.3, "v_s_m_s": 0.005},
        "inertia": {"m_eff_kg": 1.5},
        "gain": {"g": 0.004},
        "offset": {"c_n": -0.7},
        "eccentricity": {"a_n": 0.4, "r_m": 0.03, "phi_rad": 0.7},
        "maxwell_slip": {"sigma_n_m": 4000.0, "w": 0.5},
        "backlash": {"width_m": 0.002},
        "cable_stretch": {"k_n_m": 5000.0},
        "sensor_creep": {"c": 0.05, "tau_s": 0.2},
        "spring": {"k_n_m": 20.0, "l0_m": 2.0},
    },
}


def _online_signals(n: int, m: int) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.8e-3, 1.3e-3, n))  # jittered cycles
    phase = np.arange(m)
    v = 0.05 * np.sin(2.0 * t[:, None] + phase) + 0.01 * np.sin(13.0 * t[:, None])
    length = 2.0 + 0.025 * (1 - np.cos(2.0 * t[:, None] + phase)) + 0.001 * phase
    reading = 200.0 + 40.0 * np.sin(0.7 * t[:, None] + phase) + rng.normal(0, 0.4, (n, m))
    return t, v, length, reading


@pytest.mark.parametrize("case", list(ONLINE_CASES))
def test_compensator_per_cycle_equals_the_batch_form(case: str) -> None:
    base = load_config()
    cfg = dataclasses.replace(
        base, friction=dataclasses.replace(base.friction, effects=ONLINE_CASES[case])
    )
    m, n = cfg.cables, 1500
    t, v, length, reading = _online_signals(n, m)
    comp = Compensator(cfg)
    inp, out = Inputs.allocate(m), Outputs.allocate(m)
    inp.pose[:] = cfg.geometry.home_pose
    got = np.empty((n, m))
    for k in range(n):
        inp.tension_raw_n[:], inp.velocity_m_s[:], inp.length_m[:] = reading[k], v[k], length[k]
        inp.read_time_s = t[k]
        comp.step(inp, t[k], out)
        got[k] = out.tension_corrected_n
    values = cfg.friction.effect_values(m)
    params = fx.chain_params(cfg.friction, values, m)
    expected = fx.compensate_online(params, values, t, reading, v, length)
    assert_allclose(got, expected, rtol=0, atol=1e-9)
    nominal = fx.compensate_online(
        ChainParams.from_friction(base.friction, m), {}, t, reading, v, length
    )
    assert np.max(np.abs(expected - nominal)) > 0.05  # the effect changes the result


def test_online_inverse_per_cycle_equals_batch() -> None:
    m, n = 3, 400
    t, v, length, reading = _online_signals(n, m)
    values = fx.effect_values(
        {
            "gain": {"g": [0.01, -0.02, 0.0]},
            "offset": {"c_n": [0.5, 0.0, -1.0]},
            "inertia": {"m_eff_kg": [2.0, 0.0, 1.0]},
            "eccentricity": {
                "a_n": [0.3, 0.2, 0.0],
                "r_m": [0.03, 0.05, 0.05],
                "phi_rad": [0.1, 0.2, 0.0],
            },
            "drift": {"k_n_s": 0.3},  # not online: the per-cycle form leaves it
        },
        m,
    )
    s = SeriesData(t, v, length, fx.causal_acceleration(t, v), t[0])
    batch = fx.inverse(s, reading, values, online_only=True)
    out, prev, vel, pos = np.empty(m), np.zeros(m), np.zeros(m), np.zeros(m)
    inv = fx.OnlineInverse(values, m, out, vel, prev, pos)
    assert inv.names == ("offset", "gain", "eccentricity", "inertia")
    for k in range(n):
        dt = t[k] - t[k - 1] if k else 0.0
        vel[:], pos[:] = v[k], length[k]
        inv(reading[k], out, vel, prev, dt, pos)
        prev[:] = v[k]
        assert_allclose(out, batch[k], rtol=0, atol=1e-9)


@pytest.mark.parametrize(
    "case",
    [
        "gain",
        "offset",
        "eccentricity",
        "viscous",
        "coulomb",
        "coulomb_directional",
        "maxwell_slip",
        "cable_stretch",
        "backlash",
        "sensor_creep",
        "spring",
        "all",
    ],
)
def test_compensation_removes_what_the_truth_adds(case: str) -> None:
    """Forward (the plant's batch forms, ``x`` the length) then the gateway's inverse gives
    the platform tension back; inertia within the difference of the two accelerations."""
    m, n = 8, 3000
    t, v, length, _ = _online_signals(n, m)
    tp = 250.0 + 30.0 * np.sin(0.5 * t[:, None] + np.arange(m))
    fr = load_config().friction
    values = fx.effect_values(ONLINE_CASES[case], m, fr.pulley_radius_m)
    params = fx.chain_params(fr, values, m)
    ts = run(params, "simulate", tp, v, t)
    reading = fx.forward(series(t, v, length), ts, values)
    back = fx.compensate_online(params, values, t, reading, v, length)
    tol = 0.05 if "inertia" in values else 1e-8  # central vs backward difference of v
    # the first cycle knows no acceleration yet (the truth's np.gradient looks ahead)
    assert_allclose(back[1:], tp[1:], rtol=0, atol=tol)


def test_friction_config_effects_round_trip(tmp_path) -> None:
    fr = dataclasses.replace(
        load_config().friction,
        effects={"viscous": {"c_ns_m": 0.4}, "offset": {"c_n": (0.1, -0.1, 0, 0, 0, 0, 0, 0.2)}},
    )
    path = tmp_path / "fitted.yaml"
    path.write_text(yaml.safe_dump({"friction": fr.to_mapping()}))
    back = load_friction(path)
    assert back == fr
    assert back.effect_values(8)["offset"]["c_n"][7] == pytest.approx(0.2)
    values = fx.effect_values({"gain": {"g": [0.1, 0.2]}, "drift": {"k_n_s": 0.0}}, 2)
    assert FrictionConfig.effects_mapping(values) == {
        "gain": {"g": (0.1, 0.2)},
        "drift": {"k_n_s": 0.0},
    }
    assert not math.isnan(back.sigma_n_m)


@pytest.mark.parametrize("with_inertia", [False, True])
def test_gateway_with_the_plants_hidden_effects_recovers_the_platform_tension(
    with_inertia: bool,
) -> None:
    """The same effects hidden in the soft PLC's plant and written into the gateway's
    ``friction.effects`` cancel: plant and gateway read every parameter the same way."""
    from sim_plc.plant import PlantModel, sensor_batch
    from tests.plant_helpers import cyclic_config

    hidden = {
        "coulomb": {"mu": [0.02, 0.015, 0.01, 0.015, 0.025, 0.015, 0.015, 0.02], "f0_n": 1.0},
        "coulomb_directional": {
            "mu_out": [0.03, 0.015, 0.01, 0.02, 0.025, 0.015, 0.015, 0.02],
            "mu_in": 0.012,
        },
        "viscous": {"c_ns_m": 4.0},
        "stribeck": {"k": 0.4, "v_s_m_s": 0.01},
        "inertia": {"m_eff_kg": 3.0},
        "gain": {"g": [0.01, -0.02, 0.0, 0.0, 0.005, 0.0, 0.0, 0.0]},
        "offset": {"c_n": 1.5},
        "eccentricity": {"a_n": 0.8, "r_m": 0.04, "phi_rad": 0.3},
    }
    if not with_inertia:
        del hidden["inertia"]
    cfg = cyclic_config(hidden, friction={"model": "dahl"})
    model = PlantModel(cfg)
    t = np.arange(3000) * 1e-3
    sp = model.setpoints(t)
    reading = sensor_batch(model, sp, np.zeros_like(sp.velocity))  # analog, noise off
    gw = dataclasses.replace(cfg.friction, effects=hidden)
    values = gw.effect_values(8)
    params = fx.chain_params(gw, values, 8)
    back = fx.compensate_online(params, values, t, reading, sp.velocity, sp.length)
    raw_err = np.max(np.abs(reading - sp.tension_true)[1:])
    err = np.max(np.abs(back - sp.tension_true)[1:])
    assert raw_err > 5.0  # the effects are large
    if not with_inertia:
        assert err < 1e-8
    else:  # the gateway's backward difference against the truth's central difference
        gap = 3.0 * np.abs(fx.acceleration(t, sp.velocity) - fx.causal_acceleration(t, sp.velocity))
        assert 1e-4 < err <= 1.1 * np.max(gap[1:])


def test_forward_per_sample_form_equals_the_batch_form() -> None:
    """The plant's per-sample path and sensor effects against the batch forms (uniform
    samples; the per-sample inertia looks one sample ahead like ``np.gradient``)."""
    m, n, dt = 3, 800, 1e-3
    t = np.arange(n) * dt
    v = 0.05 * np.sin(3.0 * t[:, None] + np.arange(m))
    length = 2.0 + np.cumsum(v, axis=0) * dt
    ts = 200.0 + 30.0 * np.sin(5.0 * t[:, None] + np.arange(m))
    eff = fx.effect_values(
        {
            "inertia": {"m_eff_kg": [2.0, 0.0, 1.0]},
            "eccentricity": {"a_n": 0.4, "r_m": 0.03, "phi_rad": 0.2},
            "gain": {"g": [0.01, 0.0, -0.02]},
            "offset": {"c_n": 0.5},
            "drift": {"k_n_s": 0.3},
            "lowpass": {"tau_s": [0.004, 0.0, 0.01]},
            "delay": {"d_s": [0.0025, 0.004, 0.0]},
            "sensor_creep": {"c": [0.05, 0.0, -0.1], "tau_s": 0.05},
            "spring": {"k_n_m": [20.0, -3.0, 0.0], "l0_m": 2.0},
        },
        m,
    )
    batch = fx.forward(series(t, v, length), ts, eff)
    step = fx.ForwardStepper(eff, m, dt)
    t3, v3 = np.zeros(3), np.zeros((3, m))
    for k in range(n - 1):
        t3[:2], v3[:2] = t3[1:], v3[1:]
        t3[1:], v3[1], v3[2] = (t[k], t[k + 1]), v[k], v[k + 1]
        got = step.step(fx.Sample(k, t[k], t3, v3, length[k]), ts[k])
        assert_allclose(got, batch[k], rtol=0, atol=1e-9, err_msg=f"sample {k}")


def test_a_repeated_plc_sample_does_not_advance_an_online_filter() -> None:
    """The gateway reads the same PLC sample again (same heartbeat, same values): a
    stateful online inverse (the creep's filter) starts again from its state before that
    sample, so the result equals reading it once."""
    base = load_config()
    eff = {"sensor_creep": {"c": 0.2, "tau_s": 0.05}, "offset": {"c_n": 0.3}}
    cfg = dataclasses.replace(base, friction=dataclasses.replace(base.friction, effects=eff))
    m, n = cfg.cables, 300
    t, v, length, reading = _online_signals(n, m)
    once, twice = Compensator(cfg), Compensator(cfg)
    inp, out = Inputs.allocate(m), Outputs.allocate(m)
    inp.pose[:] = cfg.geometry.home_pose
    a, b = np.empty((n, m)), np.empty((n, m))
    for k in range(n):
        inp.tension_raw_n[:], inp.velocity_m_s[:], inp.length_m[:] = reading[k], v[k], length[k]
        inp.plc_heartbeat, inp.read_time_s = k % 65536, t[k]
        once.step(inp, t[k], out)
        a[k] = once.model_in_n
        twice.step(inp, t[k], out)
        if k % 3 == 0:  # every third sample read again half a cycle later
            twice.step(inp, t[k] + 0.4e-3, out)
        b[k] = twice.model_in_n
    assert_allclose(b, a, rtol=0, atol=1e-12)
    assert np.max(np.abs(a - (reading - 0.3))) > 0.05  # the creep's inverse acts


def test_a_rigid_cable_among_stretching_ones_is_written_as_a_number(tmp_path) -> None:
    """``cable_stretch`` found on some cables: the others (k = inf, absent) are written as
    ``K_MAX``, which a model file can hold and the chain takes as rigid."""
    from gateway.model.effects import cable_stretch
    from gateway.model.effects.base import ModelFile

    values = {"k_n_m": np.array([5000.0, np.inf, 8000.0])}
    fr = load_config().friction
    cable_stretch.EFFECT.to_model(values, ModelFile(fr, None, None))
    assert_allclose(values["k_n_m"], [5000.0, cable_stretch.K_MAX, 8000.0])
    written = dataclasses.replace(
        fr, effects=FrictionConfig.effects_mapping({"cable_stretch": values})
    )
    path = tmp_path / "fitted.yaml"
    path.write_text(yaml.safe_dump({"friction": written.to_mapping()}))
    back = load_friction(path)
    params = fx.chain_params(back, back.effect_values(3), 3)
    assert_allclose(params.stretch_c, [1 / 5000.0, 0.0, 1 / 8000.0])
