"""Soak: the gateway at 1 kHz against the soft PLC through the fault proxy, faults at random.

``SOAK_SECONDS`` (default 600) of gateway -> FaultProxy -> soft PLC on loopback, all in
this process (tests/reliability_helpers.GatewayRig). A seeded schedule (``SOAK_SEED``,
default 1) alternates quiet spells and fault episodes of a random kind and length; after
each episode the fault is cleared and the gateway is given ``RECOVERY_WAIT_S`` to write
an all-good frame again (a survived fault).

Printed: cycles executed, written, skipped (overruns), cycles lost (deadlines without a
write: skipped + executed without a write), faults injected by kind (proxy counters) and
episodes survived, the recovery in cycles, values lost (a channel value at the PLC that
is neither the value the constant inputs give, with status good/substituted, nor NaN
with status invalid: must be 0), RSS and open file descriptors at start and end.
Figures only, never an assertion on time.
"""

from __future__ import annotations

import os
import random
import time
from pathlib import Path
from typing import Any

import numpy as np

from tests.reliability_helpers import GatewayRig, wait_for

RECOVERY_WAIT_S = 5.0
# (kind, params, episode length range s); in-episode randomness comes from the proxy rng
MENU: tuple[tuple[str, dict[str, Any], tuple[float, float]], ...] = (
    ("delay", {"seconds": 0.2, "direction": "reply"}, (0.2, 1.0)),
    ("delay", {"seconds": 0.003, "direction": "both"}, (0.5, 2.0)),
    ("drop", {"probability": 0.05}, (0.5, 2.0)),
    ("drop", {}, (0.1, 0.5)),
    ("split", {"pieces": 3, "pause_s": 0.0003}, (0.5, 2.0)),
    ("corrupt", {"where": "header", "nbytes": 1, "probability": 0.1}, (0.2, 1.0)),
    ("wrong_tid", {"probability": 0.2}, (0.2, 1.0)),
    ("reset", {"after_bytes": 5, "count": 1}, (0.1, 0.3)),
    ("silent", {}, (0.1, 1.0)),
    ("exception", {"code": 6, "probability": 0.3}, (0.2, 1.0)),
)


def _rss_kib() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return -1


def _fds() -> int:
    try:
        return len(os.listdir("/proc/self/fd"))
    except OSError:
        return -1


def _episode(rig: GatewayRig, rng: random.Random, end: float) -> tuple[str, int | None]:
    """One quiet spell and one fault episode; (kind, recovery cycles or None)."""
    time.sleep(min(rng.uniform(0.2, 1.0), max(0.0, end - time.monotonic())))
    kind, params, (lo, hi) = MENU[rng.randrange(len(MENU))]
    rig.proxy.set_fault(kind, **params)
    time.sleep(rng.uniform(lo, hi))
    rig.proxy.clear()
    rig.oracle.watch_recovery()
    cleared_at = rig.cycles
    if not wait_for(lambda: rig.oracle.recovered_at is not None, RECOVERY_WAIT_S):
        return kind, None
    return kind, int(rig.oracle.recovered_at or 0) - cleared_at


def _soak(rig: GatewayRig, seconds: float, seed: int) -> dict[str, Any]:
    rng = random.Random(seed)
    started = time.monotonic()
    end = started + seconds
    episodes: list[tuple[str, int | None]] = []
    while time.monotonic() < end:  # bounded by the clock; each episode is bounded too
        episodes.append(_episode(rig, rng, end))
    return {"episodes": episodes, "elapsed_s": time.monotonic() - started}


def _report(rig: GatewayRig, result: dict[str, Any], mem: dict[str, int]) -> None:
    s = rig.service.stats
    episodes = result["episodes"]
    recovered = [r for _, r in episodes if r is not None]
    counters = rig.proxy.counters
    injected = {k: v for k, v in counters.items() if k in {m[0] for m in MENU}}
    expected = result["elapsed_s"] / rig.period_s
    lost = s.skipped + (s.cycles - s.written)
    print(f"soak: {result['elapsed_s']:.0f} s at {1 / rig.period_s:.0f} Hz, seed {rig.seed}")
    print(f"  cycles: executed {s.cycles}, written {s.written}, skipped {s.skipped} "
          f"(overruns {s.overruns}); deadlines ~{expected:.0f}; cycles lost {lost}")  # fmt: skip
    print(f"  faults injected (frames): {sum(injected.values())} {injected}")
    failed = len(episodes) - len(recovered)
    print(f"  fault episodes: {len(episodes)}, survived {len(recovered)}, "
          f"not recovered within {RECOVERY_WAIT_S} s: {failed}")  # fmt: skip
    if recovered:
        print(f"  recovery after clear: median {np.median(recovered):.0f} cycles, "
              f"max {max(recovered)} cycles")  # fmt: skip
    print(f"  gateway errors: {rig.errors()}, reconnects {rig.reconnects():.0f}")
    print(f"  writes at the PLC: {rig.oracle.writes} (all good {rig.oracle.all_good_writes}, "
          f"flagged {rig.oracle.flagged_writes}); values lost {rig.oracle.bad_values}")  # fmt: skip
    for line in rig.oracle.bad[:5]:
        print(f"    {line}")
    growth = mem["rss_end"] - mem["rss_start"]
    print(f"  RSS: start {mem['rss_start'] / 1024:.1f} MiB, end {mem['rss_end'] / 1024:.1f} MiB, "
          f"growth {growth / 1024:+.1f} MiB; open fds: start {mem['fd_start']}, "
          f"end {mem['fd_end']}")  # fmt: skip


def run() -> None:
    seconds = float(os.environ.get("SOAK_SECONDS", "600"))
    seed = int(os.environ.get("SOAK_SEED", "1"))
    rss_before = _rss_kib()
    with GatewayRig(seed=seed) as rig:
        rig.warm_up()
        mem = {"rss_start": _rss_kib(), "fd_start": _fds()}
        result = _soak(rig, seconds, seed)
        wait_for(lambda: False, 0.5)  # let the last writes land
        mem.update(rss_end=_rss_kib(), fd_end=_fds())
        rig.service.stop()
        _report(rig, result, mem)
    print(f"  (RSS before the rig started: {rss_before / 1024:.1f} MiB; start = after warm-up)")


if __name__ == "__main__":
    run()
