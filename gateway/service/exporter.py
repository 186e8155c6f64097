"""The bounded HTTP(S) exporter of the metrics: one selector thread, a fixed connection cap.

It runs in a process of its own (:mod:`gateway.service.exporter_proc`, fed by the loop
through shared memory), never in the loop's: a scrape flood in the loop's process held
its GIL (issue 30). It is still built to cost a known, small amount whatever the clients
do, as it shares the machine with the 1 ms cycle:

* **one thread** (``metrics-http``) serves every connection with non-blocking sockets and a
  selector; no thread per client;
* **at most** ``max_connections`` open connections; a new connection is served at once
  when its request is already there; when every slot is taken, the oldest connection that
  has sent nothing for ``EVICT_SILENT_S`` (or no complete request for ``EVICT_AFTER_S``) is
  closed for a newcomer, so idle clients cannot lock Prometheus out; when none can be
  evicted, accepting pauses until a slot frees, and the kernel queues the rest in the
  listen backlog (``backlog``);
* **a deadline per exchange**: from accept (or from the end of the previous response on a
  keep-alive connection) the client has ``timeout_s`` to finish the TLS handshake, send
  its request and read the reply; a slow client, byte by byte or not at all, is dropped at
  the deadline whatever its progress;
* **a reserve of file descriptors**: no connection is accepted while fewer than
  ``fd_reserve`` descriptors remain under the process' soft ``RLIMIT_NOFILE``, so the bus
  can always reconnect; ``EMFILE`` on accept pauses accepting instead of spinning;
* **the payload is rendered at most once per** ``cache_s``: a burst of scrapes costs one
  collection of the registry, not one each; the thread runs at nice 10 and never
  real-time, below the cycle.

* **every request is answered or its connection closed, never the thread**: anything a
  request raises (a bug, an odd byte) is caught per connection, logged and counted
  (``failed``); credentials are compared as UTF-8 bytes, whatever their characters;
* **its own health**: when it stops accepting for want of descriptors it says so once in
  the log (with the limit to raise); its counters are exported as
  ``cdpr_gateway_exporter_events_total{event}`` (served, failed, rejected, timed_out,
  evicted, accept_paused).

TLS (``certfile``/``keyfile``) and HTTP basic auth (``basic_auth_user`` and
``basic_auth_password_sha256``, the hex SHA-256 of the password) as configured in
``metrics:``. Every path serves the metrics (``/metrics`` by convention); GET and HEAD only.
"""

from __future__ import annotations

import base64
import contextlib
import errno
import hashlib
import hmac
import logging
import os
import resource
import selectors
import socket
import ssl
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, Metric

from gateway.errors import ConfigError, TemporaryError
from gateway.runtime import realtime

if TYPE_CHECKING:  # the exporter process never imports the config (and its model: numba)
    from gateway.core.config import MetricsConfig

log = logging.getLogger("cdpr_gateway.exporter")

MAX_CONNECTIONS = 64
TIMEOUT_S = 3.0  # handshake + request + reply; Prometheus' own scrape timeout is shorter
CACHE_S = 0.25
FD_RESERVE = 64
BACKLOG = 256  # a burst of scrapes waits in the kernel (no fd of ours), not in SYN retries
# When every slot is taken, a connection may give its slot to a newcomer once it has sent
# nothing for EVICT_SILENT_S, or no complete request for EVICT_AFTER_S (slow, partial).
EVICT_SILENT_S = 0.1
EVICT_AFTER_S = 1.0
MAX_HEADER_BYTES = 8192
ACCEPT_PAUSE_S = 0.25  # after EMFILE or with the fd reserve reached
TICK_S = 0.25  # longest selector wait: deadlines are checked at least this often
ACCEPT_BATCH = 16  # connections taken per wake-up of the listening socket
PROCESS_FDS = 64  # what the gateway holds besides the exporter (libraries, bus, recorder)
NOFILE_NEEDED = PROCESS_FDS + FD_RESERVE + MAX_CONNECTIONS  # check warns below this
_LISTEN, _WAKE = object(), object()  # selector keys of the listener and the wake-up pipe


