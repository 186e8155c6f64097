"""The demo's and calibrate's score measure the model, not where the plant was when the
gateway joined it: each cable is scored once the gateway's chain has travelled
``WARMUP_LENGTHS`` relaxation lengths (:class:`sim_plc.truth.ChainWarmup`)."""

from __future__ import annotations

import dataclasses
import math
import tracemalloc

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.base import Inputs, Outputs
from gateway.model import effects as fx
from gateway.model.chain_runs import run
from gateway.model.chain_schema import coulomb_coefficients
from gateway.runtime.compensator import Compensator
from sim_plc.truth import WARMUP_LENGTHS, ChainWarmup, CycleRing, TruthScorer
from tests.loop_helpers import config

PERIOD = 1e-3
NOISE_N = 0.5


def _config(effects: dict | None = None, model: str = "dahl"):
    cfg = config(period_s=PERIOD)
    return dataclasses.replace(
        cfg, friction=dataclasses.replace(cfg.friction, model=model, effects=effects or {})
    )


@settings(max_examples=30, deadline=None)
@given(
    tension=st.floats(20.0, 480.0),
    speed=st.floats(0.005, 0.3),
    mu=st.floats(0.005, 0.05),
)
def test_a_cable_warms_up_after_its_relaxation_lengths_of_travel(tension, speed, mu):
    cfg = _config({"coulomb": {"mu": mu}})
    warm = ChainWarmup(cfg)
    params = fx.chain_params(cfg.friction, cfg.friction.effect_values(cfg.cables), cfg.cables)
    lam_pos, lam_neg = coulomb_coefficients(params)
    need = (
        WARMUP_LENGTHS
        * float(np.max(np.maximum(lam_pos, lam_neg)[0]))
        * tension
        / float(params.sigma_n_m[0])
    )
    v = np.full(cfg.cables, speed)
    v[1] = -speed  # either direction
    v[2] = 0.0  # a cable at rest never warms up
    t = np.full(cfg.cables, tension)
    steps = math.ceil(need / (speed * PERIOD))
    for k in range(steps + 2):
        mask = warm.update(v, t, 100.0 + k * PERIOD)
        travelled = speed * PERIOD * k
        if travelled < need * (1 - 1e-9):
            assert not mask[0] and not mask[1]
    assert mask[0] and mask[1] and not mask[2]


def test_a_chain_without_presliding_state_is_warm_at_once():
    for model in ("coulomb", "none"):
        warm = ChainWarmup(_config(model=model))
        assert warm.update(np.zeros(8), np.full(8, 100.0), 0.0).all()


def test_the_ring_observer_with_a_warmup_allocates_nothing():
    cfg = _config()
    ring = CycleRing(cfg.cables, size=256, warmup=ChainWarmup(cfg))
    comp = Compensator(cfg)
    comp.corrected_n[:] = 200.0
    comp.velocity_m_s[:] = 0.05
    inputs = Inputs.allocate(cfg.cables)
    now = 0.0
    for _ in range(600):
        now += PERIOD
        inputs.plc_heartbeat = (inputs.plc_heartbeat + 1) & 0xFFFF
        ring(inputs, comp, now)
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for _ in range(2000):
            now += PERIOD
            inputs.plc_heartbeat = (inputs.plc_heartbeat + 1) & 0xFFFF
            ring(inputs, comp, now)
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert grown < 512, grown
    assert ring.warmup is not None and ring.warmup.all_warm


def _moving_plant(cfg, seconds: float, seed: int):
    """A noisy plant of ``cfg``'s own model (times, velocities, readings, platform
    tensions), moving from t = 0 with reversals every second or two."""
    n = int(seconds / PERIOD)
    t = np.arange(n) * PERIOD
    rng = np.random.default_rng(seed)
    ph = rng.uniform(0, 2 * math.pi, (2, cfg.cables))
    tt = t[:, None]
    v = 0.06 * np.sin(2 * math.pi * 0.3 * tt + ph[0])
    tp = 250.0 + 80.0 * np.sin(2 * math.pi * 0.15 * tt + ph[1])
    values = cfg.friction.effect_values(cfg.cables)
    ts = run(fx.chain_params(cfg.friction, values, cfg.cables), "simulate", tp, v, t)
    return t, v, ts + rng.normal(0.0, NOISE_N, ts.shape), tp


@pytest.mark.parametrize("join_s", [0.6, 2.1, 3.7])
def test_the_score_of_a_gateway_joining_a_moving_plant_is_the_noise_floor(join_s):
    """The gateway (with the plant's exact model) joins the moving plant at ``join_s``:
    its chain starts relaxed, the plant's is developed. Scored after its warm-up, the
    corrected tensions are at the sensor noise wherever it joined; scored after the
    first 0.5 s alone, the same runs read 1.7-2.5 times the noise (mu 0.025)."""
    cfg = _config({"coulomb": {"mu": 0.025}})
    t, v, ts, tp = _moving_plant(cfg, join_s + 10.0, seed=5)
    comp = Compensator(cfg)
    inp, out = Inputs.allocate(cfg.cables), Outputs.allocate(cfg.cables)
    inp.pose[:] = cfg.geometry.home_pose
    k = {"k": 0}

    def truth(into: np.ndarray) -> int:
        into[:] = tp[k["k"]]
        return k["k"] & 0xFFFF

    scorer = TruthScorer(cfg.cables, truth, every=1, warmup=ChainWarmup(cfg))
    for j in range(int(join_s / PERIOD), t.size):
        k["k"] = j
        inp.tension_raw_n[:] = ts[j]
        inp.velocity_m_s[:] = v[j]
        inp.plc_heartbeat = j & 0xFFFF
        inp.read_time_s = float(t[j])
        comp.step(inp, float(t[j]), out)
        scorer(inp, comp, float(t[j]))
    rmse = math.sqrt(float(scorer.score.corrected_sq.sum() / scorer.score.samples.sum()))
    assert scorer.score.samples.min() > 0.5 * (t.size - join_s / PERIOD)  # most is scored
    assert rmse <= 1.03 * NOISE_N, rmse
