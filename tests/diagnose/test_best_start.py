"""best_start's shortcuts (remembered results, the last winner first, simulations stopped
once a start cannot win) choose what trying every start in full chooses."""

from __future__ import annotations

import math

import numpy as np

from gateway.core.config import FrictionConfig, PulleyConfig
from gateway.diagnose.fit import _linear_step, best_start, spec_for
from gateway.diagnose.forward import CableData, Forward
from gateway.diagnose.prepare import nominal_from
from gateway.model import effects as fx
from gateway.model.chain_runs import BATCH_ROWS


def _cable(seed: int = 3) -> tuple[CableData, Forward]:
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 2.5 * BATCH_ROWS * 1e-3, 1e-3)  # three kernel batches
    v = 0.2 * np.sin(2 * np.pi * 0.4 * t) + 0.05 * np.sin(2 * np.pi * 1.7 * t)
    tp = 300.0 + 40.0 * np.sin(2 * np.pi * 0.13 * t)
    pulleys = (PulleyConfig(90.0, 0.015), PulleyConfig(60.0, 0.015))
    nom = nominal_from(FrictionConfig(model="dahl", pulleys=pulleys))
    probe = Forward(CableData(t, v, tp, tp, 0.0), nom)
    every = np.ones(t.size, bool)
    # the truth: the second start of the first chain effect with several starts
    specs = {e: spec_for(e, probe.data, nom, tp, every) for e in fx.stage_of("chain")}
    effect = next(e for e, s in specs.items() if len(s.starts) > 2)
    truth = {effect: specs[effect].starts[1]}
    ts = probe.predict(truth) + rng.normal(0.0, 0.4, t.size)
    return CableData(t, v, tp, ts, 0.0), Forward(CableData(t, v, tp, ts, 0.0), nom)


def _every_start(fw: Forward, base, effect, spec, mask) -> np.ndarray:
    best, best_sse = spec.neutral, math.inf
    for start in spec.starts:
        th = _linear_step(fw, base, effect, spec, start.astype(float), mask)
        sse = float(np.sum((fw.data.ts - fw.predict({**base, effect: th}))[mask] ** 2))
        if sse < best_sse:
            best, best_sse = th, sse
    return best


def test_best_start_chooses_what_every_start_in_full_chooses():
    data, fw = _cable()
    plain = Forward(data, fw.nom)
    mask = (np.arange(data.t.size) // 5000) % 2 == 0
    resid = data.ts - plain.predict({})
    chain = fx.stage_of("chain")
    bases = [{}, {chain[0]: spec_for(chain[0], data, fw.nom, resid, mask).neutral + 0.01}]
    for base in bases:
        for effect in chain:
            if effect in base or not fx.REGISTRY[effect].applicable(data, fw.nom):
                continue
            spec = spec_for(effect, data, fw.nom, resid, mask)
            want = _every_start(plain, base, effect, spec, mask)
            got = best_start(fw, base, effect, spec, mask)
            np.testing.assert_array_equal(got, want, err_msg=effect)
            again = best_start(fw, base, effect, spec, mask)  # remembered
            np.testing.assert_array_equal(again, want, err_msg=effect)
    # simulations stopped early are not counted: the shortcuts saved some in full
    assert fw.simulations < plain.simulations
