"""Diagnosis of a 10-minute, 1 kHz, 8-cable recording: seconds and peak memory.

Two recordings (scenario generator): a clean one (nothing to find) and one that holds a
viscous term on every cable and an offset on two of them (``DIAGNOSE_CASES=clean`` or
``hidden`` runs one). It is generated in a child process and handed over as an ``.npz`` file, so
that the figures are those of ``diagnose`` alone on a recording in memory: its wall time,
its peak Python heap (tracemalloc) and the peak resident size of the process (interpreter,
numpy/scipy/numba and the recording's arrays included). Goals: <= 60 s, <= 400 MB RSS.

Side by side against another tree (issue #19: the diagnosis of a clean 10-min recording
may take at most 1.5x the time it took before a change): ``DIAGNOSE_AGAINST=/path/to/tree
DIAGNOSE_FILES=a.csv.gz,b.csv.gz [DIAGNOSE_REPEATS=3]`` runs ``cdpr-gateway diagnose`` on
each file with this tree and that one, alternating, each under ``/usr/bin/time -v``, and
prints the median wall time, peak RSS and CPU time of each and their ratios (this tree /
that).
"""

from __future__ import annotations

import multiprocessing
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

SCENARIO_ARGS = dict(cables=8, seconds=600.0)


def _scenario(case: str = "hidden"):
    from evaluation.scenarios import Scenario

    if case == "clean":
        return Scenario("bench-clean", {}, **SCENARIO_ARGS)
    offsets = (0.0, 0.3, 0.0, 0.0, -0.3, 0.0, 0.0, 0.0)
    return Scenario(
        "bench", {"viscous": {"c_ns_m": 6.0}, "offset": {"c_n": offsets}}, **SCENARIO_ARGS
    )


def _generate(path: str, case: str) -> None:
    from evaluation.scenarios import make_recording

    rec = make_recording(_scenario(case))
    np.savez(
        path,
        t=rec.t,
        velocity=rec.velocity,
        tension_sensor=rec.tension_sensor,
        tension_platform=rec.tension_platform,
    )


def run() -> None:
    if os.environ.get("DIAGNOSE_AGAINST"):
        side_by_side(
            Path(os.environ["DIAGNOSE_AGAINST"]),
            os.environ.get("DIAGNOSE_FILES", "").split(","),
            int(os.environ.get("DIAGNOSE_REPEATS", "3")),
        )
        return
    for case in os.environ.get("DIAGNOSE_CASES", "clean,hidden").split(","):
        ctx = multiprocessing.get_context("spawn")
        proc = ctx.Process(target=_one, args=(case,))  # each case in a fresh process
        proc.start()
        proc.join()


def _one(case: str) -> None:
    from gateway.diagnose.engine import diagnose
    from gateway.recordings.reader import Recording

    with tempfile.TemporaryDirectory() as tmp:
        path = str(Path(tmp) / "rec.npz")
        proc = multiprocessing.get_context("spawn").Process(target=_generate, args=(path, case))
        proc.start()
        proc.join()
        with np.load(path) as z:
            rec = Recording(**{k: z[k] for k in z.files}, source="bench")
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    tracemalloc.start()
    start = time.perf_counter()
    diag = diagnose(rec, _scenario(case).nominal())
    seconds = time.perf_counter() - start
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    found = ", ".join(f"{f['effect']} on {f['cables']}" for f in diag.report["findings"])
    print(
        f"diagnose ({case}) {rec.samples} samples x {rec.cables} cables: {seconds:.1f} s "
        f"(goal <= 60 s), peak heap {peak / 2**20:.0f} MiB, peak RSS {rss_mb:.0f} MiB "
        f"(goal <= 400; {rss_before:.0f} MiB with the recording loaded, before diagnose); "
        f"found {found or 'none'}"
    )


def _timed(tree: Path, path: str) -> tuple[float, float, float]:
    """Wall seconds, peak RSS (MiB) and CPU seconds (user + system: on a loaded machine
    the wall time measures the load as much) of ``cdpr-gateway diagnose path`` run from
    ``tree``."""
    env = {**os.environ, "PYTHONPATH": str(tree), "OPENBLAS_NUM_THREADS": "1"}
    with tempfile.TemporaryDirectory() as tmp:
        cmd = ["/usr/bin/time", "-v", sys.executable, "-m", "gateway", "diagnose", path]
        cmd += ["--model", "config/default.yaml", "--json", str(Path(tmp) / "r.json"), "--quiet"]
        done = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    wall = re.search(r"Elapsed \(wall clock\) time.*: (?:(\d+):)?(\d+):([\d.]+)", done.stderr)
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", done.stderr)
    cpu = re.findall(r"(?:User|System) time \(seconds\): ([\d.]+)", done.stderr)
    if done.returncode not in (0, 1) or wall is None or rss is None or len(cpu) != 2:
        raise RuntimeError(f"{tree}: diagnose {path} failed: {done.stderr[-500:]}")
    h, m, sec = wall.groups()
    seconds = int(h or 0) * 3600 + int(m) * 60 + float(sec)
    return seconds, int(rss.group(1)) / 1024, float(cpu[0]) + float(cpu[1])


def side_by_side(other: Path, files: list[str], repeats: int) -> None:
    """Each file diagnosed by this tree and by ``other``, alternating (module docstring)."""
    here = Path(__file__).resolve().parent.parent
    for path in filter(None, files):
        runs: dict[Path, list[tuple[float, float, float]]] = {here: [], other: []}
        for _ in range(repeats):
            for tree in (other, here):
                runs[tree].append(_timed(tree, path))
                wall, rss, cpu = runs[tree][-1]
                print(f"  {path} {tree}: {wall:.1f} s, {rss:.0f} MiB, CPU {cpu:.1f} s", flush=True)
        med = {t: [statistics.median(r[k] for r in rs) for k in range(3)] for t, rs in runs.items()}
        for tree, rs in runs.items():
            walls = ", ".join(f"{w:.0f}" for w, _, _ in rs)
            print(
                f"{path} {tree}: median {med[tree][0]:.0f} s ({walls}), "
                f"{med[tree][1]:.0f} MiB, CPU {med[tree][2]:.0f} s"
            )
        ratio = [med[here][k] / med[other][k] for k in range(3)]
        print(
            f"{path}: time ratio {ratio[0]:.2f}, RSS ratio {ratio[1]:.2f}, CPU ratio "
            f"{ratio[2]:.2f} (this tree / {other})"
        )


if __name__ == "__main__":
    run()
