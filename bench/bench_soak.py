"""Soak: the gateway at 1 kHz against the soft PLC through the fault proxy, faults at random.

``SOAK_SECONDS`` (default 600) of gateway -> FaultProxy -> soft PLC on loopback: the
gateway (cyclic service + Modbus driver) in this process; the soft PLC, its heartbeat,
the proxy and the write oracle (tests/reliability_helpers.WriteOracle) in a child
process. A seeded schedule (``SOAK_SEED``, default 1) alternates quiet spells and fault
episodes of a random kind and length; after each episode the fault is cleared and the
gateway is given ``RECOVERY_WAIT_S`` to write an all-good frame again (a survived
fault). ``SOAK_FAULTS=0`` runs the same schedule without faults: a baseline for the
cycles the machine's load alone costs.

Printed: cycles executed, written, skipped (overruns), cycles lost (deadlines without a
write: skipped + executed without a write), faults injected by kind (proxy counters) and
episodes survived, the recovery in cycles, values lost (a channel value at the PLC that
is neither the value the constant inputs give, with status good/substituted, nor NaN
with status invalid: must be 0), the gateway process' RSS and open file descriptors at
start (after warm-up) and end. Figures only, never an assertion on time.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import os
import random
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from drivers.modbus_tcp import ModbusTcpDriver
from evaluation.faultproxy import FaultProxy
from gateway.core.config import load_config
from gateway.runtime.loop import CyclicService
from gateway.service.metrics import make_registry
from tests.reliability_helpers import (
    PlcHeartbeat,
    WriteOracle,
    gateway_config,
    soft_plc,
    wait_for,
)

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


class PlcSide:
    """The soft PLC, its heartbeat, the fault proxy and the write oracle in a child process
    (the gateway's process holds only the gateway, as in production)."""

    def __init__(self, seed: int) -> None:
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_plc_main, args=(child, seed), daemon=True)
        self._proc.start()
        self.port = int(self.call("port"))

    def call(self, op: str, *args: Any) -> Any:
        self._conn.send((op, args))
        if not self._conn.poll(30.0):
            raise TimeoutError(f"soft PLC process: no answer to {op}")
        return self._conn.recv()

    def close(self) -> None:
        with contextlib.suppress(OSError, EOFError, TimeoutError):
            self.call("quit")
        self._proc.join(10.0)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(5.0)


def _plc_main(conn: Any, seed: int) -> None:
    """Child process: serve commands until 'quit' (bounded: the parent always ends it).
    pymodbus' error log (frame dumps on every reset the proxy injects) is silenced."""
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    with contextlib.ExitStack() as stack:
        server, image, _ = stack.enter_context(soft_plc())
        stack.callback(PlcHeartbeat(image).start().stop)
        proxy = FaultProxy("127.0.0.1", server.port, seed=seed).start()
        stack.callback(proxy.stop)
        written = [0]
        oracle = WriteOracle(image, lambda: written[0])
        inner = oracle.hook(server.registers.write)

        def counted(address: int, values: list[int]) -> None:
            written[0] += 1
            inner(address, values)

        server.registers.write = counted  # type: ignore[method-assign]
        ops: dict[str, Callable[..., Any]] = {
            "port": lambda: proxy.port,
            "set_fault": lambda kind, params: proxy.set_fault(kind, **params),
            "clear": proxy.clear,
            "freeze": oracle.freeze,
            "watch": oracle.watch_recovery,
            "recovered": lambda: oracle.recovered_at is not None,
            "good_writes": lambda: oracle.all_good_writes,
            "report": lambda: {
                "counters": proxy.counters,
                "writes": oracle.writes,
                "all_good": oracle.all_good_writes,
                "flagged": oracle.flagged_writes,
                "bad_values": oracle.bad_values,
                "bad": oracle.bad[:5],
            },
        }
        while True:
            op, args = conn.recv()
            if op == "quit":
                conn.send(None)
                return
            conn.send(ops[op](*args))


class Gateway:
    """The gateway in this process: cyclic service + Modbus driver, pointed at the proxy."""

    def __init__(self, port: int, period_s: float = 0.001) -> None:
        self.period_s = period_s
        self.cfg = gateway_config(load_config(), port, period_s, timeout_s=0.05)
        self.service = CyclicService(self.cfg, ModbusTcpDriver(self.cfg), history=4096)
        self.registry = make_registry(self.service)
        self._thread = threading.Thread(target=self.service.run, daemon=True, name="gateway")
        self._thread.start()

    def stop(self) -> None:
        self.service.stop()
        self._thread.join(10.0)

    def errors(self) -> dict[str, float]:
        return {
            s.labels["kind"]: s.value
            for family in self.registry.collect()
            for s in family.samples
            if s.name == "cdpr_gateway_errors_total"
        }

    def reconnects(self) -> float:
        v = self.registry.get_sample_value("cdpr_gateway_reconnects_total", {"bus": "modbus_tcp"})
        return float(v or 0.0)


