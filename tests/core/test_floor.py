"""The floor stands on nothing compiled: importing any module of ``gateway.core`` (the
config, the YAML loader, the register map ...) or the compile helper loads no numba, so a
driver, ``check`` and every ``--help`` do not pay for the physics (2.3-2.8 s for
``diagnose --help`` when the config imported the effects registry, issue 28)."""

from __future__ import annotations

import os
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import gateway.core

ROOT = Path(__file__).resolve().parents[2]
CORE = sorted(f"gateway.core.{m.name}" for m in pkgutil.iter_modules(gateway.core.__path__))


def _loads_numba(*statements: str) -> bool:
    """Whether running ``statements`` in a fresh interpreter leaves numba imported."""
    code = "; ".join([*statements, "import sys", "print('numba' in sys.modules)"])
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    return out.stdout.strip() == "True"


def test_the_check_sees_numba_when_it_is_loaded() -> None:
    assert _loads_numba("import gateway.model.chain_kernels")  # the physics does load it


@pytest.mark.parametrize("module", ["gateway.core", *CORE, "gateway.fastcall"])
def test_a_floor_module_loads_no_numba(module: str) -> None:
    assert len(CORE) >= 8  # config, configtypes, files, registermap, ...
    assert not _loads_numba(f"import {module}")


def test_loading_the_shipped_config_loads_no_numba() -> None:
    # default.yaml has no fitted effects: nothing to hand to the effects registry
    assert not _loads_numba(
        "from gateway.core.config import DEFAULT_CONFIG_PATH, load_config",
        "load_config(DEFAULT_CONFIG_PATH)",
    )
