"""Run the benchmarks: ``python -m bench`` (all but the soak) or ``python -m bench model statics``.

The 600-s soak, the calibrate table (~30 min) and the real recordings (~6 min, data read
from outside the checkout) run only when named (``python -m bench soak``, ``make soak``,
``python -m bench calibrate``, ``python -m bench real``), and so do the wrench reference's
(``python -m bench wrench``: two 10-min diagnoses, minutes each), ``wrench_lsq`` and
``joint`` (five 10-min diagnoses and one of three).
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
import time
from pathlib import Path

# minutes each: only when named, not in `make bench`
ONLY_BY_NAME = {"soak", "calibrate", "real", "wrench_lsq", "wrench", "joint"}


def main(argv: list[str]) -> int:
    here = Path(__file__).parent
    names = sorted(
        m.name.removeprefix("bench_")
        for m in pkgutil.iter_modules([str(here)])
        if m.name.startswith("bench_")
    )
    chosen = argv or [n for n in names if n not in ONLY_BY_NAME]
    unknown = [n for n in chosen if n not in names]
    if unknown:
        print(f"unknown benchmark(s): {', '.join(unknown)}; known: {', '.join(names)}")
        return 2
    for name in chosen:
        print(f"== bench {name}", flush=True)
        start = time.perf_counter()
        importlib.import_module(f"bench.bench_{name}").run()
        print(f"   ({time.perf_counter() - start:.1f} s)\n", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
