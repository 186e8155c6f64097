"""The plant: agreement with gateway.model, ADC and S7 codes, config, step vs batch."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from gateway import cli
from gateway.errors import ConfigError, InfeasiblePoseError
from gateway.model import chain_runs, chain_schema, kinematics, statics
from gateway.recordings.reader import read_recording
from sim_plc.config import load_sim_config
from sim_plc.image import ProcessImage
from sim_plc.plant import (
    Plant,
    PlantModel,
    counts_to_newton,
    digitise,
    make_recording,
    sensor_batch,
    stream_recording,
)
from tests.plant_helpers import REPLICATE_YAML, cyclic_config, make_config


def test_noise_off_statics_and_chain_agree_with_model_to_1e_9() -> None:
    cfg = make_config({"noise_std_n": 0.0, "trajectory": {"kind": "random"}})
    model = PlantModel(cfg)
    t = np.arange(3000) * 0.001
    sp = model.setpoints(t)
    a, b = np.array(cfg.geometry.frame_anchors_m), np.array(cfg.geometry.platform_anchors_m)
    s = model.trajectory.evaluate(t)
    geo, lim = cfg.geometry, model.sim.tension
    omega = kinematics.angular_velocity_from_euler_rates(s.pose[:, 3:], s.velocity[:, 3:])
    for k in range(0, t.size, 97):
        twist = np.concatenate([s.velocity[k, :3], omega[k]])
        assert_allclose(sp.length[k], kinematics.cable_lengths(a, b, s.pose[k]), atol=1e-12)
        assert_allclose(
            sp.velocity[k], kinematics.cable_velocities(a, b, s.pose[k], twist), atol=1e-12
        )
        w = statics.gravity_wrench(
            sp.mass[k], geo.gravity_m_s2, s.pose[k]
        ) + statics.inertial_wrench(sp.mass[k], s.acceleration[k, :3])
        tau = statics.distribute_tensions(
            kinematics.structure_matrix(a, b, s.pose[k]), w, lim.min_n, lim.max_n
        )
        assert_allclose(sp.tension_true[k], tau, atol=1e-9)
        assert_allclose(sp.a_mat[k] @ tau + w, 0.0, atol=1e-9)
    analog = sensor_batch(model, sp, np.zeros((t.size, 8)))
    params = chain_schema.ChainParams.from_friction(cfg.friction, 8)
    expected = chain_runs.run(params, "simulate", sp.tension_true, sp.velocity, t)
    assert_allclose(analog, expected, atol=1e-9)
    rec = make_recording(cfg, None, 3.0)
    step = 500.0 / 27648
    assert np.max(np.abs(rec.tension_sensor - expected)) <= 0.5 * step + 1e-9


def test_digitise_s7_format_saturation_and_codes() -> None:
    t = np.array([0.0, 250.0, 500.0, 550.0, 587.0, 590.0, 1000.0, -50.0, -100.0, 0.004])
    counts = digitise(t, 500.0, 27648, saturation_n=600.0)
    assert counts.dtype == np.int16
    assert counts.tolist() == [0, 13824, 27648, 30413, 32459, 32767, 32767, -2765, -32768, 0]
    back = counts_to_newton(counts, 500.0, 27648)
    assert_allclose(back[:5], [0.0, 250.0, 500.0, 30413 * 500 / 27648, 32459 * 500 / 27648])
    assert np.isnan(back[5]) and np.isnan(back[6]) and np.isnan(back[8])
    # a sensor whose output saturates below the overflow limit never reports overflow
    assert digitise(np.array([1000.0]), 500.0, 27648, saturation_n=550.0)[0] == 30413


def test_overrange_reading_from_an_offset_is_flagged_in_the_recording() -> None:
    offset = {"c_n": [400, 0, 0, 0, 0, 0, 0, 0]}
    cfg = make_config({"noise_std_n": 0.0, "effects": {"offset": offset}})
    rec = make_recording(cfg, None, 0.2)
    assert np.all(np.isnan(rec.tension_sensor[:, 0]))  # 600+ N: overflow code 32767
    assert np.all(np.isfinite(rec.tension_sensor[:, 1:]))


def test_mass_falls_at_the_extrusion_rate_while_printing() -> None:
    cfg = make_config({"noise_std_n": 0.0})
    rec = make_recording(cfg, None, 4.0)
    assert rec.mass[0] == pytest.approx(40.0)
    assert rec.mass[-1] == pytest.approx(40.0 - 0.1 * rec.t[-1], abs=1e-9)
    const = make_recording(make_config({"extrusion_kg_s": 0.0}), None, 1.0)
    assert np.all(const.mass == 40.0)


def test_record_command_round_trips_through_the_reader(tmp_path, capsys) -> None:
    out = tmp_path / "rec.csv.gz"
    argv = ["record", "--config", str(REPLICATE_YAML), "--seconds", "0.5", "--out", str(out)]
    assert cli.main(argv) == 0
    assert "record:" in capsys.readouterr().err
    rec = read_recording(out)
    direct = make_recording(make_config(), None, 0.5)
    assert rec.samples == 500 and rec.cables == 8
    assert rec.metadata["source"] == "sim_plc"
    assert rec.metadata["seed"] == "1" and rec.metadata["effects"] == "none"
    assert_allclose(rec.tension_sensor, direct.tension_sensor, rtol=1e-9)
    assert_allclose(rec.tension_platform, direct.tension_platform, rtol=1e-9)
    assert_allclose(rec.pose, direct.pose, atol=1e-9)
    assert_allclose(rec.mass, direct.mass, rtol=1e-9)


def test_record_seed_gives_another_recording_of_the_same_machine(tmp_path) -> None:
    paths = [tmp_path / "a.csv", tmp_path / "b.csv"]
    for path, seed in zip(paths, ("1", "2"), strict=True):
        argv = [
            "record",
            "--config",
            str(REPLICATE_YAML),
            "--seconds",
            "0.3",
            "--out",
            str(path),
            "--quiet",
            "--seed",
            seed,
        ]
        assert cli.main(argv) == 0
    a, b = (read_recording(p) for p in paths)
    assert (a.metadata["seed"], b.metadata["seed"]) == ("1", "2")
    assert_allclose(a.tension_platform, b.tension_platform, rtol=1e-12)  # same motion here
    noise = a.tension_sensor - b.tension_sensor  # independent noise draws
    assert 0.3 < float(np.std(noise[~np.isnan(noise)])) < 1.5


def test_step_agrees_with_batch_across_chunks() -> None:
    effects = {
        "inertia": {"m_eff_kg": 2.0},
        "eccentricity": {"a_n": 1.0, "phi_rad": 0.3},
        "gain": {"g": 0.01},
        "offset": {"c_n": [2.0, 0, 0, 0, 0, 0, 0, -1.0]},
        "drift": {"k_n_s": 0.1},
        "lowpass": {"tau_s": 0.005},
        "delay": {"d_s": [0.002, 0, 0, 0.0035, 0, 0, 0, 0.01]},
        "viscous": {"c_ns_m": 30.0},
        "presliding": {"sigma_n_m": 800.0},
        "mass_change": {"q_kg_s": 0.5},
    }
    cfg = cyclic_config(effects, noise_std_n=0.5)
    n = 700
    rec = make_recording(cfg, None, n * 0.001)
    plant, image = Plant(cfg, chunk=64), ProcessImage(8)
    out = np.empty((n, 8))
    for k in range(n):
        plant.step(image)
        out[k] = plant.model.reading(plant.counts)
        if k == 200:
            assert image.raw_counts.tolist() == plant.counts.tolist()
            assert image.time_s == pytest.approx(0.2)
            assert_allclose(image.velocity_m_s, rec.velocity[k])
            assert_allclose(image.length_m, rec.length[k])
            assert_allclose(image.pose, rec.pose[k])
    assert image.plc_heartbeat == n
    # the last batch sample uses a one-sided difference for the inertia term
    assert_allclose(out[:-1], rec.tension_sensor[:-1], atol=1e-9)


def test_step_agrees_with_batch_with_the_transmission_effects() -> None:
    """Maxwell-slip elements, cable stretch, backlash, creep and a spring hidden at once:
    the soft PLC's per-cycle plant gives the batch recording's readings."""
    effects = {
        "maxwell_slip": {"sigma_n_m": 5000.0, "w": 0.4},
        "cable_stretch": {"k_n_m": [5000.0, 2e4, 5000.0, 5000.0, 1e4, 5000.0, 5000.0, 3000.0]},
        "backlash": {"width_m": 0.002},
        "sensor_creep": {"c": 0.05, "tau_s": 0.1},
        "spring": {"k_n_m": 20.0, "l0_m": 2.8},
    }
    cfg = cyclic_config(effects, noise_std_n=0.5)
    n = 700
    rec = make_recording(cfg, None, n * 0.001)
    plant, image = Plant(cfg, chunk=64), ProcessImage(8)
    out = np.empty((n, 8))
    for k in range(n):
        plant.step(image)
        out[k] = plant.model.reading(plant.counts)
    assert_allclose(out, rec.tension_sensor, atol=1e-9)
    clean = make_recording(cyclic_config(None, noise_std_n=0.5), None, n * 0.001)
    assert np.nanmax(np.abs(rec.tension_sensor - clean.tension_sensor)) > 1.0


def test_the_streamed_recording_is_the_batch_recording() -> None:
    """``record``'s block-by-block plant (the chain's state and previous sample carried
    from block to block, :func:`gateway.model.chain_runs.run`'s ``previous``) gives the
    batch recording's columns exactly, on the general path (Maxwell-slip, stretch, play)."""
    effects = {
        "maxwell_slip": {"sigma_n_m": 5000.0, "w": 0.4},
        "cable_stretch": {"k_n_m": 5000.0},
        "backlash": {"width_m": 0.002},
    }
    cfg = cyclic_config(effects, noise_std_n=0.5)
    whole = make_recording(cfg, None, 0.9)
    blocks = list(stream_recording(cfg, None, 0.9, chunk=130))
    assert len(blocks) == 7
    for col in ("t", "velocity", "tension_sensor", "tension_platform"):
        got = np.concatenate([getattr(r, col) for r in blocks])
        np.testing.assert_array_equal(got, getattr(whole, col), err_msg=col)


