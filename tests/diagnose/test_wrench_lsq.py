"""The engineer's least squares against the wrench balance (gateway/diagnose/wrench_lsq.py):
``baseline.least_squares`` of the wrench reference, the shape of the platform one
(gateway/diagnose/lsq.py, :func:`lsq.assemble`).

Recordings: tests/diagnose/test_wrench.py's (the soft PLC's plant, closed-form tension
distribution, 0.4 N noise, 250 Hz, 8 cables), short ones here.
"""

from __future__ import annotations

import functools
import math
from dataclasses import replace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.diagnose import wrench, wrench_lsq
from gateway.diagnose.plots import summary
from gateway.diagnose.wrench_report import WrenchDiagnosis
from sim_plc.plant import make_recording
from tests.diagnose.test_wrench import plant_config, wrench_report
from tests.diagnose_helpers import check_report

SECONDS = 6.0
COULOMB_OFFSET = {
    "coulomb": {"f0_n": 1.0},
    "offset": {"c_n": [1.5, 0.0, 0.0, -1.2, 0.0, 1.0, 0.0, 0.0]},
}


@functools.cache
def prepared(effects: str, noise_seed: int = 3) -> wrench.Prepared:
    """A short pose-and-mass recording of ``effects`` (``"clean"`` or ``"coulomb_offset"``)
    prepared as :class:`WrenchReference` prepares it; the motion of seed 3, the sensor noise
    of ``noise_seed``."""
    cfg = plant_config(COULOMB_OFFSET if effects == "coulomb_offset" else {}, 3)
    cfg = replace(cfg, sim_plc=cfg.sim_plc | {"seed": noise_seed})
    rec = replace(make_recording(cfg, None, SECONDS), tension_platform=None)
    return wrench.prepare(rec, cfg, cfg.friction)


def masks(prep: wrench.Prepared) -> tuple[np.ndarray, np.ndarray]:
    """The diagnosis' training samples among its rows and its held-out samples (every
    sample), as :class:`WrenchUnit` and :class:`WrenchReference` make them."""
    train = (prep.blocks[prep.rows] % 2 == 0) & prep.warm[prep.rows]
    return train, (prep.blocks % 2 == 1) & prep.warm


def test_wrench_report_carries_the_least_squares_baseline() -> None:
    """Present, schema-valid, the catalogue scored exactly as the report's ``final`` (force
    residual, held-out samples), and its sentence in the summary."""
    rep = wrench_report("clean")
    check_report(rep)
    ls = rep["baseline"]["least_squares"]
    assert set(ls["fits"]) == {"coulomb_viscous"} and ls["best"] == "coulomb_viscous"
    cv = ls["fits"]["coulomb_viscous"]
    assert set(cv["parameters"]) == set(wrench_lsq.TERMS)
    assert all(len(v) == rep["cables"] for v in cv["parameters"].values())
    assert cv["per_cable_holdout_rmse_n"] == [] and ls["compared_on"] == "holdout"
    assert math.isclose(ls["catalogue"]["holdout_rmse_n"], rep["final"]["holdout_rmse_n"])
    assert ls["beaten"] == (rep["final"]["holdout_rmse_n"] <= cv["holdout_rmse_n"])
    diag = WrenchDiagnosis(rep, np.zeros(1), np.zeros((1, 3)), np.zeros((1, 3)), [], [], [], [])
    assert ls["sentence"] in summary(diag, "clean.csv")


def test_baseline_beats_the_nominal_model_on_a_real_coulomb_and_offset() -> None:
    """Coulomb f0 1 N and offsets on three cables, the nominal model as the catalogue: the
    engineer's fit lowers the held-out force residual below the nominal's, and that of a
    second recording of the same motion (other sensor noise: on another motion of the
    soft PLC, twice as fast, its viscous term, which stands in for the chain's Dahl
    friction, does not carry over); the block says the catalogue does not beat it and
    ranks its terms."""
    prep, vprep = prepared("coulomb_offset"), prepared("coulomb_offset", noise_seed=4)
    train, test = masks(prep)
    r0 = prep.whiten(prep.model.residual({}, rows=prep.rows))
    force = prep.model.residual({})[:, :3]
    vforce = vprep.model.residual({})[:, :3]
    nominal_hold = float(np.sqrt(np.mean(force[test] ** 2)))
    nominal_val = float(np.sqrt(np.mean(vforce**2)))
    ls = wrench_lsq.block(prep, r0, train, test, force, force, (vprep.model, nominal_val))
    check_report_block(ls)
    assert math.isclose(ls["catalogue"]["holdout_rmse_n"], nominal_hold)
    assert math.isclose(ls["catalogue"]["validation_rmse_n"], nominal_val)
    cv = ls["fits"]["coulomb_viscous"]
    assert cv["holdout_rmse_n"] < 0.9 * nominal_hold, (cv["holdout_rmse_n"], nominal_hold)
    assert cv["validation_rmse_n"] < 0.9 * nominal_val, (cv["validation_rmse_n"], nominal_val)
    assert ls["compared_on"] == "validation" and not ls["beaten"] and ls["margin"] < 0
    assert {t["term"] for t in ls["terms"]} == set(wrench_lsq.TERMS)
    assert ls["terms"][0]["rise_n"] > 0 and "does not beat" in ls["sentence"]
    assert "from the Coulomb + viscous + offset fit" in ls["sentence"]


def check_report_block(ls: dict) -> None:
    """``ls`` as a wrench report's ``baseline.least_squares``, through the schema."""
    rep = wrench_report("clean")
    check_report({**rep, "baseline": {**rep["baseline"], "least_squares": ls}})


@given(
    fc=st.lists(st.floats(-3.0, 3.0), min_size=8, max_size=8),
    c=st.lists(st.floats(-40.0, 40.0), min_size=8, max_size=8),
    b=st.lists(st.floats(-5.0, 5.0), min_size=8, max_size=8),
)
@settings(max_examples=15, deadline=None)
def test_the_fit_takes_out_its_own_law(fc, c, b) -> None:
    """A wrench residual made by the baseline's own law (per cable Coulomb, viscous and
    offset through the structure matrix, no noise), whatever the values: the fit takes it
    out on every sample, held out or not (the null space of ``A`` included: what it
    leaves there moves no wrench)."""
    prep = prepared("clean")
    train, _ = masks(prep)
    data = prep.model.data
    law = {"coulomb_n": np.array(fc), "viscous_ns_m": np.array(c), "offset_n": np.array(b)}
    wr = -np.einsum("nim,nm->ni", data.structure(), wrench_lsq._correction(data.v, law))
    fitted = wrench_lsq.fit(prep, prep.whiten(wr[prep.rows]), train)
    ((sse, n),) = wrench_lsq._sums(data, wr[:, :3], None, [fitted])
    scale = float(np.sqrt(np.mean(wr[:, :3] ** 2)))
    assert math.sqrt(sse / n) <= 1e-6 * max(scale, 1e-3), (math.sqrt(sse / n), scale)
