"""A module's name says what it is (issue 28): no module of the product, the evaluation or
the benchmarks shadows a standard-library module (``diagnose/platform.py`` did), and a name
used by two modules means one thing in each: the command line of its package (``cli``), its
pictures (``plots``), its configuration (``config``), the base classes of its plugins
(``base``). A new same-name pair fails here until it is renamed or, if it really has the
one meaning, listed with that meaning."""

from __future__ import annotations

import sys
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("gateway", "drivers", "sim_plc", "evaluation", "bench")
SHARED_MEANING = {
    "__init__": "a package",
    "__main__": "a package's `python -m` entry",
    "cli": "the command line of its package",
    "plots": "the pictures of its package",
    "config": "the configuration its package reads",
    "base": "the base classes of its package's plugins (drivers, effects)",
}


def _modules() -> list[Path]:
    return [
        p
        for pkg in PACKAGES
        for p in sorted((ROOT / pkg).rglob("*.py"))
        if "__pycache__" not in p.parts
    ]


def test_no_module_shadows_the_standard_library() -> None:
    shadowing = [str(p.relative_to(ROOT)) for p in _modules() if p.stem in sys.stdlib_module_names]
    assert shadowing == []


def test_a_name_two_modules_share_has_one_meaning() -> None:
    by_name: dict[str, list[str]] = defaultdict(list)
    for p in _modules():
        by_name[p.stem].append(str(p.relative_to(ROOT)))
    shared = {n: paths for n, paths in by_name.items() if len(paths) > 1}
    assert {n: paths for n, paths in shared.items() if n not in SHARED_MEANING} == {}
    assert len(_modules()) > 150  # the walk found the tree
