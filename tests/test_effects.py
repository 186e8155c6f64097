"""Path and sensor effects against closed forms."""

from __future__ import annotations

import numpy as np
from numpy.testing import assert_allclose

from gateway.model.effects import (
    PathSensorEffects,
    acceleration,
    apply_path_effects,
    apply_sensor_effects,
    delay,
    displacement,
    lowpass,
)


def test_displacement_and_acceleration() -> None:
    t = np.linspace(0, 2, 2001)
    v = 0.1 * np.sin(t)
    assert_allclose(displacement(t, v), 0.1 * (1 - np.cos(t)), atol=1e-7)
    assert_allclose(acceleration(t, v)[1:-1], 0.1 * np.cos(t)[1:-1], atol=1e-6)


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


def test_sensor_and_path_effect_signs() -> None:
    t = np.arange(1000) * 1e-3
    ts = np.full((1000, 2), 100.0)
    eff = PathSensorEffects(gain=np.array([0.01, 0.0]), offset_n=2.0, drift_n_s=0.5)
    out = apply_sensor_effects(t, ts, eff)
    assert_allclose(out[:, 0], 101.0 + 2.0 + 0.5 * t)
    assert_allclose(out[:, 1], 100.0 + 2.0 + 0.5 * t)
    v = np.outer(t, [1.0, 1.0])  # a = 1 m/s^2
    path = apply_path_effects(t, v, ts, PathSensorEffects(inertia_kg=0.3))
    assert_allclose(path, 100.0 - 0.3, atol=1e-9)  # the sensor reads T_p - m_eff a
    ecc = apply_path_effects(
        t,
        np.full((1000, 2), 0.1),
        ts,
        PathSensorEffects(eccentricity_a_n=1.5, eccentricity_r_m=0.05),
    )
    assert_allclose(ecc[:, 0], 100.0 + 1.5 * np.sin(0.1 * t / 0.05), atol=1e-9)
