"""``diagnose --write-model``: the fitted model file, read back by ``run`` and
``diagnose --model``.

The self-consistency tests diagnose a recording, write FITTED.yaml, and diagnose the same
recording with FITTED.yaml as the model: nothing is left to find (verdict ``none``), in
both references.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from numpy.testing import assert_allclose

from evaluation.scenarios import Scenario
from gateway.cli import main
from gateway.core.config import (
    DEFAULT_CONFIG_PATH,
    FrictionConfig,
    config_from_mapping,
    load_config,
    load_friction,
)
from gateway.core.configtypes import read_yaml
from gateway.diagnose.writemodel import compose, fitted_effects, relative_to_model, write_model
from gateway.model import chain_runs
from gateway.model import effects as fx
from gateway.recordings.reader import write_recording
from sim_plc.plant import make_recording
from tests.diagnose_helpers import write_scenario

M = 8
NOMINAL_MU = 0.015  # config/default.yaml


def _report(findings: list[dict]) -> dict:
    return {"cables": M, "findings": findings}


# fmt: off
REPORT = _report(
    [
        {"effect": "viscous", "cables": list(range(1, 9)), "parameters": {"c_ns_m": [12.5] * 8}},
        {"effect": "offset", "cables": [1, 4], "parameters": {"c_n": [1.5, -1.2]}},
        {"effect": "coulomb", "cables": [2], "parameters": {"mu": [0.02], "f0_n": [0.8]}},
        {"effect": "mass_change", "cables": [*range(1, 9)], "parameters": {"q_kg_s": [0.01] * M}},
    ]
)
# fmt: on


def _friction_file(tmp_path: Path) -> Path:
    path = tmp_path / "model.yaml"
    data = {"friction": read_yaml(DEFAULT_CONFIG_PATH)["friction"]}
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def test_findings_become_per_cable_values_with_neutral_elsewhere():
    eff = fitted_effects(REPORT, M)
    assert_allclose(eff["viscous"]["c_ns_m"], np.full(M, 12.5), rtol=0, atol=0)
    assert_allclose(eff["offset"]["c_n"], [1.5, 0, 0, -1.2, 0, 0, 0, 0], rtol=0, atol=0)
    mu = eff["coulomb"]["mu"]
    assert mu[1] == 0.02 and np.all(np.isnan(np.delete(mu, 1)))  # NaN: keep the nominal
    assert_allclose(eff["coulomb"]["f0_n"], [0, 0.8, 0, 0, 0, 0, 0, 0], rtol=0, atol=0)
    assert_allclose(eff["mass_change"]["q_kg_s"], [0.01], rtol=0, atol=0)


def test_friction_only_model_writes_friction_only_and_reads_back(tmp_path):
    model = _friction_file(tmp_path)
    out = tmp_path / "fitted.yaml"
    write_model(out, model, load_friction(model), REPORT)
    assert set(read_yaml(out)) == {"friction"}
    back = load_friction(out).effect_values(M)
    assert back["viscous"]["c_ns_m"].tolist() == [12.5] * M
    assert yaml.safe_load(out.read_text())["friction"]["effects"]["viscous"] == {"c_ns_m": 12.5}
    assert_allclose(back["offset"]["c_n"], [1.5, 0, 0, -1.2, 0, 0, 0, 0], rtol=0, atol=0)
    assert_allclose(back["coulomb"]["mu"], [NOMINAL_MU, 0.02, *[NOMINAL_MU] * 6], rtol=0, atol=0)
    assert_allclose(back["mass_change"]["q_kg_s"], [0.01], rtol=0, atol=0)
    nominal = load_friction(model)
    assert replace(load_friction(out), effects={}) == nominal  # the nominal model kept


def test_full_config_model_writes_a_full_config_that_run_loads(tmp_path):
    out = tmp_path / "fitted.yaml"
    write_model(out, DEFAULT_CONFIG_PATH, load_friction(DEFAULT_CONFIG_PATH), REPORT)
    cfg = load_config(out)  # what `run --config` does
    default = load_config(DEFAULT_CONFIG_PATH)
    assert cfg.geometry == default.geometry and cfg.bus == default.bus
    assert_allclose(cfg.friction.effect_values(M)["viscous"]["c_ns_m"], 12.5, rtol=0, atol=0)


def test_compose_adds_corrections_found_relative_to_the_model():
    old = fx.effect_values(
        {"gain": {"g": 0.01}, "offset": {"c_n": 1.0}, "coulomb": {"f0_n": 0.5}}, M
    )
    new = fx.effect_values(
        {"gain": {"g": 0.02}, "offset": {"c_n": 0.5}, "coulomb": {"mu": 0.02, "f0_n": 0.25}}, M
    )
    out = compose(old, new, NOMINAL_MU)
    assert_allclose(out["gain"]["g"], 1.01 * 1.02 - 1.0, rtol=1e-12)
    assert_allclose(out["offset"]["c_n"], 1.0 + 1.01 * 0.5, rtol=1e-12)
    assert_allclose(out["coulomb"]["mu"], 0.02, rtol=1e-12)  # nominal 0.015 + 0.005
    assert_allclose(out["coulomb"]["f0_n"], 0.75, rtol=1e-12)


def _plant(effects: dict, noise: float, seconds: float, seed: int = 3):
    data = read_yaml(DEFAULT_CONFIG_PATH)
    data["sim_plc"] = {
        "period_s": 1.0 / 250.0,
        "extrusion_kg_s": 0.0,
        "noise_std_n": noise,
        "seed": seed,
        "trajectory": {"kind": "random", "random": {"seed": seed}},
        "effects": effects,
        "distribution": {"method": "closed_form", "tau_min_n": 0.0, "tau_max_n": 360.0},
    }
    cfg = config_from_mapping(data, str(DEFAULT_CONFIG_PATH))
    return make_recording(cfg, None, seconds), cfg


def test_model_effects_take_the_recording_back_to_the_nominal_chain():
    """The plant with hidden effects, read relative to a model holding those effects, is
    the nominal chain's reading of the true platform tension (noise off)."""
    hidden = {
        "viscous": {"c_ns_m": 15.0},
        "offset": {"c_n": [1.5, 0, 0, -1.2, 0, 0, 0, 0]},
        "gain": {"g": 0.005},
        "inertia": {"m_eff_kg": 10.0},
        "coulomb": {"f0_n": 1.0},
    }
    rec, cfg = _plant(hidden, 0.0, 4.0)
    fitted = FrictionConfig.effects_mapping(fx.effect_values(hidden, M))
    friction = replace(cfg.friction, effects=fitted)
    out, nominal = relative_to_model(rec, friction)
    assert nominal.effects == {}
    tp = rec.tension_platform
    expect = chain_runs.run(fx.chain_params(nominal, {}, M), "simulate", tp, rec.velocity, rec.t)
    skip = 250  # the first second: the fitted chain's state settles from rest
    err = out.tension_sensor[skip:] - expect[skip:]
    # inertia: the gateway's backward difference against the truth's central one, and the
    # S7 digitisation (0.018 N) of the reading
    assert np.sqrt(np.mean(err**2)) < 0.05
    assert np.sqrt(np.mean((rec.tension_sensor[skip:] - expect[skip:]) ** 2)) > 1.0


