"""Each effect is one module that carries its behaviour: the structure, checked.

Code that serves every effect loops over the registry and branches on no effect's name, so
an effect's name stands (as a quoted string) in its own module and, at most, the registry
and the chain's law table. A fourth file naming it is a formula or a table copied out of
its module: this test fails on it.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from gateway.model import effects as fx
from gateway.model.chain import LAWS
from gateway.model.effects.base import STAGES, Effect

ROOT = Path(__file__).resolve().parents[2]
SOURCES = sorted(p for d in ("gateway", "drivers", "sim_plc") for p in (ROOT / d).rglob("*.py"))
LAW_NAMES = set(LAWS)  # a law's name is also a word of the law table (``coulomb``)


def files_naming(name: str) -> list[str]:
    pattern = re.compile(rf"[\"']{re.escape(name)}[\"']")
    return [str(p.relative_to(ROOT)) for p in SOURCES if pattern.search(p.read_text())]


@pytest.mark.parametrize("name", fx.EFFECT_NAMES)
def test_an_effect_is_named_in_at_most_three_source_files(name: str) -> None:
    files = files_naming(name)
    module = f"gateway/model/effects/{name}.py"
    if name in LAW_NAMES:  # exempt: the law's name is everywhere a chain is built
        return
    assert module in files, f"{name}: its module does not name it"
    assert len(files) <= 3, f"{name} is named in {len(files)} files: {files}"


def test_the_registry_holds_one_object_per_module() -> None:
    modules = sorted(
        p.stem
        for p in (ROOT / "gateway/model/effects").glob("*.py")
        if p.stem not in ("__init__", "base", "forms", "registry")
    )
    assert sorted(fx.EFFECT_NAMES) == modules
    for name, e in fx.REGISTRY.items():
        assert isinstance(e, Effect) and e.name == name
        assert e.stage in STAGES


@pytest.mark.parametrize("name", fx.EFFECT_NAMES)
def test_every_effect_carries_its_behaviour(name: str) -> None:
    """Parameters with units and an absent value, the forms of its stage, its online
    decision with a reason, what a finding says and plots, an example size."""
    e = fx.REGISTRY[name]
    assert e.params and all(p.unit for p in e.params)
    assert e.physics and e.look and e.plot and e.online.how
    assert set(e.example) == set(e.param_names) or set(e.example) <= set(e.param_names)
    assert e.example, name
    cls = type(e)
    overrides = {
        k
        for k in ("apply_chain", "forward", "inverse", "stepper", "mass_delta")
        if getattr(cls, k) is not getattr(Effect, k)
    }
    want = {
        "statics": {"mass_delta"},
        "chain": {"apply_chain"},
        "path": {"forward", "inverse", "stepper"},
        "sensor": {"forward", "inverse", "stepper"},
    }[e.stage]
    assert overrides == want, (name, overrides)
    if e.online.compensable and e.stage in ("path", "sensor"):
        assert e.online_kernel is not None, name
    if not e.online.compensable:
        assert e.online_kernel is None and len(e.online.how) > 20, name


@pytest.mark.parametrize("name", fx.EFFECT_NAMES)
def test_internal_and_report_parameters_round_trip(name: str) -> None:
    e = fx.REGISTRY[name]
    values = {p: float(v) for p, v in e.example.items()}
    theta = e.internal({**{p.name: p.default for p in e.params}, **values})
    back = e.report(theta)
    for p, v in values.items():
        assert back[p] == pytest.approx(v, rel=1e-12), (name, p)


@pytest.mark.parametrize("name", fx.EFFECT_NAMES)
def test_the_example_is_admissible_and_present(name: str) -> None:
    from gateway.core.config import FrictionConfig

    e = fx.REGISTRY[name]
    values = fx.effect_values({name: dict(e.example)}, 4)[name]
    assert np.all(e.present(values, FrictionConfig()))
    for prm in e.params:
        low = prm.truth_low
        if low is not None:
            assert np.all(values[prm.name] >= low)


def test_the_report_schema_names_every_registered_effect() -> None:
    """The report's schema (docs/diagnose-report.schema.json, a contract) lists exactly the
    registered effects: a new effect module is not done until its name is in it."""
    import json

    schema = json.loads((ROOT / "docs/diagnose-report.schema.json").read_text())
    enum = schema["properties"]["findings"]["items"]["properties"]["effect"]["enum"]
    assert enum == list(fx.EFFECT_NAMES)


def test_the_scenario_suite_has_a_tolerance_for_every_parameter() -> None:
    from evaluation.scenarios import tolerance

    for name, e in fx.REGISTRY.items():
        for p in e.param_names:
            assert tolerance(name, p) is not None, (name, p)
