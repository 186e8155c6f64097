"""Each effect is one module that carries its behaviour: the structure, checked.

Code that serves every effect loops over the registry and branches on no effect's name, so
an effect's name stands (as a quoted string) in its own module and, at most, the registry
and the chain's law table. A fourth file naming it is a formula or a table copied out of
its module: this test fails on it.

The same for a chain-side effect's parameter columns (:data:`gateway.model.chain_schema.COLUMNS`):
declared once in the chain's schema module, edited by the effects that set them, read by a
few users of the chain; a list of them spelled again (a draft, a builder's keywords, the
chain's kernels or runs) fails.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from gateway.model import chain_schema
from gateway.model import effects as fx
from gateway.model.chain_schema import COLUMNS, LAWS
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


EFFECTS_DIR = "gateway/model/effects/"
CHAIN_MODULE = "gateway/model/chain_schema.py"
"""The one module that declares the columns (the chain's kernels and runs are not it)."""
READERS = 3
"""Files outside the chain's module and the effects package that may read a chain column
(the clock's warm-up bound, the plant's truth, ...)."""


def files_using_field(name: str) -> list[str]:
    """Files spelling ``name`` as a field: an attribute ``.name`` or a keyword ``name=``."""
    pattern = re.compile(rf"\.{re.escape(name)}\b|\b{re.escape(name)}=")
    return [str(p.relative_to(ROOT)) for p in SOURCES if pattern.search(p.read_text())]


@pytest.mark.parametrize("col", [c for c in COLUMNS if c.owner != "nominal"], ids=str)
def test_a_chain_column_is_spelled_by_its_declaration_its_editors_and_few_readers(col) -> None:
    """A column owned by an effect: in the effects package only the modules that edit it
    in the draft (``draft.<name>``) spell it, its owner among them; at most
    :data:`READERS` other files beside the chain's module."""
    assert col.owner in fx.REGISTRY and fx.REGISTRY[col.owner].stage == "chain", col
    assert Path(chain_schema.__file__).resolve() == ROOT / CHAIN_MODULE
    files = files_using_field(col.name)
    editors = {
        f
        for f in files
        if f.startswith(EFFECTS_DIR) and f"draft.{col.name}" in (ROOT / f).read_text()
    }
    assert f"{EFFECTS_DIR}{col.owner}.py" in editors, (col.name, files)
    strays = [f for f in files if f.startswith(EFFECTS_DIR) and f not in editors]
    assert not strays, f"{col.name} spelled again in {strays}"
    others = [f for f in files if not f.startswith(EFFECTS_DIR) and f != CHAIN_MODULE]
    assert len(others) <= READERS, f"{col.name} is read in {len(others)} files: {others}"


def test_every_chain_effect_sets_only_declared_columns() -> None:
    """What a chain effect writes into the draft is a declared column (or the law)."""
    declared = {c.name for c in COLUMNS} | {"law"}
    for name in fx.stage_of("chain"):
        text = (ROOT / f"{EFFECTS_DIR}{name}.py").read_text()
        written = set(re.findall(r"draft\.(\w+)\s*(?:\[[^\]]*\])?\s*=", text))
        assert written and written <= declared, (name, written - declared)


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


def test_the_hand_kept_lists_name_the_registry() -> None:
    """The one check of every list outside the registry that names effects: the report's
    schema (docs/diagnose-report.schema.json, a contract) lists exactly the registered
    effects, in the catalogue's order; the scenario suite (evaluation/scenarios.yaml) has a
    tolerance for every parameter of every effect; each calibrate example
    (config/calibrate/*.yaml) hides registered effects by their parameters' names. A new
    effect module is not done until these name it."""
    import json

    from evaluation.scenarios import tolerance
    from gateway.core.configtypes import read_yaml

    schema = json.loads((ROOT / "docs/diagnose-report.schema.json").read_text())
    enum = schema["properties"]["findings"]["items"]["properties"]["effect"]["enum"]
    assert enum == list(fx.EFFECT_NAMES)
    for name, e in fx.REGISTRY.items():
        for p in e.param_names:
            assert tolerance(name, p) is not None, (name, p)
    examples = sorted((ROOT / "config/calibrate").glob("*.yaml"))
    assert examples
    for path in examples:
        hidden = read_yaml(path)["sim_plc"]["effects"]
        for name, params in hidden.items():
            assert name in fx.REGISTRY, (path.name, name)
            assert set(params) <= set(fx.REGISTRY[name].param_names), (path.name, name)