def _diagnose(rec_path: Path, model: Path, tmp_path: Path, tag: str, write: Path | None = None):
    out = tmp_path / f"{tag}.json"
    argv = ["diagnose", str(rec_path), "--model", str(model), "--json", str(out), "--quiet"]
    if write is not None:
        argv += ["--write-model", str(write)]
    assert main(argv) == 0
    return json.loads(out.read_text())


@pytest.mark.long
def test_self_consistency_wrench_reference(tmp_path, capsys):
    """Wrench reference (pose and mass only, closed-form controller): diagnosing with the
    written model finds nothing."""
    rec, _ = _plant({"viscous": {"c_ns_m": 15.0}}, 0.4, 20.0)
    path = tmp_path / "rec.csv.gz"
    write_recording(path, replace(rec, tension_platform=None))
    fitted = tmp_path / "fitted.yaml"
    first = _diagnose(path, DEFAULT_CONFIG_PATH, tmp_path, "first", fitted)
    assert first["reference"] == "wrench"
    assert [f["effect"] for f in first["findings"]] == ["viscous"]
    c = load_config(fitted).friction.effect_values(M)["viscous"]["c_ns_m"]
    assert_allclose(c, 15.0, rtol=0.15)
    second = _diagnose(path, fitted, tmp_path, "second")
    assert second["findings"] == []
    assert "verdict: none" in capsys.readouterr().out
    assert second["final"]["rmse_n"] < first["baseline"]["rmse_n"]


