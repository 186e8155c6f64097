"""The real-like generator's own physics (tests/reallike.py) and its scorer's baseline; the
suite run through the diagnosis is the ``long`` test at the end."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evaluation import sealing
from tests import reallike as rl
from tests import reallike_cases as rc

SHORT = rl.Run(seed=3, seconds=60.0, dwell_s=(2.0, 6.0))
machines = st.builds(
    rl.Machine,
    cables=st.integers(4, 8),
    mass_kg=st.floats(20.0, 60.0),
    mu_out=st.floats(0.005, 0.05),
    mu_in=st.floats(0.005, 0.05),
    f0_n=st.floats(0.0, 15.0),
    c_ns_m=st.floats(0.0, 250.0),
    sigma_n_m=st.sampled_from([0.0, 1500.0, 5000.0]),
)
FAST = settings(max_examples=8, deadline=None)


@FAST
@given(machines, st.integers(0, 1000))
def test_statics_hold_the_platform_with_positive_tensions(m: rl.Machine, seed: int) -> None:
    tr = rl.simulate(m, rl.Run(seed=seed, seconds=30.0, dwell_s=(1.0, 3.0)))
    d = rl.anchors(m)[None, :, :] - tr.pos[:, None, :]
    u = d / np.linalg.norm(d, axis=2)[:, :, None]
    force = np.einsum("nkj,nk->nj", u, tr.tp)
    need = m.mass_kg * (tr.acc + np.array([0.0, 0.0, rl.G]))
    assert np.abs(force - need).max() < 1e-6 * m.mass_kg * rl.G
    assert tr.tp.min() > 0.0


@FAST
@given(machines, st.integers(0, 1000))
def test_friction_never_exceeds_its_level_and_coulomb_opposes_motion(
    m: rl.Machine, seed: int
) -> None:
    tr = rl.simulate(m, rl.Run(seed=seed, seconds=30.0, dwell_s=(1.0, 3.0)))
    tn = tr.tp - m.c_ns_m * tr.v
    level = max(rl.lambdas(m)) * np.abs(tn) + m.f0_n
    assert np.all(np.abs(tr.friction) <= level.max() + 1e-9)
    # the drive absorbs power: viscous always, Coulomb at every moving sample
    assert np.all((tr.tp - tr.ts) * tr.v >= -1e-9) if m.sigma_n_m == 0 else True
    if m.sigma_n_m == 0:
        assert np.all(tr.friction[tr.v == 0] == 0)


def test_force_held_at_rest_remembers_the_last_direction() -> None:
    m = rl.Machine(f0_n=10.0, sigma_n_m=3000.0)
    tr = rl.simulate(m, SHORT)
    last = np.zeros_like(tr.v)
    for j in range(m.cables):
        nz = np.flatnonzero(tr.v[:, j])
        idx = np.maximum.accumulate(np.where(tr.v[:, j] != 0, np.arange(tr.v.shape[0]), 0))
        last[:, j] = np.sign(tr.v[idx, j])
        last[: nz[0], j] = 0.0
    rest = (tr.v == 0) & (last != 0)
    assert rest.mean() > 0.3  # long standstills under load
    # at rest the state is held, unchanged, with the sign of the last motion (a cable whose
    # speed changes sign just before a stop for less than its relaxation length L / sigma
    # keeps the earlier sign: hence most, not all) and at least f0 / 2
    held = (tr.v[1:] == 0) & (tr.v[:-1] == 0)
    assert np.array_equal(tr.friction[1:][held], tr.friction[:-1][held])
    assert np.mean(np.sign(tr.friction[rest]) == last[rest]) > 0.9
    assert np.mean(np.abs(tr.friction[rest]) > 0.5 * m.f0_n) > 0.9
    both = [np.any(rest & (last > 0)), np.any(rest & (last < 0))]
    assert all(both)
    # the Coulomb law holds nothing at rest
    coul = rl.simulate(rl.Machine(f0_n=10.0), SHORT)
    assert np.all(coul.friction[coul.v == 0] == 0)


@pytest.mark.parametrize("gain, offset", [(-0.06, 4.0), (0.05, -9.0)])
def test_reading_is_the_drive_force_through_the_torque_constant(gain: float, offset: float) -> None:
    m = rl.Machine(f0_n=8.0, c_ns_m=150.0, gain=gain, offset_n=offset, noise_frac=0.15)
    tr = rl.simulate(m, SHORT)
    x = np.column_stack([tr.ts.ravel(), np.ones(tr.ts.size)])
    (scale, zero), *_ = np.linalg.lstsq(x, tr.reading.ravel(), rcond=None)
    assert scale == pytest.approx(1 + gain, abs=1e-12)
    assert zero == pytest.approx(offset, abs=1e-9)
    # the logged noise is noise_frac of the cable's mean load (quantum and blanks aside)
    cols = rl.generate(m, SHORT)
    t = cols["t"]
    for i in range(m.cables):
        clean = np.interp(t, tr.t, tr.reading[:, i])
        sd = np.nanstd(cols[f"tension_sensor_{i + 1}"] - clean)
        assert sd == pytest.approx(m.noise_frac * tr.tp[:, i].mean(), rel=0.15)
        assert np.isnan(cols[f"tension_sensor_{i + 1}"]).sum() == SHORT.blanks
    steps = np.diff(t)
    assert steps.max() > 1.5 and steps.min() > 0  # gaps, and t increases


def test_baseline_spans_coulomb_viscous_offset(tmp_path: Path) -> None:
    """Noise-free, a machine inside the engineer's model is fitted to ~0 (the scorer's
    baseline is a real fit; what is left, 0.2 N, is the Coulomb step at a move's start and
    end sampled at 10 Hz); a gain it lacks leaves an error of several N."""
    inside = rl.Machine(f0_n=9.0, c_ns_m=180.0, offset_n=-6.0, noise_frac=0.0, quantum_n=1e-6)
    runs = [rl.Run(seed=s, seconds=80.0, blanks=0) for s in (1, 2)]
    paths = [rl.write(tmp_path / f"{k}.csv", rl.generate(inside, r)) for k, r in enumerate(runs)]
    assert rc.baseline_rmse([paths[0]], paths[1]) < 0.5
    out = rl.Machine(f0_n=9.0, gain=0.08, noise_frac=0.0, quantum_n=1e-6)
    paths = [rl.write(tmp_path / f"g{k}.csv", rl.generate(out, r)) for k, r in enumerate(runs)]
    assert rc.baseline_rmse([paths[0]], paths[1]) > 2.0


def test_sealed_file_is_the_recorded_draw(tmp_path: Path) -> None:
    sealing.check(Path("docs/diagnose-suite.md"), rc.SEALED_FILE)
    again = tmp_path / "sealed.yaml"
    rc.write_sealed(again, 20261130)
    assert again.read_bytes() == rc.SEALED_FILE.read_bytes()
    for case in rc.sealed_cases():
        assert 4 <= case.machine.cables <= 8 and case.rate_hz in (10, 15, 20, 30, 100)


def test_truth_names_are_catalogue_effects() -> None:
    from gateway.model.effects.registry import REGISTRY

    for case in (*rc.CASES, *rc.sealed_cases()):
        for name, params in case.truth.items():
            assert name in REGISTRY
            assert set(params) <= {p.name for p in REGISTRY[name].params}


def test_scores_round_trip_and_the_table_names_what_was_not_run() -> None:
    """A case scored by one process (``--results``) is the same score when another loads it
    (``--load``); the table counts only what was run and names the rest."""
    case = rc.CASES[1]
    splits = [
        rc.Split([1, 2], 0, {"viscous": [1, 2, 3, 4]}, [], (21.5, 17.9), 17.9, 30.0),
        rc.Split([0, 2], 1, {"viscous": [1, 2, 3, 4]}, [rc.LOSES], (20.0, 18.0), 17.5, 31.0),
    ]
    sc = rc.Score(case, splits, wall=70.0, cpu=65.0)
    again = rc.Score.from_json(sc.to_json(), {case.name: case})
    assert again == sc and not again.passed and again.same_set
    text = rc.table([again], [], "0" * 64, "", ["clean_4", "sealed_1"])
    assert "Not run: clean_4, sealed_1." in text
    assert "0/1 cases passed" in text and "least squares on 1/2 runs" in text
    assert "2+3 / 1" in text and "1+3 / 2" in text


def test_a_missed_parameter_is_named_with_its_truth_and_tolerance() -> None:
    truth = {"viscous": {"c_ns_m": 200.0}, "offset": {"c_n": -8.0}}
    finding = {"effect": "viscous", "parameters": {"c_ns_m": [150.0, 290.0]}}
    assert rc._param_misses(truth, finding) == ["viscous c_ns_m 150..290 (200 +- 60)"]
    assert rc._param_misses(truth, {"effect": "offset", "parameters": {"c_n": [-7.0]}}) == []
    assert rc._param_misses(truth, {"effect": "spring", "parameters": {}}) == []


@pytest.mark.long
@pytest.mark.parametrize(
    "name",
    [
        pytest.param(
            "clean_4",
            marks=pytest.mark.xfail(
                strict=True,
                reason="open since diagnose takes several recordings (the scorer then fits "
                "two): no finding (right), but the engineer's least squares fitted on two "
                "recordings scores 14.7383 N on the third against the nominal model's "
                "14.7387 N (issue 29 item 3: never worse than the baseline)",
            ),
        ),
        "robot4_viscous_offset",
    ],
)
def test_tuning_subset_scores_strictly(name: str) -> None:
    """Two tuning machines through ``cdpr-gateway diagnose`` (one split each): the clean one
    gets no finding, the issue's 4-cable robot its shared viscous term and offset on every
    cable, and both at or below the engineer's least squares on the validation recording."""
    (case,) = [c for c in rc.CASES if c.name == name]
    sc = rc.score(case, splits=1)
    assert sc.passed, [(s.found, s.errors, s.validation, s.baseline) for s in sc.splits]