@dataclass
class _Conn:
    sock: socket.socket
    deadline: float
    accepted: float
    handshaking: bool = False
    inbox: bytearray = field(default_factory=bytearray)
    outbox: memoryview | None = None
    close_after: bool = False
    closed: bool = False
    heard: bool = False  # bytes arrived since accept / the last reply

    def evictable(self, now: float) -> bool:
        """Nothing being written, and silent or slow (see ``EVICT_SILENT_S``)."""
        age = now - self.accepted
        limit = EVICT_AFTER_S if self.heard else EVICT_SILENT_S
        return self.outbox is None and age >= limit


@dataclass
class ExporterCounters:
    """What the exporter did; read by tests and the bench probe (not exported)."""

    accepted: int = 0
    served: int = 0
    timed_out: int = 0
    evicted: int = 0
    rejected: int = 0  # bad requests, auth failures and failed handshakes
    failed: int = 0  # requests whose handling raised: answered by closing that connection
    accept_paused: int = 0
    renders: int = 0
    peak_connections: int = 0


def open_fds() -> int:
    """Open file descriptors of this process (Linux /proc; 0 where unknown)."""
    try:
        return len(os.listdir("/proc/self/fd")) - 1  # minus the listing's own
    except OSError:
        return 0


def _auth_checker(user: str | None, digest: str | None) -> Callable[[str], bool] | None:
    """Basic auth as bytes: the configured user as UTF-8, the password's SHA-256 over the
    bytes the client sent (any characters; both compared in constant time)."""
    if user is None or digest is None:
        return None
    expected = digest.lower().encode("ascii", "replace")
    user_bytes = user.encode("utf-8")

    def check(header: str) -> bool:
        if not header.startswith("Basic "):
            return False
        try:  # the header was decoded as latin-1: one byte per character
            token = base64.b64decode(header[6:].encode("latin-1"), validate=True)
        except ValueError:
            return False
        name, _, password = token.partition(b":")
        got = hashlib.sha256(password).hexdigest().encode("ascii")
        return hmac.compare_digest(name, user_bytes) & hmac.compare_digest(got, expected)

    return check


def _response(
    status: str, body: bytes, headers: list[tuple[str, str]], head: bool, keep_alive: bool
) -> bytes:
    lines = [
        f"HTTP/1.1 {status}",
        f"Content-Length: {len(body)}",
        "Connection: " + ("keep-alive" if keep_alive else "close"),
    ]
    lines += [f"{k}: {v}" for k, v in headers]
    return ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1") + (b"" if head else body)


