"""The soft PLC's Modbus TCP server: a lean asyncio MBAP server over a :class:`ProcessImage`.

The register map comes from ``cfg.bus.modbus_tcp.registers`` (default: the shipped map).
Holding registers (functions 3, 6, 16, 23; function 4 reads the same registers) are laid
out in three areas, every other address is illegal (Modbus exception 2):

* the PLC's inputs, read-only: raw S7 counts, setpoints, pose, PLC heartbeat; the area
  is padded with reserved read-only registers (read as 0) up to the next multiple of 8,
  so the default area is 0..55 as a PLC data block would be;
* the gateway's outputs, writable: corrected tensions, channel status, gateway heartbeat
  and state, estimated wrench (default 100..137);
* the simulation's side channel, read-only, served only by the soft PLC (it is in no
  gateway register map): the plant's true platform tensions (float32, from register
  ``TRUTH_ADDRESS`` = 200) followed by the PLC heartbeat of the same plant step (uint16,
  register 216 for 8 cables), so an observer (the demo) can tell which reading of the
  gateway a truth sample belongs to.

Reads are encoded on demand from the image (under ``image.lock``); accepted writes are
decoded into the image and counted in ``image.gateway_writes``. A write that touches a
read-only or unmapped register is refused as a whole (exception 2); a request whose
counts or length are out of range gets exception 3, an unknown function exception 1
(Modbus application protocol v1.1b3), and the connection keeps serving. Any unit id is
served and echoed.

Framing (Modbus messaging on TCP/IP v1.0b): every complete MBAP frame in the receive
buffer is answered, in order, so requests pipelined in one segment (or split across
segments) all get their replies, written back together. A header the server will not
serve -- protocol id other than 0, length 0 or 1 (no function code), length above 266
(more than any request's own byte count can describe) -- closes the connection after
the replies already due: the client sees EOF instead of a silent socket. Memory per
connection is bounded (at most one partial frame is kept); a client that does not read
its replies is paused (flow control).
At most ``max_connections`` connections are served; further ones are closed at once.

The server was pymodbus 3.16's until it lost pipelined requests (its transport clears the
receive buffer on every send) and left connections with a bad header silently dead; this
one is also cheaper per request (``python -m bench.modbus_floor``).

The server runs its own asyncio loop in a daemon thread: ``start()`` returns once it
listens, ``port`` is the bound port (``port=0`` asks the OS), ``stop()`` is safe twice.
Modbus/TCP Security (``tls``): the same MBAP frames inside TLS 1.2+, client certificates
checked against the CA when ``verify_peer``.
"""

from __future__ import annotations

import asyncio
import contextlib
import ssl
import struct
import threading
from concurrent.futures import Future
from typing import Any

from gateway.core.config import Config, TlsConfig
from gateway.errors import GatewayError
from sim_plc.image import ProcessImage
from sim_plc.modbus_image import (
    ImageRegisters,
    RequestHandler,
)

# The spec's largest ADU is 260 bytes (MBAP length 254); a request up to the largest its own
# byte count can describe (function 23: 10 + 255 bytes, + the unit id) is still read and
# answered with exception 3; a longer length field is a stream we will not follow.
MAX_MBAP_LENGTH = 266
MAX_CONNECTIONS = 64
TLS_HANDSHAKE_TIMEOUT_S = 5.0
_MBAP = struct.Struct(">HHHB")  # transaction id, protocol id, length, unit id
_HEAD = struct.Struct(">HHH")


def server_tls_context(tls: TlsConfig) -> ssl.SSLContext:
    """Server side of Modbus/TCP Security: our certificate, and (``verify_peer``) client
    certificates required and checked against ``cafile``."""
    ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH, cafile=tls.cafile)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    ctx.load_cert_chain(tls.certfile, tls.keyfile)
    ctx.verify_mode = ssl.CERT_REQUIRED if tls.verify_peer else ssl.CERT_NONE
    return ctx


def _close_transports(loop: asyncio.AbstractEventLoop) -> None:
    """Abort every socket transport the loop still holds and let their ``connection_lost``
    callbacks close the sockets before the loop goes away.

    The backstop after :meth:`ModbusPlcServer._shut_down` (or a failed start): a transport
    left open is otherwise left to the garbage collector (a ResourceWarning at some random
    later point, which fails whichever test is running then)."""
    transports = getattr(loop, "_transports", None)  # selector loops: fd -> transport
    for transport in list(transports.values()) if transports else []:
        if transport is not None and not transport.is_closing():
            transport.abort()
    # close() and abort() close the socket in a callback queued with call_soon, also for
    # transports that were already closing: run the loop until those have run
    for _ in range(3):
        loop.run_until_complete(asyncio.sleep(0))


