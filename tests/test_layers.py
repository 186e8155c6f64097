"""The drivers layer depends only on the bottom layer (gateway.fastcall, gateway.errors,
gateway.core's config, register map, files, resources, ring) and on itself: never on the
physics, the soft PLC, the loop or the tools."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import drivers

ALLOWED_PROJECT_IMPORTS = (
    "drivers",
    "gateway.fastcall",
    "gateway.errors",
    "gateway.core.config",
    "gateway.core.registermap",
    "gateway.core.resources",
    "gateway.core.files",
    "gateway.core.ring",
)
PROJECT_PACKAGES = ("drivers", "gateway", "sim_plc", "evaluation", "tests", "bench")
DRIVER_FILES = sorted(Path(drivers.__file__).parent.glob("*.py"))


def _imports(path: Path) -> list[str]:
    names: list[str] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.append(node.module)
    return names


@pytest.mark.parametrize("path", DRIVER_FILES, ids=lambda p: p.name)
def test_drivers_import_only_the_bottom_layer(path: Path) -> None:
    project = [n for n in _imports(path) if n.split(".")[0] in PROJECT_PACKAGES]
    bad = [
        n
        for n in project
        if not any(n == a or n.startswith(a + ".") for a in ALLOWED_PROJECT_IMPORTS)
    ]
    assert bad == [], f"{path.name} imports {bad}"


def test_the_virtual_driver_is_among_the_checked_files() -> None:
    assert {"virtual.py", "modbus_tcp.py", "canopen.py", "s7.py"} <= {p.name for p in DRIVER_FILES}
