"""Say so when numba compiles: the first run after installing compiles the kernels once.

numba caches each compiled kernel (``@njit(cache=True)``) beside its source, or in
``NUMBA_CACHE_DIR``; the first run after installing (or after an upgrade) compiles them,
which took ~100 s for the first ``record`` here and looked like a hang. :func:`compiling`
wraps the code that loads a set of kernels: when one it surely compiles is not in the cache
yet, it says in one line that they compile once and where they are kept, a line every
``TICK_S`` while it lasts, and how long it took. Warm, it says nothing.

Read from numba's cache objects as they are (``Dispatcher._cache``): where that is not
there (another numba), nothing is said, nothing fails.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

TICK_S = 10.0


def _index(kernel: Any) -> Path | None:
    cache = getattr(kernel, "_cache", None)
    path = getattr(getattr(cache, "_cache_file", None), "_index_path", None)
    return Path(path) if path else None


def _cached(kernel: Any) -> bool:
    """numba's index for ``kernel`` exists and matches its source file (numba's own check,
    the file's time stamp and size); True when this numba keeps it elsewhere."""
    cache_file = getattr(getattr(kernel, "_cache", None), "_cache_file", None)
    load = getattr(cache_file, "_load_index", None)
    if load is not None:
        try:
            return bool(load())  # {} when missing or stale
        except Exception:  # an unreadable index is one numba overwrites: compiling
            return False
    path = _index(kernel)
    return path is None or path.exists()


def uncached(kernels: Iterable[Any]) -> list[Any]:
    """The kernels numba would compile rather than load from its cache."""
    return [k for k in kernels if not _cached(k)]


@contextlib.contextmanager
def compiling(what: str, sentinels: Iterable[Any], say: Callable[[str], None]) -> Iterator[None]:
    """Around the code that first calls a set of kernels: ``sentinels`` are kernels it
    surely compiles (one per source file is enough: numba compiles a file's kernels as they
    are called, and their cache goes stale together when the file changes)."""
    cold = uncached(sentinels)
    if not cold:
        yield
        return
    where = Path(cold[0]._cache.cache_path)
    say(
        f"{what}: compiling the numba kernels, once: they are cached in {where} for the "
        "next runs (`cdpr-gateway warmup` does it ahead)"
    )
    start = time.monotonic()
    done = threading.Event()

    def tick() -> None:
        while not done.wait(TICK_S):
            say(f"{what}: still compiling ({time.monotonic() - start:.0f} s)")

    ticker = threading.Thread(target=tick, name="compile-progress", daemon=True)
    ticker.start()
    try:
        yield
    finally:
        done.set()
        ticker.join()
    say(f"{what}: compiled in {time.monotonic() - start:.1f} s")
