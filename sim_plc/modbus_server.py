"""The soft PLC's Modbus TCP server (pymodbus 3.16), serving a :class:`ProcessImage`.

The register map comes from ``cfg.bus.modbus_tcp.registers`` (default: issue 3's map).
Holding registers (functions 3, 6, 16, 23; function 4 reads the same registers) are laid
out in three areas, every other address is illegal (Modbus exception 2):

* the PLC's inputs, read-only: raw S7 counts, setpoints, pose, PLC heartbeat; the area
  is padded with reserved read-only registers (read as 0) up to the next multiple of 8,
  so the default area is 0..55 as a PLC data block would be;
* the gateway's outputs, writable: corrected tensions, channel status, gateway heartbeat
  and state, estimated wrench (default 100..137);
* the simulation truth block, read-only (default 200..215).

Reads are encoded on demand from the image (under ``image.lock``); accepted writes are
decoded into the image and counted in ``image.gateway_writes``. A write that touches a
read-only or unmapped register is refused as a whole (exception 2). Malformed requests
(unknown function, count 0 or too large) get exception replies from pymodbus and the
connection keeps serving.

pymodbus' ``SimDevice`` with an ``action`` coroutine is the documented 3.x hook for a
datastore whose values live elsewhere: the action runs before every access, refreshes the
registers from the image on reads and sees the values of writes.

The server runs its own asyncio loop in a daemon thread: ``start()`` returns once it
listens, ``port`` is the bound port (``port=0`` asks the OS), ``stop()`` is safe twice.
"""

from __future__ import annotations

import asyncio
import gc
import ssl
import threading
import weakref
from concurrent.futures import Future
from typing import Any

import numpy as np
from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer, ModbusTlsServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.registers import FieldCodec, Span, layout_map
from gateway.config import Config, RegisterField, TlsConfig
from gateway.errors import GatewayError
from sim_plc.image import ProcessImage

INPUT_AREA_ALIGN = 8
REGISTER_FUNCTIONS = frozenset((3, 4, 6, 16, 23))
_DECODABLE = frozenset((1, 2, 3, 4, 5, 6, 7, 8, 11, 12, 15, 16, 17, 20, 21, 22, 23, 24, 43))


class _ExceptionFixer:
    """pymodbus 3.16 answers a request it cannot decode (unknown function, count 0 or too
    large) with function code 0x80 and exception 1; rewrite that reply to the standard form:
    ``0x80 | function`` with exception 1 (illegal function) or 3 (illegal data value).

    Used as the server's ``trace_packet`` hook; the error reply is sent synchronously while
    the request is handled, so the last request seen is the one being answered.
    """

    def __init__(self) -> None:
        self.last_function = 0

    def __call__(self, sending: bool, data: bytes) -> bytes:
        if not sending:
            if len(data) >= 8:
                self.last_function = data[7]
            return data
        if len(data) == 9 and data[7] == 0x80 and 0 < self.last_function < 0x80:
            fc = self.last_function
            code = ExcCodes.ILLEGAL_VALUE if fc in _DECODABLE else ExcCodes.ILLEGAL_FUNCTION
            return data[:7] + bytes((0x80 | fc, int(code)))
        return data


