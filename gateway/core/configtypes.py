"""YAML mappings -> frozen dataclasses, validated once, errors naming file and key.

``convert(cls, data, key, source)`` walks the dataclass' type hints and builds it from a
plain mapping. Supported field types: ``bool``, ``int``, ``float``, ``str``, ``Literal``,
``X | None``, ``tuple[X, ...]``, ``tuple[X, Y, Z]``, ``dict[str, X]`` and nested
dataclasses. Unknown keys and missing required keys are errors; a dataclass may check
its own values in ``__post_init__`` by raising ``ValueError`` and the message is
prefixed with the file and the dotted key path.

Every numeric key has a range, stated once: a dataclass' ``RANGES`` maps each of its
``int`` / ``float`` fields (plain, optional or in a tuple) to ``(low, high)``, inclusive.
:func:`convert` refuses a value outside it naming the file and the key; a dataclass built
in code refuses it too, when it derives from :class:`Ranged` (its ``__post_init__``), so
no ``__post_init__`` restates a range: it checks only what relates two keys (a test walks
the whole config and checks that no numeric field lacks a range, and that both ways of
building refuse a value beyond each bound).

Files are read by :func:`read_yaml` through :func:`gateway.core.files.read_regular`:
regular files under a size limit only (a device or a FIFO is refused at once). It is the
one YAML loader of the project (config, model files, scenario and calibrate files): a
mapping key given twice, at any depth (``loop:`` twice, ``port:`` twice), is refused with
the file, the line and the dotted key, never "the last one wins"; so is a number no key
can hold (an integer beyond 64 bits, a float literal beyond the float range).
"""

from __future__ import annotations

import dataclasses
import math
import reprlib
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin

import yaml

from gateway.core.files import MAX_YAML_BYTES, read_regular
from gateway.errors import ConfigError

T = TypeVar("T")
Range = tuple[float, float]

MAX_YAML_DEPTH = 100  # nesting levels of a YAML document
MAX_YAML_NODES = 1_000_000  # nodes of a document with every alias expanded
MAX_ITEMS = 10_000  # items of one list (anchors, pulleys, columns)
MAX_INT_BITS = 64  # an integer of a file: a register, a port, a seed; never wider
MAX_NUMBER_CHARS = 100  # the text of one number (a 64-bit integer in binary: 66)
_INT_TAG = "tag:yaml.org,2002:int"
_FLOAT_TAG = "tag:yaml.org,2002:float"
_MERGE_TAG = "tag:yaml.org,2002:merge"
_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxstring, _REPR.maxother = 2, 60, 60
_REPR.maxlist = _REPR.maxtuple = _REPR.maxdict = _REPR.maxset = 4


def _short(value: Any) -> str:
    """A bounded repr for error messages (an alias bomb must not be printed in full)."""
    return _REPR.repr(value)


class _BoundedLoader(yaml.SafeLoader):
    """``SafeLoader`` that refuses deep nesting and alias expansion beyond the limits.

    Every composed node records its expanded size (aliases counted at the size of what
    they name), so a billion-laughs document is refused while it is composed, before
    anything walks it; the nesting depth is checked before the composer recurses.
    """

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0
        self._sizes: dict[int, int] = {}

    def compose_node(self, parent: Any, index: Any) -> Any:
        mark = self.peek_event().start_mark
        if self.check_event(yaml.AliasEvent):
            return super().compose_node(parent, index)  # its size is already known
        self._depth += 1
        if self._depth > MAX_YAML_DEPTH:
            raise yaml.composer.ComposerError(
                None, None, f"nested deeper than {MAX_YAML_DEPTH} levels", mark
            )
        try:
            node = super().compose_node(parent, index)
        finally:
            self._depth -= 1
        size = 1
        if isinstance(node, yaml.SequenceNode):
            size += sum(self._sizes.get(id(c), 1) for c in node.value)
        elif isinstance(node, yaml.MappingNode):
            size += sum(
                self._sizes.get(id(k), 1) + self._sizes.get(id(v), 1) for k, v in node.value
            )
        if size > MAX_YAML_NODES:
            raise yaml.composer.ComposerError(
                None, None, f"aliases expand to more than {MAX_YAML_NODES} nodes", mark
            )
        self._sizes[id(node)] = size
        return node


class _DocumentError(Exception):
    """A document the loader refuses after composing it: line (1-based) and message."""

    def __init__(self, line: int, message: str) -> None:
        super().__init__(message)
        self.line = line


