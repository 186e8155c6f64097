"""Freed large arrays go back to the operating system (glibc's malloc tuned once).

glibc serves an allocation from its heap when it is below a *dynamic* mmap threshold, and
every large mmapped block that is freed raises that threshold (up to 32 MiB). After the
first few frees, the 1-30 MB numpy temporaries of a long diagnosis (one cable's series,
its simulations, residuals) land in the heap, where freed ones stay resident between
live ones: on a 10-min, 8-cable recording 60-90 MB of peak RSS beyond what is alive.
:func:`return_large_frees` fixes the threshold (``mallopt(M_MMAP_THRESHOLD)``, which
also ends the dynamic adjustment), so that every block of ``threshold`` bytes or more is
its own mapping, unmapped when freed. Results are unchanged (only where memory lives);
it costs a page fault per page of each new large array. No-op where there is no glibc.
"""

from __future__ import annotations

import ctypes

M_MMAP_THRESHOLD = -3  # glibc malloc.h
DEFAULT_THRESHOLD = 1 << 20
_set: list[int] = []


def return_large_frees(threshold: int = DEFAULT_THRESHOLD) -> bool:
    """Make blocks of ``threshold`` bytes or more separate mappings (once per process);
    True when glibc took the setting."""
    if _set:
        return True
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # not glibc (macOS, Windows): nothing to do
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    if mallopt(M_MMAP_THRESHOLD, int(threshold)) != 1:  # musl's stub returns 0
        return False
    _set.append(int(threshold))
    return True


def trim_heap() -> bool:
    """Give the free pages inside glibc's heap back to the system (``malloc_trim(0)``):
    after many small blocks are freed (a matplotlib figure: tens of MB) that are not at
    the heap's top. True when it was called; no-op where there is no glibc."""
    try:
        malloc_trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):
        return False
    malloc_trim.argtypes = (ctypes.c_size_t,)
    malloc_trim.restype = ctypes.c_int
    malloc_trim(0)
    return True
