"""Shared pieces of the Modbus tests: configs on free ports, a filled process image, the
soft PLC server as a context manager, raw MBAP frames and a tiny scripted fake server."""

from __future__ import annotations

import contextlib
import dataclasses
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from gateway.core.config import Config, load_config
from sim_plc.image import ProcessImage
from sim_plc.modbus_server import ModbusPlcServer

LOCALHOST = "127.0.0.1"


def config_for(port: int, cfg: Config | None = None, **modbus: Any) -> Config:
    """The default config (or ``cfg``) with the Modbus client pointed at ``port``."""
    cfg = cfg or load_config()
    modbus.setdefault("timeout_s", 1.0)  # generous: the test machine is shared and slow
    mb = dataclasses.replace(cfg.bus.modbus_tcp, host=LOCALHOST, port=port, **modbus)
    return dataclasses.replace(cfg, bus=dataclasses.replace(cfg.bus, modbus_tcp=mb))


def filled_image(cables: int = 8) -> ProcessImage:
    """A process image with distinct, exactly representable values in every variable."""
    img = ProcessImage(cables)
    img.raw_counts[:] = np.arange(cables) * 3000 + 100
    img.velocity_m_s[:] = np.linspace(-0.5, 0.5, cables)
    img.length_m[:] = 1.0 + 0.25 * np.arange(cables)
    img.pose[:] = (0.125, -0.25, 1.5, 0.0625, -0.03125, 0.5)
    img.plc_heartbeat = 4242
    img.true_tension_n[:] = 100.0 + 12.5 * np.arange(cables)
    return img


@contextlib.contextmanager
def plc_server(
    image: ProcessImage | None = None, cfg: Config | None = None, port: int = 0
) -> Iterator[tuple[ModbusPlcServer, ProcessImage, Config]]:
    """A running soft PLC server on a free loopback port; yields (server, image, cfg)."""
    cfg = cfg or load_config()
    image = image if image is not None else filled_image(cfg.cables)
    server = ModbusPlcServer(cfg, image, host=LOCALHOST, port=port)
    server.start()
    try:
        yield server, image, config_for(server.port, cfg)
    finally:
        server.stop()


def mbap(pdu: bytes, tid: int = 1, unit: int = 1) -> bytes:
    """A Modbus TCP frame around ``pdu``."""
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def raw_transaction(sock: socket.socket, pdu: bytes, tid: int = 1) -> bytes:
    """Send one request and return the reply's PDU (function code onwards)."""
    sock.sendall(mbap(pdu, tid))
    header = _recv_exact(sock, 7)
    rtid, _proto, length, _unit = struct.unpack(">HHHB", header)
    assert rtid == tid, f"reply tid {rtid} != {tid}"
    return _recv_exact(sock, length - 1)


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionResetError("closed")
        data += chunk
    return data


def words(values: np.ndarray, dtype: str) -> list[int]:
    """Values packed as big-endian ``dtype`` and split into register words."""
    return np.asarray(values, dtype=dtype).view(">u2").astype(int).tolist()


def from_words(regs: list[int], dtype: str) -> np.ndarray:
    """Register words back to values of big-endian ``dtype``."""
    return np.asarray(regs, dtype=">u2").view(dtype).astype(float)


Responder = Callable[[bytes, int], list[tuple[float, bytes]]]


class FakeServer:
    """A scripted TCP peer: for the k-th request frame (k = 0, 1, ...) ``respond(frame, k)``
    returns (delay_s, bytes) pairs sent in order. One connection at a time, bounded."""

    def __init__(self, respond: Responder) -> None:
        self.respond = respond
        self.listener = socket.create_server((LOCALHOST, 0))
        self.listener.settimeout(0.1)
        self.port = self.listener.getsockname()[1]
        self.requests: list[bytes] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        deadline = time.monotonic() + 30.0
        while not self._stop.is_set() and time.monotonic() < deadline:
            try:
                conn, _ = self.listener.accept()
            except TimeoutError:
                continue
            with conn:
                self._serve(conn, deadline)

    def _serve(self, conn: socket.socket, deadline: float) -> None:
        conn.settimeout(0.1)
        while not self._stop.is_set() and time.monotonic() < deadline:
            try:
                header = _recv_exact(conn, 7)
                frame = header + _recv_exact(conn, struct.unpack(">H", header[4:6])[0] - 1)
            except TimeoutError:
                continue
            except OSError:
                return
            k = len(self.requests)
            self.requests.append(frame)
            for delay, data in self.respond(frame, k):
                if self._stop.wait(delay):
                    return
                conn.sendall(data)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.listener.close()

    def __enter__(self) -> FakeServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def fc3_reply(request: bytes, tid: int | None = None, regs: dict[int, int] | None = None) -> bytes:
    """A valid function-3/23 reply to ``request``: registers 0 except ``regs`` (offset in
    the read span -> value); the request's transaction id unless ``tid`` is given."""
    rtid, _, _, unit = struct.unpack(">HHHB", request[:7])
    fc = request[7]
    count = struct.unpack(">H", request[10:12])[0]
    values = np.zeros(count, dtype=">u2")
    for k, v in (regs or {}).items():
        values[k] = v
    pdu = bytes((fc, 2 * count)) + values.tobytes()
    return mbap(pdu, rtid if tid is None else tid, unit)


def exception_reply(request: bytes, code: int) -> bytes:
    """An exception reply to ``request``."""
    rtid, _, _, unit = struct.unpack(">HHHB", request[:7])
    return mbap(bytes((0x80 | request[7], code)), rtid, unit)
