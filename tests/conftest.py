"""Suite-wide test settings.

Hypothesis runs without a per-example deadline: the machines are shared and noisy, and
speed is measured in benchmarks (make bench), never asserted in tests.

Two profiles: ``cdpr`` (the default) draws new examples on every run, so a developer's runs
keep exploring; ``ci`` (``HYPOTHESIS_PROFILE=ci``, set by ``.ci/run``) draws the same
examples every time, so a submission is judged on one reproducible set and a new find
shows up on a developer's machine first, with its failing example printed.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

from tests.warm_kernels import PARTS

settings.register_profile(
    "cdpr",
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
    print_blob=True,
)
settings.register_profile("ci", parent=settings.get_profile("cdpr"), derandomize=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "cdpr"))


def pytest_configure(config: pytest.Config) -> None:
    """With pytest-xdist workers, compile numba's kernels once, before they start
    (tests/warm_kernels.py: two parts side by side); a cold cache was otherwise compiled by
    each worker and each CLI subprocess at once. Warm, a few seconds. Not in the workers
    and not without xdist (one process compiles each kernel once anyway)."""
    if hasattr(config, "workerinput") or not getattr(config.option, "numprocesses", None):
        return
    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(root), env.get("PYTHONPATH")) if p)
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "tests.warm_kernels", part],
            cwd=root,
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        for part in PARTS
    ]
    for part, proc in zip(PARTS, procs, strict=True):
        try:
            _, err = proc.communicate(timeout=900)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
        if proc.returncode != 0:  # the tests that use the kernels say what is wrong
            tail = err.strip().splitlines()[-1:] or ["(no output)"]
            print(f"warm_kernels {part}: exit {proc.returncode}: {tail[0]}", file=sys.stderr)
