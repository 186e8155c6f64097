"""``cdpr-gateway warmup [--config FILE]``: compile the numba kernels ahead, once.

The first run after installing compiles the kernels that the gateway's cycle, the soft
PLC's plant and the diagnosis use (numba caches them beside the sources, or in
``NUMBA_CACHE_DIR``; :mod:`gateway.core.firstrun` says so when it happens). This command
does it ahead, saying what it compiles and how long it takes, so that the daemon's first
start, the first ``demo`` and the first ``diagnose`` do not. The systemd unit runs it as
``ExecStartPre`` and ``make demo`` before the demo; warm, it takes a few seconds.

What it runs is one list, :data:`EXERCISES`: each entry calls the code a set of commands
calls, on a few samples (the configured model; and every registered effect at its example
values, so that a model file naming any effect finds its kernels compiled). It then says
whether that left every compiled function of the tree in numba's cache
(:func:`untouched`: each is compiled or loaded, or compiled into a kernel that is); a
function none of the exercises reaches is named, and ``tests/sim_plc/test_warmup.py``
fails on it.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import pkgutil
import re
import sys
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from gateway.core.config import Config

EPILOG = """example:
  cdpr-gateway warmup --config /etc/cdpr-gateway/gateway.yaml"""

PACKAGES = ("gateway", "drivers")
"""The packages whose compiled functions the commands call (the soft PLC's run from
:mod:`gateway.model`)."""
_JIT = re.compile(r"\bnjit\b|\bnumba\.jit\b|@jit\b")
_SAMPLES = 8
_CABLES = 2


def configure_parser(command: str, parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config",
        metavar="FILE",
        help="the config whose model the kernels are compiled for (default: the bundled "
        "loopback config)",
    )
    parser.epilog = EPILOG
    parser.formatter_class = argparse.RawDescriptionHelpFormatter


def _cycle(cfg: Config) -> None:
    from drivers.virtual import VirtualDriver
    from gateway.runtime.loop import CyclicService

    CyclicService(cfg, VirtualDriver(cfg), history=16)  # its log says when it compiles


def _bus(cfg: Config) -> None:
    from drivers.base import make_driver

    make_driver(cfg)  # built, not opened: a driver compiles its register codecs here


def _soft_plc(cfg: Config) -> None:
    from sim_plc.image import ProcessImage
    from sim_plc.modbus_image import ImageRegisters
    from sim_plc.plant import Plant

    plant, image = Plant(cfg, chunk=4), ProcessImage(cfg.cables)
    for _ in range(10):
        plant.step(image)
    if cfg.bus.modbus_tcp is not None:  # the registers sim-plc serves
        regs = ImageRegisters(cfg, image)
        out = regs.output_area
        regs.write(out.start, regs.read(out.start, out.count))


def _record(cfg: Config) -> None:
    from sim_plc.plant import make_recording, stream_recording

    make_recording(cfg, None, 0.01)  # calibrate: the batch plant (it says so)
    for _ in stream_recording(cfg, None, 0.01, chunk=4):  # record: block by block
        pass


def _series(cables: int) -> tuple[Any, np.ndarray]:
    from gateway.model import effects as fx

    t = np.arange(_SAMPLES) * 1e-3
    v = 0.1 * np.sin(np.arange(_SAMPLES * cables).reshape(_SAMPLES, cables))
    x = 2.0 + np.cumsum(v, axis=0) * 1e-3
    s = fx.SeriesData(t, v, x, fx.acceleration(t, v), 0.0)
    return s, np.full((_SAMPLES, cables), 300.0) + v


def _every_effect(cables: int) -> Any:
    from gateway.model import effects as fx

    return fx.effect_values({n: dict(e.example) for n, e in fx.REGISTRY.items()}, cables)


def _chains(cfg: Config) -> None:
    """The chain both ways, as a batch run (replay, diagnose, replicate, the wrench
    reference) and per cycle (the gateway, the plant): the nominal chain of each law and
    the nominal plus each chain-side effect (stretch, play, Maxwell-slip elements, ...)."""
    from gateway.model import chain_runs
    from gateway.model import effects as fx
    from gateway.model.chain_schema import LAWS

    s, y = _series(_CABLES)
    every = _every_effect(_CABLES)
    chains = [fx.chain_params(cfg.friction, {}, _CABLES).with_model(law) for law in LAWS]  # type: ignore[arg-type]
    chains += [fx.chain_params(cfg.friction, {n: every[n]}, _CABLES) for n in fx.stage_of("chain")]
    out = np.empty(_CABLES)
    for p in chains:
        for direction in ("compensate", "simulate"):
            chain_runs.run(p, direction, y, s.v, s.t)
        for forward in (True, False):
            chain_runs.ChainStepper(p, 1e-3, forward).step(y[0], s.v[0], out)


def _effects(cfg: Config) -> None:
    """Every registered path and sensor effect: the batch forms (the plant's recording,
    the diagnosis), the plant's per-sample steppers and the gateway's online inverse."""
    from gateway.model import effects as fx

    s, y = _series(_CABLES)
    every = _every_effect(_CABLES)
    fx.inverse(s, fx.forward(s, y, every), every)
    stepper = fx.ForwardStepper(every, _CABLES, 1e-3)
    stepper.step(fx.Sample(1, float(s.t[1]), s.t[:3], s.v[:3], s.x[1]), y[1].copy())
    fx.compensate_online(fx.chain_params(cfg.friction, every, _CABLES), every, s.t, y, s.v, s.x)
    out = np.empty(_CABLES)
    online = fx.OnlineInverse(every, _CABLES, out, s.v[1], s.v[0], s.x[1])
    online(y[1], out, s.v[1], s.v[0], 1e-3, s.x[1])


def _diagnosis(cfg: Config) -> None:
    from gateway.diagnose import lsq
    from gateway.diagnose.engine import load_kernels

    load_kernels(cfg.friction)
    lsq.dahl_force(np.full(3, 100.0), np.array([0.0, 1e-4, -1e-4]), 0.01, 0.0, 500.0)


EXERCISES: tuple[tuple[str, str, Callable[[Config], None]], ...] = (
    ("the gateway's cycle", "run, demo", _cycle),
    ("the bus driver's codecs", "run, check --connect", _bus),
    ("the soft PLC", "sim-plc, demo", _soft_plc),
    ("the batch plant", "record, calibrate", _record),
    ("the chain, both ways", "replay, diagnose, replicate, run", _chains),
    ("every registered effect", "diagnose, record, run with a fitted model", _effects),
    ("the diagnosis", "diagnose, calibrate, fleet", _diagnosis),
)
"""What warmup runs: (what, the commands that call it, the exercise on a config)."""


def compiled_functions(packages: Iterable[str] = PACKAGES) -> dict[str, Any]:
    """Every numba dispatcher defined in a module of ``packages`` (the modules whose source
    applies numba's decorators, imported), by dotted name."""
    from numba.core.dispatcher import Dispatcher

    found: dict[str, Any] = {}
    for pkg in packages:
        root = importlib.import_module(pkg)
        for info in pkgutil.walk_packages(root.__path__, f"{pkg}."):
            spec = importlib.util.find_spec(info.name)
            origin = getattr(spec, "origin", None)
            if info.ispkg or not origin or not _JIT.search(Path(origin).read_text()):
                continue
            module = importlib.import_module(info.name)
            for name, obj in vars(module).items():
                if isinstance(obj, Dispatcher) and obj.py_func.__module__ == module.__name__:
                    found[f"{module.__name__}.{name}"] = obj
    return found


def _callees(d: Any, dispatchers: set[int]) -> list[Any]:
    """The dispatchers ``d``'s source calls (by a global name or ``module.name``): numba
    compiles them into ``d`` (or inlines them)."""
    names = d.py_func.__code__.co_names
    glb = d.py_func.__globals__
    out = []
    for n in names:
        obj = glb.get(n)
        if obj is not None and id(obj) in dispatchers:
            out.append(obj)
        elif isinstance(obj, type(sys)):  # a module: its attributes the code names
            out += [getattr(obj, a) for a in names if id(getattr(obj, a, None)) in dispatchers]
    return out


def untouched(functions: dict[str, Any]) -> list[str]:
    """The names of ``functions`` this process neither compiled nor loaded from the cache
    (no signature) and that no function it did calls (numba compiles a callee into its
    caller, or inlines it), sorted."""
    ids = {id(d) for d in functions.values()}
    reached = [d for d in functions.values() if d.signatures]
    seen = {id(d) for d in reached}
    while reached:
        for c in _callees(reached.pop(), ids):
            if id(c) not in seen:
                seen.add(id(c))
                reached.append(c)
    return sorted(n for n, d in functions.items() if id(d) not in seen)


def run_command(command: str, args: argparse.Namespace) -> int:
    from gateway.core.config import DEFAULT_CONFIG_PATH, load_config

    def say(line: str) -> None:
        print(f"warmup: {line}", file=sys.stderr, flush=True)

    start = time.monotonic()
    cfg = load_config(args.config or DEFAULT_CONFIG_PATH)
    for what, _commands, exercise in EXERCISES:
        begin = time.monotonic()
        exercise(cfg)
        say(f"{what}: {time.monotonic() - begin:.1f} s")
    functions = compiled_functions()
    missed = untouched(functions)
    took = time.monotonic() - start
    if missed:
        say(
            f"{len(missed)} of {len(functions)} compiled functions not compiled ahead (the "
            f"first command that calls one compiles it): {', '.join(missed)} ({took:.1f} s)"
        )
    else:
        say(f"every compiled function ({len(functions)}) is in numba's cache ({took:.1f} s)")
    return 0