class _MbapConnection(asyncio.Protocol):
    """One client connection: MBAP framing, pipelining, closing on a bad header."""

    def __init__(self, server: ModbusPlcServer) -> None:
        self.server = server
        self.handler = server.handler
        self.buf = bytearray()
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        if len(self.server.connections) >= self.server.max_connections:
            self.server.refused += 1
            transport.close()
            return
        self.server.connections.add(self)

    def connection_lost(self, exc: Exception | None) -> None:
        self.server.connections.discard(self)
        self.buf.clear()

    def data_received(self, data: bytes) -> None:
        buf = self.buf
        buf += data
        replies: list[bytes] = []
        pos, size = 0, len(buf)
        while size - pos >= 6:
            tid, protocol, length = _HEAD.unpack_from(buf, pos)
            if protocol != 0 or not 2 <= length <= MAX_MBAP_LENGTH:
                self._refuse(replies)
                return
            end = pos + 6 + length
            if end > size:
                break
            unit = buf[pos + 6]
            reply = self.handler.handle(bytes(buf[pos + 7 : end]))
            replies.append(_MBAP.pack(tid, 0, len(reply) + 1, unit) + reply)
            pos = end
        if pos:
            del buf[:pos]
        if replies and self.transport is not None:
            self.transport.write(b"".join(replies))

    def _refuse(self, replies: list[bytes]) -> None:
        """A frame we will not serve: send what is due, then close the connection."""
        self.buf.clear()
        self.server.bad_frames += 1
        if self.transport is not None:
            if replies:
                self.transport.write(b"".join(replies))
            self.transport.close()  # flushes the pending replies first

    def pause_writing(self) -> None:  # the client does not read: stop reading it
        if self.transport is not None:
            self.transport.pause_reading()

    def resume_writing(self) -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.resume_reading()


class ModbusPlcServer:
    """The soft PLC's Modbus TCP server over a :class:`ProcessImage` (see module doc)."""

    def __init__(
        self,
        cfg: Config,
        image: ProcessImage,
        host: str = "127.0.0.1",
        port: int = 5020,
        tls: TlsConfig | None = None,
        max_connections: int = MAX_CONNECTIONS,
    ) -> None:
        self.cfg = cfg
        self.tls = tls
        self.image = image
        self.host = host
        self.port = port
        self.max_connections = int(max_connections)
        self.registers = ImageRegisters(cfg, image)
        self.handler = RequestHandler(self.registers)
        self.connections: set[_MbapConnection] = set()
        self.bad_frames = 0  # connections closed for a header the server will not serve
        self.refused = 0  # connections closed at once: ``max_connections`` reached
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._stopping: asyncio.Event | None = None

    @property
    def thread(self) -> threading.Thread | None:
        """The serving thread while the server runs."""
        return self._thread

    async def _serve(self, ready: Future[int]) -> None:
        loop = asyncio.get_running_loop()
        self._stopping = asyncio.Event()
        ctx = server_tls_context(self.tls) if self.tls is not None else None
        try:
            listener = await loop.create_server(
                lambda: _MbapConnection(self),
                self.host,
                self.port,
                ssl=ctx,
                ssl_handshake_timeout=TLS_HANDSHAKE_TIMEOUT_S if ctx is not None else None,
                reuse_address=True,
            )
        except OSError as exc:
            ready.set_exception(
                GatewayError(f"modbus server: cannot listen on {self.host}:{self.port}: {exc}")
            )
            return
        ready.set_result(listener.sockets[0].getsockname()[1])
        try:
            await self._stopping.wait()
        finally:
            await self._shut_down(listener)

    async def _shut_down(self, listener: asyncio.Server) -> None:
        """Accept nothing more, let the connections already accepted be made, close the
        listener, then drop every connection.

        The order matters. asyncio accepts a connection in one loop turn and makes its
        transport in a task one turn later, which attaches it to the listener; on a closed
        listener that asserts (3.11 ``Server._attach``), and asyncio then drops the
        half-made transport with its socket open: a ResourceWarning at some later garbage
        collection, failing whichever test runs then. A client whose connect completed in
        the kernel's backlog just before ``stop()`` (a driver opened and closed at once)
        hits this."""
        loop = asyncio.get_running_loop()
        for sock in listener.sockets:
            # also cancels an accept callback already queued for this turn
            loop.remove_reader(sock.fileno())
        # the accept tasks created so far were queued before this task's next step: one
        # turn makes (and attaches) their transports, the next runs connection_made
        for _ in range(2):
            await asyncio.sleep(0)
        listener.close()
        for conn in list(self.connections):
            if conn.transport is not None:
                conn.transport.abort()
        for _ in range(3):  # the aborts close the sockets in callbacks: let them run
            await asyncio.sleep(0)

    def _run(self, ready: Future[int]) -> None:
        loop = asyncio.new_event_loop()
        asyncio.set_event_loop(loop)  # this thread's loop
        self._loop = loop
        try:
            loop.run_until_complete(self._serve(ready))
        except BaseException as exc:  # report start-up failures to start()
            if not ready.done():
                ready.set_exception(exc)
        finally:
            _close_transports(loop)
            pending = asyncio.all_tasks(loop)
            for task in pending:
                task.cancel()
            loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
            _close_transports(loop)
            loop.run_until_complete(loop.shutdown_asyncgens())
            asyncio.set_event_loop(None)
            loop.close()

    def start(self, timeout_s: float = 5.0) -> None:
        """Listen in a background thread; return once listening (``port`` is then bound)."""
        if self._thread is not None:
            raise GatewayError("modbus server: already started")
        ready: Future[int] = Future()
        self._thread = threading.Thread(
            target=self._run, args=(ready,), daemon=True, name="modbus-plc"
        )
        self._thread.start()
        try:
            self.port = ready.result(timeout=timeout_s)
        except BaseException:
            self._thread.join(timeout_s)
            self._thread = None
            raise

    def stop(self, timeout_s: float = 5.0) -> None:
        """Close the listener and every connection; safe to call more than once."""
        thread, loop, stopping = self._thread, self._loop, self._stopping
        if thread is None:
            return
        self._thread = None
        if loop is not None and stopping is not None:
            with contextlib.suppress(RuntimeError):  # the loop ended on its own
                loop.call_soon_threadsafe(stopping.set)
        thread.join(timeout=timeout_s)
        self._loop = None
        self._stopping = None

    def __enter__(self) -> ModbusPlcServer:
        self.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()
