"""Per-cycle compensation: validation flags, substitution, the model, the wrench."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from drivers.base import ChannelStatus, Inputs, Outputs
from gateway.model.chain_runs import ChainStepper
from gateway.model.chain_schema import ChainParams
from gateway.runtime.compensator import (
    FLAG_NAN,
    FLAG_RANGE,
    FLAG_STALE,
    FLAG_STUCK,
    Compensator,
)
from tests.loop_helpers import config

DT = 0.001


def setup(**loop):
    cfg = config(**loop)
    comp = Compensator(cfg)
    inp = Inputs.allocate(cfg.cables)
    out = Outputs.allocate(cfg.cables)
    inp.pose[:] = cfg.geometry.home_pose
    return cfg, comp, inp, out


def feed(comp, inp, out, k, tension, velocity):
    inp.tension_raw_n[:] = tension
    inp.velocity_m_s[:] = velocity
    inp.read_time_s = float(k)  # a new read every cycle
    inp.plc_heartbeat = k & 0xFFFF  # of a new PLC sample (the heartbeat counts them)
    comp.step(inp, k * DT, out)


def test_good_channels_equal_the_model_and_friction_is_the_difference():
    cfg, comp, inp, out = setup()
    ref = ChainStepper(ChainParams.from_friction(cfg.friction, cfg.cables), DT)
    expected = np.zeros(cfg.cables)
    rng = np.random.default_rng(1)
    for k in range(200):
        t = 200 + 50 * np.sin(0.05 * k + np.arange(8)) + rng.normal(0, 0.5, 8)
        v = 0.1 * np.cos(0.05 * k + np.arange(8))
        feed(comp, inp, out, k, t, v)
        ref.step(t, v, expected, 0.0 if k == 0 else DT)  # no travel before the first cycle
        assert_allclose(out.tension_corrected_n, expected, rtol=0, atol=1e-9)
    assert np.all(out.channel_status == ChannelStatus.GOOD)
    assert_allclose(comp.friction_n, comp.corrected_n - inp.tension_raw_n, atol=1e-12)
    assert np.any(np.abs(comp.friction_n) > 1.0)  # the model does something


def test_nan_is_substituted_then_invalid_after_substitute_max():
    _, comp, inp, out = setup(substitute_max_s=0.01)
    t = np.full(8, 200.0)
    for k in range(5):
        feed(comp, inp, out, k, t, 0.05)
    bad = t.copy()
    bad[3] = np.nan
    feed(comp, inp, out, 5, bad, 0.05)
    assert comp.flags[3] == FLAG_NAN
    assert out.channel_status[3] == ChannelStatus.SUBSTITUTED
    assert comp.used_n[3] == 200.0  # the last good value
    assert np.isfinite(out.tension_corrected_n[3])
    for k in range(6, 16):
        feed(comp, inp, out, k, bad, 0.05)
    assert out.channel_status[3] == ChannelStatus.INVALID
    assert np.isnan(out.tension_corrected_n[3])
    assert np.all(np.isnan(out.wrench))  # no wrench from an incomplete set
    assert np.all(out.channel_status[[0, 1, 2, 4, 5, 6, 7]] == ChannelStatus.GOOD)
    assert np.all(np.isfinite(comp.stepper.state))  # the model state never sees NaN
    assert comp.flag_events == 1
    feed(comp, inp, out, 16, t, 0.05)
    assert out.channel_status[3] == ChannelStatus.GOOD
    assert np.all(np.isfinite(out.wrench))


@pytest.mark.parametrize("value", [501.0, 593.0, -30.0])
def test_out_of_range_is_flagged(value):
    _, comp, inp, out = setup()
    t = np.full(8, 100.0)
    feed(comp, inp, out, 0, t, 0.0)
    t[0] = value
    feed(comp, inp, out, 1, t, 0.0)
    assert comp.flags[0] == FLAG_RANGE
    assert out.channel_status[0] == ChannelStatus.SUBSTITUTED


def test_small_negative_noise_and_full_range_are_good():
    _, comp, inp, out = setup()
    t = np.full(8, 100.0)
    t[0], t[1] = -2.0, 500.0
    feed(comp, inp, out, 0, t, 0.0)
    assert np.all(comp.flags == 0)


def test_stuck_only_while_the_cable_moves():
    _, comp, inp, out = setup(stuck_after_s=0.05)
    t = np.full(8, 100.0)
    v = np.zeros(8)
    v[:4] = 0.1  # cables 0-3 move, 4-7 rest; nothing changes in the readings
    for k in range(100):
        feed(comp, inp, out, k, t, v)
    assert np.all(comp.flags[:4] & FLAG_STUCK)
    assert np.all(comp.flags[4:] == 0)
    t2 = t.copy()
    t2[:4] += 0.1
    feed(comp, inp, out, 100, t2, v)
    assert np.all(comp.flags == 0)


def test_no_fresh_data_is_stale():
    _, comp, inp, out = setup(stale_after_s=0.005)
    inp.tension_raw_n[:] = 100.0
    inp.read_time_s = 1.0
    for k in range(10):  # the driver keeps delivering the same read
        inp.tension_raw_n[:] = 100.0 + 0.01 * k
        comp.step(inp, k * DT, out)
    assert np.all(comp.flags & FLAG_STALE)
    assert np.all(out.channel_status == ChannelStatus.SUBSTITUTED)


def test_mark_unread_flags_without_stepping_the_model():
    _, comp, inp, out = setup()
    feed(comp, inp, out, 0, np.full(8, 100.0), 0.1)
    state = comp.stepper.state.copy()
    comp.mark_unread(0.002)
    assert np.all(comp.flags & FLAG_STALE)
    assert np.all(comp.status == ChannelStatus.SUBSTITUTED)
    comp.mark_unread(1.0)
    assert np.all(comp.status == ChannelStatus.INVALID)
    assert_allclose(comp.stepper.state, state)


def test_never_good_channel_is_invalid_at_once():
    _, comp, inp, out = setup()
    t = np.full(8, 100.0)
    t[7] = np.nan
    feed(comp, inp, out, 0, t, 0.0)
    assert out.channel_status[7] == ChannelStatus.INVALID
    assert np.isnan(out.tension_corrected_n[7])


def test_inertia_holds_its_acceleration_when_a_plc_sample_is_read_twice():
    """Each PLC sample (heartbeat k) read on two cycles: the inertia term is m_eff times
    the acceleration between samples on both cycles, never 0 and then twice that."""
    import dataclasses

    base = config()
    friction = dataclasses.replace(base.friction, effects={"inertia": {"m_eff_kg": 20.0}})
    comp = Compensator(dataclasses.replace(base, friction=friction))
    inp, out = Inputs.allocate(base.cables), Outputs.allocate(base.cables)
    inp.pose[:] = base.geometry.home_pose
    acc = 0.5  # m/s^2 between samples two cycles apart
    inp.tension_raw_n[:] = 200.0
    for cycle in range(40):
        k = cycle // 2
        inp.plc_heartbeat = k
        inp.velocity_m_s[:] = 0.05 + acc * k * 2 * DT
        inp.read_time_s = float(cycle)
        comp.step(inp, cycle * DT, out)
        if k >= 1:
            assert_allclose(comp.model_in_n, 200.0 + 20.0 * acc, rtol=0, atol=1e-9)


def test_inertia_acceleration_ignores_the_jitter_of_arrival_times():
    """PLC samples 1 ms apart (heartbeat +1 each) read at jittered times (+-40 % of a
    period): the acceleration uses the PLC's averaged sample spacing, so the inertia term
    stays at m_eff * a instead of swinging with each arrival's jitter."""
    import dataclasses

    base = config()
    friction = dataclasses.replace(base.friction, effects={"inertia": {"m_eff_kg": 20.0}})
    comp = Compensator(dataclasses.replace(base, friction=friction))
    inp, out = Inputs.allocate(base.cables), Outputs.allocate(base.cables)
    inp.pose[:] = base.geometry.home_pose
    inp.tension_raw_n[:] = 200.0
    acc = 0.5
    rng = np.random.default_rng(3)
    errors = []
    for k in range(600):
        inp.plc_heartbeat = k & 0xFFFF
        inp.velocity_m_s[:] = 0.05 + acc * k * DT
        now = k * DT + rng.uniform(-0.4, 0.4) * DT
        comp.step(inp, now, out)
        if k >= 300:  # after the spacing estimate has settled
            errors.append(np.max(np.abs(comp.model_in_n - (200.0 + 20.0 * acc))))
    assert max(errors) < 0.05 * 20.0 * acc  # within 5 % of the term (jitter alone: +-70 %)
