"""Calling a compiled kernel without numba's per-call type dispatch.

A numba dispatcher works out the types of its arguments on every call; for tuples of
arrays (the structured state the kernels take) that costs about 1-2 us per call, more
than the kernels themselves. :func:`entry_point` compiles (or loads from the cache) the
kernel for the types of example arguments once and returns the compiled entry, which
only unboxes. The caller must then pass arguments of exactly those types on every call:
the cycle's own preallocated buffers, Python floats and bools.

A compile helper, not physics: it stands below every layer that compiles a kernel (the
model, the drivers' output gate, the loop) and imports numba only when called, so that
importing it (or a module that takes it) loads nothing compiled.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


def entry_point(dispatcher: Any, *args: Any) -> Callable[..., Any]:
    """The compiled entry of ``dispatcher`` for the types of ``args`` (see module doc)."""
    import numba  # when a kernel is compiled, never at import

    sig = tuple(numba.typeof(a) for a in args)
    dispatcher.compile(sig)
    return dispatcher.overloads[sig].entry_point
