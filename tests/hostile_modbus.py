"""A hostile Modbus TCP server for tests and the reconnect probe (loopback only, bounded).

:class:`HostileServer` listens on 127.0.0.1 (ephemeral port) and answers every request
according to its ``mode``:

* ``good``: a valid reply (function 3/23 registers zero except the PLC heartbeat, 16 echo);
* ``foreign_unit``: a valid reply from another unit id (``unit_id + 1``), then, with
  ``then_good``, the valid one;
* ``exception``: exception code ``exception_code`` (6: server device busy);
* ``malformed``: a frame whose MBAP length is 0;
* ``accept_drop``: accepts the connection and closes it at once;
* ``reset_mid_frame``: half a reply, then a TCP reset (SO_LINGER 0);
* ``split``: a valid reply in ``pieces`` parts spread over ``latency_s``;
* ``latency``: a valid reply, whole, after ``latency_s``;
* ``tls_refuse``: a TLS server (``tls_cert``/``tls_key``) that requires a client
  certificate signed by its own certificate, so it refuses every client certificate
  made elsewhere (see :func:`make_tls_pair`).

``connections`` counts accepted connections (the reconnect-storm figure), ``requests``
the request frames. One connection is served at a time, in one thread; everything stops
after ``max_seconds``.
"""

from __future__ import annotations

import dataclasses
import socket
import ssl
import struct
import threading
import time
from dataclasses import dataclass
from typing import Any

from gateway.core.config import Config, load_config
from tests.tls_helpers import self_signed

LOCALHOST = "127.0.0.1"
MODES = (
    "good",
    "foreign_unit",
    "exception",
    "malformed",
    "accept_drop",
    "reset_mid_frame",
    "split",
    "latency",
    "tls_refuse",
)
HEARTBEAT_OFFSET = 52  # the PLC heartbeat in the default read span 0..52


def _mbap(pdu: bytes, tid: int, unit: int) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def valid_reply(request: bytes, heartbeat: int, unit: int | None = None) -> bytes:
    """A valid reply to ``request`` (function 3, 23 or 16)."""
    tid, _, _, req_unit = struct.unpack(">HHHB", request[:7])
    fc = request[7]
    if fc == 16:
        return _mbap(request[7:12], tid, req_unit if unit is None else unit)
    count = struct.unpack(">H", request[10:12])[0]
    regs = bytearray(2 * count)
    if count > HEARTBEAT_OFFSET:
        struct.pack_into(">H", regs, 2 * HEARTBEAT_OFFSET, heartbeat & 0xFFFF)
    return _mbap(bytes((fc, 2 * count)) + bytes(regs), tid, req_unit if unit is None else unit)


@dataclass
class HostileConfig:
    mode: str = "good"
    heartbeat: int = 1234
    then_good: bool = False
    exception_code: int = 6
    latency_s: float = 0.0
    pieces: int = 3
    max_seconds: float = 30.0
    tls_cert: str = ""
    tls_key: str = ""


class HostileServer:
    """See the module doc. Context manager; ``close()`` is safe twice."""

    def __init__(self, mode: str = "good", **options: float | int | bool | str) -> None:
        if mode not in MODES:
            raise ValueError(f"unknown mode {mode!r}")
        self.cfg = HostileConfig(mode=mode, **options)  # type: ignore[arg-type]
        self.listener = socket.create_server((LOCALHOST, 0), backlog=64)
        self.listener.settimeout(0.05)
        self.port: int = self.listener.getsockname()[1]
        self.connections = 0
        self.requests = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="hostile-modbus", daemon=True)
        self._thread.start()

    def __enter__(self) -> HostileServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.listener.close()

    # --- serving ------------------------------------------------------------------------
    def _run(self) -> None:
        end = time.monotonic() + self.cfg.max_seconds
        while not self._stop.is_set() and time.monotonic() < end:
            try:
                conn, _ = self.listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            self.connections += 1
            with conn:
                if self.cfg.mode == "accept_drop":
                    continue
                if self.cfg.mode == "tls_refuse":
                    self._refuse_tls(conn)
                    continue
                self._serve(conn, end)

    def _refuse_tls(self, conn: socket.socket) -> None:
        ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH, cafile=self.cfg.tls_cert)
        ctx.load_cert_chain(self.cfg.tls_cert, self.cfg.tls_key)
        ctx.verify_mode = ssl.CERT_REQUIRED
        conn.settimeout(0.5)
        try:
            with ctx.wrap_socket(conn, server_side=True) as tls:
                tls.recv(1)
        except (OSError, ssl.SSLError):
            pass

    def _serve(self, conn: socket.socket, end: float) -> None:
        conn.settimeout(0.05)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        buf = b""
        while not self._stop.is_set() and time.monotonic() < end:
            try:
                chunk = conn.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            if not chunk:
                return
            buf += chunk
            while len(buf) >= 7:
                size = 6 + struct.unpack(">H", buf[4:6])[0]
                if len(buf) < size:
                    break
                request, buf = buf[:size], buf[size:]
                if request[2:4] != b"\x00\x00" or size < 12:  # not Modbus (a TLS hello)
                    continue  # silence, as a plain PLC gives
                self.requests += 1
                if not self._answer(conn, request):
                    return

    def _answer(self, conn: socket.socket, request: bytes) -> bool:
        """Send the mode's answer; False when the connection is finished."""
        c = self.cfg
        unit = request[6]
        good = valid_reply(request, c.heartbeat)
        try:
            if c.mode == "good":
                conn.sendall(good)
            elif c.mode == "foreign_unit":
                conn.sendall(valid_reply(request, c.heartbeat + 1, unit=(unit + 1) & 0xFF))
                if c.then_good:
                    conn.sendall(good)
            elif c.mode == "exception":
                tid = struct.unpack(">H", request[:2])[0]
                conn.sendall(_mbap(bytes((0x80 | request[7], c.exception_code)), tid, unit))
            elif c.mode == "malformed":
                conn.sendall(request[:4] + b"\x00\x00" + request[6:8])
            elif c.mode == "reset_mid_frame":
                conn.sendall(good[: len(good) // 2])
                conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
                return False
            elif c.mode == "latency":
                if self._stop.wait(c.latency_s):
                    return False
                conn.sendall(good)
            elif c.mode == "split":
                self._send_split(conn, good)
        except OSError:
            return False
        return True

    def _send_split(self, conn: socket.socket, reply: bytes) -> None:
        n = max(1, self.cfg.pieces)
        step = -(-len(reply) // n)
        for k in range(n):
            if self._stop.wait(self.cfg.latency_s / n):
                return
            conn.sendall(reply[k * step : (k + 1) * step])


def make_tls_pair(directory: str) -> dict[str, str]:
    """Self-signed server and client certificates (127.0.0.1) from the openssl command:
    the client trusts the server; the server trusts only itself, so it refuses the
    client. Paths by name: server_cert, server_key, client_cert, client_key."""
    paths = {}
    for who in ("server", "client"):
        cert, key = self_signed(directory, who)
        paths[f"{who}_cert"], paths[f"{who}_key"] = str(cert), str(key)
    return paths


def gateway_config(port: int, **modbus: Any) -> Config:
    """The default config pointed at a hostile server on loopback (metrics off)."""
    cfg = load_config()
    mb = dataclasses.replace(cfg.bus.modbus_tcp, host=LOCALHOST, port=port, **modbus)
    bus = dataclasses.replace(cfg.bus, driver="modbus_tcp", modbus_tcp=mb)
    metrics = dataclasses.replace(cfg.metrics, enabled=False)
    return dataclasses.replace(cfg, bus=bus, metrics=metrics)
