"""Every registered effect, one meaning end to end: hidden in the soft PLC's plant ->
recorded -> diagnosed (the platform-tension reference, and the wrench reference where the
effect's module says it identifies it) -> ``--write-model`` -> diagnosed again with the
fitted model -> nothing left to find.

The plant, the diagnosis (both references), the model file and the gateway's model read
every parameter the same way: a parameter read differently anywhere on the way leaves a
finding in the second diagnosis (or misses the first).
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from evaluation.scenarios import tolerance
from gateway.cli import main
from gateway.core.config import DEFAULT_CONFIG_PATH, Config, config_from_mapping, load_config
from gateway.core.configtypes import read_yaml
from gateway.model import effects as fx
from gateway.recordings.reader import write_recording
from sim_plc.plant import make_recording

NOISE = 0.4
SECONDS = 20.0
RATE = 250.0
CLOSED_FORM = {"method": "closed_form", "tau_min_n": 0.0, "tau_max_n": 360.0}


LIVELY = {"max_frequency_hz": 1.5, "amplitude": [0.1, 0.075, 0.05, 0.02, 0.02, 0.03]}
"""A lively random motion (up to 1.5 Hz, half the default amplitude) for the effects of
the group that acts on fast changes (inertia, a delay, a low-pass: its accelerations tell
them apart); the others get the default motion (0.02-0.3 Hz, travel over several pulley
turns, many reversals)."""


def plant_config(effects: dict, seed: int = 3, lively: bool = False) -> Config:
    data = read_yaml(DEFAULT_CONFIG_PATH)
    data["sim_plc"] = {
        "period_s": 1.0 / RATE,
        "extrusion_kg_s": 0.0,
        "noise_std_n": NOISE,
        "seed": seed,
        "trajectory": {"kind": "random", "random": {**(LIVELY if lively else {}), "seed": seed}},
        "effects": effects,
        "distribution": CLOSED_FORM,
    }
    return config_from_mapping(data, str(DEFAULT_CONFIG_PATH))


def diagnose(rec: Path, model: Path, tmp: Path, tag: str, write: Path | None = None) -> dict:
    out = tmp / f"{tag}.json"
    argv = ["diagnose", str(rec), "--model", str(model), "--json", str(out), "--quiet"]
    if write is not None:
        argv += ["--write-model", str(write)]
    assert main(argv) == 0
    return json.loads(out.read_text())


def within_tolerance(name: str, truth: dict[str, float], fitted: dict) -> list[str]:
    """The fitted parameters (every cable) outside the scenario suite's tolerances."""
    nominal_mu = float(np.mean(load_config().friction.mu))
    bad = []
    for p, values in fitted.items():
        tol = tolerance(name, p)
        if tol is None or p not in truth:
            continue
        kind, limit = tol
        if kind == "angle":
            continue  # a phase against the cable length: checked by its contribution below
        t = truth[p]
        for v in values:
            err = abs(v - t)
            if kind == "rel":
                err /= abs(t)
            elif kind == "change":
                err /= abs(t - nominal_mu)
            if err > limit:
                bad.append(f"{p} = {v:.5g} (true {t:.5g}, {kind} {limit})")
    return bad


@pytest.mark.long
@pytest.mark.parametrize("name", fx.EFFECT_NAMES)
def test_hidden_found_written_and_then_nothing_left(name: str, tmp_path: Path) -> None:
    effect = fx.REGISTRY[name]
    truth = dict(effect.example)
    cfg = plant_config({name: truth}, lively=effect.group == "dynamics")
    full = make_recording(cfg, None, SECONDS)
    references = {"platform_tension": full}
    if effect.wrench:
        references["wrench"] = replace(full, tension_platform=None)
    for ref, rec in references.items():
        path = tmp_path / f"{ref}.csv.gz"
        write_recording(path, rec)
        fitted = tmp_path / f"{ref}-fitted.yaml"
        first = diagnose(path, DEFAULT_CONFIG_PATH, tmp_path, f"{ref}-first", fitted)
        assert first["reference"] == ref
        found = [f["effect"] for f in first["findings"]]
        assert found == [name], (ref, found)
        finding = first["findings"][0]
        if effect.per_cable:
            assert finding["cables"] == list(range(1, 9)), (ref, finding["cables"])
        # the model file means what the plant means (a phase against the cable length)
        friction = load_config(fitted).friction
        assert set(friction.effects) == {name}
        written = {p: list(v) for p, v in friction.effect_values(8)[name].items()}
        assert not within_tolerance(name, truth, written), (
            ref,
            within_tolerance(name, truth, written),
        )
        if any((tolerance(name, p) or ("",))[0] == "angle" for p in truth):
            # a phase L0 / r away from the recording's start is only as good as r there:
            # the written model's contribution over the recorded lengths is what must match
            series = fx.SeriesData(full.t, full.velocity, full.length, full.velocity, 0.0)
            zero = np.zeros_like(full.velocity)
            want = fx.forward(series, zero, fx.effect_values({name: truth}, 8))
            got = fx.forward(series, zero, friction.effect_values(8))
            scale = float(np.max(np.abs(want)))
            assert np.max(np.abs(got - want)) < 0.2 * scale, ref
        second = diagnose(path, fitted, tmp_path, f"{ref}-second")
        assert second["findings"] == [], (ref, [f["effect"] for f in second["findings"]])
        assert second["final"]["rmse_n"] < first["baseline"]["rmse_n"]
