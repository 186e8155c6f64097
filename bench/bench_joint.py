"""What one machine's recordings cost diagnosed together (issue 29's cost bound).

``python -m bench joint``: three recordings of one machine (``record`` of
``config/calibrate/viscous.yaml``, seeds 1-3: another motion and noise draw each, the same
hidden viscous friction), ``BENCH_JOINT_SECONDS`` long (default 600: the issue's 10-min
recording), as Parquet. Each ``diagnose`` runs in a child process of its own, timed by
``os.wait4`` (user + system CPU, the child's peak RSS):

* **one recording, this tree against the tree before** (``BENCH_JOINT_BASE``, default
  ``dc4feb0~1``: the last commit before issue 29's pooling and sessions; ``none`` skips
  it): the bound is 1.3x in CPU and in memory;
* **three recordings jointly** (``diagnose REC REC REC``: one set of findings for the
  machine) against the three diagnosed one at a time: the bound is the sum plus 20 % in
  CPU (and the largest of the three plus 20 % in memory would be the same bound per
  process: printed as the ratio to the sum and to the largest).

The reports' findings are printed beside the figures. Figures only: nothing asserts.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.trees import tree_of

ROOT = Path(__file__).resolve().parent.parent
MODEL = ROOT / "config" / "default.yaml"
CONFIG = ROOT / "config" / "calibrate" / "viscous.yaml"


def _env(tree: Path) -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": str(tree), "PYTHONDONTWRITEBYTECODE": "1"}
    env.setdefault("OPENBLAS_NUM_THREADS", "1")  # as make test
    return env


def _timed(argv: list[str], tree: Path) -> tuple[float, float, float]:
    """(CPU s, peak RSS MiB, wall s) of one child process."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "gateway.cli", *argv],
        cwd=str(tree),
        env=_env(tree),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    err = proc.stderr.read().decode() if proc.stderr else ""
    if status != 0:
        raise RuntimeError(f"{' '.join(argv[:2])}: status {status}: {err[-600:]}")
    return usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024, wall


def _findings(report: Path) -> str:
    found = json.loads(report.read_text())["findings"]
    return ", ".join(sorted({f["effect"] for f in found})) or "none"


def _diagnose(recs: list[Path], out: Path, tree: Path) -> tuple[float, float, float, str]:
    model = tree / MODEL.relative_to(ROOT)  # each tree reads its own config's keys
    argv = ["diagnose", *map(str, recs), "--model", str(model), "--json", str(out), "--quiet"]
    cpu, rss, wall = _timed(argv, tree)
    return cpu, rss, wall, _findings(out)


def run() -> None:
    seconds = float(os.environ.get("BENCH_JOINT_SECONDS", "600"))
    base_rev = os.environ.get("BENCH_JOINT_BASE", "dc4feb0~1")
    with tempfile.TemporaryDirectory(prefix="bench-joint-") as name:
        tmp = Path(name)
        recs = []
        for seed in (1, 2, 3):
            path = tmp / f"viscous-{seed}.parquet"
            argv = ["record", "--config", str(CONFIG), "--seconds", f"{seconds:g}"]
            argv += ["--out", str(path), "--seed", str(seed), "--quiet", "--robot", "viscous"]
            _timed(argv, ROOT)
            recs.append(path)
        print(f"  3 recordings of {seconds:g} s of one machine (viscous hidden, seeds 1-3)")
        print("  what                          CPU s   peak RSS MiB  wall s  findings")

        def line(what: str, cpu: float, rss: float, wall: float, found: str) -> None:
            print(f"  {what:<29} {cpu:7.1f}  {rss:12.0f}  {wall:6.1f}  {found}", flush=True)

        base = None if base_rev == "none" else tree_of(base_rev, tmp)
        if base is not None:
            _diagnose(recs[:1], tmp / "base.json", base)  # compiles its kernels: not timed
            b = _diagnose(recs[:1], tmp / "base.json", base)
            line(f"one recording, {base_rev}", *b)
        alone = []
        for i, rec in enumerate(recs):
            alone.append(_diagnose([rec], tmp / f"alone-{i}.json", ROOT))
            line(f"one recording (seed {i + 1})", *alone[-1])
        joint = _diagnose(recs, tmp / "joint.json", ROOT)
        line("three jointly", *joint)
        if base is not None:
            print(
                f"  one recording, this tree / {base_rev}: CPU {alone[0][0] / b[0]:.2f}x, "
                f"peak RSS {alone[0][1] / b[1]:.2f}x (bound 1.3x)"
            )
        cpu_sum = sum(a[0] for a in alone)
        print(
            f"  three jointly / the three alone: CPU {joint[0] / cpu_sum:.2f}x of the sum "
            f"(bound 1.2x); peak RSS {joint[1] / max(a[1] for a in alone):.2f}x the largest, "
            f"{joint[1] / sum(a[1] for a in alone):.2f}x the sum"
        )
        print(f"  load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
