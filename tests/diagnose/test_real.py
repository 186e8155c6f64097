"""Real recordings (EMPS, the da Vinci transmission): the converters, the least-squares
baseline, and the blind diagnosis against the published figures and the baseline.

The datasets are read where they lie (``$REAL_DATA``, default the shared data directory
next to the checkout) and never copied into the project; without them the tests that read
them are skipped (a fresh CI machine has none), the baseline's own test still runs.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest

from evaluation import baseline, realdata, realsuite
from gateway.recordings.reader import Recording

DATA = Path(
    os.environ.get("REAL_DATA", Path(__file__).resolve().parents[3] / "shared" / "data" / "real")
)
needs_data = pytest.mark.skipif(
    not (DATA / "emps").is_dir() or not (DATA / "davinci").is_dir(),
    reason=f"no real recordings under {DATA} (set REAL_DATA)",
)


@needs_data
def test_emps_converts_to_minus_the_motor_force_of_a_cart_without_load():
    """Independent of the diagnosis: plain least squares of the converted recording's
    ``-T_s = m a + c v + f0 sgn(v) + offset`` reproduces the published identification."""
    rec = realdata.emps(DATA)
    assert rec.cables == 1 and rec.samples == 24841
    assert np.all(rec.tension_platform == 0.0)
    v = rec.velocity[:, 0]
    a = np.gradient(v, rec.t)
    x = np.column_stack([a, v, np.sign(v), np.ones_like(v)])[100:-100]
    theta, *_ = np.linalg.lstsq(x, -rec.tension_sensor[100:-100, 0], rcond=None)
    pub = realdata.EMPS_PUBLISHED
    for got, key in zip(theta, ("m_eff_kg", "c_ns_m", "f0_n", "offset_n"), strict=True):
        assert got == pytest.approx(pub[key], rel=0.02), key


@needs_data
def test_davinci_trials_convert_and_join():
    one = realdata.davinci_trial(DATA, realdata.L4, "01")
    assert one.samples > 19000 and one.cables == 1
    cut = realdata.davinci_trial(DATA, realdata.L4, "07")
    assert cut.t[-1] < 10.0  # the servo upset after 17.25 s is left out
    # the friction opposes the motion: T_s - T_p falls with the velocity's sign
    d = (one.tension_sensor - one.tension_platform)[:, 0]
    assert np.corrcoef(d, np.sign(one.velocity[:, 0]))[0, 1] < -0.3
    joined = realdata.join([one, cut], "two")
    segs = realdata.segments(joined.t)
    assert [s.stop - s.start for s in segs] == [one.samples, cut.samples]
    assert np.all(np.diff(joined.t) > 0)
    keep = realdata.scored(joined.t)
    assert not keep[0] and keep[segs[0].stop - 1] and not keep[segs[1].start]


def _synthetic(theta: np.ndarray, seconds: float, seed: int) -> Recording:
    """Two trials of a sine stroke under a varying load, read by the baseline's own model
    with ``theta`` plus 0.05 N of noise."""
    rng = np.random.default_rng(seed)
    trials = []
    for k in range(2):
        t = np.arange(0.0, seconds, 1e-3)
        x = 0.0026 * np.sin(2 * math.pi * (0.2 + 0.1 * k) * t)
        v = np.gradient(x, t)
        tp = 8.0 + 5.0 * np.sin(2 * math.pi * 0.13 * t + k)
        trials.append(
            Recording(
                t=t,
                velocity=v[:, None],
                tension_sensor=tp[:, None],
                tension_platform=tp[:, None],
                length=x[:, None],
            )
        )
    rec = realdata.join(trials, "synthetic")
    ts = baseline.predict(theta, rec) + rng.normal(0.0, 0.05, rec.samples)
    rec.tension_sensor[:, 0] = ts
    return rec


def test_the_baseline_recovers_its_own_parameters():
    """The least-squares baseline fitted on recordings of its own model finds its
    parameters (so a comparison with it measures the diagnosis, not a broken fit)."""
    truth = np.array([0.05, 0.2, 1.5, 4.8, 30.0, 400.0, -0.5])
    rec = _synthetic(truth, 12.0, seed=3)
    got = baseline.fit(rec)
    want = dict(zip(baseline.NAMES, truth, strict=True))
    values = dict(zip(baseline.NAMES, got.theta, strict=True))
    for name in ("g", "mu", "f0_n", "c_ns_m", "k_n_m"):
        assert values[name] == pytest.approx(want[name], rel=0.1, abs=0.02), name
    assert values["log10_sigma_n_m"] == pytest.approx(want["log10_sigma_n_m"], abs=0.15)
    assert realdata.rmse(rec, baseline.predict(got.theta, rec)[:, None]) < 0.06


@needs_data
@pytest.mark.long
def test_emps_blind_within_the_published_identification():
    """Blank model (no friction law, no pulleys), validated on the pulses recording:
    inertia, viscous and Coulomb within 5/10/10 % of the published values."""
    res = realsuite.run_emps(DATA)
    assert {"inertia", "viscous", "coulomb"} <= set(res["found"])
    for key, tol in realdata.EMPS_TARGETS.items():
        assert res["errors"][key] <= tol, (key, res["got"][key])
    assert res["validation"][1] < 0.2 * res["validation"][0]


@pytest.fixture(scope="module")
def davinci():
    return realsuite.run_davinci(DATA, refits=False)


@needs_data
@pytest.mark.long
def test_davinci_blind_explains_most_of_the_transmission(davinci):
    """Blank model: the diagnosis finds the transmission's friction and lowers the error
    of both validation sets (never fitted) to under a fifth."""
    scored = davinci["scored"]
    assert "coulomb" in davinci["found"]
    for key in ("validation", "other_series"):
        assert scored[key]["tool"] < 0.2 * scored[key]["before"], key


@needs_data
@pytest.mark.long
def test_davinci_block_errors_cover_the_spread_between_the_two_l4_sets(davinci):
    """The issue's uncertainty item: fitted on the 6 validation trials instead, every
    common parameter lies within twice the two fits' combined errors from refits that
    leave out whole trials, while the Jacobian's errors are far too small for Coulomb's
    mu (the spread is a model-form error that each trial's conditions make different)."""
    sets = realdata.davinci_sets(DATA)
    other = realsuite._estimates(
        realsuite._diagnose(sets.validation, realdata.DAVINCI_MODEL, None)["report"]
    )
    rows = realsuite.spread({"fit": davinci["estimates"]["fit"], "validation": other})
    assert {r["effect"] for r in rows} >= {"coulomb"}
    for r in rows:
        (a, b), (ja, jb), (ba, bb) = r["values"], r["jacobian"], r["blocks"]
        assert abs(a - b) <= 2 * math.hypot(ba, bb), r
        if (r["effect"], r["parameter"]) == ("coulomb", "mu"):
            assert abs(a - b) > 5 * math.hypot(ja, jb), r


@needs_data
@pytest.mark.long
def test_davinci_blind_meets_the_issues_baseline(davinci):
    """The issue's target (its engineer's least-squares baseline: 1.64 N on the 6 L_4
    validation trials, 1.44 N on L_2), and on the L_4 validation trials no worse than this
    project's own baseline either (measured: 1.33 N against 1.48 N; L_2 1.24 N against
    1.44 N; docs/diagnose-suite.md)."""
    scored = davinci["scored"]
    for key, target in realdata.DAVINCI_TARGETS_N.items():
        assert scored[key]["tool"] <= target, key
    assert scored["validation"]["tool"] <= scored["validation"]["baseline"]


@needs_data
@pytest.mark.long
@pytest.mark.xfail(
    strict=True,
    reason="open: on L_2 the blind diagnosis reaches 1.24 N, this project's least-squares "
    "baseline (fitted on the same 9 trials) 1.19 N (docs/diagnose-suite.md)",
)
def test_davinci_blind_is_no_worse_than_our_baseline_on_the_other_series(davinci):
    scored = davinci["scored"]
    assert scored["other_series"]["tool"] <= scored["other_series"]["baseline"]


def test_the_spread_table_compares_the_fits_with_both_errors():
    """``realsuite.spread``: the common effects' parameters of several fits, the standard
    deviation between them and each error's root mean square (-1: not computed)."""
    fits = {
        "a": {"coulomb": {"mu": (0.20, 0.001, 0.01)}, "viscous": {"c_ns_m": (5.0, 0.1, 0.2)}},
        "b": {"coulomb": {"mu": (0.22, 0.002, 0.02)}},
        "c": {"coulomb": {"mu": (0.24, -1.0, 0.02)}, "offset": {"c_n": (1.0, 0.1, 0.1)}},
    }
    (row,) = realsuite.spread(fits)
    assert (row["effect"], row["parameter"]) == ("coulomb", "mu")
    assert row["values"] == [0.20, 0.22, 0.24]
    assert row["sd"] == pytest.approx(0.02)
    assert row["rms_jacobian"] == pytest.approx(math.sqrt((0.001**2 + 0.002**2) / 2))
    assert row["rms_blocks"] == pytest.approx(math.sqrt((0.01**2 + 2 * 0.02**2) / 3))