def _episode(gw: Gateway, plc: PlcSide, rng: random.Random, end: float) -> int | None:
    """One quiet spell and one fault episode; recovery in cycles (polled, an upper bound)
    or None when the gateway did not write an all-good frame within RECOVERY_WAIT_S."""
    time.sleep(min(rng.uniform(0.2, 1.0), max(0.0, end - time.monotonic())))
    kind, params, (lo, hi) = MENU[rng.randrange(len(MENU))]
    if os.environ.get("SOAK_FAULTS", "1") != "0":  # SOAK_FAULTS=0: the same schedule, clean
        plc.call("set_fault", kind, params)
    time.sleep(rng.uniform(lo, hi))
    plc.call("watch")
    plc.call("clear")
    cleared_at = gw.service.stats.cycles
    if not wait_for(lambda: bool(plc.call("recovered")), RECOVERY_WAIT_S, poll_s=0.001):
        return None
    return int(gw.service.stats.cycles) - cleared_at


def _report(gw: Gateway, plc: dict[str, Any], res: dict[str, Any]) -> None:
    s = gw.service.stats
    recovered = [r for r in res["episodes"] if r is not None]
    injected = {k: v for k, v in plc["counters"].items() if k in {m[0] for m in MENU}}
    lost = s.skipped + (s.cycles - s.written)
    deadlines = res["elapsed_s"] / gw.period_s
    print(f"soak: {res['elapsed_s']:.0f} s at {1 / gw.period_s:.0f} Hz, seed {res['seed']}")
    print(
        f"  cycles: executed {s.cycles}, written {s.written}, skipped {s.skipped} "
        f"(overruns {s.overruns}); deadlines ~{deadlines:.0f}; cycles lost {lost}"
    )
    print(f"  faults injected (frames): {sum(injected.values())} {injected}")
    failed = len(res["episodes"]) - len(recovered)
    print(
        f"  fault episodes: {len(res['episodes'])}, survived {len(recovered)}, "
        f"not recovered within {RECOVERY_WAIT_S} s: {failed}"
    )
    if recovered:
        print(
            f"  recovery after clear (polled, upper bound): median "
            f"{np.median(recovered):.0f} cycles, max {max(recovered)} cycles"
        )
    print(f"  gateway errors: {gw.errors()}, reconnects {gw.reconnects():.0f}")
    print(
        f"  writes at the PLC: {plc['writes']} (all good {plc['all_good']}, flagged "
        f"{plc['flagged']}); values lost {plc['bad_values']}"
    )
    for line in plc["bad"]:
        print(f"    {line}")
    m = res["mem"]
    growth = m["rss_end"] - m["rss_start"]
    print(
        f"  gateway process RSS: start {m['rss_start'] / 1024:.1f} MiB, end "
        f"{m['rss_end'] / 1024:.1f} MiB, growth {growth / 1024:+.1f} MiB; open fds: "
        f"start {m['fd_start']}, end {m['fd_end']}"
    )


def run() -> None:
    seconds = float(os.environ.get("SOAK_SECONDS", "600"))
    seed = int(os.environ.get("SOAK_SEED", "1"))
    plc = PlcSide(seed)
    try:
        gw = Gateway(plc.port)
        try:
            assert wait_for(lambda: plc.call("good_writes") >= 100, 30.0), "no warm-up"
            plc.call("freeze")
            mem = {"rss_start": _rss_kib(), "fd_start": _fds()}
            rng, started = random.Random(seed), time.monotonic()
            end, episodes = started + seconds, []
            while time.monotonic() < end:  # bounded by the clock; each episode is bounded
                episodes.append(_episode(gw, plc, rng, end))
            elapsed = time.monotonic() - started
            mem.update(rss_end=_rss_kib(), fd_end=_fds())
        finally:
            gw.stop()
        res = {"episodes": episodes, "elapsed_s": elapsed, "seed": seed, "mem": mem}
        _report(gw, plc.call("report"), res)
    finally:
        plc.close()


if __name__ == "__main__":
    run()