def _key_text(node: yaml.Node) -> str | None:
    return str(node.value) if isinstance(node, yaml.ScalarNode) else None


def _check_number(node: yaml.ScalarNode, key: str, loader: _BoundedLoader) -> None:
    """Refuse a number no key can hold, before PyYAML turns it into an ``int`` (whose
    digit limit raises ``ValueError``) or a float (``inf`` from 400 digits)."""
    line = node.start_mark.line + 1
    shown = key or "<top>"
    if len(node.value) > MAX_NUMBER_CHARS:
        raise _DocumentError(
            line, f"'{shown}': a number of {len(node.value)} characters is too large"
        )
    value = loader.construct_object(node)
    if node.tag == _INT_TAG and abs(value) >= 1 << MAX_INT_BITS:
        raise _DocumentError(line, f"'{shown}': integer {value} is too large (beyond 64 bits)")
    if node.tag == _FLOAT_TAG and math.isinf(value) and "inf" not in node.value.lower():
        raise _DocumentError(line, f"'{shown}': number {node.value} is too large for a float")


def _check_document(root: yaml.Node, loader: _BoundedLoader) -> None:
    """Walk the composed document once: every mapping's keys unique, every number holdable.

    A node reached again through an alias is walked once (the size limit bounds the rest).
    """
    seen: set[int] = set()
    stack: list[tuple[yaml.Node, str]] = [(root, "")]
    while stack:
        node, key = stack.pop()
        if id(node) in seen:
            continue
        seen.add(id(node))
        if isinstance(node, yaml.ScalarNode):
            if node.tag in (_INT_TAG, _FLOAT_TAG):
                _check_number(node, key, loader)
        elif isinstance(node, yaml.SequenceNode):
            stack.extend((child, _join(key, i)) for i, child in enumerate(node.value))
        elif isinstance(node, yaml.MappingNode):
            first: dict[tuple[str, str], int] = {}
            children = []
            for k, v in node.value:
                text = _key_text(k)
                if k.tag == _MERGE_TAG or text is None:
                    children.append((k, key))
                    children.append((v, key))
                    continue
                dotted = _join(key, text)
                line = k.start_mark.line + 1
                if (k.tag, text) in first:
                    raise _DocumentError(
                        line,
                        f"duplicate key '{dotted}' (first at line {first[k.tag, text]})",
                    )
                first[k.tag, text] = line
                children.append((k, dotted))
                children.append((v, dotted))
            stack.extend(reversed(children))


def _fail(source: str, key: str, message: str) -> ConfigError:
    where = f"{source}: " if source else ""
    return ConfigError(f"{where}{key or '<top>'}: {message}")


def _join(key: str, name: str | int) -> str:
    if isinstance(name, int):
        return f"{key}[{name}]"
    return f"{key}.{name}" if key else name


def _in_range(value: float, rng: Range | None, key: str, source: str) -> None:
    if rng is not None and not rng[0] <= value <= rng[1]:
        raise _fail(source, key, f"must be in {rng[0]:g}..{rng[1]:g}, got {_short(value)}")


