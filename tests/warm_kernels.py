"""Compile numba's kernels once before the pytest-xdist workers start (tests/conftest.py).

A cold cache (a fresh clone, a changed kernel source) is otherwise compiled by every
process that needs a kernel first, at the same time: both workers and the CLI subprocesses
of the tests (``record``, ``replicate``, ``sim-plc``) each compiled the soft PLC's plant,
tens of seconds of CPU apiece on a 2-core machine. Here the work of ``cdpr-gateway
warmup`` (sim_plc/warmup.py) is split in two parts run side by side, one per core:
``plant`` (the batch and the per-cycle plant: the longest) and ``rest`` (the gateway's
cycle and the diagnosis); warm, each takes a few seconds. Only kernels are compiled here;
nothing is asserted (the tests check what the kernels compute).

``python -m tests.warm_kernels PART``.
"""

from __future__ import annotations

import sys

PARTS = ("plant", "rest")


def warm(part: str) -> None:
    from gateway.core.config import DEFAULT_CONFIG_PATH, load_config

    cfg = load_config(DEFAULT_CONFIG_PATH)
    if part == "plant":
        from sim_plc.plant import Plant, make_recording

        make_recording(cfg, None, 0.01)
        plant = Plant(cfg, chunk=4)
        for _ in range(10):
            plant.step()
    elif part == "rest":
        from drivers.virtual import VirtualDriver
        from gateway.diagnose.engine import load_kernels
        from gateway.runtime.loop import CyclicService

        CyclicService(cfg, VirtualDriver(cfg), history=16)
        load_kernels(cfg.friction)
    else:
        raise SystemExit(f"warm_kernels: unknown part {part!r} (choose from {', '.join(PARTS)})")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit(f"usage: python -m tests.warm_kernels {{{','.join(PARTS)}}}")
    warm(sys.argv[1])
