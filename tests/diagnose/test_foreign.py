"""The diagnosis on recordings it has never seen: made by an independent generator
(:class:`tests.diagnose_helpers.Foreign`), other pulley chains, rates, noise and CSV quirks.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from gateway.cli import main
from gateway.core.config import FrictionConfig, PulleyConfig
from gateway.diagnose.engine import diagnose
from gateway.diagnose.forward import CableData
from gateway.diagnose.prepare import deadband, nominal_from, velocity_noise, warmup_mask
from gateway.recordings.reader import Recording
from tests.diagnose_helpers import Foreign, check_report, generate, model_yaml, write_csv

P1 = ((150.0, 0.03),)
P2 = ((120.0, 0.02), (45.0, 0.02))
P5 = tuple((w, 0.01) for w in (30.0, 60.0, 90.0, 45.0, 20.0))


def _run(fo: Foreign, nominal: str | None = None, pulleys=None) -> dict:
    """Diagnose a foreign recording through the Python API; the report."""
    cols = generate(fo)
    m = fo.cables
    rec = Recording(
        t=cols["t"],
        velocity=np.column_stack([cols[f"velocity_{i}"] for i in range(1, m + 1)]),
        tension_sensor=np.column_stack([cols[f"tension_sensor_{i}"] for i in range(1, m + 1)]),
        tension_platform=np.column_stack([cols[f"tension_platform_{i}"] for i in range(1, m + 1)]),
        source="foreign",
    )
    fr = FrictionConfig(
        model=nominal or fo.model,  # type: ignore[arg-type]
        pulleys=tuple(PulleyConfig(w, mu) for w, mu in (pulleys or fo.pulleys)),
        sigma_n_m=fo.sigma_n_m,
    )
    report = diagnose(rec, fr).report
    check_report(report)
    return report


def _effects(report: dict) -> list[str]:
    return [f["effect"] for f in report["findings"]]


def test_warmup_skips_the_unknown_start_of_the_friction_state():
    """A recording that starts mid-motion: the first few relaxation lengths are not scored."""
    t = np.arange(0.0, 10.0, 1e-3)
    v = np.full(t.size, 0.1)
    d = CableData(t, v, np.full(t.size, 300.0), np.full(t.size, 300.0), 0.0)
    nom = nominal_from(FrictionConfig(sigma_n_m=500.0))
    mask = warmup_mask(d, nom)
    lam = 0.015 * 2 * np.sin(np.radians(45.0))
    expect_x = 4.0 * lam * 300.0 / 500.0  # relaxation lengths of travel, m
    first = int(np.argmax(mask))
    assert first > 0 and mask[first:].all()
    assert d.x[first] == pytest.approx(expect_x, abs=2e-4)
    still = CableData(t, np.zeros(t.size), d.tp, d.ts, 0.0)
    assert warmup_mask(still, nom).sum() >= 0.9 * t.size  # capped at 10 %


def test_warmup_again_after_a_gap_in_the_rows():
    """Rows missing for 0.5 s: how the cable moved (and the tension along the way) is
    unknown, so the friction state after the gap is, as at the start; jitter is no gap."""
    t = np.arange(0.0, 10.0, 4e-3)
    t = t + np.random.default_rng(2).uniform(-8e-4, 8e-4, t.size)  # +-0.8 ms: no gap
    t = t[(t < 5.0) | (t > 5.5)]
    v = np.full(t.size, 0.1)
    d = CableData(t, v, np.full(t.size, 300.0), np.full(t.size, 300.0), 0.0)
    nom = nominal_from(FrictionConfig(sigma_n_m=500.0))
    mask = warmup_mask(d, nom)
    after = int(np.searchsorted(t, 5.5))
    need = 4.0 * 0.015 * 2 * np.sin(np.radians(45.0)) * 300.0 / 500.0  # m of travel
    assert not mask[after] and mask[after - 1]  # the last sample before the gap counts
    back = after + int(np.argmax(mask[after:]))
    assert d.x[back] - d.x[after] == pytest.approx(need, abs=1e-3)
    assert mask[back:].all()
    assert mask[int(np.argmax(mask)) : after].all()  # nothing masked between start and gap


def test_velocity_deadband_only_for_a_noisy_velocity_column():
    rng = np.random.default_rng(0)
    t = np.arange(0.0, 20.0, 4e-3)
    v = 0.1 * np.clip(np.sin(2 * np.pi * 0.2 * t) * 2, -1, 1)
    assert velocity_noise(v) < 1e-6
    np.testing.assert_array_equal(deadband(v), v)
    noisy = v + rng.normal(0, 2e-4, t.size)
    assert velocity_noise(noisy) == pytest.approx(2e-4, rel=0.15)
    db = deadband(noisy)
    assert np.all((db == 0) | (np.abs(db) >= 8e-4))


@pytest.mark.parametrize(
    "fo, nominal",
    [
        # a long recording that starts in mid-motion (friction state not relaxed)
        (Foreign(rate_hz=100, seconds=120), None),
        # a measured velocity logged instead of the setpoint, Coulomb model: sign chatter
        (Foreign(vel_noise=2e-4, model="coulomb"), None),
        # nothing missing, other chains, rates, noise colours
        (Foreign(pulleys=P1, noise="mixed"), None),
        (Foreign(pulleys=P5, rate_hz=5000, seconds=10, fine_hz=20000, noise="hum"), None),
        (Foreign(rig=True, tension=300, noise="mixed", jitter=0.3, gaps=4), None),
        (Foreign(motion="constant", noise="coloured"), None),
        (Foreign(motion="slow", tension=20, noise_n=0.05, noise="quant"), None),
    ],
    ids=["start_mid_motion_120s", "noisy_velocity", "p1", "p5_5khz", "rig", "constant", "slow"],
)
def test_no_finding_when_nothing_is_missing(fo, nominal):
    report = _run(fo, nominal)
    assert _effects(report) == []


@pytest.mark.parametrize(
    "fo, effect, name, value, rel",
    [
        (Foreign(rate_hz=100, effects={"delay": {"d_s": 0.04}}), "delay", "d_s", 0.04, 0.05),
        (Foreign(effects={"lowpass": {"tau_s": 0.08}}), "lowpass", "tau_s", 0.08, 0.05),
        (Foreign(effects={"viscous": {"c_ns_m": 300.0}}), "viscous", "c_ns_m", 300.0, 0.05),
        (Foreign(effects={"offset": {"c_n": -15.0}}), "offset", "c_n", -15.0, 0.03),
        (
            Foreign(tension=2000, noise_n=1.0, effects={"gain": {"g": 0.004}}),
            "gain",
            "g",
            0.004,
            0.1,
        ),
        (
            Foreign(tension=20, noise_n=0.05, effects={"viscous": {"c_ns_m": 2.0}}),
            "viscous",
            "c_ns_m",
            2.0,
            0.1,
        ),
        (
            Foreign(rig=True, tension=150, model="coulomb", effects={"offset": {"c_n": 1.0}}),
            "offset",
            "c_n",
            1.0,
            0.15,
        ),
        (Foreign(sigma_n_m=200.0), "presliding", "sigma_n_m", 200.0, 0.1),
        (Foreign(noise="hum", effects={"offset": {"c_n": 1.0}}), "offset", "c_n", 1.0, 0.1),
        (Foreign(t0=1.7e9, effects={"drift": {"k_n_s": 0.05}}), "drift", "k_n_s", 0.05, 0.1),
    ],
    ids=[
        "delay40ms_100hz",
        "lowpass80ms",
        "viscous300",
        "offset-15",
        "gain_2kN",
        "viscous_20N",
        "rig_coulomb_offset",
        "presliding_vs_coulomb_nominal",
        "offset_hum",
        "drift_epoch",
    ],
)
def test_effect_outside_the_suite_is_named_and_fitted(fo, effect, name, value, rel):
    nominal = "coulomb" if effect == "presliding" else None
    report = _run(fo, nominal)
    assert _effects(report) == [effect]
    got = report["findings"][0]["parameters"][name][0]
    assert got == pytest.approx(value, rel=rel)
    assert report["final"]["holdout_rmse_n"] < report["baseline"]["rmse_n"]


@pytest.mark.slow
def test_eccentricity_of_a_large_pulley_and_five_pulley_delay():
    ecc = {"eccentricity": {"a_n": 2.0, "r_m": 0.2, "phi_rad": 1.0}}
    report = _run(Foreign(seconds=60, effects=ecc))
    assert _effects(report) == ["eccentricity"]
    assert report["findings"][0]["parameters"]["r_m"][0] == pytest.approx(0.2, rel=0.05)
    report = _run(Foreign(pulleys=P5, cables=2, effects={"delay": {"d_s": 0.01}}))
    assert _effects(report) == ["delay"]
    assert report["findings"][0]["cables"] == [1, 2]


def test_cli_reads_a_foreign_csv_with_quirks(tmp_path):
    """Metadata, shuffled and unknown columns, CRLF, scientific notation, gzip, blanks."""
    fo = Foreign(effects={"delay": {"d_s": 0.02}}, blanks=30, pulleys=P2)
    rec = write_csv(tmp_path / "rec.csv.gz", generate(fo), quirks=True)
    model = tmp_path / "model.yaml"
    model.write_text(model_yaml(P2, "dahl", sigma=fo.sigma_n_m), encoding="utf-8")
    out = tmp_path / "r.json"
    assert main(["diagnose", str(rec), "--model", str(model), "--json", str(out), "--quiet"]) == 0
    report = json.loads(out.read_text())
    check_report(report)
    assert report["skipped_rows"] == 30
    assert _effects(report) == ["delay"]
    assert report["findings"][0]["parameters"]["d_s"][0] == pytest.approx(0.02, rel=0.1)


def test_report_says_when_a_mismatch_outside_the_candidates_remains(tmp_path):
    """High loads and a quiet sensor: the generator's Dahl chain (explicit, its state clipped
    to the Coulomb level when the load drops at rest) differs from the nominal one in ways
    no candidate holds. No finding, but the report says that the residual left is far above
    the noise instead of implying that the model is right."""
    fo = Foreign(tension=2000, noise_n=0.1)
    report = _run(fo)
    assert _effects(report) == []
    fin = report["final"]
    assert fin["noise_n"] == pytest.approx(0.1, rel=0.3)
    assert fin["unexplained_n"] > 5 * fin["noise_n"]
    clean = _run(Foreign(noise_n=0.3, model="coulomb"))
    assert clean["final"]["unexplained_n"] < 2 * clean["final"]["noise_n"]


def test_summary_mentions_unexplained_residual():
    from types import SimpleNamespace

    from gateway.diagnose.plots import summary

    rep = {
        "cables": 1,
        "samples": 10,
        "baseline": {"rmse_n": 3.0},
        "final": {"rmse_n": 3.0, "holdout_rmse_n": 3.0, "noise_n": 0.1, "unexplained_n": 2.99},
        "findings": [],
        "regime_shares": {},
        "mismatch": [],
    }
    text = summary(SimpleNamespace(report=rep), "x.csv")  # type: ignore[arg-type]
    assert "none of the candidate effects explains" in text
    rep["final"] = {**rep["final"], "holdout_rmse_n": 0.1, "unexplained_n": 0.0}
    assert "none of the candidate effects explains" not in summary(
        SimpleNamespace(report=rep), "x.csv"
    )  # type: ignore[arg-type]


def test_screen_frees_the_kept_linear_parameters():
    """A drift screened on top of an offset that holds the drift's mean: with the offset's
    linear part free the pair is recovered exactly (noise-free), not a weakened drift."""
    from gateway.diagnose.fit import linear_refit, spec_for
    from gateway.diagnose.forward import Forward

    t = np.arange(0.0, 30.0, 0.01)
    v = 0.1 * np.sin(2 * np.pi * 0.2 * t)
    tp = 300 + 50 * np.sin(2 * np.pi * 0.05 * t)
    nom = nominal_from(FrictionConfig())
    probe = Forward(CableData(t, v, tp, tp, 0.0), nom)
    truth = probe.predict({"offset": np.array([0.2]), "drift": np.array([0.02])})
    d = CableData(t, v, tp, truth, 0.0)
    fw = Forward(d, nom)
    mask = np.ones(t.size, bool)
    specs = {e: spec_for(e, d, nom, truth, mask) for e in ("offset", "drift")}
    mean_offset = np.array([0.2 + 0.02 * 15.0])  # what an offset alone takes
    out = linear_refit(fw, {"offset": mean_offset, "drift": np.zeros(1)}, specs, mask)
    assert out["offset"][0] == pytest.approx(0.2, abs=1e-6)
    assert out["drift"][0] == pytest.approx(0.02, abs=1e-8)


def _fine_grid(fo: Foreign) -> tuple[np.ndarray, ...]:
    """The generator's fine grid for ``fo`` as it draws it (the sample times first, from
    the same generator): times, setpoint velocity, platform tension, wrap (rad), mu."""
    from tests.diagnose_helpers import _motion, sample_times

    rng = np.random.default_rng(fo.seed)
    fine = np.arange(0.0, fo.seconds, 1.0 / fo.fine_hz)
    sample_times(fo, rng)
    v, tp, _ = _motion(fo, fine, rng)
    wrap = np.radians([p[0] for p in fo.pulleys])
    mu = np.array([p[1] for p in fo.pulleys])
    return fine, v, tp, wrap, mu


def test_generator_dahl_with_f0_agrees_with_the_model_chain():
    """The independent generator's Dahl chain with f0 (explicit Euler, normal force from the
    actual tensions) and the model's (exact step, F_R = lambda T + f0 / n) on the same fine
    grid differ only by the law's second-order detail (~1 % of f0, docs/physics.md), not by
    a non-Dahl clamp |F| <= F_R (which made them differ by 0.3 N RMS, 0.45 N at standstill
    on this motion and biased the fitted f0 by -10 %)."""
    from gateway.model.chain_runs import run
    from gateway.model.chain_schema import ChainParams
    from tests.diagnose_helpers import _chain

    fo = Foreign(seconds=15.0, effects={"coulomb": {"f0_n": 3.0}})
    fine, v, tp, wrap, mu = _fine_grid(fo)
    gen = _chain(tp, v, 1.0 / fo.fine_hz, wrap, mu, 3.0, fo.sigma_n_m, True)
    params = ChainParams.build("dahl", 1, wrap, mu, sigma_n_m=fo.sigma_n_m, f0_n=3.0)
    diff = gen - run(params, "simulate", tp[:, None], v[:, None], fine)[:, 0]
    still = v == 0
    assert still.sum() > 1000 and (~still).sum() > 1000
    assert np.sqrt(np.mean(diff[~still] ** 2)) < 0.08
    assert np.sqrt(np.mean(diff[still] ** 2)) < 0.08


def test_generator_coulomb_load_agrees_with_the_model_chain():
    """The independent generator's load-dependent coefficient (its own law from
    docs/physics.md sec. 4, ``(mu + mu1 |T|) F_N`` exact per pulley) and the model's first
    order ``(lambda + 2 sin(alpha/2) mu1 |T|) |T|`` on the same fine grid, at the sealed
    case's size: the growth's part of the sensor tension agrees to 6 % of itself, and a
    wrong growth (half of it) is far off. They differ by O(mu), not by mu1: ``2 sin(alpha/2)``
    is ``d lambda / d mu`` at mu -> 0; at mu 0.02 the exact one is about ``(1 -+ lambda/2)``
    of it per direction (measured: the generator's growth 0.967x the model's paying out,
    1.036x hauling in, 3.4 % RMS, whether mu1 is 1e-5 or 2e-5)."""
    from gateway.model.chain_runs import run
    from gateway.model.chain_schema import ChainParams
    from tests.diagnose_helpers import _chain

    fo = Foreign(seconds=15.0, model="coulomb", tension=300.0)
    fine, v, tp, wrap, mu = _fine_grid(fo)
    mu1 = 2e-5

    def gen(m1: float) -> np.ndarray:
        return _chain(tp, v, 1.0 / fo.fine_hz, wrap, mu, 0.0, fo.sigma_n_m, False, mu1=m1)

    def model(m1: float) -> np.ndarray:
        params = ChainParams.build("coulomb", 1, wrap, mu, mu_load=m1)
        return run(params, "simulate", tp[:, None], v[:, None], fine)[:, 0]

    moving = v != 0
    assert moving.sum() > 1000
    growth_gen = (gen(mu1) - gen(0.0))[moving]
    growth_model = (model(mu1) - model(0.0))[moving]
    size = np.sqrt(np.mean(growth_model**2))
    assert size > 1.0  # the effect is there, N
    assert np.sqrt(np.mean((growth_gen - growth_model) ** 2)) < 0.06 * size
    half = (model(mu1 / 2) - model(0.0))[moving]
    assert np.sqrt(np.mean((growth_gen - half) ** 2)) > 0.3 * size
