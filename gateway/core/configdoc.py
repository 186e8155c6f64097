"""The configuration reference (docs/config.md), generated from the config schema.

Every key of :class:`gateway.core.config.Config`, section by section: its type, default,
unit (from the key's suffix, the project's naming rule: ``_s`` seconds, ``_n`` newtons,
``_ns_m`` N s/m ...), range (the dataclass' ``RANGES``) and one line of meaning (the
comment beside the field, or the comment lines right above it). The schema is the one
place each of these is stated; ``tests/core/test_config_doc.py`` fails when the document
and the schema differ, and when a key has no meaning written beside it.

    python -m gateway.core.configdoc docs/config.md     # write it
    python -m gateway.core.configdoc --check docs/config.md
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import io
import re
import sys
import tokenize
import types
import typing
from pathlib import Path
from typing import Any

UNITS = (  # longest suffix first
    ("_ns_m", "N s/m"),
    ("_n_m", "N/m"),
    ("_m_s2", "m/s²"),
    ("_m_s", "m/s"),
    ("_kg_s", "kg/s"),
    ("_bytes", "bytes"),
    ("_deg", "deg"),
    ("_rad", "rad"),
    ("_kg", "kg"),
    ("_us", "µs"),
    ("_ms", "ms"),
    ("_hz", "Hz"),
    ("_s", "s"),
    ("_n", "N"),
    ("_m", "m"),
)

HEADER = """# Configuration reference

Generated from the config schema (`gateway/core/config.py`) by
`python -m gateway.core.configdoc docs/config.md`; `tests/core/test_config_doc.py` fails when
the two differ. One YAML file; every section may be left out except `geometry` (defaults
apply); an unknown key, a duplicate key or a value out of range stops the program with the
file and the dotted key, exit status 2. `config/default.yaml` is the commented reference;
`cdpr-gateway check --config FILE` validates a file without touching the PLC.

