"""The effects of real cable transmissions hidden by the foreign generator.

:mod:`tests.diagnose_helpers` integrates them from the equations of docs/physics.md (sec.
3, 4), on its own fine grid, without :mod:`gateway.model`: a second reading of the doc. The
diagnosis must name each on every cable with its parameters within the scenario suite's
tolerances: a model that drifted from its doc, or a doc that says something the model does
not do, fails here.
"""

from __future__ import annotations

import pytest

from evaluation.scenarios import tolerance
from tests.diagnose_helpers import Foreign, run_foreign

CASES = {
    "coulomb_directional": {"mu_out": 0.024, "mu_in": 0.017},
    "maxwell_slip": {"sigma_n_m": 8000.0, "w": 0.5},
    "cable_stretch": {"k_n_m": 5000.0},
    "backlash": {"width_m": 0.003},
    "sensor_creep": {"c": 0.05, "tau_s": 0.3},
    "spring": {"k_n_m": 20.0, "l0_m": 0.1},
}
SKIP = {("spring", "l0_m")}
"""The generator's travel starts half a second before its first row (the diagnosis's
travel at that row): a length is off by that travel, the stiffness is not."""


@pytest.mark.long  # ~2-15 s each, 6 effects
@pytest.mark.parametrize("name", list(CASES))
def test_the_foreign_generator_hides_it_and_the_diagnosis_names_it(name: str) -> None:
    truth = CASES[name]
    fo = Foreign(effects={name: truth}, cables=2)
    diag = run_foreign(fo)
    findings = diag.report["findings"]
    assert [f["effect"] for f in findings] == [name]
    assert findings[0]["cables"] == [1, 2]
    mu_mean = sum(mu for _, mu in fo.pulleys) / len(fo.pulleys)
    for param, fitted in findings[0]["parameters"].items():
        if (name, param) in SKIP or param not in truth:
            continue
        kind, limit = tolerance(name, param) or ("", 0.0)
        assert kind in ("rel", "abs", "change"), (name, param)
        for value in fitted:
            err = abs(value - truth[param])
            if kind == "rel":
                err /= abs(truth[param])
            elif kind == "change":  # relative to the change from the pulleys' mean mu
                err /= abs(truth[param] - mu_mean)
            assert err <= limit, (name, param, value, truth[param])
