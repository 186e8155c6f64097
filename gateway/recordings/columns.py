"""Recordings from other loggers: ``--columns`` renames a file's columns to the recording
format's names (docs/recording-format.md, "Recordings from other loggers").

``--columns t=time,tension_sensor_1=F1,...`` or ``--columns MAP.yaml`` (a mapping
``t: time``, read by the project's one YAML loader, :func:`gateway.core.configtypes.read_yaml`):
each key is a name of the recording format, each value the name of the file's column
that holds it. A key that is no column of the format, a pair without ``=``, a key given
twice or a file column given for two keys is refused in one line naming it
(:class:`ConfigError`, exit 2) before any file is read; a value the file does not have is
refused by the reader (:func:`rename`), listing the columns found.

Imported by the commands' argument parsers: no numpy, no numba.
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Mapping
from pathlib import Path

from gateway.errors import ConfigError, RecordingError

MAX_CABLES = 1024  # cable indices 1..m, m at most this (the reader's limit)
MAX_PAIRS = 8192  # the reader's MAX_COLUMNS
PLATFORM_COLUMNS = ("t", "x", "y", "z", "rx", "ry", "rz", "mass")
PER_CABLE = (
    "velocity",
    "tension_sensor",
    "tension_platform",
    "length",
    "tension_corrected",
    "status",
)
_PER_CABLE = re.compile(r"^(" + "|".join(PER_CABLE) + r")_([1-9][0-9]{0,3})$", re.ASCII)
KNOWN = (
    f"{', '.join(PLATFORM_COLUMNS)}, {', '.join(f'{k}_i' for k in PER_CABLE)} (i = 1..{MAX_CABLES})"
)
EXPECTED = (
    "t, and per cable i = 1..m velocity_i, tension_sensor_i and tension_platform_i "
    "(or x, y, z, rx, ry, rz, mass for all cables)"
)
LISTED = 30  # column names shown in an error, at most


def is_format_column(name: str) -> bool:
    """Whether ``name`` is a column of the recording format (docs/recording-format.md)."""
    if name in PLATFORM_COLUMNS:
        return True
    match = _PER_CABLE.match(name)
    return match is not None and int(match.group(2)) <= MAX_CABLES


def add_columns_option(parser: argparse.ArgumentParser) -> None:
    """``--columns MAP`` on a command that reads recordings."""
    parser.add_argument(
        "--columns",
        help="a recording from another logger: its columns renamed to the format's, "
        "NAME=COLUMN pairs (t=time,tension_sensor_1=F1,...) or a YAML file of them "
        "(docs/recording-format.md)",
    )


def column_map(value: str | None) -> dict[str, str] | None:
    """The mapping (format name -> file column) that ``--columns VALUE`` gives: the pairs
    written inline, or those of the YAML file it names; None without the option."""
    if value is None:
        return None
    if "=" in value and not Path(value).is_file():
        return _checked(_inline(value), "--columns")
    from gateway.core.configtypes import read_yaml

    path = Path(value)
    if not path.exists():
        raise ConfigError(
            f"--columns {value}: no such file, and not NAME=COLUMN pairs (t=time,...)"
        )
    data = read_yaml(path)  # errors name the file and line
    pairs: dict[str, str] = {}
    for key, column in data.items():
        if isinstance(column, bool) or not isinstance(column, str | int):
            raise ConfigError(
                f"{path}: {key}: the value must be a column name of the file, "
                f"not {type(column).__name__}"
            )
        pairs[str(key)] = str(column)
    return _checked(pairs, str(path))


def _inline(value: str) -> dict[str, str]:
    pairs: dict[str, str] = {}
    for item in value.split(","):
        key, eq, column = item.partition("=")
        key, column = key.strip(), column.strip()
        if not eq or not key:
            raise ConfigError(f"--columns: {item.strip()!r} is not NAME=COLUMN (t=time,...)")
        if key in pairs:
            raise ConfigError(f"--columns: {key!r} is given twice")
        pairs[key] = column
    return pairs


def _checked(pairs: dict[str, str], source: str) -> dict[str, str]:
    if not pairs:
        raise ConfigError(f"{source}: no NAME=COLUMN pairs")
    if len(pairs) > MAX_PAIRS:
        raise ConfigError(f"{source}: more than {MAX_PAIRS} pairs")
    taken: dict[str, str] = {}
    for key, column in pairs.items():
        if not is_format_column(key):
            raise ConfigError(
                f"{source}: {key!r} is not a column of the recording format ({KNOWN})"
            )
        if not column:
            raise ConfigError(f"{source}: {key}: no file column named")
        if column in taken:
            raise ConfigError(
                f"{source}: {key}: the file's column {column!r} is already {taken[column]!r}"
            )
        taken[column] = key
    return pairs


def listed(names: list[str]) -> str:
    """``a, b, c`` (the first :data:`LISTED`, then how many in all)."""
    shown = ", ".join(names[:LISTED])
    return shown if len(names) <= LISTED else f"{shown}, ... ({len(names)} in all)"


def found_and_expected(names: list[str]) -> str:
    """What an error about a missing column adds: the columns found, the ones expected and
    the option that maps them (one line)."""
    return (
        f" (columns found: {listed(names)}; expected: {EXPECTED}; a file from another logger: "
        "--columns t=COLUMN,velocity_1=COLUMN,...)"
    )


def rename(where: str, names: list[str], columns: Mapping[str, str] | None) -> list[str]:
    """The file's column ``names`` with ``columns`` (format name -> file column) applied;
    ``where`` (``FILE:LINE``, ``FILE: schema``) starts an error: a column the file does not
    have, or a new name that another column of the file has already."""
    if not columns:
        return names
    index = {name: i for i, name in enumerate(names)}
    out = list(names)
    for key, column in columns.items():
        if column not in index:
            raise RecordingError(
                f"{where}: --columns {key}={column}: the file has no column {column!r} "
                f"(columns found: {listed(names)})"
            )
        out[index[column]] = key
    renamed = set(columns.values())
    for key, column in columns.items():
        if key in index and key not in renamed:
            raise RecordingError(
                f"{where}: --columns {key}={column}: the file has a column {key!r} of its own "
                "(a column has one name: rename or remove that one)"
            )
    return out