def _areas(cfg: Config) -> tuple[Span, Span, Span | None]:
    """The input (padded), output and truth areas of the configured map."""
    rmap = cfg.bus.modbus_tcp.registers
    layout = layout_map(rmap)
    inputs = Span.covering(list(layout.inputs.values()))
    outputs = layout.write_span
    truth = layout.truth_span
    padded_end = -(-inputs.end // INPUT_AREA_ALIGN) * INPUT_AREA_ALIGN
    others = [outputs.start] + ([truth.start] if truth is not None else [])
    limit = min([s for s in others if s >= inputs.end] + [65536])
    inputs = Span(inputs.start, min(padded_end, limit) - inputs.start)
    return inputs, outputs, truth


class _TrackConnections:
    """Remembers a pymodbus server's connections, so that ``close_all`` can make sure no
    transport outlives the server (pymodbus 3.16 can leave one open when a client
    connects or disconnects while the server shuts down)."""

    handlers: weakref.WeakSet[Any]

    def handle_new_connection(self) -> Any:
        protocol = super().handle_new_connection()  # type: ignore[misc]
        self.handlers.add(protocol)
        return protocol

    def close_all(self) -> None:
        for protocol in list(self.handlers):
            transport = getattr(protocol, "transport", None)
            if transport is not None and not transport.is_closing():
                transport.close()


class _PlcTcpServer(_TrackConnections, ModbusTcpServer):
    """Plain Modbus TCP."""


class _PlcTlsServer(_TrackConnections, ModbusTlsServer):
    """Modbus/TCP Security: the same MBAP frames inside TLS (pymodbus' TLS framer)."""


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

    A connection accepted while the server shuts down is in no list of pymodbus': without
    this its socket is left to the garbage collector (a ResourceWarning at some random
    later point, which fails whichever test is running then)."""
    transports = getattr(loop, "_transports", None)  # selector loops: fd -> transport
    for transport in list(transports.values()) if transports else []:
        if transport is not None and not transport.is_closing():
            transport.abort()
    # close() and abort() close the socket in a callback queued with call_soon, also for
    # transports that were already closing: run the loop until those have run
    for _ in range(3):
        loop.run_until_complete(asyncio.sleep(0))


def _close_orphaned_sockets(loop: asyncio.AbstractEventLoop) -> None:
    """Close the socket of any transport of the (finished) ``loop`` that still holds one.

    pymodbus 3.16 can drop its reference to a connection that a client opens while the
    server shuts down, and asyncio then no longer lists the transport either (its fd slot
    is reused): nothing closes the socket until the garbage collector does, with a
    ResourceWarning. The loop has ended, so no callback will touch these sockets again.
    """
    for obj in gc.get_objects():
        # type(), not isinstance(): some objects (canopen's placeholder network) raise
        # on any attribute access, __class__ included
        if issubclass(type(obj), asyncio.Transport) and getattr(obj, "_loop", None) is loop:
            sock = getattr(obj, "_sock", None)
            if sock is not None:
                sock.close()
                obj._sock = None


class ImageRegisters:
    """The register image of one :class:`ProcessImage` and its codecs (no I/O, no loop).

    Words are kept big-endian in ``data`` (``2 * (end - base)`` bytes from ``base``).
    """

    def __init__(self, cfg: Config, image: ProcessImage) -> None:
        self.image = image
        self.rmap = cfg.bus.modbus_tcp.registers
        self.input_area, self.output_area, self.truth_area = _areas(cfg)
        areas = [a for a in (self.input_area, self.output_area, self.truth_area) if a]
        self.base = min(a.start for a in areas)
        self.end = max(a.end for a in areas)
        self.data = bytearray(2 * (self.end - self.base))
        self.words = np.frombuffer(self.data, dtype=">u2")
        sensor = cfg.sensor

        def codec(f: RegisterField) -> FieldCodec:
            return FieldCodec(f, self.data, self.base, 0, sensor)

        r = self.rmap
        self._in = [
            (codec(r.raw_tensions), "raw_counts", True),
            (codec(r.setpoint_velocities), "velocity_m_s", False),
            (codec(r.setpoint_lengths), "length_m", False),
            (codec(r.pose), "pose", False),
            (codec(r.plc_heartbeat), "plc_heartbeat", True),
        ]
        if r.platform_mass is not None:
            self._in.append((codec(r.platform_mass), "platform_mass_kg", False))
        self._out = [
            (codec(r.corrected_tensions), "corrected_n"),
            (codec(r.channel_status), "channel_status"),
            (codec(r.gateway_heartbeat), "gateway_heartbeat"),
            (codec(r.gateway_state), "gateway_state"),
            (codec(r.wrench), "wrench"),
        ]
        self._truth = codec(r.true_tensions) if r.true_tensions is not None else None
        self._scratch = {c.field.address: np.zeros(c.count) for c, _ in self._out}

    def simdata(self) -> list[SimData]:
        """pymodbus blocks: one per area, read-only except the outputs."""
        blocks = [
            SimData(
                self.input_area.start, self.input_area.count, 0, DataType.REGISTERS, readonly=True
            ),
            SimData(self.output_area.start, self.output_area.count, 0, DataType.REGISTERS),
        ]
        if self.truth_area is not None:
            t = self.truth_area
            blocks.append(SimData(t.start, t.count, 0, DataType.REGISTERS, readonly=True))
        return blocks

    def refresh(self) -> None:
        """Encode the whole image into ``data``; the caller holds ``image.lock``."""
        img = self.image
        for c, name, raw in self._in:
            c.encode(getattr(img, name), raw=raw)
        for c, name in self._out:
            value = getattr(img, name)
            c.encode(value & 0xFFFF if isinstance(value, int) else value)
        if self._truth is not None:
            self._truth.encode(img.true_tension_n)

    def read(self, address: int, count: int) -> list[int]:
        """Current register values ``address .. address + count - 1`` from the image."""
        with self.image.lock:
            self.refresh()
        off = address - self.base
        return self.words[off : off + count].tolist()

    def write(self, address: int, values: list[int]) -> None:
        """Apply a gateway write to the output area and decode it into the image."""
        lo, hi = address, address + len(values)
        off = address - self.base
        img = self.image
        with img.lock:
            self.refresh()
            self.words[off : off + len(values)] = values
            for c, name in self._out:
                f = c.field
                if f.address < hi and lo < f.end:
                    buf = c.decode(self._scratch[f.address])
                    if isinstance(getattr(img, name), int):
                        setattr(img, name, int(buf[0]))
                    else:
                        getattr(img, name)[...] = buf
            img.gateway_writes += 1


class ModbusPlcServer:
    """The soft PLC's Modbus TCP server over a :class:`ProcessImage` (see module doc)."""

    def __init__(
        self,
        cfg: Config,
        image: ProcessImage,
        host: str = "127.0.0.1",
        port: int = 5020,
        tls: TlsConfig | None = None,
    ) -> None:
        self.cfg = cfg
        self.tls = tls
        self.image = image
        self.host = host
        self.port = port
        self.registers = ImageRegisters(cfg, image)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._server: ModbusTcpServer | None = None
        self._listener: Any = None
        self._stopped = threading.Event()

    async def _action(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        if function_code not in REGISTER_FUNCTIONS:
            return ExcCodes.ILLEGAL_FUNCTION
        regs = self.registers
        if values is None:
            off = address - start_address
            registers[off : off + count] = regs.read(address, count)
            return None
        out = regs.output_area
        if not (out.start <= address and address + count <= out.end):
            return ExcCodes.ILLEGAL_ADDRESS
        regs.write(address, [int(v) for v in values])
        return None

    async def _serve(self, ready: Future[int]) -> None:
        device = SimDevice(id=0, simdata=self.registers.simdata(), action=self._action)
        server: _PlcTcpServer | _PlcTlsServer
        if self.tls is None:
            server = _PlcTcpServer(
                device, address=(self.host, self.port), trace_packet=_ExceptionFixer()
            )
        else:
            server = _PlcTlsServer(
                device,
                address=(self.host, self.port),
                sslctx=server_tls_context(self.tls),
                framer=FramerType.TLS,
                trace_packet=_ExceptionFixer(),
            )
        server.handlers = weakref.WeakSet()
        self._server = server
        if not await server.listen():
            ready.set_exception(
                GatewayError(f"modbus server: cannot listen on {self.host}:{self.port}")
            )
            return
        self._listener = server.transport  # asyncio's Server: closed first at shutdown
        sock = server.transport.sockets[0]  # type: ignore[attr-defined]
        ready.set_result(sock.getsockname()[1])
        await server.serving
        # shutdown() closed the listener and the connections; let their transports finish
        # (connection_lost callbacks) before the loop goes away
        await asyncio.sleep(0.01)
        server.close_all()
        await asyncio.sleep(0.01)

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
            if isinstance(self._listener, asyncio.AbstractServer):
                self._listener.close()  # accept nothing more while the loop winds down
            # a connection accepted just before the shutdown is wrapped in a transport by a
            # task of the loop; cancelled unstarted, that task would leak the socket: let
            # such tasks run, then abort every transport, then cancel what is left
            for _ in range(3):
                loop.run_until_complete(asyncio.sleep(0))
            _close_transports(loop)
            pending = asyncio.all_tasks(loop)
            for task in pending:
                task.cancel()
            loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
            _close_transports(loop)
            loop.run_until_complete(loop.shutdown_asyncgens())
            _close_transports(loop)
            asyncio.set_event_loop(None)
            loop.close()
            self._stopped.set()

    def start(self, timeout_s: float = 5.0) -> None:
        """Listen in a background thread; return once listening (``port`` is then bound)."""
        if self._thread is not None:
            raise GatewayError("modbus server: already started")
        ready: Future[int] = Future()
        self._stopped.clear()
        self._thread = threading.Thread(
            target=self._run, args=(ready,), daemon=True, name="modbus-plc"
        )
        self._thread.start()
        self.port = ready.result(timeout=timeout_s)

    def stop(self, timeout_s: float = 5.0) -> None:
        """Close the listener and every connection; safe to call more than once."""
        thread, loop, server = self._thread, self._loop, self._server
        if thread is None:
            return
        self._thread = None
        if loop is not None and server is not None and not loop.is_closed():
            try:
                fut = asyncio.run_coroutine_threadsafe(server.shutdown(), loop)
                fut.result(timeout=timeout_s)
            except RuntimeError:  # the loop ended on its own
                pass
        thread.join(timeout=timeout_s)
        if loop is not None and not thread.is_alive():
            _close_orphaned_sockets(loop)
        self._loop = None
        self._server = None
        self._listener = None

    def __enter__(self) -> ModbusPlcServer:
        self.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()
