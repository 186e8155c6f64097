"""The compensator steps the Dahl chain with the PLC's time between the samples it
compensates: a deadline skipped after an overrun loses no cable travel; the read
patterns of a polled PLC are tested in test_compensator_samples.py."""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.testing import assert_allclose

from drivers.base import ChannelStatus, Inputs, Outputs
from gateway.model.chain_runs import ChainStepper
from gateway.runtime.compensator import MAX_GAP_PERIODS, Compensator
from tests.loop_helpers import config

PERIOD = 0.001
SUBSTITUTED = int(ChannelStatus.SUBSTITUTED)


def run(times: list[float]) -> Compensator:
    """A compensator stepped at the fake-clock ``times`` on one constant moving reading of
    a PLC that samples every ``PERIOD`` (its heartbeat counts them)."""
    cfg = config(period_s=PERIOD, stuck_after_s=10.0)
    comp = Compensator(cfg)
    inputs = Inputs.allocate(cfg.cables)
    out = Outputs.allocate(cfg.cables)
    inputs.tension_raw_n[:] = np.linspace(80.0, 250.0, cfg.cables)
    inputs.velocity_m_s[:] = np.linspace(-0.3, 0.3, cfg.cables)
    inputs.pose[:] = cfg.geometry.home_pose
    for t in times:
        inputs.plc_heartbeat = round((t - times[0]) / PERIOD) & 0xFFFF
        inputs.read_time_s = t
        comp.step(inputs, t, out)
    return comp


def one_go(comp: Compensator, dts: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """The same inputs through a fresh chain stepped with ``dts`` (state, output)."""
    lp = config(period_s=PERIOD).loop
    ref = ChainStepper(comp.params, PERIOD, True, lp.fixed_point_tol_n, lp.fixed_point_max_iter)
    out = np.zeros(comp.cables)
    for dt in dts:
        ref.step(comp.model_in_n, comp.velocity_m_s, out, dt)
    return ref.state, out


def test_a_skipped_cycle_steps_the_travel_of_both_periods():
    t0 = 100.0
    comp = run([t0, t0 + PERIOD, t0 + 3 * PERIOD])  # the deadline at t0 + 2 ms skipped
    state, out = one_go(comp, [0.0, PERIOD, 2 * PERIOD])
    assert_allclose(comp.stepper.state, state, rtol=0, atol=1e-9)
    assert_allclose(comp.corrected_n, out, rtol=0, atol=1e-9)
    # a fixed period would have lost a period of travel: the state is measurably different
    fixed, _ = one_go(comp, [0.0, PERIOD, PERIOD])
    assert np.max(np.abs(comp.stepper.state - fixed)) > 1e-3


def test_after_an_outage_the_step_is_bounded():
    t0 = 100.0
    comp = run([t0, t0 + PERIOD, t0 + 2.0])  # 2 s without a step
    state, _ = one_go(comp, [0.0, PERIOD, MAX_GAP_PERIODS * PERIOD])
    assert_allclose(comp.stepper.state, state, rtol=0, atol=1e-9)
    unbounded, _ = one_go(comp, [0.0, PERIOD, 2.0 - PERIOD])
    assert np.max(np.abs(comp.stepper.state - unbounded)) > 1e-3
    assert comp.clock.resyncs == 0  # the count advanced no faster than the time: a gap


def test_on_canopen_every_cycle_is_a_sample():
    """CANopen: each cycle is one SYNC's samples and the heartbeat comes in a slow PDO
    (every 10th cycle), so a constant velocity and heartbeat are no repeated read: the
    chain steps the time since the previous cycle."""
    cfg = config(period_s=PERIOD)
    cfg = dataclasses.replace(cfg, bus=dataclasses.replace(cfg.bus, driver="canopen"))
    comp = Compensator(cfg)
    inputs, out = Inputs.allocate(cfg.cables), Outputs.allocate(cfg.cables)
    inputs.tension_raw_n[:] = 200.0
    inputs.velocity_m_s[:] = 0.1
    inputs.pose[:] = cfg.geometry.home_pose
    times = [100.0 + k * PERIOD for k in range(5)]
    for t in times:
        inputs.read_time_s = t
        comp.step(inputs, t, out)
    state, _ = one_go(comp, [0.0] + [PERIOD] * 4)
    assert_allclose(comp.stepper.state, state, rtol=0, atol=1e-9)
    assert np.max(np.abs(state)) > 1e-3  # it moved
