"""``cdpr-gateway warmup`` compiles every compiled function a command can call (issue 32
item 4): the check enumerates numba's dispatchers in the tree, so a new kernel that none of
warmup's exercises reaches fails here, not on a user's first run."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from sim_plc import warmup

ROOT = Path(__file__).resolve().parents[2]

PROBE = """
import argparse, json
from gateway.core import firstrun
from sim_plc import warmup

warmup.run_command("warmup", argparse.Namespace(config=None))
functions = warmup.compiled_functions()
standalone = [d for d in functions.values() if d.targetoptions.get("inline") != "always"]
print(json.dumps({
    "functions": sorted(functions),
    "untouched": warmup.untouched(functions),
    "not_cached": sorted(d.py_func.__qualname__ for d in firstrun.uncached(standalone)),
}))
"""


def test_warmup_leaves_every_compiled_function_in_the_cache() -> None:
    """In a process of its own (nothing else compiled there), warmup reaches every numba
    function of ``gateway`` and ``drivers`` (called: compiled or loaded; or compiled into
    one that is), each in numba's cache after it, and says so."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), OPENBLAS_NUM_THREADS="1")
    out = subprocess.run(
        [sys.executable, "-c", PROBE], cwd=ROOT, env=env, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr[-3000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    functions = set(got["functions"])
    # the enumeration sees the kernels of every kind, the ones a warmup once missed among them
    assert {
        "gateway.model.chain_kernels.compensate_kernel",
        "gateway.model.chain_kernels._step_cable",
        "drivers.kernels.s7_encode_all",
        "drivers.kernels.encode_fields",
        "gateway.model.effects.sensor_creep.inverse_step",
        "gateway.model.effects.sensor_creep._inverse_batch",
        "gateway.runtime.compensator._finish",
    } <= functions
    assert len(functions) >= 40
    assert got["untouched"] == []
    assert got["not_cached"] == []
    assert f"every compiled function ({len(functions)}) is in numba's cache" in out.stderr


KERNELS = """
import math

from numba import njit

from pkg_under_test import leaf


@njit(cache=True, inline="always")
def _inlined(x):
    return x + 1.0


@njit(cache=True)
def _callee(x):
    return 2.0 * _inlined(x)


@njit(cache=True)
def used(x):
    return _callee(x) + leaf.twice(x)


@njit(cache=True)
def unused(x):
    return math.sqrt(x)
"""

LEAF = """
from numba import njit


@njit(cache=True)
def twice(x):
    return 2.0 * x


@njit(cache=True)
def orphan(x):
    return x
"""


def test_untouched_names_what_no_call_reached(tmp_path, monkeypatch) -> None:
    """The check itself: a function called, its callees (by name, inlined or by
    ``module.name``) are reached; one nothing calls is named, in another module too."""
    pkg = tmp_path / "pkg_under_test"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "kernels.py").write_text(KERNELS)
    (pkg / "leaf.py").write_text(LEAF)
    (pkg / "plain.py").write_text("def njit_free():\n    return 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    functions = warmup.compiled_functions(["pkg_under_test"])
    assert sorted(functions) == [
        "pkg_under_test.kernels._callee",
        "pkg_under_test.kernels._inlined",
        "pkg_under_test.kernels.unused",
        "pkg_under_test.kernels.used",
        "pkg_under_test.leaf.orphan",
        "pkg_under_test.leaf.twice",
    ]
    assert warmup.untouched(functions) == sorted(functions)  # nothing called yet
    assert functions["pkg_under_test.kernels.used"](1.0) == 6.0
    assert warmup.untouched(functions) == [
        "pkg_under_test.kernels.unused",
        "pkg_under_test.leaf.orphan",
    ]
