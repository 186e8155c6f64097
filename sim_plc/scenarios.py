"""Scenario suite for the diagnosis: recordings with concealed effects, and clean ones.

Each :class:`Scenario` names the effects the "real" machine has beyond the nominal model
(parameter names and units of recording.md), their sizes chosen to be concealed: at or
below the sensor noise in the raw residual and smaller than the friction the nominal
model already holds, or confined to a narrow regime (reversals, low speed). The
recording is made by :func:`make_recording` (one function, so that the generator can be
swapped for the soft PLC's plant): truth chain (:func:`gateway.model.chain.simulate`)
-> path and sensor effects (:mod:`gateway.model.effects`) -> Gaussian noise -> S7
quantisation (27648 counts = sensor range).

``python -m sim_plc.scenarios --table docs/diagnose-suite.md`` runs the diagnosis on
every scenario and writes the results table.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gateway.config import FrictionConfig, PulleyConfig
from gateway.model import effects as fx
from gateway.model.chain import ChainParams, simulate
from gateway.recording import Recording

NOISE_N = 0.4
RANGE_N = 500.0
ADC_FULL_SCALE = 27648


@dataclass(frozen=True)
class Scenario:
    """One recording to diagnose: truth effects, motion and sensor options."""

    name: str
    effects: dict[str, dict[str, float]] = field(default_factory=dict)
    cables: int = 2
    seconds: float = 30.0
    seed: int = 1
    rate_hz: float = 1000.0
    uneven: bool = False
    rig: bool = False  # single-axis test rig: one cable, forces of either sign
    nominal_model: str = "dahl"
    noise_n: float = NOISE_N
    slow: bool = False

    def nominal(self) -> FrictionConfig:
        """The nominal model file's friction mapping (what the diagnosis is given)."""
        pulleys = (PulleyConfig(90.0, 0.015), PulleyConfig(60.0, 0.015), PulleyConfig(30.0, 0.015))
        return FrictionConfig(model=self.nominal_model, pulleys=pulleys, sigma_n_m=500.0)  # type: ignore[arg-type]


def motion(sc: Scenario) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times (N,) s, setpoint velocities (N, m) m/s and platform tensions (N, m) N.

    Velocity: a 0.2 Hz oscillation on a slow travel (reversals, low and high speed, net
    travel for eccentricity) with pauses (rest); tensions: a slow load change plus a
    faster component; on the rig they cross zero.
    """
    rng = np.random.default_rng(sc.seed)
    n = int(sc.seconds * sc.rate_hz)
    if sc.uneven:
        dt = rng.uniform(0.4, 1.6, n) / sc.rate_hz
        t = np.concatenate(([0.0], np.cumsum(dt[1:])))
    else:
        t = np.arange(n) / sc.rate_hz
    m = 1 if sc.rig else sc.cables
    ph = rng.uniform(0, 2 * math.pi, (4, m))
    tt = t[:, None]
    gate = np.clip(2.5 * np.sin(2 * math.pi * 0.043 * tt + ph[0]) + 1.8, 0.0, 1.0)
    v = gate * (0.08 * np.sin(2 * math.pi * 0.21 * tt + ph[1]))
    v = v + 0.035 * np.sin(2 * math.pi * 0.027 * tt + ph[2])
    if sc.rig:
        tp = 150 * np.sin(2 * math.pi * 0.071 * tt + ph[3]) + 40 * np.sin(2 * math.pi * 0.37 * tt)
    else:
        tp = 180 + 70 * np.sin(2 * math.pi * 0.061 * tt + ph[3]) + 25 * np.sin(
            2 * math.pi * 0.33 * tt + ph[0]
        )
    return t, v, tp


def _truth_chain(sc: Scenario, m: int) -> ChainParams:
    nom = sc.nominal()
    e = sc.effects
    mu = np.asarray(nom.mu)
    model = nom.model
    sigma = nom.sigma_n_m
    if "coulomb" in e:
        mu = mu * e["coulomb"].get("mu", float(np.mean(mu))) / float(np.mean(mu))
    if "presliding" in e:
        model, sigma = "dahl", e["presliding"]["sigma_n_m"]
    return ChainParams.build(
        model=model, cables=m, wrap_rad=np.asarray(nom.wrap_rad), mu=mu, sigma_n_m=sigma,
        f0_n=e.get("coulomb", {}).get("f0_n", 0.0),
        stribeck_k=e.get("stribeck", {}).get("k", 0.0),
        stribeck_v_m_s=e.get("stribeck", {}).get("v_s_m_s", 0.01),
        viscous_ns_m=nom.viscous_ns_m + e.get("viscous", {}).get("c_ns_m", 0.0),
    )  # fmt: skip


def _path_sensor(sc: Scenario) -> fx.PathSensorEffects:
    e = sc.effects
    ecc = e.get("eccentricity", {})
    return fx.PathSensorEffects(
        inertia_kg=e.get("inertia", {}).get("m_eff_kg", 0.0),
        eccentricity_a_n=ecc.get("a_n", 0.0),
        eccentricity_r_m=ecc.get("r_m", 0.05),
        eccentricity_phi_rad=ecc.get("phi_rad", 0.0),
        gain=e.get("gain", {}).get("g", 0.0),
        offset_n=e.get("offset", {}).get("c_n", 0.0),
        drift_n_s=e.get("drift", {}).get("k_n_s", 0.0),
        lowpass_tau_s=e.get("lowpass", {}).get("tau_s", 0.0),
        delay_s=e.get("delay", {}).get("d_s", 0.0),
    )


def make_recording(sc: Scenario) -> Recording:
    """The recording the "real" machine of ``sc`` produces (see the module docstring)."""
    t, v, tp = motion(sc)
    m = v.shape[1]
    ts = simulate(_truth_chain(sc, m), tp, v, t)
    eff = _path_sensor(sc)
    ts = fx.apply_sensor_effects(t, fx.apply_path_effects(t, v, ts, eff), eff)
    rng = np.random.default_rng(sc.seed + 1000)
    ts = ts + rng.normal(0.0, sc.noise_n, ts.shape)
    step = RANGE_N / ADC_FULL_SCALE
    ts = np.round(ts / step) * step
    return Recording(t=t, velocity=v, tension_sensor=ts, tension_platform=tp,
                     metadata={"source": "sim_plc.scenarios", "scenario": sc.name})  # fmt: skip