class MetricsServer:
    """Serve ``registry`` on ``cfg.host:cfg.port`` (port 0: any free port, see ``.port``)."""

    def __init__(
        self,
        cfg: MetricsConfig,
        registry: CollectorRegistry,
        source: str = "",
        *,
        max_connections: int = MAX_CONNECTIONS,
        timeout_s: float = TIMEOUT_S,
        cache_s: float = CACHE_S,
        fd_reserve: int = FD_RESERVE,
        backlog: int = BACKLOG,
    ) -> None:
        where = f"{source}: " if source else ""
        if (cfg.basic_auth_user is None) != (cfg.basic_auth_password_sha256 is None):
            raise ConfigError(
                f"{where}metrics.basic_auth_user and metrics.basic_auth_password_sha256 go together"
            )
        if not 0 <= cfg.port <= 65535:  # getaddrinfo would silently wrap 99999 to 34463
            raise ConfigError(f"{where}metrics.port: must be in 0..65535, got {cfg.port}")
        self._auth = _auth_checker(cfg.basic_auth_user, cfg.basic_auth_password_sha256)
        self._tls: ssl.SSLContext | None = None
        if cfg.certfile is not None:
            try:
                self._tls = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
                self._tls.load_cert_chain(cfg.certfile, cfg.keyfile)
            except (OSError, ssl.SSLError) as exc:
                raise ConfigError(f"{where}metrics.certfile: {exc}") from exc
        try:
            infos = socket.getaddrinfo(cfg.host, cfg.port, type=socket.SOCK_STREAM)
            family = infos[0][0]
            self._listener = socket.socket(family, socket.SOCK_STREAM)
        except OSError as exc:
            raise ConfigError(f"{where}metrics.host: cannot resolve {cfg.host}: {exc}") from exc
        try:
            self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._listener.bind(infos[0][4])
            self._listener.listen(backlog)
            self._listener.setblocking(False)
        except OSError as exc:
            self._listener.close()
            # a port in use may be free after a restart; anything else is the config's
            error = TemporaryError if exc.errno == errno.EADDRINUSE else ConfigError
            raise error(
                f"{where}metrics.port: cannot serve metrics on {cfg.host}:{cfg.port}: {exc}"
            ) from exc
        self.host = cfg.host
        self.port = int(self._listener.getsockname()[1])
        self.registry = registry
        self.max_connections = max_connections
        self.timeout_s = timeout_s
        self.cache_s = cache_s
        self.fd_reserve = fd_reserve
        self.counters = ExporterCounters()
        with contextlib.suppress(ValueError):  # a second exporter on one registry
            registry.register(_HealthCollector(self.counters))
        self._conns: dict[int, _Conn] = {}
        self._payload = b""
        self._rendered_at = -float("inf")
        self._accepting = False
        self._resume_at = 0.0
        self._short_logged = False  # the descriptor shortage of this episode was logged
        self._failures_logged = 0
        self._selector = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._selector.register(self._wake_r, selectors.EVENT_READ, _WAKE)
        self._set_accepting(True)
        self._stop = False
        self._thread: threading.Thread | None = threading.Thread(
            target=self._serve, name="metrics-http", daemon=True
        )
        self._thread.start()

    # ---- lifecycle -----------------------------------------------------------------------

    def close(self) -> None:
        """Stop serving and close every connection; safe to call twice."""
        if self._thread is None:
            return
        self._stop = True
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")
        self._thread.join(timeout=5)
        self._thread = None
        for conn in list(self._conns.values()):
            self._drop(conn)
        self._selector.close()
        self._listener.close()
        self._wake_r.close()
        self._wake_w.close()

    @property
    def connections(self) -> int:
        return len(self._conns)

    # ---- the selector loop ---------------------------------------------------------------

    def _serve(self) -> None:
        realtime.below_the_cycle()
        while not self._stop:
            now = time.monotonic()
            wait = TICK_S
            if self._conns:
                wait = min(wait, min(c.deadline for c in self._conns.values()) - now)
            if not self._accepting and self._resume_at > now:
                wait = min(wait, self._resume_at - now)
            for key, _ in self._selector.select(max(wait, 0.0)):
                if key.data is _WAKE:
                    self._wake_r.recv(64)
                elif key.data is _LISTEN:
                    self._guarded(self._accept)
                else:
                    self._service(key.data)
            now = time.monotonic()
            for conn in [c for c in self._conns.values() if c.deadline <= now]:
                self.counters.timed_out += 1
                self._drop(conn)
            self._maybe_resume()

    def _guarded(self, work: Callable[[], None]) -> None:
        """Run ``work``; whatever it raises is logged and counted, the thread lives on."""
        try:
            work()
        except Exception:
            self._failed(None)

    def _failed(self, conn: _Conn | None) -> None:
        self.counters.failed += 1
        if self._failures_logged < 10:  # bounded: a flood must not flood the log
            self._failures_logged += 1
            log.exception("metrics: a request failed; its connection is closed")
        if conn is not None and not conn.closed:
            with contextlib.suppress(Exception):
                self._drop(conn)

    def _set_accepting(self, on: bool) -> None:
        if on and not self._accepting:
            self._selector.register(self._listener, selectors.EVENT_READ, _LISTEN)
        elif not on and self._accepting:
            self._selector.unregister(self._listener)
        self._accepting = on

    def _maybe_resume(self) -> None:
        if self._accepting or time.monotonic() < self._resume_at:
            return
        if len(self._conns) < self.max_connections or self._evictable():
            self._set_accepting(True)

    def _evictable(self) -> list[_Conn]:
        now = time.monotonic()
        return [c for c in self._conns.values() if c.evictable(now)]

    def _fds_short(self) -> bool:
        soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
        return soft != resource.RLIM_INFINITY and open_fds() + 1 > soft - self.fd_reserve

    def _pause(self, descriptors: bool = False) -> None:
        if descriptors and not self._short_logged:
            self._short_logged = True
            soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
            log.warning(
                "metrics: not accepting connections: %d of %d descriptors open, %d kept for "
                "the bus; raise RLIMIT_NOFILE (LimitNOFILE= in the unit)",
                open_fds(),
                soft,
                self.fd_reserve,
            )
        self.counters.accept_paused += 1
        self._resume_at = time.monotonic() + ACCEPT_PAUSE_S
        self._set_accepting(False)

    def _accept(self) -> None:
        for _ in range(ACCEPT_BATCH):
            if len(self._conns) >= self.max_connections:
                idle = self._evictable()
                if not idle:
                    self._set_accepting(False)  # resumed when a slot frees
                    return
                self.counters.evicted += 1
                self._drop(min(idle, key=lambda c: c.accepted))
            if self._fds_short():
                self._pause(descriptors=True)
                return
            try:
                sock, _ = self._listener.accept()
            except BlockingIOError:
                return
            except OSError as exc:
                if exc.errno in (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM):
                    self._pause(descriptors=exc.errno in (errno.EMFILE, errno.ENFILE))
                return
            self._short_logged = False  # accepting again: a new shortage is logged anew
            self._adopt(sock)

    def _adopt(self, sock: socket.socket) -> None:
        now = time.monotonic()
        sock.setblocking(False)
        conn = _Conn(sock, now + self.timeout_s, now)
        with contextlib.suppress(OSError):
            conn.heard = bool(sock.recv(1, socket.MSG_PEEK))
        if self._tls is not None:
            try:
                conn.sock = self._tls.wrap_socket(
                    sock, server_side=True, do_handshake_on_connect=False
                )
            except (OSError, ValueError):
                sock.close()
                self.counters.rejected += 1
                return
            conn.handshaking = True
        self._conns[conn.sock.fileno()] = conn
        self._selector.register(conn.sock, selectors.EVENT_READ, conn)
        self.counters.accepted += 1
        self.counters.peak_connections = max(self.counters.peak_connections, len(self._conns))
        if conn.heard:
            self._service(conn)  # the request (or ClientHello) is already here

    def _drop(self, conn: _Conn) -> None:
        fd = conn.sock.fileno()
        if fd >= 0 and self._conns.pop(fd, None) is not None:
            with contextlib.suppress(KeyError, ValueError):
                self._selector.unregister(conn.sock)
        conn.closed = True
        conn.sock.close()

    # ---- one connection ------------------------------------------------------------------

    def _service(self, conn: _Conn) -> None:
        conn.heard = True  # called on a readiness event or with bytes already received
        try:
            if conn.handshaking:
                assert isinstance(conn.sock, ssl.SSLSocket)
                conn.sock.do_handshake()  # raises SSLWant* until done
                conn.handshaking = False
            if conn.outbox is not None:
                self._write(conn)
            if conn.outbox is None and not conn.closed:
                self._read(conn)
            self._process(conn)
        except ssl.SSLWantReadError:
            self._interest(conn, selectors.EVENT_READ)
        except ssl.SSLWantWriteError:
            self._interest(conn, selectors.EVENT_WRITE)
        except (BlockingIOError, InterruptedError):
            self._interest(conn, selectors.EVENT_WRITE if conn.outbox else selectors.EVENT_READ)
        except (OSError, ValueError):
            self.counters.rejected += conn.handshaking
            self._drop(conn)
        except Exception:  # a bug in one request: that connection, never the thread
            self._failed(conn)

    def _interest(self, conn: _Conn, events: int) -> None:
        if not conn.closed:
            self._selector.modify(conn.sock, events, conn)

    def _read(self, conn: _Conn) -> None:
        """Take what the socket holds (up to the header limit); EOF closes."""
        while len(conn.inbox) <= MAX_HEADER_BYTES:
            try:
                chunk = conn.sock.recv(4096)
            except (ssl.SSLWantReadError, BlockingIOError):
                return
            if not chunk:
                self._drop(conn)  # the client closed
                return
            conn.inbox += chunk

    def _process(self, conn: _Conn) -> None:
        """Answer every complete request received, one at a time, while the socket takes
        the replies; then wait for more input or for room to write."""
        while not conn.closed and conn.outbox is None:
            end = conn.inbox.find(b"\r\n\r\n")
            if end < 0:
                if len(conn.inbox) > MAX_HEADER_BYTES:
                    self._queue(conn, "431 Request Header Fields Too Large", b"", [], False, False)
                    continue
                self._interest(conn, selectors.EVENT_READ)
                return
            request = bytes(conn.inbox[:end])
            del conn.inbox[: end + 4]
            self._respond(conn, request)
        if not conn.closed:
            self._interest(conn, selectors.EVENT_WRITE)

    def _respond(self, conn: _Conn, request: bytes) -> None:
        try:
            head, *header_lines = request.decode("latin-1").split("\r\n")
            method, _target, version = head.split(" ")
        except ValueError:
            self._queue(conn, "400 Bad Request", b"bad request\n", [], False, False)
            return
        headers = {}
        for line in header_lines:
            name, sep, value = line.partition(":")
            if sep:
                headers[name.strip().lower()] = value.strip()
        keep = version == "HTTP/1.1" and headers.get("connection", "").lower() != "close"
        head_only = method == "HEAD"
        if headers.get("content-length", "0") not in ("", "0") or "transfer-encoding" in headers:
            self._queue(conn, "400 Bad Request", b"no request body\n", [], False, False)
        elif method not in ("GET", "HEAD"):
            self._queue(
                conn,
                "405 Method Not Allowed",
                b"GET only\n",
                [("Allow", "GET, HEAD")],
                False,
                False,
            )
        elif self._auth is not None and not self._auth(headers.get("authorization", "")):
            self.counters.rejected += 1
            self._queue(
                conn,
                "401 Unauthorized",
                b"unauthorized\n",
                [("WWW-Authenticate", 'Basic realm="cdpr-gateway"')],
                head_only,
                keep,
            )
        else:
            try:
                payload = self._render()
            except Exception:  # a collector bug must not end the exporter thread
                log.exception("metrics: rendering the registry failed")
                self._queue(
                    conn, "500 Internal Server Error", b"collector failed\n", [], False, False
                )
                return
            self.counters.served += 1
            self._queue(
                conn, "200 OK", payload, [("Content-Type", CONTENT_TYPE_LATEST)], head_only, keep
            )

    def _render(self) -> bytes:
        now = time.monotonic()
        if now - self._rendered_at >= self.cache_s:
            self._payload = generate_latest(self.registry)
            self._rendered_at = now
            self.counters.renders += 1
        return self._payload

    def _queue(
        self,
        conn: _Conn,
        status: str,
        body: bytes,
        headers: list[tuple[str, str]],
        head: bool,
        keep_alive: bool,
    ) -> None:
        conn.outbox = memoryview(_response(status, body, headers, head, keep_alive))
        conn.close_after = not keep_alive
        self._write(conn)

    def _write(self, conn: _Conn) -> None:
        """Send what the socket takes; raises BlockingIOError/SSLWantWrite when it is full."""
        assert conn.outbox is not None
        while conn.outbox:
            conn.outbox = conn.outbox[conn.sock.send(conn.outbox) :]
        conn.outbox = None
        if conn.close_after:
            self._drop(conn)
            return
        now = time.monotonic()
        conn.deadline, conn.accepted = now + self.timeout_s, now  # keep-alive: next exchange
        conn.heard = bool(conn.inbox)


class _HealthCollector:
    """The exporter's own counters as ``cdpr_gateway_exporter_events_total{event}``."""

    EVENTS = ("served", "failed", "rejected", "timed_out", "evicted", "accept_paused")

    def __init__(self, counters: ExporterCounters) -> None:
        self.counters = counters

    def collect(self) -> Iterator[Metric]:
        family = CounterMetricFamily(
            "cdpr_gateway_exporter_events",
            "What the metrics exporter did: requests served or failed, clients rejected, "
            "timed out or evicted, pauses of accepting (descriptors or connection cap).",
            labels=["event"],
        )
        for event in self.EVENTS:
            family.add_metric([event], float(getattr(self.counters, event)))
        yield family
