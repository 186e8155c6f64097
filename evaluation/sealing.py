"""Seals of the sealed suites: each sealed case file's SHA-256, recorded in
docs/diagnose-suite.md's "## Seals" section with the date and the reason it was (re)drawn.

The sealed cases are drawn once and checked in; a table run refuses to score a sealed file
whose hash is not the last one recorded for it (:func:`check`), and the test suite checks
the same (tests/diagnose/test_sealed.py). Resealing (a new draw, a generator change that
alters the cases) is explicit: :func:`add` appends a line, so the doc says so.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import re
from pathlib import Path
from typing import Any

import yaml

from evaluation.suitedoc import replace_section, section
from gateway.errors import GatewayError

HEADING = "## Seals"
ROOT = Path(__file__).resolve().parent.parent
_LINE = re.compile(r"^- `(?P<file>[^`]+)` SHA-256 `(?P<hash>[0-9a-f]{64})`")


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def recorded(doc: Path) -> dict[str, str]:
    """File (relative to the repository) -> the last hash recorded for it in ``doc``."""
    out: dict[str, str] = {}
    for line in section(doc, HEADING).splitlines():
        m = _LINE.match(line)
        if m:
            out[m["file"]] = m["hash"]
    return out


def relative(path: Path) -> str:
    """The name a seal records: relative to the repository (absolute outside it)."""
    full = path.resolve()
    return full.relative_to(ROOT).as_posix() if full.is_relative_to(ROOT) else full.as_posix()


def check(doc: Path, path: Path) -> str:
    """The file's hash if it is the one ``doc`` records last for it; else GatewayError."""
    got, rel = sha256(path), relative(path)
    want = recorded(doc).get(rel)
    if want != got:
        raise GatewayError(
            f"{rel}: SHA-256 {got[:12]}... is not the seal {doc} records "
            f"({'none' if want is None else want[:12] + '...'}): sealed cases are not redrawn "
            "quietly; reseal with --reseal REASON"
        )
    return got


def add(doc: Path, path: Path, reason: str) -> str:
    """Record ``path``'s current hash in ``doc`` with today's date and ``reason``."""
    old = section(doc, HEADING)
    lines = (
        old.rstrip("\n").splitlines()
        if old
        else [
            HEADING,
            "",
            "The sealed case files and their SHA-256 (the last line per file counts); a table run "
            "and `tests/diagnose/test_sealed.py` refuse a file whose hash is not recorded here. "
            "A new line means the cases were redrawn, and says why.",
            "",
        ]
    )
    digest = sha256(path)
    today = _dt.date.today().isoformat()
    lines.append(f"- `{relative(path)}` SHA-256 `{digest}` ({today}: {reason})")
    replace_section(doc, "\n".join(lines) + "\n")
    return digest


def case_line(case: dict[str, Any]) -> str:
    """One case as the sealed files hold it: a flow-style list item on one line (the
    files are written and appended line by line, so a case's bytes never move)."""
    return "  - " + yaml.safe_dump(case, default_flow_style=True, sort_keys=False, width=10**6)


def append_case(path: Path, case: dict[str, Any], names: set[str], how: str) -> None:
    """Append ``case`` to the sealed file ``path`` (whose cases are named ``names``) after a
    comment saying ``how`` it was drawn; the cases before it untouched; refused if the file
    has a case of its name."""
    if case["name"] in names:
        raise ValueError(f"{path}: already has a case {case['name']}")
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(f"# appended: {how}\n" + case_line(case))
