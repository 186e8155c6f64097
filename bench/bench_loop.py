"""The gateway's 1 kHz cycle against the soft PLC over Modbus TCP on loopback, and the floor.

``python -m bench loop`` (``BENCH_SECONDS`` shortens the default 60 s). The soft PLC runs
as a subprocess (``cdpr-gateway sim-plc --port 0``); the gateway runs in this process for
the whole duration; right after, against the same server, the floor: a bare socket loop
doing the same function-23 transaction (``bench.modbus_floor.floor_roundtrips``).
Printed: cycles, overrun %, cycle-start jitter p50/p99/p99.9, the phases, round trip
p50/p99, CPU % and peak RSS of this process, and the gateway/floor round-trip ratio.
Then the same figures for CANopen on python-can's virtual bus (soft PLC in process).
Goals (issue 4, 2-core machine): overruns <= 0.1 %, jitter p99 <= 200 us, ratio <= 1.3,
RSS <= 80 MB. ``BENCH_BUSY_WAIT_S`` overrides ``loop.busy_wait_s``. Figures only: nothing
here asserts on time.
"""

from __future__ import annotations

import dataclasses
import os
import resource
import socket
import struct
import time
from typing import Any

import numpy as np

from gateway.config import Config, load_config
from gateway.daemon import build_driver
from gateway.loop import CyclicService
from gateway.stats import Ring
from sim_plc.demo import InProcessCanopenPlc, SoftPlc, with_port

FLOOR_MAX = 20000  # floor transactions (back to back)


def _us(ring: Ring | np.ndarray, *qs: float) -> str:
    data = ring.recent() if isinstance(ring, Ring) else ring
    if not data.size:
        return "n/a"
    return " / ".join(f"{v * 1e6:.0f}" for v in np.percentile(data, qs)) + " us"


