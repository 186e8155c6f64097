"""The cycle says "compiling" only when it does: its sentinels (:func:`cycle_kernels`) are
kernels building the cycle compiles, whatever the model, so a second start says nothing."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

PROBE = """
import logging
logging.basicConfig(level=logging.INFO)
from drivers.virtual import VirtualDriver
from gateway.core import firstrun
from gateway.core.config import DEFAULT_CONFIG_PATH, load_config
from gateway.runtime.loop import CyclicService, cycle_kernels

cfg = load_config(DEFAULT_CONFIG_PATH)
CyclicService(cfg, VirtualDriver(cfg), history=16)
print([k.py_func.__qualname__ for k in firstrun.uncached(cycle_kernels())])
"""


def test_a_second_start_of_the_cycle_says_nothing_about_compiling(tmp_path) -> None:
    """Built twice on one empty cache: the first build compiles (and says so) and leaves no
    sentinel uncached; the second says nothing about compiling. (On the tree before, the
    general compensate kernel was a sentinel the default model never compiles: every start
    said "compiling".)"""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path), PYTHONPATH=str(ROOT))
    env["OPENBLAS_NUM_THREADS"] = "1"
    said = []
    for _ in range(2):
        out = subprocess.run(
            [sys.executable, "-c", PROBE], cwd=ROOT, env=env, capture_output=True, text=True
        )
        assert out.returncode == 0, out.stderr[-3000:]
        assert out.stdout.strip().splitlines()[-1] == "[]"
        said.append(out.stderr)
    assert "gateway: compiling the numba kernels" in said[0]
    assert "compiling" not in said[1], said[1]
