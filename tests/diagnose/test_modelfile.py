"""``--write-model`` keeps the model file byte for byte except ``friction.effects``: a
property over generated layouts (comments, flow and block friction, an effects entry already
there or not, a friction-only file, no friction section) and generated effects."""

from __future__ import annotations

import math
import re

import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.core.config import DEFAULT_CONFIG_PATH, load_friction
from gateway.diagnose.modelfile import MARK, with_effects
from gateway.diagnose.writemodel import write_model

DEFAULT = DEFAULT_CONFIG_PATH.read_text()
FRICTION_BLOCK = re.search(r"(?ms)^friction:.*?(?=^loop:)", DEFAULT).group(0)

numbers = st.floats(-5, 5, allow_nan=False).map(lambda x: round(x, 4))
effects_st = st.dictionaries(
    st.sampled_from(["viscous", "offset", "gain", "inertia"]),
    st.dictionaries(
        st.sampled_from(["c_ns_m", "c_n", "g", "m_eff_kg"]),
        numbers | st.lists(numbers, min_size=8, max_size=8),
        min_size=1,
        max_size=2,
    ),
    max_size=3,
)


def layouts(old_effects: dict, comment: str) -> dict[str, str]:
    """The same model in several layouts, each with ``old_effects`` in it (if any)."""
    block = FRICTION_BLOCK
    flow = (
        "friction: {model: dahl, sigma_n_m: 500.0"
        + (
            f", effects: {yaml.safe_dump(old_effects, default_flow_style=True).strip()}"
            if old_effects
            else ""
        )
        + "}  # flow\n\n"
    )
    if old_effects:
        dumped = yaml.safe_dump({"effects": old_effects}, default_flow_style=None)
        block = block.rstrip("\n") + "\n" + "".join(f"  {ln}\n" for ln in dumped.splitlines())
        block += f"  # {comment}\n\n"
    without = re.sub(r"(?ms)^friction:.*?(?=^loop:)", "", DEFAULT)
    return {
        "block": DEFAULT.replace(FRICTION_BLOCK, block).replace("# cdpr-gateway", f"# {comment}"),
        "flow": DEFAULT.replace(FRICTION_BLOCK, flow),
        "friction only": block.replace("friction:", f"# {comment}\nfriction:"),
        "top level": "# a friction mapping alone\n"
        + "".join(ln[2:] + "\n" for ln in block.splitlines()[1:] if ln.startswith("  ")),
        "no friction": without,
    }


def unchanged_outside(old: str, new: str) -> str:
    """The text of ``old`` that ``new`` changed (between their common prefix and suffix)."""
    p = 0
    while p < min(len(old), len(new)) and old[p] == new[p]:
        p += 1
    s = 0
    while s < min(len(old), len(new)) - p and old[-1 - s] == new[-1 - s]:
        s += 1
    return old[p : len(old) - s]


def effects_of(text: str) -> dict:
    data = yaml.safe_load(text)
    friction = data.get("friction", data if "geometry" not in data else {}) or {}
    return friction.get("effects", {})


def same(a, b) -> bool:
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(map(same, a, b))
    return math.isclose(a, b) if isinstance(a, float) else a == b


@settings(max_examples=25, deadline=None)
@given(
    old=effects_st,
    new=effects_st,
    comment=st.sampled_from(["note", "x: y # z", "é"]),
    notes=st.lists(st.sampled_from(["clamped: a", "folded: b"]), max_size=2),
)
def test_only_friction_effects_changes(old, new, comment, notes) -> None:
    for name, text in layouts(old, comment).items():
        if name == "no friction" and old:
            continue
        out = with_effects(text, new, notes)
        assert same(effects_of(out), new), name
        rest_old, rest_new = yaml.safe_load(text), yaml.safe_load(out)
        for data in (rest_old, rest_new):  # everything else parses the same
            (data.get("friction") if "friction" in data else data).pop("effects", None)
            if "friction" in data and not data["friction"]:
                data.pop("friction")
        if name != "no friction" or not new:
            assert rest_old == rest_new, name
        changed = unchanged_outside(text, out)
        if not old:  # nothing to replace: the new entry is inserted, not a byte else moves
            assert changed == "", (name, changed)
        else:  # what changed of the old text lies in the old effects entry, nothing else
            assert all(
                k not in changed for k in ("model:", "sigma_n_m", "pulleys", "loop:", "# flow")
            ), (name, changed)
        if new and name != "flow":
            assert MARK in out and all(f"# {n}" in out for n in notes), name
        assert with_effects(out, new, notes) == out, name  # written twice: the same file


def test_write_model_keeps_the_default_config_byte_for_byte(tmp_path) -> None:
    report = {
        "cables": 8,
        "findings": [
            {"effect": "viscous", "cables": list(range(1, 9)), "parameters": {"c_ns_m": [24.9] * 8}}
        ],
    }
    out = tmp_path / "fitted.yaml"
    write_model(out, DEFAULT_CONFIG_PATH, load_friction(DEFAULT_CONFIG_PATH), report)
    text = out.read_text()
    assert unchanged_outside(DEFAULT, text) == ""  # 91 -> 133 lines before: comments lost
    assert len(text.splitlines()) <= len(DEFAULT.splitlines()) + 6
    assert load_friction(out).effects == {"viscous": {"c_ns_m": 24.9}}
