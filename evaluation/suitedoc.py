"""docs/diagnose-suite.md is written by several programs (the scenario suite, the foreign
cases, the real recordings), each its own sections: :func:`replace_section` replaces one
section (from its heading line to the next ``#`` or ``##`` heading) and keeps the rest, so
any one of them can be rerun alone. A section not yet in the file is appended.
"""

from __future__ import annotations

from pathlib import Path


def _split(text: str) -> list[str]:
    """The file's sections: each starts at a ``# `` or ``## `` heading (the first may not)."""
    parts: list[str] = []
    current: list[str] = []
    for line in text.splitlines(keepends=True):
        if line.startswith(("# ", "## ")) and current:
            parts.append("".join(current))
            current = []
        current.append(line)
    if current:
        parts.append("".join(current))
    return parts


def replace_section(path: Path, text: str) -> None:
    """Put ``text`` (starting with its heading line) in place of the section of ``path``
    with the same heading, or append it."""
    heading = text.splitlines()[0].rstrip()
    old = path.read_text(encoding="utf-8") if path.exists() else ""
    parts = _split(old)
    body = text.rstrip("\n") + "\n\n"
    for i, part in enumerate(parts):
        if part.splitlines()[0].rstrip() == heading:
            parts[i] = body
            break
    else:
        if parts and not parts[-1].endswith("\n\n"):
            parts[-1] = parts[-1].rstrip("\n") + "\n\n"
        parts.append(body)
    path.write_text("".join(parts).rstrip("\n") + "\n", encoding="utf-8")


def section(path: Path, heading: str) -> str:
    """The text of the section of ``path`` with ``heading`` ('' if none)."""
    if not path.exists():
        return ""
    for part in _split(path.read_text(encoding="utf-8")):
        if part.splitlines()[0].rstrip() == heading:
            return part
    return ""
