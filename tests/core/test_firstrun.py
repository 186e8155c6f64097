"""The first run says that numba compiles, once (gateway/core/firstrun.py)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

from gateway.core import firstrun

KERNEL = """
from numba import njit


@njit(cache=True)
def twice(x):
    return 2.0 * x
"""


def _load(path: Path, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def test_a_cold_kernel_is_said_once_and_a_warm_one_not_at_all(tmp_path, monkeypatch):
    src = tmp_path / "kernel_under_test.py"
    src.write_text(KERNEL)
    mod = _load(src, "kernel_under_test")
    said: list[str] = []
    assert firstrun.uncached([mod.twice]) == [mod.twice]
    with firstrun.compiling("test", [mod.twice], said.append):
        assert mod.twice(2.0) == 4.0
    assert len(said) == 2, said
    assert said[0].startswith("test: compiling the numba kernels, once")
    assert str(tmp_path / "__pycache__") in said[0]
    assert said[1].startswith("test: compiled in ")
    # the index is written: a new process (here: the module loaded again) is warm
    del sys.modules["kernel_under_test"]
    again = _load(src, "kernel_under_test")
    assert firstrun.uncached([again.twice]) == []
    quiet: list[str] = []
    with firstrun.compiling("test", [again.twice], quiet.append):
        assert again.twice(3.0) == 6.0
    assert quiet == []
    # the source changed: numba's index is stale, and it is said again
    src.write_text(KERNEL + "\n# changed\n")
    del sys.modules["kernel_under_test"]
    changed = _load(src, "kernel_under_test")
    assert firstrun.uncached([changed.twice]) == [changed.twice]


def test_a_long_compile_ticks(monkeypatch):
    monkeypatch.setattr(firstrun, "TICK_S", 0.01)
    monkeypatch.setattr(firstrun, "uncached", lambda kernels: list(kernels))

    class Fake:
        class _cache:
            cache_path = "/nowhere"

    said: list[str] = []
    import time

    with firstrun.compiling("slow", [Fake()], said.append):
        time.sleep(0.1)
    assert any(s.startswith("slow: still compiling") for s in said), said
    assert said[-1].startswith("slow: compiled in ")


def test_non_numba_objects_are_never_cold():
    assert firstrun.uncached([len, object()]) == []
