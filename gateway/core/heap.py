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
    the heap's top; and LLVM's resident code and data, which only loading a kernel uses
    (:func:`drop_clean_pages`). True when malloc_trim was called; no-op where there is no
    glibc."""
    drop_clean_pages()
    try:
        malloc_trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):
        return False
    malloc_trim.argtypes = (ctypes.c_size_t,)
    malloc_trim.restype = ctypes.c_int
    malloc_trim(0)
    return True


MADV_DONTNEED = 4  # linux/mman.h
LOADER_LIBRARIES = ("libllvmlite", "libarrow", "libparquet")
"""Libraries whose code runs only while numba loads or compiles a kernel: LLVM (llvmlite),
~69 MiB of resident code and read-only data once the diagnosis' kernels are loaded (36 MiB of
it touched by its ~700 static initialisers when the library is loaded), none of it needed
while the kernels run; or while a Parquet file is read or written: Arrow and Parquet, ~30
MiB resident after a diagnosis reads a 10-min recording, none of it needed after."""


def drop_clean_pages(libraries: tuple[str, ...] = LOADER_LIBRARIES) -> int:
    """Unmap the resident pages of ``libraries`` that are unchanged copies of the file
    (``madvise(MADV_DONTNEED)`` on each of their mappings that holds no private, i.e.
    written, page: its smaps ``Anonymous: 0 kB``): they stay in the page cache, and a later
    use faults them back in (LLVM loading another kernel). Only where the memory is
    counted changes, never what the process computes. Returns the bytes that were
    resident; 0 where there is no ``/proc/self/smaps`` or ``madvise``."""
    try:
        with open("/proc/self/smaps", encoding="ascii", errors="replace") as f:
            text = f.read()
        madvise = ctypes.CDLL(None, use_errno=True).madvise
    except (OSError, AttributeError):
        return 0
    madvise.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)
    madvise.restype = ctypes.c_int
    dropped = 0
    for start, stop, perms, rss, anon in _mappings(text, libraries):
        if "w" in perms or anon is None or anon or not rss:  # None: no Anonymous line
            continue
        if madvise(start, stop - start, MADV_DONTNEED) == 0:
            dropped += rss
    return dropped


def _mappings(text: str, libraries: tuple[str, ...]):
    """(start, stop, perms, Rss bytes, Anonymous bytes or None if not listed) of the smaps
    entries of files whose name starts with one of ``libraries``."""
    entry: list | None = None
    for line in text.splitlines():
        head = line.split(None, 5)
        if head and not head[0].endswith(":"):  # a mapping's first line
            if entry is not None:
                yield tuple(entry)
            entry = None
            path = head[5] if len(head) > 5 else ""
            if path.rsplit("/", 1)[-1].startswith(libraries):
                lo, hi = (int(x, 16) for x in head[0].split("-"))
                entry = [lo, hi, head[1], 0, None]
        elif entry is not None and head and head[0] in ("Rss:", "Anonymous:"):
            entry[3 if head[0] == "Rss:" else 4] = int(head[1]) * 1024
    if entry is not None:
        yield tuple(entry)