Units come from the key's suffix: `_s` seconds, `_n` newtons, `_m` metres, `_kg`, `_deg`,
`_rad`, `_m_s` m/s, `_ns_m` N s/m, `_n_m` N/m, `_us` microseconds. Ranges are inclusive.
"""


def unit_of(name: str) -> str:
    for suffix, unit in UNITS:
        if name.endswith(suffix):
            return unit
    return ""


def field_comments(cls: type) -> dict[str, str]:
    """Per field of ``cls``: its trailing comment, else the comment lines right above it."""
    try:
        source = inspect.getsource(cls)
    except (OSError, TypeError):
        return {}
    out: dict[str, str] = {}
    above: list[str] = []
    lines = source.splitlines()
    comments: dict[int, str] = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            comments[tok.start[0]] = tok.string.lstrip("#").strip()
    for i, line in enumerate(lines, start=1):
        stripped = line.strip()
        if stripped.startswith("#"):
            above.append(comments.get(i, ""))
            continue
        m = re.match(r"\s{4}([a-z_][a-z0-9_]*)\s*:", line)
        if m and not stripped.startswith(("def ", "return")):
            trailing = comments.get(i)
            out[m.group(1)] = trailing if trailing else " ".join(above)
        above = []
    return out


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin is typing.Literal:
        return " \\| ".join(f"`{a}`" for a in args)
    if origin in (typing.Union, types.UnionType):
        names = [_type_name(a) for a in args if a is not type(None)]
        return " \\| ".join(names) + (" or null" if type(None) in args else "")
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return f"list of {_type_name(args[0])}"
        return f"list of {len(args)} {_type_name(args[0])}"
    if origin is dict:
        return "mapping"
    if dataclasses.is_dataclass(tp):
        return "mapping"
    return {float: "number", int: "integer", bool: "boolean", str: "string"}.get(tp, str(tp))


def _default(f: dataclasses.Field) -> str:
    if f.default is not dataclasses.MISSING:
        value = f.default
    elif f.default_factory is not dataclasses.MISSING:
        value = f.default_factory()
    else:
        return "required"
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, tuple) and value and dataclasses.is_dataclass(value[0]):
        return "see `config/default.yaml`"
    if isinstance(value, tuple):
        text = "[" + ", ".join(_default_value(v) for v in value) + "]"
        return text if len(text) <= 40 else "see `config/default.yaml`"
    if isinstance(value, dict):
        return "{}"
    return _default_value(value)


def _default_value(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, str):
        return f"`{v}`"
    return str(v)


def _range(cls: type, name: str) -> str:
    rng = getattr(cls, "RANGES", {}).get(name)
    if rng is None:
        return ""
    lo, hi = rng
    return f"{_default_value(lo)} .. {_default_value(hi)}"


def _section_type(tp: Any) -> type | None:
    """The dataclass a field holds (also through ``X | None``), or None for a leaf."""
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        return tp
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        inner = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(inner) == 1 and dataclasses.is_dataclass(inner[0]):
            return inner[0]  # type: ignore[return-value]
    return None


def _first_paragraph(cls: type) -> str:
    doc = inspect.getdoc(cls) or ""
    if doc.startswith(cls.__name__ + "("):  # dataclass' generated signature: no docstring
        return ""
    text = " ".join(doc.split("\n\n", 1)[0].split())
    return re.sub(r":\w+:`~?([^`]+)`", r"`\1`", text).replace("``", "`")  # reST -> Markdown


@dataclasses.dataclass
class Row:
    key: str
    type: str
    default: str
    unit: str
    range: str
    meaning: str


@dataclasses.dataclass
class Section:
    key: str
    intro: str
    rows: list[Row]


def sections(root: type | None = None, prefix: str = "") -> list[Section]:
    """Every section of the schema below ``root`` (default :class:`Config`), in file order."""
    if root is None:
        from gateway.core.config import Config

        root = Config
    hints = typing.get_type_hints(root)
    notes = field_comments(root)
    here = Section(prefix or "top level", "" if not prefix else _first_paragraph(root), [])
    below: list[Section] = []
    for f in dataclasses.fields(root):
        if f.metadata.get("file") is False:
            continue
        tp = hints[f.name]
        sub = _section_type(tp)
        key = f"{prefix}.{f.name}" if prefix else f.name
        if sub is not None and _is_table(sub):
            below.extend(_table_sections(sub, key))
            continue
        if sub is not None:
            below.extend(sections(sub, key))
            continue
        meaning = notes.get(f.name, "")
        if sub is None and typing.get_origin(tp) is tuple:
            inner = typing.get_args(tp)[0]
            if dataclasses.is_dataclass(inner):  # a list of mappings: its keys as one line
                sub_notes = field_comments(inner)  # type: ignore[arg-type]
                keys = ", ".join(
                    f"`{g.name}`" + (f" ({sub_notes[g.name]})" if sub_notes.get(g.name) else "")
                    for g in dataclasses.fields(inner)
                )
                meaning = f"{meaning} Each: {keys}".strip()
        here.rows.append(
            Row(
                key=f"`{key}`",
                type=_type_name(tp),
                default=_default(f),
                unit=unit_of(f.name),
                range=_range(root, f.name),
                meaning=meaning,
            )
        )
    if not prefix:  # the top level's own keys (sim_plc) after the sections
        return below + ([here] if here.rows else [])
    return ([here] if here.rows else []) + below


def _is_table(cls: type) -> bool:
    """A mapping whose every entry is the same kind of block (the register map)."""
    hints = typing.get_type_hints(cls)
    kinds = {_section_type(hints[f.name]) for f in dataclasses.fields(cls)}
    return len(kinds) == 1 and None not in kinds


def _block(value: Any) -> str:
    if value is None:
        return "none"
    text = f"{value.address}, {value.count} x {value.type}"
    return text + (f" ({value.format})" if getattr(value, "format", "plain") != "plain" else "")


def _table_sections(cls: type, key: str) -> list[Section]:
    """One row per entry (its default block), then the block's own keys once."""
    hints = typing.get_type_hints(cls)
    notes = field_comments(cls)
    rows = []
    kind: type | None = None
    for f in dataclasses.fields(cls):
        kind = _section_type(hints[f.name])
        rows.append(
            Row(f"`{key}.{f.name}`", "block", _block(f.default), "", "", notes.get(f.name, ""))
        )
    intro = _first_paragraph(cls) + " Default: first register, count x type."
    out = [Section(key, intro, rows)]
    assert kind is not None
    block = sections(kind, f"{key}.NAME")
    for sec in block:
        sec.intro = _first_paragraph(kind)
    return out + block


def render() -> str:
    out = [HEADER]
    for sec in sections():
        out.append(f"\n## `{sec.key}`\n")
        if sec.intro:
            out.append(f"\n{sec.intro}\n")
        out.append("\n| key | type | default | unit | range | meaning |\n")
        out.append("|---|---|---|---|---|---|\n")
        for r in sec.rows:
            meaning = r.meaning.replace("|", "\\|")
            out.append(f"| {r.key} | {r.type} | {r.default} | {r.unit} | {r.range} | {meaning} |\n")
    return "".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m gateway.core.configdoc")
    parser.add_argument("path", type=Path, help="docs/config.md")
    parser.add_argument("--check", action="store_true", help="compare; exit 1 when they differ")
    args = parser.parse_args(argv)
    text = render()
    if args.check:
        same = args.path.is_file() and args.path.read_text(encoding="utf-8") == text
        if not same:
            print(f"{args.path}: differs from the config schema; regenerate it", file=sys.stderr)
        return 0 if same else 1
    args.path.write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
