"""Every comment, docstring and document cites what exists (issue 28 item 5).

A comment that names a file (``gateway/runtime/loop.py``, ``docs/physics.md``), a document
by its bare name (``recording-format.md``), a section by number (``physics.md sec. 4``) or
an object by its dotted name (``:func:`gateway.diagnose.engine.diagnose```) is checked
statically against the tree: the file exists, the document has a heading numbered so, the
module defines the name (and a class the member). Read as text, nothing imported.
"""

from __future__ import annotations

import ast
import re
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ("gateway", "drivers", "sim_plc", "bench", "tests", "evaluation")
# a path inside the tree, as comments write it (no globs, placeholders or folders)
PATH = re.compile(
    r"(?<![\w/.-])((?:gateway|drivers|sim_plc|bench|tests|evaluation|docs|config|deploy)"
    r"/[\w./-]*\w)"
)
ROLE = re.compile(
    r":(?:func|class|mod|meth|data|attr|exc):`~?((?:gateway|drivers|sim_plc)\.[\w.]+)`"
)
BARE_DOC = re.compile(r"(?<![\w/.-])([\w-]+\.md)\b")
SECTION = re.compile(r"((?:docs/)?[\w-]+\.md),? sec(?:tion|\.)\s*(\d+[a-z]?)\b")
INSTALLED_ONLY = ("gateway/data",)  # package data a wheel has, a checkout maps (setup.py)
# documents the tools write (diagnose --report, fleet) and test fixtures' file names: outputs,
# not citations
WRITTEN = {"summary.md", "fleet.md", "suite.md", "d.md"}
SEAL_RECORD = re.compile(r"^- `[^`]+` SHA-256 `[0-9a-f]{64}`")  # evaluation/sealing.py


def _files() -> list[Path]:
    out = [p for pkg in SOURCES if (ROOT / pkg).is_dir() for p in (ROOT / pkg).rglob("*.py")]
    out += [*sorted((ROOT / "docs").glob("*.md")), ROOT / "README.md"]
    out += sorted((ROOT / "deploy").rglob("*.yml")) + sorted((ROOT / "config").rglob("*.yaml"))
    return [p for p in out if "__pycache__" not in p.parts]


@cache
def _top_level(path: Path) -> dict[str, ast.AST | None]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    names: dict[str, ast.AST | None] = {}
    for node in tree.body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            names[node.name] = node
        elif isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names.update({t.id: None for t in targets if isinstance(t, ast.Name)})
        elif isinstance(node, ast.Import | ast.ImportFrom):
            names.update({(a.asname or a.name).split(".")[0]: None for a in node.names})
    return names


def _members(cls: ast.ClassDef) -> set[str]:
    found: set[str] = set()
    for node in ast.walk(cls):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            found.add(node.name)
        targets = (
            node.targets
            if isinstance(node, ast.Assign)
            else [node.target]
            if isinstance(node, ast.AnnAssign)
            else []
        )
        for t in targets:
            if isinstance(t, ast.Name):
                found.add(t.id)
            elif isinstance(t, ast.Attribute):
                found.add(t.attr)
    return found


def resolves(dotted: str) -> bool:
    """``pkg.module.name[.member]`` names a module of the tree that defines it."""
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        base = ROOT.joinpath(*parts[:i])
        for module in (base.with_suffix(".py"), base / "__init__.py"):
            if module.is_file():
                rest = parts[i:]
                if not rest:
                    return True
                top = _top_level(module)
                if rest[0] not in top:
                    return False
                node = top[rest[0]]
                if len(rest) == 1 or not isinstance(node, ast.ClassDef):
                    return True
                return rest[1] in _members(node)
    return False


@cache
def _numbered(doc: Path) -> set[str]:
    heads = [line for line in doc.read_text(encoding="utf-8").splitlines() if line.startswith("#")]
    return {m.group(1) for h in heads if (m := re.match(r"#+\s*(\d+[a-z]?)[.\s]", h))}


def broken_citations() -> list[str]:
    bad = []
    docs = {p.name for p in (ROOT / "docs").glob("*.md")} | {"README.md"}
    for f in _files():
        rel = f.relative_to(ROOT)
        for i, line in enumerate(f.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            where = f"{rel}:{i}"
            if SEAL_RECORD.match(line):  # a seal's history names the file where it was then
                continue
            for m in PATH.finditer(line):
                path = m.group(1).rstrip(".")
                if (
                    any(c in path for c in "*{<")
                    or "NAME" in path
                    or path.startswith(INSTALLED_ONLY)
                ):
                    continue
                if not ((ROOT / path).exists() or (ROOT / path).with_suffix(".py").exists()):
                    bad.append(f"{where}: no file {path}")
            for m in ROLE.finditer(line):
                if not resolves(m.group(1)):
                    bad.append(f"{where}: no object {m.group(1)}")
            for m in BARE_DOC.finditer(line):
                name = m.group(1)
                if name not in docs | WRITTEN and not (ROOT / name).exists():
                    bad.append(f"{where}: no document {name}")
            for m in SECTION.finditer(line):
                doc = ROOT / "docs" / Path(m.group(1)).name
                if doc.is_file() and m.group(2) not in _numbered(doc):
                    bad.append(f"{where}: {doc.name} has no section {m.group(2)}")
    return bad


def test_every_citation_names_what_exists():
    assert broken_citations() == []


def test_the_check_finds_what_is_broken():
    assert resolves("gateway.diagnose.engine.diagnose")
    assert not resolves("gateway.diagnose.engine.no_such_function")
    assert resolves("gateway.core.config.LoopConfig.input_age_limit_s")
    assert not resolves("gateway.core.config.LoopConfig.no_such_member")
    assert "4" in _numbered(ROOT / "docs" / "physics.md")
    assert "99" not in _numbered(ROOT / "docs" / "physics.md")
    assert PATH.search("see gateway/runtime/loop.py here").group(1) == "gateway/runtime/loop.py"
    missing = "no-such-document" + ".md"
    assert BARE_DOC.search(f"(see {missing}: house style)").group(1) == missing
