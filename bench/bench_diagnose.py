"""Diagnosis of a 10-minute, 1 kHz, 8-cable recording: seconds and peak memory.

Two recordings (scenario generator): a clean one (nothing to find) and one that holds a
viscous term on every cable and an offset on two of them (``DIAGNOSE_CASES=clean`` or
``hidden`` runs one). It is generated in a child process and handed over as an ``.npz`` file, so
that the figures are those of ``diagnose`` alone on a recording in memory: its wall time,
its peak Python heap (tracemalloc) and the peak resident size of the process (interpreter,
numpy/scipy/numba and the recording's arrays included). Goals: <= 60 s, <= 400 MB RSS.
"""

from __future__ import annotations

import multiprocessing
import os
import resource
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

SCENARIO_ARGS = dict(cables=8, seconds=600.0)


def _scenario(case: str = "hidden"):
    from sim_plc.scenarios import Scenario

    if case == "clean":
        return Scenario("bench-clean", {}, **SCENARIO_ARGS)
    offsets = (0.0, 0.3, 0.0, 0.0, -0.3, 0.0, 0.0, 0.0)
    return Scenario(
        "bench", {"viscous": {"c_ns_m": 6.0}, "offset": {"c_n": offsets}}, **SCENARIO_ARGS
    )


def _generate(path: str, case: str) -> None:
    from sim_plc.scenarios import make_recording

    rec = make_recording(_scenario(case))
    np.savez(
        path,
        t=rec.t,
        velocity=rec.velocity,
        tension_sensor=rec.tension_sensor,
        tension_platform=rec.tension_platform,
    )


def run() -> None:
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


if __name__ == "__main__":
    run()