def _floor(host: str, port: int, service: CyclicService, n: int) -> dict[str, np.ndarray]:
    """The floor back to back, and paced at the loop period (one transaction per call)."""
    try:
        from bench.modbus_floor import floor_roundtrips
    except ImportError as exc:
        print(f"  floor: not available ({exc})")
        return {}
    layout = getattr(service.driver, "layout", None)
    kwargs: dict[str, Any] = {}
    if layout is not None:
        kwargs = {"read_span": layout.read_span, "write_span": layout.write_span}
    unit = service.cfg.bus.modbus_tcp.unit_id
    floor_roundtrips(host, port, 200, unit, **kwargs)  # warm-up
    back_to_back = floor_roundtrips(host, port, n, unit, **kwargs)
    return {"back to back": back_to_back, "paced 1 kHz": _paced(host, port, n // 4, service)}


def _paced(host: str, port: int, n: int, service: CyclicService) -> np.ndarray:
    """The floor's fc23 transaction once per loop period on one socket (the loop's rhythm)."""
    from bench.modbus_floor import DEFAULT_READ_SPAN, DEFAULT_WRITE_SPAN, _fc23_frame

    layout = getattr(service.driver, "layout", None)
    read_span = layout.read_span if layout is not None else DEFAULT_READ_SPAN
    write_span = layout.write_span if layout is not None else DEFAULT_WRITE_SPAN
    frame = _fc23_frame(service.cfg.bus.modbus_tcp.unit_id, read_span, write_span)
    reply_len = 9 + 2 * read_span.count
    rx = bytearray(reply_len)
    view = memoryview(rx)
    out = np.empty(n)
    with socket.create_connection((host, port), timeout=1.0) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        deadline = time.perf_counter()
        for i in range(n):
            deadline += service.period_s
            struct.pack_into(">H", frame, 0, i & 0xFFFF)
            t0 = time.perf_counter()
            sock.sendall(frame)
            got = 0
            while got < reply_len:
                k = sock.recv_into(view[got:])
                if k == 0:
                    raise ConnectionResetError(f"{host}:{port}: connection closed")
                got += k
            out[i] = time.perf_counter() - t0
            rest = deadline - time.perf_counter()
            if rest > 0:
                time.sleep(rest)
    return out


def _timed_run(service: CyclicService, cycles: int) -> tuple[float, float]:
    """Run ``cycles``; return (wall s, CPU fraction of one core of this process)."""
    usage0, wall0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    service.run(cycles=cycles)
    usage1, wall1 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    cpu = usage1.ru_utime + usage1.ru_stime - usage0.ru_utime - usage0.ru_stime
    return wall1 - wall0, cpu / (wall1 - wall0)


def _report(title: str, service: CyclicService, wall: float, cpu: float) -> None:
    stats = service.stats
    print(f"  {title}, {wall:.1f} s, busy-wait {service.busy_wait_s * 1e6:.0f} us")
    print(f"  cycles              {stats.cycles} (written {stats.written})")
    print(f"  overruns            {stats.overruns} ({100 * stats.overruns / stats.cycles:.3f} %),"
          f" {stats.skipped} deadlines skipped")  # fmt: skip
    print(f"  jitter p50/p99/p99.9  {_us(stats.jitter_ring, 50, 99, 99.9)}")
    print(f"  cycle p50/p99       {_us(stats.cycle_ring, 50, 99)}")
    print(f"  phases p50: read {_us(stats.read_ring, 50)}, compensate "
          f"{_us(stats.compensate_ring, 50)}, write {_us(stats.write_ring, 50)}")  # fmt: skip
    print(f"  round trip p50/p99  {_us(stats.roundtrip_ring, 50, 99)}")
    print(f"  errors              {sum(stats.errors.values())} {stats.errors}")
    print(f"  CPU                 {100 * cpu:.0f} % of one core (this process)")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"  peak RSS            {peak:.0f} MB (this process so far)")


def run_modbus(cfg: Config, seconds: float) -> None:
    cycles = max(1, round(seconds / cfg.loop.period_s))
    plc = SoftPlc(str(cfg.source), "modbus_tcp")
    try:
        live = with_port(cfg, "modbus_tcp", plc.host, plc.port)
        service = CyclicService(live, build_driver(live), history=cycles + 16)
        wall, cpu = _timed_run(service, cycles)
        floor = _floor(plc.host, plc.port, service, min(cycles, FLOOR_MAX))
    finally:
        plc.close()
    _report("gateway vs soft PLC (subprocess) over modbus_tcp on loopback", service, wall, cpu)
    gw = service.stats.roundtrip_ring.recent()
    for name, times in floor.items():
        print(f"  floor {name:<13} round trip p50/p99 {_us(times, 50, 99)} (n={times.size}); "
              f"ratio gateway/floor p50 {np.median(gw) / np.median(times):.2f}, "
              f"p99 {np.percentile(gw, 99) / np.percentile(times, 99):.2f}")  # fmt: skip


def run_canopen(cfg: Config, seconds: float) -> None:
    """The loop paced by the soft PLC's SYNC on python-can's virtual bus, all in process.

    Jitter here is the lateness of the data after its SYNC; the round trip is the read
    call (it waits for the SYNC set); CPU includes the PLC's and the plant's threads.
    """
    cycles = max(1, round(seconds / cfg.bus.canopen.sync_period_s))
    plc = InProcessCanopenPlc(cfg)
    try:
        service = CyclicService(plc.cfg, build_driver(plc.cfg), history=cycles + 16)
        wall, cpu = _timed_run(service, cycles)
    finally:
        plc.close()
    _report("gateway vs soft PLC over canopen (virtual bus, in process)", service, wall, cpu)


def run() -> None:
    seconds = float(os.environ.get("BENCH_SECONDS", "60"))
    cfg = load_config()
    if "BENCH_BUSY_WAIT_S" in os.environ:  # spin before each deadline (config loop.busy_wait_s)
        loop = dataclasses.replace(cfg.loop, busy_wait_s=float(os.environ["BENCH_BUSY_WAIT_S"]))
        cfg = dataclasses.replace(cfg, loop=loop)
    run_modbus(cfg, seconds)
    print()
    run_canopen(cfg, seconds)
    print(f"  load average        {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
