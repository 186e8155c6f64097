"""A fault-injecting TCP proxy for loopback tests and benchmarks.

``FaultProxy(target_host, target_port)`` listens on 127.0.0.1 (a free port unless told)
and relays every client connection to the target. Faults set with
:meth:`FaultProxy.set_fault` act on what passes through; :meth:`FaultProxy.clear` removes
them. Both directions are cut into Modbus/TCP frames (MBAP header: transaction id,
protocol id, length, unit id) so that a fault acts on whole requests and replies; with
``framing="raw"`` every received chunk counts as one frame.

Faults (``kind`` and its parameters); each also takes ``count=N`` (act on the next N
frames, then expire) or ``probability=p`` (act on each frame with probability p), default
every frame:

* ``delay``: ``seconds``, ``direction`` = ``"reply"`` | ``"request"`` | ``"both"``;
* ``drop``: replies discarded;
* ``split``: a reply sent in ``pieces`` TCP segments ``pause_s`` apart;
* ``corrupt``: ``nbytes`` bytes XOR-ed with a random non-zero value, at positions drawn
  from ``where`` = ``"any"`` (the whole frame) | ``"header"`` (MBAP + function code +
  byte count, bytes 0-8) | ``"data"`` (after byte 8);
* ``wrong_tid``: bytes 0-1 (transaction id) of a reply replaced by ``tid + offset``;
* ``reset``: ``after_bytes`` of a reply sent, then the client connection closed with
  SO_LINGER 0 (the client sees a TCP RST mid-frame);
* ``silent``: requests are read and discarded, nothing is answered (the target sees
  nothing), new connections are accepted (and connected upstream) and stay silent;
* ``exception``: a request is answered by the proxy with Modbus exception ``code``
  (6 server busy, 2 illegal data address, ...) and not forwarded: a PLC refusing it.

Random choices come from one ``random.Random(seed)``; with the same traffic the same
faults are injected. :attr:`FaultProxy.counters` says what was injected. One thread runs
a ``selectors`` loop; every wait in it is bounded.
"""

from __future__ import annotations

import contextlib
import random
import selectors
import socket
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

KINDS = ("delay", "drop", "split", "corrupt", "wrong_tid", "reset", "silent", "exception")
_PARAMS: dict[str, dict[str, Any]] = {
    "delay": {"seconds": 0.01, "direction": "reply"},
    "drop": {},
    "split": {"pieces": 3, "pause_s": 0.002},
    "corrupt": {"nbytes": 1, "where": "any"},
    "wrong_tid": {"offset": 0x1000},
    "reset": {"after_bytes": 3},
    "silent": {},
    "exception": {"code": 6},
}
_MBAP_LEN = 7
_MAX_FRAME = 260  # Modbus/TCP ADU limit (MBAP 7 + PDU 253)
_SELECT_MAX_S = 0.05
_CONNECT_TIMEOUT_S = 1.0
_JOIN_TIMEOUT_S = 2.0


@dataclass
class _Fault:
    kind: str
    params: dict[str, Any]
    count: int | None  # frames left; None: unlimited
    probability: float


@dataclass
class _Pipe:
    """One direction of one connection: what is waiting to be sent, and when."""

    dst: socket.socket
    queue: deque[tuple[float, bytes, bool]] = field(default_factory=deque)  # (due, data, rst)
    buffer: bytearray = field(default_factory=bytearray)  # bytes received, not yet framed
    last_due: float = 0.0


@dataclass
class _Conn:
    client: socket.socket
    server: socket.socket
    to_server: _Pipe
    to_client: _Pipe
    closed: bool = False