def test_heartbeat_wraps_at_16_bits() -> None:
    plant, image = Plant(make_config()), ProcessImage(8)
    image.plc_heartbeat = 65535
    plant.step(image)
    assert image.plc_heartbeat == 0
    plant.step(image)
    assert image.plc_heartbeat == 1


def test_true_tensions_in_image_are_the_statics() -> None:
    cfg = make_config({"noise_std_n": 0.0})
    plant, image = Plant(cfg), ProcessImage(8)
    plant.step(image)
    rec = make_recording(cfg, None, 0.01)
    assert_allclose(image.true_tension_n, rec.tension_platform[0], atol=1e-9)


@pytest.mark.parametrize(
    ("sim", "match"),
    [
        ({"trajectory": {"bogus": 1}}, r"sim_plc\.trajectory\.bogus: unknown key"),
        ({"noise_std_n": [0.1, 0.2]}, r"sim_plc\.noise_std_n: expected one value per cable"),
        ({"effects": {"viscous": {"c_ns_m": -1.0}}}, r"sim_plc\.effects\.viscous\.c_ns_m"),
        ({"effects": {"warp": {}}}, r"sim_plc\.effects\.warp: unknown effect"),
        ({"effects": {"gain": {"gg": 1}}}, r"sim_plc\.effects\.gain\.gg: unknown parameter"),
        ({"effects": {"gain": {"enabled": 1}}}, r"sim_plc\.effects\.gain\.enabled"),
        ({"friction": {"mu": 0.1}}, r"sim_plc\.friction\.mu: unknown key"),
        ({"trajectory": {"kind": "spiral"}}, r"sim_plc\.trajectory\.kind"),
        ({"period_s": "fast"}, r"sim_plc\.period_s"),
        ({"trajectory": {"kind": "file"}}, r"sim_plc\.trajectory\.file\.path"),
    ],
)
def test_config_errors_name_the_key(sim, match) -> None:
    with pytest.raises(ConfigError, match=match):
        load_sim_config(make_config(sim))


def test_sim_friction_merges_over_the_config_friction() -> None:
    sim = load_sim_config(make_config({"friction": {"sigma_n_m": 900.0}}))
    assert sim.friction.sigma_n_m == 900.0
    assert sim.friction.mu == (0.015, 0.015, 0.015)
    assert sim.tension.max_n == 490.0 and sim.initial_mass_kg == 40.0


def test_infeasible_pose_names_time_and_key() -> None:
    cfg = make_config({"initial_mass_kg": 500.0})
    with pytest.raises(InfeasiblePoseError, match=r"sim_plc\.trajectory: pose .* t = 0\.000 s"):
        make_recording(cfg, None, 0.01)
