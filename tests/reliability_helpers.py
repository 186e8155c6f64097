"""Shared helpers of the reliability tests: raw Modbus/TCP frames over bounded sockets,
and a tiny Modbus-like echo server on 127.0.0.1 (a free port).

Every socket operation here has a timeout; every loop is bounded.
"""

from __future__ import annotations

import contextlib
import socket
import struct
import threading
from collections.abc import Iterator
from typing import TYPE_CHECKING

from gateway.config import Config, load_config
from sim_plc.image import ProcessImage

if TYPE_CHECKING:
    from sim_plc.modbus_server import ModbusPlcServer

IO_TIMEOUT_S = 2.0  # generous: a reply that must come, comes within this on loopback


def mbap(
    tid: int, pdu: bytes, unit: int = 1, protocol: int = 0, length: int | None = None
) -> bytes:
    """A Modbus/TCP frame: MBAP (tid, protocol id, length = unit + PDU) + unit + PDU."""
    n = len(pdu) + 1 if length is None else length
    return struct.pack(">HHHB", tid & 0xFFFF, protocol, n, unit) + pdu


def read_pdu(address: int, count: int, function: int = 3) -> bytes:
    return struct.pack(">BHH", function, address, count)


def write_pdu(address: int, values: list[int]) -> bytes:
    """Function 16 (write multiple registers)."""
    body = struct.pack(f">{len(values)}H", *values)
    return struct.pack(">BHHB", 16, address, len(values), len(body)) + body


def rw_pdu(read_addr: int, read_count: int, write_addr: int, values: list[int]) -> bytes:
    """Function 23 (read/write multiple registers)."""
    body = struct.pack(f">{len(values)}H", *values)
    head = struct.pack(">BHHHHB", 23, read_addr, read_count, write_addr, len(values), len(body))
    return head + body


def connect(port: int, timeout_s: float = IO_TIMEOUT_S) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=timeout_s)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.settimeout(timeout_s)
    return sock


def recv_exact(sock: socket.socket, n: int) -> bytes:
    """Exactly ``n`` bytes (the socket's timeout bounds each wait); EOF raises EOFError."""
    out = bytearray()
    for _ in range(n + 1):  # at most n productive reads
        if len(out) >= n:
            break
        chunk = sock.recv(n - len(out))
        if not chunk:
            raise EOFError(f"connection closed after {len(out)} of {n} bytes")
        out += chunk
    return bytes(out)


def recv_frame(sock: socket.socket) -> bytes:
    """One Modbus/TCP frame (MBAP header, then ``length - 1`` more bytes)."""
    head = recv_exact(sock, 7)
    length = struct.unpack_from(">H", head, 4)[0]
    return head + recv_exact(sock, max(0, length - 1))


def transact(sock: socket.socket, frame: bytes) -> bytes:
    sock.sendall(frame)
    return recv_frame(sock)


def no_reply_within(sock: socket.socket, seconds: float) -> bool:
    """True if nothing (no byte, no EOF) arrives within ``seconds``; consumes nothing."""
    old = sock.gettimeout()
    sock.settimeout(seconds)
    try:
        sock.recv(1, socket.MSG_PEEK)
    except TimeoutError:
        return True
    finally:
        sock.settimeout(old)
    return False


class EchoModbusServer:
    """Answers every Modbus/TCP frame with the same frame (a stand-in Modbus server).

    Counts the frames it received (``requests``) and accepted connections. One thread per
    connection; ``stop()`` closes everything and is safe twice.
    """

    def __init__(self) -> None:
        self._listener = socket.create_server(("127.0.0.1", 0))
        self._listener.settimeout(0.1)
        self.port: int = self._listener.getsockname()[1]
        self.requests = 0
        self.connections = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._socks: list[socket.socket] = []
        self._threads: list[threading.Thread] = []
        self._accept_thread = threading.Thread(target=self._accept_loop, daemon=True)

    def start(self) -> EchoModbusServer:
        self._accept_thread.start()
        return self

    def stop(self) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        self._accept_thread.join(2.0)
        self._listener.close()
        with self._lock:
            for s in self._socks:
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)
                s.close()
        for t in self._threads:
            t.join(2.0)

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                sock, _ = self._listener.accept()
            except (TimeoutError, OSError):
                continue
            sock.settimeout(0.1)
            with self._lock:
                self.connections += 1
                self._socks.append(sock)
            t = threading.Thread(target=self._serve, args=(sock,), daemon=True)
            self._threads.append(t)
            t.start()

    def _serve(self, sock: socket.socket) -> None:
        buf = bytearray()
        while not self._stop.is_set():
            try:
                chunk = sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            if not chunk:
                return
            buf += chunk
            while len(buf) >= 7:
                size = 6 + struct.unpack_from(">H", buf, 4)[0]
                if len(buf) < size:
                    break
                frame = bytes(buf[:size])
                del buf[:size]
                with self._lock:
                    self.requests += 1
                try:
                    sock.sendall(frame)
                except OSError:
                    return


@contextlib.contextmanager
def echo_server() -> Iterator[EchoModbusServer]:
    server = EchoModbusServer().start()
    try:
        yield server
    finally:
        server.stop()


def static_image(cables: int = 8) -> ProcessImage:
    """A soft PLC image with distinct, constant inputs (raw counts inside 0..27648)."""
    import numpy as np

    img = ProcessImage(cables)
    img.raw_counts[:] = 5000 + 1500 * np.arange(cables)
    img.velocity_m_s[:] = 0.0
    img.length_m[:] = 2.0 + 0.125 * np.arange(cables)
    img.pose[:] = (0.0, 0.0, 1.5, 0.0, 0.0, 0.0)
    img.plc_heartbeat = 1
    img.true_tension_n[:] = 100.0
    return img


@contextlib.contextmanager
def soft_plc(
    image: ProcessImage | None = None, cfg: Config | None = None
) -> Iterator[tuple[ModbusPlcServer, ProcessImage, Config]]:
    """The soft PLC's Modbus server on a free loopback port: (server, image, config)."""
    from sim_plc.modbus_server import ModbusPlcServer  # lands with the modbus branch

    cfg = cfg or load_config()
    image = image if image is not None else static_image(cfg.cables)
    server = ModbusPlcServer(cfg, image, host="127.0.0.1", port=0)
    server.start()
    try:
        yield server, image, cfg
    finally:
        server.stop()
