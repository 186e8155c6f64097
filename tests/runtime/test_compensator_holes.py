"""Regressions of the compensation with fitted effects.

#1: a single reply with ``length_1 = NaN`` under a fitted eccentricity left cable 1 at NaN
with status 0 until restart (plausibility let NaN through, the Dahl state stayed NaN).
#6: after the PLC held its heartbeat and setpoints for 1 s, the fitted inertia term was
17-81 % of its size over the next 600 ms (the PLC's sample spacing estimate took the hold
as one sample of 1 s).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from drivers.base import ChannelStatus, Inputs, Outputs
from drivers.virtual import VirtualDriver
from gateway.runtime.compensator import Compensator
from gateway.runtime.loop import CyclicService
from tests.loop_helpers import FakeClock, config, live_image

GOOD = int(ChannelStatus.GOOD)
SUBSTITUTED = int(ChannelStatus.SUBSTITUTED)


def _with_effects(cfg, effects, model: str | None = None):
    friction = dataclasses.replace(cfg.friction, effects=effects)
    if model is not None:
        friction = dataclasses.replace(friction, model=model)
    return dataclasses.replace(cfg, friction=friction)


def test_one_nan_cable_length_does_not_poison_the_cable():
    cfg = _with_effects(
        config(busy_wait_s=0.0, stuck_after_s=10.0),
        {"eccentricity": {"a_n": 2.0, "r_m": 0.05, "phi_rad": 0.3}},
    )
    img = live_image(cfg)
    img.length_m[:] = 1.5
    clock = FakeClock()
    drv = VirtualDriver(cfg, image=img)
    svc = CyclicService(cfg, drv, clock=clock, sleep=clock.sleep, history=4096)
    frames: list[tuple[int, np.ndarray, np.ndarray]] = []

    def poke(n: int) -> None:
        img.length_m[0] = np.nan if n == 100 else 1.5

    def record(inputs: Inputs, comp: Compensator, now: float) -> None:
        frames.append((drv.reads, comp.status.copy(), comp.corrected_n.copy()))

    drv.on_read = poke
    svc.add_observer(record)
    svc.run(cycles=600)
    for n, status, corrected in frames:  # never a non-finite value marked usable
        usable = status <= SUBSTITUTED
        assert np.all(np.isfinite(corrected[usable])), (n, status, corrected)
    late = [(s, c) for n, s, c in frames if n > 200]
    assert all(s[0] == GOOD and np.isfinite(c[0]) for s, c in late)  # cable 1 recovered
    assert np.all(np.isfinite(svc.comp.stepper.state))


def test_fitted_inertia_is_right_right_after_the_plc_held():
    m_eff = 20.0
    cfg = _with_effects(
        config(busy_wait_s=0.0, stuck_after_s=10.0), {"inertia": {"m_eff_kg": m_eff}}, "none"
    )
    comp = Compensator(cfg)
    inputs, out = Inputs.allocate(cfg.cables), Outputs.allocate(cfg.cables)
    inputs.pose[:] = cfg.geometry.home_pose
    inputs.length_m[:] = 1.5
    period = cfg.loop.period_s

    def velocity(k: int) -> float:  # the PLC's sample k (its own time k ms)
        return 0.2 * np.sin(2 * np.pi * 0.8 * k * period)

    now, k = 10.0, 0
    ratios = []
    for cycle in range(3000):
        now += period
        held = 1000 <= cycle < 2000  # the PLC holds sample k for 1 s
        if not held:
            k += 1
        inputs.plc_heartbeat = k & 0xFFFF
        inputs.velocity_m_s[:] = velocity(k)
        inputs.tension_raw_n[:] = 200.0 + 1e-3 * k
        inputs.read_time_s = now
        comp.step(inputs, now, out)
        if 2002 <= cycle < 2600:  # after the hold: the term a sample's acceleration gives
            want = m_eff * (velocity(k) - velocity(k - 1)) / period
            got = comp.model_in_n[0] - comp.used_n[0]
            if abs(want) > 1.0:
                ratios.append(got / want)
    assert len(ratios) > 300
    np.testing.assert_allclose(ratios, 1.0, atol=0.05)
