"""Diagnosis of a 10-minute, 1 kHz, 8-cable recording: seconds and peak memory.

The recording (scenario generator, not timed) holds a viscous term on every cable and an
offset on two of them; the figure is the wall time of ``diagnose`` and its peak Python
heap (tracemalloc) plus the process' peak resident size. Goal: <= 60 s.
"""

from __future__ import annotations

import resource
import time
import tracemalloc

from gateway.diagnose.engine import diagnose
from sim_plc.scenarios import Scenario, make_recording

SCENARIO = Scenario(
    "bench",
    {"viscous": {"c_ns_m": 6.0}, "offset": {"c_n": (0.0, 0.3, 0.0, 0.0, -0.3, 0.0, 0.0, 0.0)}},
    cables=8,
    seconds=600.0,
)


def run() -> None:
    rec = make_recording(SCENARIO)
    tracemalloc.start()
    start = time.perf_counter()
    diag = diagnose(rec, SCENARIO.nominal())
    seconds = time.perf_counter() - start
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    found = ", ".join(f"{f['effect']} on {f['cables']}" for f in diag.report["findings"])
    print(
        f"diagnose {rec.samples} samples x {rec.cables} cables: {seconds:.1f} s "
        f"(goal <= 60 s), peak heap {peak / 2**20:.0f} MiB, peak RSS {rss_mb:.0f} MiB; "
        f"found {found or 'none'}"
    )


if __name__ == "__main__":
    run()
