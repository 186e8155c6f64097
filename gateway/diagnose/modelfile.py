"""The fitted effects written into a copy of the model file, byte for byte elsewhere.

:func:`with_effects` returns the model file's text with only its ``friction.effects``
entry replaced (or added): comments, key order, flow lists and spacing everywhere else
stay as they were. It finds the entry with the YAML parser's own node positions
(``yaml.compose``: every node knows where it starts and ends in the text), so the file is
never re-emitted. Why not a round-trip YAML library (ruamel.yaml): it re-emits the whole
file and normalises what it keeps (spacing inside flow lists such as ``[ 2.0,  1.5, 3.0]``,
indentation), so the rest is not byte for byte; a separate model file included by path
would change the config's schema and make ``run --config FITTED.yaml`` a two-file affair.

Where the entry goes: the ``friction:`` mapping of a full config (appended as a new
``friction:`` section when the file has none), or the top level of a model file that is
a ``friction:`` mapping alone. A block mapping gets a block entry at the mapping's
indentation, with ``notes`` as comment lines above it; a flow mapping (``{...}``) gets a
flow entry (no room for comments there: ``notes`` are left out).
"""

from __future__ import annotations

from typing import Any

import yaml

MARK = "# fitted by cdpr-gateway diagnose --write-model"  # first line of our comment block


def _end(node: yaml.Node) -> int:
    """Text index just after the last character that belongs to ``node``."""
    if isinstance(node, yaml.MappingNode) and node.value and not node.flow_style:
        return _end(node.value[-1][1])
    if isinstance(node, yaml.SequenceNode) and node.value and not node.flow_style:
        return _end(node.value[-1])
    return node.end_mark.index


def _line_end(text: str, index: int) -> int:
    """Index just after the newline of the line holding ``index`` (or the text's end)."""
    nl = text.find("\n", index)
    return len(text) if nl < 0 else nl + 1


def _line_start(text: str, index: int) -> int:
    return text.rfind("\n", 0, index) + 1


def _block(effects: dict[str, Any], indent: int, notes: list[str]) -> str:
    pad = " " * indent
    body = yaml.safe_dump({"effects": effects}, sort_keys=False, default_flow_style=None)
    lines = [f"{pad}{MARK}", *(f"{pad}# {n}" for n in notes)]
    lines += [pad + line for line in body.splitlines()]
    return "\n".join(lines) + "\n"


def _flow(effects: dict[str, Any]) -> str:
    return yaml.safe_dump(effects, default_flow_style=True, width=1 << 16).strip()


def _target(root: yaml.MappingNode) -> yaml.MappingNode | None:
    """The mapping that holds ``effects``; None when a full config has no (or an empty)
    ``friction:`` section."""
    keys = {k.value: v for k, v in root.value}
    if "friction" in keys:
        node = keys["friction"]
        return node if isinstance(node, yaml.MappingNode) and node.value else None
    return root if "geometry" not in keys else None


def with_effects(text: str, effects: dict[str, Any], notes: list[str] | None = None) -> str:
    """``text`` (a model file or full config) with ``friction.effects`` set to ``effects``
    (plain YAML types) and nothing else changed; unchanged text for no effects where the
    file has none."""
    notes = notes or []
    root = yaml.compose(text)
    if not isinstance(root, yaml.MappingNode):
        raise ValueError("the model file is not a mapping")
    mapping = _target(root)
    if mapping is None:  # a full config without friction: (or with an empty one)
        if not effects:
            return text
        keys = {k.value: (k, v) for k, v in root.value}
        if "friction" in keys:  # 'friction:' with nothing (or {}) after it: replace the value
            key, value = keys["friction"]
            start, end = _line_start(text, key.start_mark.index), _line_end(text, _end(value))
            return text[:start] + "friction:\n" + _block(effects, 2, notes) + text[end:]
        sep = "" if text.endswith("\n") or not text else "\n"
        return text + sep + "friction:\n" + _block(effects, 2, notes)
    entries = {k.value: (k, v) for k, v in mapping.value}
    if mapping.flow_style:
        if "effects" in entries:
            value = entries["effects"][1]
            return (
                text[: value.start_mark.index] + _flow(effects or {}) + text[value.end_mark.index :]
            )
        if not effects:
            return text
        close = mapping.end_mark.index - 1  # the '}'
        return text[:close] + f", effects: {_flow(effects)}" + text[close:]
    indent = mapping.value[0][0].start_mark.column
    if "effects" in entries:
        key, value = entries["effects"]
        start = probe = _line_start(text, key.start_mark.index)
        while probe > 0:  # our own comment block above the key goes with it
            above = _line_start(text, probe - 1)
            line = text[above:probe].strip()
            if not line.startswith("#"):
                break
            probe = above
            if line == MARK:
                start = above
                break
        end = _line_end(text, _end(value))
        block = _block(effects, indent, notes) if effects else ""
        return text[:start] + block + text[end:]
    if not effects:
        return text
    at = _line_end(text, _end(mapping.value[-1][1]))
    sep = "" if text[:at].endswith("\n") else "\n"
    return text[:at] + sep + _block(effects, indent, notes) + text[at:]
