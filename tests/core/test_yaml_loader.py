"""The one YAML loader (:func:`gateway.core.configtypes.read_yaml`) means what a file says:
a key given twice at any depth is refused with the file, the line and the dotted key (the
last one silently won: ``heartbeat_timeout_s: 0.1`` then ``30`` disabled the watchdog), and
a number no key can hold is refused in one line naming the key (a 400-digit number gave an
``OverflowError`` traceback, a 5000-digit ``unit_id`` a ``ValueError`` traceback)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gateway.cli import main
from gateway.core.config import DEFAULT_CONFIG_PATH
from gateway.core.configtypes import load_yaml_text, read_yaml
from gateway.errors import ConfigError

DEFAULT_TEXT = DEFAULT_CONFIG_PATH.read_text()


def _check(capsys, path: Path) -> tuple[int, list[str]]:
    status = main(["check", "--config", str(path)])
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err + captured.out
    return status, [ln for ln in captured.err.splitlines() if ln.strip()]


def _insert_after(text: str, anchor: str, line: str) -> str:
    """``text`` with ``line`` inserted after the first line that starts with ``anchor``
    (indentation kept), i.e. a second copy of a key the shipped config already has."""
    lines = text.splitlines(keepends=True)
    for i, ln in enumerate(lines):
        if ln.lstrip().startswith(anchor):
            indent = ln[: len(ln) - len(ln.lstrip())]
            return "".join([*lines[: i + 1], indent + line + "\n", *lines[i + 1 :]])
    raise AssertionError(f"{anchor!r} not in the shipped config")


def _line_of(text: str, anchor: str) -> int:
    return next(i for i, ln in enumerate(text.splitlines(), 1) if ln.lstrip().startswith(anchor))


@pytest.mark.parametrize(
    ("anchor", "extra", "dotted"),
    [
        ("heartbeat_timeout_s:", "heartbeat_timeout_s: 30", "loop.heartbeat_timeout_s"),
        ("port:", "port: 5021", "bus.modbus_tcp.port"),
    ],
)
def test_check_refuses_a_duplicate_key_naming_file_line_and_key(
    tmp_path, capsys, anchor, extra, dotted
) -> None:
    text = _insert_after(DEFAULT_TEXT, anchor, extra)
    path = tmp_path / "config.yaml"
    path.write_text(text)
    status, err = _check(capsys, path)
    first = _line_of(text, anchor)
    assert status == 2 and len(err) == 1, err
    assert f"{path}:{first + 1}: duplicate key '{dotted}' (first at line {first})" in err[0]


def test_check_refuses_a_second_section(tmp_path, capsys) -> None:
    path = tmp_path / "config.yaml"
    path.write_text(DEFAULT_TEXT + "\nloop:\n  heartbeat_timeout_s: 30\n")
    status, err = _check(capsys, path)
    assert status == 2 and len(err) == 1, err
    assert re.search(rf"{re.escape(str(path))}:\d+: duplicate key 'loop' \(first at line ", err[0])


@pytest.mark.parametrize(
    ("key", "number"),
    [
        ("loop.heartbeat_timeout_s", "9" * 400 + ".0"),  # OverflowError before
        ("loop.heartbeat_timeout_s", "9" * 400),  # an int too large for a float
        ("loop.heartbeat_timeout_s", "1" + "0" * 40 + ".0e+300"),  # inf, not a number
        ("bus.modbus_tcp.unit_id", "1" * 5000),  # ValueError (int digit limit) before
        ("bus.modbus_tcp.unit_id", str(2**64)),  # beyond any register
    ],
)
def test_check_refuses_a_number_too_large_naming_the_key(tmp_path, capsys, key, number) -> None:
    data = yaml.safe_load(DEFAULT_TEXT)
    section, _, name = key.rpartition(".")
    node = data
    for part in section.split("."):
        node = node[part]
    node[name] = 0  # placeholder, replaced in the text (PyYAML cannot dump such numbers)
    text = yaml.safe_dump(data, sort_keys=False).replace(f"{name}: 0\n", f"{name}: {number}\n")
    path = tmp_path / "config.yaml"
    path.write_text(text)
    status, err = _check(capsys, path)
    assert status == 2 and len(err) == 1, err
    assert f"'{key}'" in err[0] and "too large" in err[0] and len(err[0]) < 300, err


def test_merge_keys_and_distinct_keys_still_load() -> None:
    text = "a: &x {b: 1, c: 2}\nd:\n  <<: *x\n  b: 3\n'1': s\n1: i\nn: .inf\n"
    assert load_yaml_text(text, "f.yaml") == {
        "a": {"b": 1, "c": 2},
        "d": {"b": 3, "c": 2},
        "1": "s",
        1: "i",
        "n": float("inf"),
    }


def test_every_shipped_yaml_loads(tmp_path) -> None:
    from gateway.core.resources import data_dir

    files = sorted(data_dir().rglob("*.yaml"))
    assert files
    for path in files:
        assert read_yaml(path) == yaml.safe_load(path.read_text()), path


# --- the property: one duplicated key at any depth is refused and named -------------------

KEYS = st.text("abcdefgh_", min_size=1, max_size=6)
LEAVES = st.one_of(st.integers(-1000, 1000), st.booleans(), st.text("xyz", max_size=3))
TREES = st.recursive(
    LEAVES,
    lambda inner: st.one_of(
        st.dictionaries(KEYS, inner, min_size=1, max_size=4),
        st.lists(inner, min_size=1, max_size=3),
    ),
    max_leaves=20,
)
DOCS = st.dictionaries(KEYS, TREES, min_size=1, max_size=4)


def _mappings(node: Any, path: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """The paths of every mapping in ``node``."""
    found: list[tuple[Any, ...]] = []
    if isinstance(node, dict):
        found.append(path)
        for k, v in node.items():
            found += _mappings(v, (*path, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            found += _mappings(v, (*path, i))
    return found


def _dotted(path: tuple[Any, ...]) -> str:
    out = ""
    for p in path:
        out = f"{out}[{p}]" if isinstance(p, int) else (f"{out}.{p}" if out else p)
    return out


def _block(node: Any, indent: int, dup: tuple[tuple[Any, ...], str] | None, path=()) -> list[str]:
    """``node`` as block YAML lines; at the mapping ``dup[0]`` the key ``dup[1]`` is written
    a second time (with a different value) after its first copy."""
    pad = "  " * indent
    if isinstance(node, dict):
        lines: list[str] = []
        for k, v in node.items():
            lines += _entry(pad, f"{k}:", v, indent, dup, (*path, k))
            if dup is not None and dup[0] == path and dup[1] == k:
                lines.append(f"{pad}{k}: again")
        return lines
    lines = []
    for i, v in enumerate(node):
        lines += _entry(pad, "-", v, indent, dup, (*path, i))
    return lines


def _entry(pad: str, head: str, v: Any, indent: int, dup, path) -> list[str]:
    if isinstance(v, dict | list) and v:
        return [f"{pad}{head}", *_block(v, indent + 1, dup, path)]
    return [f"{pad}{head} {yaml.safe_dump(v, default_flow_style=True).strip().splitlines()[0]}"]


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(DOCS, st.data())
def test_one_duplicated_key_at_any_depth_is_refused_and_named(doc, data) -> None:
    clean = "\n".join(_block(doc, 0, None)) + "\n"
    assert load_yaml_text(clean, "gen.yaml") == doc  # the generator writes what it means
    where = data.draw(st.sampled_from(_mappings(doc)))
    mapping = doc
    for p in where:
        mapping = mapping[p]
    key = data.draw(st.sampled_from(sorted(mapping)))
    text = "\n".join(_block(doc, 0, (where, key))) + "\n"
    with pytest.raises(ConfigError) as info:
        load_yaml_text(text, "gen.yaml")
    dotted = _dotted((*where, key))
    message = str(info.value)
    assert "\n" not in message
    assert re.fullmatch(
        rf"gen\.yaml:(\d+): duplicate key '{re.escape(dotted)}' \(first at line (\d+)\)", message
    ), message
    second, first = map(int, re.fullmatch(r"gen\.yaml:(\d+).*line (\d+)\)", message).groups())
    lines = text.splitlines()
    assert lines[second - 1].strip() == f"{key}: again"
    assert lines[first - 1].lstrip().removeprefix("- ").startswith(f"{key}:")