class FaultProxy:
    """TCP proxy between a client and ``target_host:target_port`` that injects faults."""

    def __init__(
        self,
        target_host: str,
        target_port: int,
        listen_host: str = "127.0.0.1",
        listen_port: int = 0,
        seed: int = 0,
        framing: str = "mbap",
    ) -> None:
        if framing not in ("mbap", "raw"):
            raise ValueError(f"FaultProxy: framing must be 'mbap' or 'raw', not {framing!r}")
        self.target = (target_host, target_port)
        self._listen_addr = (listen_host, listen_port)
        self._framing = framing
        self._rng = random.Random(seed)
        self._lock = threading.Lock()
        self._faults: dict[str, _Fault] = {}
        self._counters: dict[str, int] = {}
        self._conns: list[_Conn] = []
        self._sel: selectors.BaseSelector | None = None
        self._listener: socket.socket | None = None
        self._wake_r: socket.socket | None = None
        self._wake_w: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self.port = 0

    # --- public API -------------------------------------------------------------------
    def start(self) -> FaultProxy:
        """Bind, listen and start the relay thread; returns self."""
        if self._thread is not None:
            return self
        listener = socket.create_server(self._listen_addr, backlog=16)
        listener.setblocking(False)
        self._listener = listener
        self.port = listener.getsockname()[1]
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._sel = selectors.DefaultSelector()
        self._sel.register(listener, selectors.EVENT_READ, "accept")
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._stopping.clear()
        self._thread = threading.Thread(target=self._run, name="faultproxy", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Close every connection and the listener, join the thread; safe to call twice."""
        thread, self._thread = self._thread, None
        if thread is None:
            return
        self._stopping.set()
        self._wake()
        thread.join(_JOIN_TIMEOUT_S)
        for conn in list(self._conns):
            self._close_conn(conn, rst=False)
        for sock in (self._listener, self._wake_r, self._wake_w):
            if sock is not None:
                sock.close()
        if self._sel is not None:
            self._sel.close()
        self._listener = self._wake_r = self._wake_w = self._sel = None

    def set_fault(
        self, kind: str, *, count: int | None = None, probability: float = 1.0, **params: Any
    ) -> None:
        """Add (or replace) the fault ``kind``; see the module docstring for parameters."""
        if kind not in KINDS:
            raise ValueError(f"FaultProxy: unknown fault {kind!r} (known: {', '.join(KINDS)})")
        unknown = set(params) - set(_PARAMS[kind])
        if unknown:
            raise ValueError(f"FaultProxy: fault {kind!r} has no parameter {sorted(unknown)}")
        if not 0.0 <= probability <= 1.0:
            raise ValueError(f"FaultProxy: probability {probability} not in 0..1")
        if count is not None and count < 0:
            raise ValueError(f"FaultProxy: count {count} < 0")
        merged = {**_PARAMS[kind], **params}
        if kind == "delay" and merged["direction"] not in ("reply", "request", "both"):
            raise ValueError(f"FaultProxy: delay direction {merged['direction']!r}")
        if kind == "corrupt" and merged["where"] not in ("any", "header", "data"):
            raise ValueError(f"FaultProxy: corrupt where {merged['where']!r}")
        with self._lock:
            self._faults[kind] = _Fault(kind, merged, count, probability)
        self._wake()

    def clear(self, kind: str | None = None) -> None:
        """Remove one fault, or all of them."""
        with self._lock:
            if kind is None:
                self._faults.clear()
            else:
                self._faults.pop(kind, None)
        self._wake()

    def active_faults(self) -> list[str]:
        with self._lock:
            return sorted(self._faults)

    @property
    def counters(self) -> dict[str, int]:
        """A copy of the counters: injected faults by kind, plus ``connections``,
        ``requests`` and ``replies`` (frames forwarded) and ``upstream_failures``."""
        with self._lock:
            return dict(self._counters)

    def __enter__(self) -> FaultProxy:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --- relay thread -----------------------------------------------------------------
    def _wake(self) -> None:
        if self._wake_w is not None:
            with contextlib.suppress(OSError):
                self._wake_w.send(b"x")

    def _count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._counters[name] = self._counters.get(name, 0) + n

    def _fire(self, kind: str) -> _Fault | None:
        """The fault ``kind`` if it acts on this frame (draws from the rng, uses a count)."""
        with self._lock:
            fault = self._faults.get(kind)
            if fault is None:
                return None
            if fault.probability < 1.0 and self._rng.random() >= fault.probability:
                return None
            if fault.count is not None:
                fault.count -= 1
                if fault.count <= 0:
                    del self._faults[kind]
            self._counters[kind] = self._counters.get(kind, 0) + 1
            return fault

    def _peek(self, kind: str) -> _Fault | None:
        with self._lock:
            return self._faults.get(kind)

    def _run(self) -> None:
        sel = self._sel
        assert sel is not None
        while not self._stopping.is_set():
            timeout = self._next_due_in()
            for key, _ in sel.select(timeout):
                if key.data == "accept":
                    self._accept()
                elif key.data == "wake":
                    with contextlib.suppress(OSError):
                        self._wake_r.recv(4096)  # type: ignore[union-attr]
                else:
                    conn, side = key.data
                    self._on_readable(conn, side)
            self._flush_due()

    def _next_due_in(self) -> float:
        now = time.monotonic()
        due = [p.queue[0][0] for c in self._conns for p in (c.to_server, c.to_client) if p.queue]
        if not due:
            return _SELECT_MAX_S
        return min(_SELECT_MAX_S, max(0.0, min(due) - now))

    def _accept(self) -> None:
        assert self._listener is not None and self._sel is not None
        try:
            client, _ = self._listener.accept()
        except (BlockingIOError, InterruptedError):
            return
        self._count("connections")
        client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:  # connected even while silent, so that clearing ``silent`` resumes service
            server = socket.create_connection(self.target, timeout=_CONNECT_TIMEOUT_S)
        except OSError:
            self._count("upstream_failures")
            _close_with_rst(client)
            return
        server.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        server.setblocking(False)
        client.setblocking(False)
        conn = _Conn(client, server, _Pipe(server), _Pipe(client))
        self._conns.append(conn)
        self._sel.register(client, selectors.EVENT_READ, (conn, "client"))
        self._sel.register(server, selectors.EVENT_READ, (conn, "server"))

    def _on_readable(self, conn: _Conn, side: str) -> None:
        sock = conn.client if side == "client" else conn.server
        if conn.closed:
            return
        try:
            data = sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self._close_conn(conn, rst=False)
            return
        if side == "client":
            self._on_request(conn, data)
        else:
            self._on_reply_bytes(conn, data)

    def _on_request(self, conn: _Conn, data: bytes) -> None:
        for frame in self._frames(conn.to_server, data):
            self._count("requests")
            if self._peek("silent") is not None:
                self._count("silent")
                continue
            exc = self._fire("exception")
            if exc is not None and len(frame) >= 8:  # answered here, never forwarded
                tid, _proto, _len, unit = struct.unpack_from(">HHHB", frame, 0)
                reply = struct.pack(">HHHBBB", tid, 0, 3, unit, frame[7] | 0x80, exc.params["code"])
                self._enqueue(conn.to_client, reply, 0.0)
                continue
            self._enqueue(conn.to_server, frame, self._delay_for("request"))

    def _frames(self, pipe: _Pipe, data: bytes) -> list[bytes]:
        """Cut ``data`` (appended to what ``pipe`` holds) into whole MBAP frames; bytes that
        cannot start a Modbus frame pass as one piece; raw framing: ``data`` itself."""
        if self._framing == "raw":
            return [data]
        pipe.buffer += data
        out: list[bytes] = []
        while len(pipe.buffer) >= _MBAP_LEN:
            length = struct.unpack_from(">H", pipe.buffer, 4)[0]
            size = 6 + length
            if length < 2 or size > _MAX_FRAME:  # not a Modbus frame: pass it on whole
                size = len(pipe.buffer)
            if len(pipe.buffer) < size:
                break
            out.append(bytes(pipe.buffer[:size]))
            del pipe.buffer[:size]
        return out

    def _delay_for(self, direction: str) -> float:
        fault = self._peek("delay")
        if fault is None or fault.params["direction"] not in (direction, "both"):
            return 0.0
        fault = self._fire("delay")
        return float(fault.params["seconds"]) if fault is not None else 0.0

    def _on_reply_bytes(self, conn: _Conn, data: bytes) -> None:
        for frame in self._frames(conn.to_client, data):
            self._on_reply(conn, frame)
            if conn.closed:
                return

    def _on_reply(self, conn: _Conn, frame: bytes) -> None:
        """Apply the reply faults to one frame and queue what is left of it."""
        self._count("replies")
        if self._peek("silent") is not None:
            self._count("silent")
            return
        if self._fire("drop") is not None:
            return
        frame = self._mutate(frame)
        delay = self._delay_for("reply")
        reset = self._fire("reset")
        if reset is not None:
            cut = max(0, min(int(reset.params["after_bytes"]), len(frame) - 1))
            self._enqueue(conn.to_client, frame[:cut], delay, rst=True)
            return
        split = self._fire("split")
        if split is None or len(frame) < 2:
            self._enqueue(conn.to_client, frame, delay)
            return
        pieces = max(2, min(int(split.params["pieces"]), len(frame)))
        bounds = sorted(self._rng.sample(range(1, len(frame)), pieces - 1))
        start = 0
        for k, end in enumerate([*bounds, len(frame)]):
            extra = delay + k * float(split.params["pause_s"])
            self._enqueue(conn.to_client, frame[start:end], extra)
            start = end

    def _mutate(self, frame: bytes) -> bytes:
        out = bytearray(frame)
        tid_fault = self._fire("wrong_tid")
        if tid_fault is not None and len(out) >= 2:
            tid = struct.unpack_from(">H", out, 0)[0]
            struct.pack_into(">H", out, 0, (tid + int(tid_fault.params["offset"])) & 0xFFFF)
        corrupt = self._fire("corrupt")
        if corrupt is not None:
            where = corrupt.params["where"]
            lo, hi = {"any": (0, len(out)), "header": (0, min(9, len(out)))}.get(
                where, (min(9, len(out)), len(out))
            )
            positions = range(lo, hi)
            n = min(int(corrupt.params["nbytes"]), len(positions))
            for pos in self._rng.sample(positions, n):
                out[pos] ^= self._rng.randrange(1, 256)
        return bytes(out)

    def _enqueue(self, pipe: _Pipe, data: bytes, delay: float, rst: bool = False) -> None:
        due = max(time.monotonic() + delay, pipe.last_due)  # keep the byte order
        pipe.last_due = due
        pipe.queue.append((due, data, rst))

    def _flush_due(self) -> None:
        now = time.monotonic()
        for conn in list(self._conns):
            for pipe in (conn.to_server, conn.to_client):
                while pipe.queue and pipe.queue[0][0] <= now and not conn.closed:
                    _, data, rst = pipe.queue.popleft()
                    if not self._send(conn, pipe, data):
                        break
                    if rst:
                        self._count("resets_sent")
                        self._close_conn(conn, rst=True)

    def _send(self, conn: _Conn, pipe: _Pipe, data: bytes) -> bool:
        """Send all of ``data`` (loopback: bounded by a short blocking timeout)."""
        if not data:
            return True
        try:
            pipe.dst.settimeout(_CONNECT_TIMEOUT_S)
            pipe.dst.sendall(data)
            pipe.dst.setblocking(False)
        except OSError:
            self._close_conn(conn, rst=False)
            return False
        return True

    def _close_conn(self, conn: _Conn, rst: bool) -> None:
        if conn.closed:
            return
        conn.closed = True
        with contextlib.suppress(ValueError):
            self._conns.remove(conn)
        for sock in (conn.client, conn.server):
            if self._sel is not None:
                with contextlib.suppress(KeyError, ValueError):
                    self._sel.unregister(sock)
            if rst:
                _close_with_rst(sock)
            else:
                sock.close()


def _close_with_rst(sock: socket.socket) -> None:
    """Close so that the peer sees a TCP RST (SO_LINGER on, timeout 0)."""
    with contextlib.suppress(OSError):
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    sock.close()
