"""Another revision of this checkout, for a benchmark's before/after side by side."""

from __future__ import annotations

import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def tree_of(rev: str, tmp: str | Path) -> Path | None:
    """``git archive`` of ``rev`` unpacked into ``tmp/base``; None (said) when not a git
    checkout or no such revision."""
    try:
        archive = subprocess.run(
            ["git", "-C", str(ROOT), "archive", rev], capture_output=True, check=True
        ).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        print(f"  base {rev}: not available ({exc}); this tree only")
        return None
    dest = Path(tmp) / "base"
    dest.mkdir()
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return dest
