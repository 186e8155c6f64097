"""Every numeric key of the config has a range, and a value outside it is refused with one
line naming the file and the key (``reconnect_min_s: -1``, ``timeout_s: 1e9``,
``connect_timeout_s: -1``, ``sync_period_s: 1e-9``, ``range_n: 1e300`` were accepted).

The test is structural: it walks every dataclass of :class:`gateway.core.config.Config`,
demands a ``RANGES`` entry for each int/float field, and tries a value beyond each bound.
"""

from __future__ import annotations

import copy
import dataclasses
import types
import typing
from collections.abc import Iterator
from typing import Any, get_args, get_origin

import pytest

from gateway.core.config import DEFAULT_CONFIG_PATH, Config, config_from_mapping, load_config
from gateway.core.configtypes import read_yaml
from gateway.errors import ConfigError

Path_ = tuple[str | int, ...]


def _numeric(tp: Any) -> bool:
    if tp in (int, float):
        return True
    if get_origin(tp) in (typing.Union, types.UnionType, tuple):
        return any(_numeric(a) for a in get_args(tp) if a is not Ellipsis)
    return False


def _dataclass_in(tp: Any) -> tuple[type | None, bool]:
    """(the dataclass a field holds, whether in a list)."""
    if dataclasses.is_dataclass(tp):
        return tp, False  # type: ignore[return-value]
    origin = get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        for a in get_args(tp):
            if dataclasses.is_dataclass(a):
                return a, False
    if origin is tuple:
        args = get_args(tp)
        if args and dataclasses.is_dataclass(args[0]):
            return args[0], True
    return None, False


def walk(cls: type, path: Path_ = ()) -> Iterator[tuple[Path_, type, str, Any]]:
    """(path of the field, its class, field name, field type) of every numeric field."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        tp = hints[f.name]
        inner, listed = _dataclass_in(tp)
        if inner is not None:
            yield from walk(inner, (*path, f.name, 0) if listed else (*path, f.name))
        elif _numeric(tp) and tp is not bool:
            yield (*path, f.name), cls, f.name, tp


FIELDS = list(walk(Config))


def test_every_numeric_key_has_a_range() -> None:
    missing = [".".join(map(str, p)) for p, cls, name, _ in FIELDS if name not in cls.RANGES]
    assert missing == []
    assert len(FIELDS) > 60


def _current(cfg: Config, path: Path_) -> Any:
    value: Any = cfg
    for part in path:
        value = value[part] if isinstance(part, int) else getattr(value, part)
    return value


def _set(data: dict, path: Path_, value: Any, cfg: Config) -> None:
    """Set ``path`` in the raw mapping; a section it lacks is filled from ``cfg``."""
    node: Any = data
    for depth, part in enumerate(path[:-1]):
        if isinstance(part, int):
            node = node[part]
            continue
        if not isinstance(node.get(part), dict | list):
            current = _current(cfg, path[: depth + 1])
            node[part] = _plain(dataclasses.asdict(current)) if current is not None else {}
        node = node[part]
    node[path[-1]] = value


def _beyond(low: float, high: float, integer: bool) -> list[float]:
    out = [high * 2 + 1 if high > 0 else high + 1, low - abs(low) - 1]
    return [int(v) if integer else float(v) for v in out]


def _replace_leaf(current: Any, value: float) -> Any:
    """``value`` in place of the first number of ``current`` (nested tuples kept)."""
    if isinstance(current, tuple):
        if not current:
            return [value]
        return [_replace_leaf(current[0], value), *[_plain(c) for c in current[1:]]]
    return value


def _plain(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    return [_plain(c) for c in x] if isinstance(x, tuple | list) else x


CASES = [
    pytest.param(path, cls, name, tp, id=".".join(map(str, path)))
    for path, cls, name, tp in FIELDS
    if name in cls.RANGES
]


@pytest.mark.parametrize(("path", "cls", "name", "tp"), CASES)
def test_a_value_beyond_each_bound_is_refused_naming_the_key(path, cls, name, tp) -> None:
    base = read_yaml(DEFAULT_CONFIG_PATH)
    cfg = load_config()
    low, high = cls.RANGES[name]
    integer = int in (tp, *get_args(tp)) or any(int in get_args(a) for a in get_args(tp))
    key = ".".join(f"[{p}]" if isinstance(p, int) else p for p in path).replace(".[", "[")
    for bad in _beyond(low, high, integer):
        data = copy.deepcopy(base)
        _set(data, path, _replace_leaf(_current(cfg, path), bad), cfg)
        with pytest.raises(ConfigError) as err:
            config_from_mapping(data, "cfg.yaml")
        text = str(err.value)
        assert text.startswith("cfg.yaml: ") and key in text and "\n" not in text, text


@pytest.mark.parametrize(
    ("section", "key", "value"),
    [
        ("bus.modbus_tcp", "reconnect_min_s", -1),
        ("bus.modbus_tcp", "timeout_s", 1e9),
        ("bus.modbus_tcp", "connect_timeout_s", -1),
        ("bus.canopen", "sync_period_s", 1e-9),
        ("sensor", "range_n", 1e300),
    ],
)
def test_the_values_the_hostile_round_slipped_through(section, key, value) -> None:
    data = read_yaml(DEFAULT_CONFIG_PATH)
    node = data
    for part in section.split("."):
        node = node.setdefault(part, {})
    node[key] = value
    with pytest.raises(ConfigError, match=rf"cfg.yaml: {section}.{key}: must be in"):
        config_from_mapping(data, "cfg.yaml")


def _to_leaf(current: Any, value: float) -> Any:
    """``current`` with its first number replaced by ``value``, as the field's own type."""
    if isinstance(current, tuple):
        return (_to_leaf(current[0], value), *current[1:]) if current else (value,)
    return value


@pytest.mark.parametrize(("path", "cls", "name", "tp"), CASES)
def test_a_config_built_in_code_refuses_the_same_values(path, cls, name, tp) -> None:
    """The range is stated once (``RANGES``) and holds for a section built in code too
    (``dataclasses.replace``, as the model writer and the tests build them), not only for
    one read from a file: no ``__post_init__`` has to restate it."""
    cfg = load_config()
    owner = _current(cfg, path[:-1])
    if owner is None:  # an optional section the default config leaves out: build it bare
        owner = cls(**{})
    low, high = cls.RANGES[name]
    integer = int in (tp, *get_args(tp)) or any(int in get_args(a) for a in get_args(tp))
    for bad in [*_beyond(low, high, integer), *([] if integer else [float("nan")])]:
        leaf = _to_leaf(getattr(owner, name), bad)
        with pytest.raises(ValueError, match=rf"^{name} must be in "):
            dataclasses.replace(owner, **{name: leaf})
    dataclasses.replace(owner, **{name: getattr(owner, name)})  # the value it has is fine


def test_every_section_with_ranges_checks_them_when_built() -> None:
    from gateway.core.configtypes import Ranged

    owners = {cls for _, cls, _, _ in FIELDS}
    assert owners and all(issubclass(c, Ranged) for c in owners), [
        c.__name__ for c in owners if not issubclass(c, Ranged)
    ]
