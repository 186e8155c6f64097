"""The first run after installing: what numba's compile adds to a user's first commands.

Each command runs twice in a child process with the same, initially empty,
``NUMBA_CACHE_DIR`` (what a fresh install has: no cached kernel): cold (it compiles and
caches what it uses), then warm (it loads them). Printed per command: wall and CPU seconds
and peak RSS, cold and warm, and the cold run's extra wall time, the figure issue 32
item 4 bounds (the first command that needs the kernels spends <= 20 s more than a warm
run).

The commands, in a user's first-hour order: ``record`` (the soft PLC's batch plant),
``diagnose`` of that recording (the diagnosis kernels), ``demo --offline`` (the gateway's
cycle and the per-cycle plant), and ``warmup`` (everything, what the service unit runs
ahead). Each cold run starts from an empty cache of its own, so each figure is that
command's alone.

``BENCH_FIRSTRUN_SRC`` runs the children from another source tree (e.g. an unpacked older
commit, for a before/after comparison side by side); ``BENCH_FIRSTRUN_ONLY`` a comma list
of the command names. Figures only: nothing here asserts.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _commands(work: Path) -> dict[str, list[str]]:
    rec = str(work / "first.parquet")
    return {
        "record": ["record", "--seconds", "20", "--out", rec, "--quiet"],
        "diagnose": [
            "diagnose",
            rec,
            "--model",
            str(ROOT / "config" / "default.yaml"),
            "--json",
            str(work / "r.json"),
            "--quiet",
        ],
        "demo": ["demo", "--offline", "--seconds", "3", "--quiet"],
        "warmup": ["warmup"],
    }


def _run(src: Path, argv: list[str], cache: Path) -> tuple[float, float, float, int]:
    """(wall s, CPU s, peak RSS MiB, exit status) of one child (its own rusage, by wait4)."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(src))
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    start = time.perf_counter()
    with tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "gateway", *argv],
            cwd=src,
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=err,
        )
        _, status, use = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        wall = time.perf_counter() - start
        if proc.returncode != 0:
            err.seek(0)
            print(f"   {argv[0]}: exit {proc.returncode}: {err.read().strip()[-300:]}")
    return wall, use.ru_utime + use.ru_stime, use.ru_maxrss / 1024.0, proc.returncode


def run() -> None:
    src = Path(os.environ.get("BENCH_FIRSTRUN_SRC", ROOT)).resolve()
    only = [s for s in os.environ.get("BENCH_FIRSTRUN_ONLY", "").split(",") if s]
    print(f"   source {src}; each command cold (empty NUMBA_CACHE_DIR) then warm")
    print(
        f"   {'command':10s} {'cold wall':>10s} {'cold CPU':>9s} {'warm wall':>10s} "
        f"{'warm CPU':>9s} {'extra':>7s} {'peak RSS':>9s}"
    )
    with tempfile.TemporaryDirectory(prefix="bench-firstrun-") as tmp:
        work = Path(tmp)
        commands = _commands(work)
        # the diagnosis needs the recording: record it first, warm, from its own cache
        prep = work / "prep-cache"
        _run(src, commands["record"], prep)
        for name, argv in commands.items():
            if only and name not in only:
                continue
            cache = work / f"cache-{name}"
            cold = _run(src, argv, cache)
            warm = _run(src, argv, cache)
            print(
                f"   {name:10s} {cold[0]:9.1f}s {cold[1]:8.1f}s {warm[0]:9.1f}s "
                f"{warm[1]:8.1f}s {cold[0] - warm[0]:6.1f}s {cold[2]:7.0f} MiB",
                flush=True,
            )