def test_self_consistency_platform_tension_reference(tmp_path):
    sc = Scenario(
        "wm", {"viscous": {"c_ns_m": 8.0}, "offset": {"c_n": 1.5}}, cables=1, seconds=20.0
    )
    rec, model = write_scenario(tmp_path, sc)
    fitted = tmp_path / "fitted.yaml"
    first = _diagnose(rec, model, tmp_path, "first", fitted)
    assert first["reference"] == "platform_tension"
    assert {f["effect"] for f in first["findings"]} == {"viscous", "offset"}
    assert set(read_yaml(fitted)) == {"friction"}
    second = _diagnose(rec, fitted, tmp_path, "second")
    assert second["findings"] == []


def test_write_model_into_missing_directory_fails_before_the_work(tmp_path, capsys):
    rec, model = write_scenario(tmp_path, Scenario("wm", {}, cables=1, seconds=2.0))
    bad = tmp_path / "missing" / "fitted.yaml"
    argv = ["diagnose", str(rec), "--model", str(model), "--json", str(tmp_path / "r.json")]
    assert main([*argv, "--write-model", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "--write-model" in err and err.count("\n") == 1
    assert not (tmp_path / "r.json").exists()


@pytest.mark.parametrize("text", ["friction: {effects: {viscos: {c_ns_m: 1.0}}}"])
def test_model_with_unknown_effect_is_refused(tmp_path, capsys, text):
    rec, _ = write_scenario(tmp_path, Scenario("wm", {}, cables=1, seconds=2.0))
    model = tmp_path / "bad.yaml"
    model.write_text(text, encoding="utf-8")
    argv = ["diagnose", str(rec), "--model", str(model), "--json", str(tmp_path / "r.json")]
    assert main(argv) == 2
    assert "viscos" in capsys.readouterr().err


def test_inadmissible_fitted_values_are_clamped_and_named(tmp_path):
    """A negative f0 (mu and f0 trade off on a cable of nearly constant tension) cannot be
    written: it becomes 0 and the file's header says so."""
    report = _report(
        [
            {
                "effect": "coulomb",
                "cables": [1, 2],
                "parameters": {"mu": [0.015, 0.017], "f0_n": [1.2, -0.24]},
            }
        ]
    )
    out = tmp_path / "fitted.yaml"
    write_model(out, DEFAULT_CONFIG_PATH, load_friction(DEFAULT_CONFIG_PATH), report)
    f0 = load_config(out).friction.effect_values(M)["coulomb"]["f0_n"]
    assert_allclose(f0, [1.2, 0, 0, 0, 0, 0, 0, 0], rtol=0, atol=0)
    assert "# clamped: coulomb.f0_n on cable 2: fitted -0.24" in out.read_text()


def test_negative_f0_folds_into_mu_at_the_mean_tension(tmp_path):
    rec, _ = _plant({}, 0.0, 2.0)
    report = _report(
        [
            {
                "effect": "coulomb",
                "cables": [1, 2],
                "parameters": {"mu": [0.015, 0.027], "f0_n": [1.2, -9.0]},
            }
        ]
    )
    out = tmp_path / "fitted.yaml"
    friction = load_friction(DEFAULT_CONFIG_PATH)
    write_model(out, DEFAULT_CONFIG_PATH, friction, report, rec)
    eff = load_config(out).friction.effect_values(M)["coulomb"]
    k = float(np.sum(2 * np.sin(0.5 * np.asarray(friction.wrap_rad))))
    t2 = float(np.mean(rec.tension_sensor[:, 1]))
    assert eff["f0_n"][1] == 0.0 and eff["f0_n"][0] == 1.2
    assert_allclose(eff["mu"][1] * k * t2, 0.027 * k * t2 - 9.0, rtol=1e-9)  # same level
    assert "# folded: coulomb on cable 2" in out.read_text()
