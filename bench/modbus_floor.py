"""The floor of a Modbus TCP cycle: a bare socket loop doing the gateway's transaction.

``floor_roundtrips`` sends the same function-23 frame as the driver (write
``write_span``, read ``read_span``) over a plain TCP socket with ``TCP_NODELAY`` and
reads the reply with ``recv_into``; no decoding, no checks beyond the frame length. The
gateway benchmark prints it beside the driver's round trip (goal: ratio <= 1.3).

Runnable alone: ``python -m bench.modbus_floor [N]`` starts a soft PLC server on a free
loopback port and prints the server's, the floor's and the driver's round trips side by
side (blocks of each, interleaved); ``python -m bench.modbus_floor HOST PORT N`` measures
the floor against a running server.
"""

from __future__ import annotations

import socket
import struct
import sys
import time
from dataclasses import replace
from typing import Any

import numpy as np

from drivers.base import Inputs, Outputs
from drivers.registers import Span

DEFAULT_READ_SPAN = Span(0, 53)  # the default map's inputs
DEFAULT_WRITE_SPAN = Span(100, 38)  # the default map's outputs


def _fc23_frame(unit_id: int, read_span: Span, write_span: Span) -> bytearray:
    nbytes = 2 * write_span.count
    pdu = struct.pack(
        ">BHHHHB", 23, read_span.start, read_span.count, write_span.start, write_span.count, nbytes
    )
    frame = bytearray(struct.pack(">HHHB", 0, 0, len(pdu) + nbytes + 1, unit_id))
    frame += pdu + bytes(nbytes)
    return frame


def floor_roundtrips(
    host: str,
    port: int,
    n: int,
    unit_id: int = 1,
    read_span: Span = DEFAULT_READ_SPAN,
    write_span: Span = DEFAULT_WRITE_SPAN,
    timeout_s: float = 1.0,
) -> np.ndarray:
    """``n`` function-23 round trips (s), shape (n,), measured send -> full reply.

    The written registers are zeros; run it against a server whose outputs may be
    overwritten (the soft PLC). Raises ``OSError``/``TimeoutError`` on socket trouble.
    """
    frame = _fc23_frame(unit_id, read_span, write_span)
    reply_len = 7 + 2 + 2 * read_span.count
    rx = bytearray(reply_len + 16)
    view = memoryview(rx)
    times = np.empty(n)
    with socket.create_connection((host, port), timeout=timeout_s) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        for i in range(n):
            struct.pack_into(">H", frame, 0, i & 0xFFFF)
            t0 = time.perf_counter()
            sock.sendall(frame)
            got = 0
            while got < reply_len:
                k = sock.recv_into(view[got:reply_len])
                if k == 0:
                    raise ConnectionResetError(f"{host}:{port}: connection closed")
                got += k
            times[i] = time.perf_counter() - t0
            if rx[7] != 23:
                raise OSError(f"{host}:{port}: function 23 answered with function {rx[7]}")
    return times


def driver_roundtrips(driver: Any, n: int) -> np.ndarray:
    """``n`` cycles of ``exchange(outputs, inputs)`` (one function-23 transaction each), s."""
    inputs = Inputs.allocate(driver.cables)
    outputs = Outputs.allocate(driver.cables)
    times = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter()
        driver.exchange(outputs, inputs)
        times[i] = time.perf_counter() - t0
    return times


def _thread_cpu_s(thread: Any) -> float:
    """CPU time (s) the thread ``thread`` has used so far (Linux: its own CPU clock)."""
    return time.clock_gettime(time.pthread_getcpuclockid(thread.ident))


def server_cost(n: int = 5000) -> tuple[float, np.ndarray]:
    """The soft PLC server's own CPU per request (s) over ``n`` floor round trips, and
    the round trips: the server in this process, its thread's CPU clock read before and
    after (so the client's and the kernel's loopback work on the client side are out)."""
    from gateway.core.config import load_config
    from sim_plc.image import ProcessImage
    from sim_plc.modbus_server import ModbusPlcServer

    cfg = load_config()
    server = ModbusPlcServer(cfg, ProcessImage(cfg.cables), port=0)
    server.start()
    try:
        thread = server._thread  # the serving thread (private: a bench reads it)
        floor_roundtrips("127.0.0.1", server.port, 500)  # warm up
        cpu0 = _thread_cpu_s(thread)
        times = floor_roundtrips("127.0.0.1", server.port, n)
        cpu = _thread_cpu_s(thread) - cpu0
    finally:
        server.stop()
    return cpu / n, times


def side_by_side(n: int = 5000, blocks: int = 5) -> dict[str, np.ndarray]:
    """Soft PLC server on a free port; floor and driver in interleaved blocks of n/blocks."""
    from drivers.modbus_tcp import ModbusTcpDriver
    from gateway.core.config import load_config
    from sim_plc.image import ProcessImage
    from sim_plc.modbus_server import ModbusPlcServer

    cfg = load_config()
    server = ModbusPlcServer(cfg, ProcessImage(cfg.cables), port=0)
    server.start()
    try:
        mb = replace(cfg.bus.modbus_tcp, port=server.port)
        cfg = replace(cfg, bus=replace(cfg.bus, modbus_tcp=mb))
        driver = ModbusTcpDriver(cfg)
        lay = driver.layout
        floor, drv = [], []
        with driver:
            driver_roundtrips(driver, 200)  # warm up both paths
            floor_roundtrips(
                "127.0.0.1", server.port, 200, mb.unit_id, lay.read_span, lay.write_span
            )
            for _ in range(blocks):
                floor.append(
                    floor_roundtrips(
                        "127.0.0.1",
                        server.port,
                        n // blocks,
                        mb.unit_id,
                        lay.read_span,
                        lay.write_span,
                    )
                )
                drv.append(driver_roundtrips(driver, n // blocks))
    finally:
        server.stop()
    return {"floor": np.concatenate(floor), "driver": np.concatenate(drv)}


def _report(name: str, t: np.ndarray) -> str:
    p50, p99 = np.percentile(t, [50, 99]) * 1e6
    return f"{name:<8} fc23 round trip  p50 {p50:6.0f} us  p99 {p99:6.0f} us  (n={len(t)})"


def main(argv: list[str]) -> int:
    if len(argv) >= 2:
        n = int(argv[2]) if len(argv) > 2 else 5000
        print(_report("floor", floor_roundtrips(argv[0], int(argv[1]), n)))
        return 0
    per_request, times = server_cost(int(argv[0]) if argv else 5000)
    print(
        f"server   CPU per fc23 request {per_request * 1e6:6.1f} us (its thread's clock); "
        + _report("", times).strip()
    )
    res = side_by_side(int(argv[0]) if argv else 5000)
    for name, t in res.items():
        print(_report(name, t))
    ratio50 = np.median(res["driver"]) / np.median(res["floor"])
    ratio99 = np.percentile(res["driver"], 99) / np.percentile(res["floor"], 99)
    print(f"driver / floor: p50 {ratio50:.2f}  p99 {ratio99:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