def _convert_value(tp: Any, value: Any, key: str, source: str, rng: Range | None = None) -> Any:
    origin = get_origin(tp)
    if tp is Any:
        return value
    if origin is typing.Union or origin is types.UnionType:
        args = get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert_value(arg, value, key, source, rng)
            except ConfigError as exc:
                errors.append(str(exc))
        if errors:
            raise ConfigError(errors[-1])
        raise _fail(source, key, "bad value")
    if origin is Literal:
        allowed = get_args(tp)
        if value not in allowed:
            choices = ", ".join(repr(a) for a in allowed)
            raise _fail(source, key, f"{_short(value)} is not one of {choices}")
        return value
    if dataclasses.is_dataclass(tp):
        return convert(tp, value, key, source)  # type: ignore[arg-type]
    if origin is tuple:
        args = get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise _fail(source, key, f"expected a list, got {type(value).__name__}")
        if len(args) == 2 and args[1] is Ellipsis:
            if len(value) > MAX_ITEMS:
                raise _fail(source, key, f"more than {MAX_ITEMS} items")
            return tuple(
                _convert_value(args[0], v, _join(key, i), source, rng) for i, v in enumerate(value)
            )
        if len(value) != len(args):
            raise _fail(source, key, f"expected {len(args)} items, got {len(value)}")
        return tuple(
            _convert_value(a, v, _join(key, i), source, rng)
            for i, (a, v) in enumerate(zip(args, value, strict=True))
        )
    if origin is dict:
        _, vt = get_args(tp)
        if not isinstance(value, Mapping):
            raise _fail(source, key, f"expected a mapping, got {type(value).__name__}")
        return {str(k): _convert_value(vt, v, _join(key, str(k)), source) for k, v in value.items()}
    if tp is bool:
        if not isinstance(value, bool):
            raise _fail(source, key, f"expected true or false, got {_short(value)}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise _fail(source, key, f"expected an integer, got {_short(value)}")
        _in_range(value, rng, key, source)
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _fail(source, key, f"expected a number, got {_short(value)}")
        if not math.isfinite(value):
            raise _fail(source, key, f"expected a finite number, got {_short(value)}")
        _in_range(value, rng, key, source)
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise _fail(source, key, f"expected a string, got {_short(value)}")
        return value
    raise _fail(source, key, f"unsupported field type {tp!r}")  # pragma: no cover


def convert(cls: type[T], data: Any, key: str = "", source: str = "") -> T:
    """Build dataclass ``cls`` from mapping ``data``; errors name ``source`` and ``key``."""
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise _fail(source, key, f"expected a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = [k for k in data if k not in fields]
    if unknown:  # a field with metadata {"file": False} is filled in by the loader
        known = ", ".join(sorted(n for n, f in fields.items() if f.metadata.get("file", True)))
        raise _fail(source, _join(key, str(unknown[0])), f"unknown key (known here: {known})")
    kwargs: dict[str, Any] = {}
    ranges: dict[str, Range] = getattr(cls, "RANGES", {})
    for name, field in fields.items():
        if name in data:
            rng = ranges.get(name)
            kwargs[name] = _convert_value(hints[name], data[name], _join(key, name), source, rng)
        elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
            raise _fail(source, _join(key, name), "required key is missing")
    try:
        return cls(**kwargs)
    except ValueError as exc:
        # a check that names its field ("period_s must be ...") is reported at that key
        message = str(exc)
        first = message.split(" ", 1)[0].rstrip(":")
        if first in fields and " " in message:
            raise _fail(source, _join(key, first), message.split(" ", 1)[1]) from exc
        raise _fail(source, key, message) from exc


def read_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML file whose top level is a mapping; errors name the file and line."""
    path = Path(path)
    raw = read_regular(path, MAX_YAML_BYTES, "YAML file")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start})") from None
    return load_yaml_text(text, str(path))


def load_yaml_text(text: str, source: str) -> dict[str, Any]:
    """The mapping a YAML text holds, with :func:`read_yaml`'s checks; errors name
    ``source`` (a file name) and the line."""
    loader = _BoundedLoader(text)
    try:
        root = loader.get_single_node()  # composed, bounded in depth and expanded size
        if root is not None:
            _check_document(root, loader)
            data = loader.construct_document(root)
        else:
            data = None
    except _DocumentError as exc:
        raise ConfigError(f"{source}:{exc.line}: {exc}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}, column {mark.column + 1}:" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"{source}:{where} not valid YAML: {problem}") from None
    finally:
        loader.dispose()
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: top level must be a mapping")
    return data


def _numbers(value: Any) -> typing.Iterator[float]:
    """The numbers of a field's value: itself, or those of a (nested) tuple; None: none."""
    if isinstance(value, tuple | list):
        for v in value:
            yield from _numbers(v)
    elif isinstance(value, int | float) and not isinstance(value, bool):
        yield value


def check_ranges(obj: Any) -> None:
    """Raise ``ValueError("<field> must be in low..high, got v")`` for the first number of
    ``obj``'s fields outside its class' ``RANGES`` (NaN included)."""
    for name, (low, high) in getattr(type(obj), "RANGES", {}).items():
        for v in _numbers(getattr(obj, name)):
            if not low <= v <= high:
                raise ValueError(f"{name} must be in {low:g}..{high:g}, got {_short(v)}")


class Ranged:
    """Base of a config dataclass with ``RANGES``: every construction, from a file or in
    code, checks them. A subclass' own ``__post_init__`` calls ``super().__post_init__()``
    first and checks only what relates its keys."""

    RANGES: typing.ClassVar[dict[str, Range]] = {}

    def __post_init__(self) -> None:
        check_ranges(self)


def require(condition: bool, message: str) -> None:
    """For ``__post_init__``: raise ``ValueError(message)`` unless ``condition``."""
    if not condition:
        raise ValueError(message)
