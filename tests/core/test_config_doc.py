"""docs/config.md is the config schema, generated (gateway/core/configdoc.py): every key
with its type, default, unit, range and one line of meaning, stated once in the schema."""

from __future__ import annotations

from pathlib import Path

import yaml

from gateway.core import configdoc

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "config.md"


def test_the_document_is_the_schema():
    assert DOC.read_text(encoding="utf-8") == configdoc.render(), (
        "docs/config.md differs from the config schema: "
        "python -m gateway.core.configdoc docs/config.md"
    )


def test_every_key_says_what_it_means():
    rows = [r for s in configdoc.sections() for r in s.rows]
    assert len(rows) > 60
    assert [r.key for r in rows if not r.meaning.strip()] == []


def _keys(data: dict, prefix: str = "") -> set[str]:
    out = set()
    for k, v in data.items():
        key = f"{prefix}.{k}" if prefix else k
        if k == "registers" and isinstance(v, dict):  # each entry is a block (one row)
            out |= {f"{key}.{name}" for name in v}
        elif isinstance(v, dict) and k not in ("sim_plc", "effects"):
            out |= _keys(v, key)
        else:
            out.add(key)
    return out


def test_every_key_the_shipped_configs_use_is_documented():
    documented = {r.key.strip("`") for s in configdoc.sections() for r in s.rows}
    for path in sorted((ROOT / "config").rglob("*.yaml")):
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
        used = _keys(data) - {"sim_plc", "replicate"}
        used = {k for k in used if not k.startswith("replicate.")}
        assert used <= documented, (path.name, sorted(used - documented))


def test_units_follow_the_key_suffix():
    assert configdoc.unit_of("viscous_ns_m") == "N s/m"
    assert configdoc.unit_of("sigma_n_m") == "N/m"
    assert configdoc.unit_of("period_s") == "s"
    assert configdoc.unit_of("max_cable_speed_m_s") == "m/s"
    assert configdoc.unit_of("unit_id") == ""
