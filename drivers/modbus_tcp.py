"""Modbus TCP client driver: the gateway's side of the PLC's MB_SERVER.

One transaction per cycle. With ``use_fc23`` :meth:`exchange` (outputs, inputs) is ONE
function-23 read/write transaction (write the outputs span, read the inputs span);
:meth:`write_from` always sends at once with function 16 and :meth:`read_into` reads
with function 3. Without ``use_fc23`` an exchange is a function-16 write then a
function-3 read (the 3+16 fallback for servers without function 23).

Why a socket-level MBAP client and not pymodbus' client: the cycle is 1 ms and the
gateway benchmark holds the driver's round trip against a bare socket loop doing the same
function-23 transaction (goal: ratio <= 1.3). pymodbus' client builds PDU objects, encodes
register lists in Python loops and, in 3.x, runs its sync client over a transaction
manager with per-call allocations, which costs more than the loopback round trip itself.
Here every frame is a preallocated ``bytearray``: the header is patched with
``struct.pack_into``, the outputs are encoded straight into the request frame and the
inputs decoded straight out of the reply buffer by :class:`drivers.registers.FieldCodec`
numpy views, ``recv_into`` fills the reply, ``TCP_NODELAY`` is set. pymodbus stays the
soft PLC's server and the independent client in the tests.

Robustness: one request in flight; a reply whose transaction id is not the one awaited
(a late reply to a request that timed out, or garbage) or whose unit id is not
``unit_id`` (another device behind the same address) is read whole and dropped, never
decoded (``dropped_replies``; ``foreign_unit_replies`` for the unit id). Every wait for
reply bytes is computed from the transaction's own deadline (``timeout_s`` after the
request), so a slow reply never shortens the next one's wait. Read timeouts raise
:class:`DriverTimeoutError`; three in a row, a closed or broken connection drop the
socket, and every later call raises :class:`DriverIOError` ("not connected") until the
loop reconnects through :meth:`Driver.poll_connect`: the TCP connect and the TLS
handshake are non-blocking and advanced by at most the caller's budget per call, with
the base class's backoff (``reconnect_min_s`` doubling to ``reconnect_max_s``, reset only
by a good data reply). Errors carry the cause: the errno text of a refused connect, the
TLS verification reason. Exception replies raise :class:`DriverIOError` naming the
function, the register and the exception. Optional TLS (Modbus/TCP Security, port 802)
with the ``ssl`` module.
"""

from __future__ import annotations

import errno
import os
import select
import socket
import ssl
import struct
import time
from typing import Any

import numpy as np

from drivers.base import Backoff, Driver, Inputs, Outputs
from drivers.registers import FieldCodec, FieldGroup, Span, check_outputs, layout_map, value_band
from gateway.core.config import ModbusTcpConfig
from gateway.errors import ConfigError, DriverInitError, DriverIOError, DriverTimeoutError

FC_READ = 3
FC_WRITE = 16
FC_READ_WRITE = 23
MBAP = 7
MAX_TIMEOUTS_IN_A_ROW = 3
RX_FRAME_MAX = MBAP - 1 + 254  # the largest MBAP frame
EXCEPTION_NAMES = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "server device failure",
    5: "acknowledge",
    6: "server device busy",
    10: "gateway path unavailable",
    11: "gateway target failed to respond",
}
_HEADER = struct.Struct(">HHHB")


def _tls_context(mb: ModbusTcpConfig) -> ssl.SSLContext | None:
    if mb.tls is None:
        return None
    tls = mb.tls
    ctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=tls.cafile)
    ctx.load_cert_chain(tls.certfile, tls.keyfile)
    if not tls.verify_peer:
        ctx.check_hostname = False
        ctx.verify_mode = ssl.CERT_NONE
    return ctx


class ModbusTcpDriver(Driver):
    """Modbus TCP client for the configured register map (see module doc)."""

    name = "modbus_tcp"

    def __init__(self, config: Any) -> None:
        super().__init__(config)
        self.mb: ModbusTcpConfig = config.bus.modbus_tcp
        self.where = self.mb.endpoint
        self.layout = layout_map(self.mb.registers)
        self._check_counts()
        check_outputs(self.mb.registers, config.sensor)
        try:
            self._ssl = _tls_context(self.mb)
        except (OSError, ssl.SSLError) as exc:
            raise DriverInitError(f"{self.where}: TLS setup: {exc}") from exc
        self.backoff = Backoff(self.mb.reconnect_min_s, self.mb.reconnect_max_s)
        self._sock: socket.socket | None = None
        self._pending: socket.socket | None = None  # a connection being set up
        self._handshaking = False  # _pending is a TLS socket in its handshake
        self._connect_deadline = 0.0
        self._tid = 0
        self._timeouts_in_a_row = 0
        self._outgoing: tuple[Outputs, int] | None = None  # the frame's outputs, while sent
        self.foreign_unit_replies = 0  # replies from another unit id (also dropped_replies)
        self._build_frames(config)
        self.plc_heartbeat_modulus = {"float32": 0, "int32": 2**32, "uint32": 2**32}.get(
            self.mb.registers.plc_heartbeat.type, 2**16
        )

    def output_bands(self) -> tuple[tuple[float, float], tuple[float, float]]:
        r = self.mb.registers
        return value_band(r.corrected_tensions), value_band(r.wrench)

    @property
    def combines_write_and_read(self) -> bool:
        return self.mb.use_fc23

    # --- setup ------------------------------------------------------------------------
    def _check_counts(self) -> None:
        r = self.mb.registers
        expect = {
            "raw_tensions": (r.raw_tensions, self.cables),
            "setpoint_velocities": (r.setpoint_velocities, self.cables),
            "setpoint_lengths": (r.setpoint_lengths, self.cables),
            "pose": (r.pose, 6),
            "plc_heartbeat": (r.plc_heartbeat, 1),
            "corrected_tensions": (r.corrected_tensions, self.cables),
            "gateway_heartbeat": (r.gateway_heartbeat, 1),
            "gateway_state": (r.gateway_state, 1),
            "channel_status": (r.channel_status, self.cables),
            "wrench": (r.wrench, 6),
        }
        if r.platform_mass is not None:
            expect["platform_mass"] = (r.platform_mass, 1)
        for name, (f, n) in expect.items():
            if f.count != n:
                raise ConfigError(f"bus.modbus_tcp.registers.{name}: count {f.count}, need {n}")

    def _build_frames(self, config: Any) -> None:
        rs, ws = self.layout.read_span, self.layout.write_span
        nbytes = 2 * ws.count
        self._rx = bytearray(2 * RX_FRAME_MAX)
        self._have = 0  # bytes in _rx
        self._consumed = 0  # size of the frame at _rx[0] once it has been used
        self._sock_timeout = 0.0
        self._rxv = memoryview(self._rx)
        self._wdata = bytearray(nbytes)
        self._fc23 = self._frame(
            FC_READ_WRITE,
            struct.pack(">HHHHB", rs.start, rs.count, ws.start, ws.count, nbytes),
            nbytes,
        )
        self._fc3 = self._frame(FC_READ, struct.pack(">HH", rs.start, rs.count), 0)
        self._fc16 = self._frame(FC_WRITE, struct.pack(">HHB", ws.start, ws.count, nbytes), nbytes)
        sensor = config.sensor
        r = self.mb.registers
        off = MBAP + 2

        def inp(f: Any) -> FieldCodec:
            return FieldCodec(f, self._rx, rs.start, off, sensor)

        self._raw = inp(r.raw_tensions)
        self._vel = inp(r.setpoint_velocities)
        self._len = inp(r.setpoint_lengths)
        self._pose = inp(r.pose)
        self._hb = inp(r.plc_heartbeat)
        self._mass = inp(r.platform_mass) if r.platform_mass is not None else None
        self._mass_value = np.zeros(1)

        def outp(f: Any, wrap: bool = False) -> FieldCodec:
            return FieldCodec(f, self._wdata, ws.start, 0, sensor, wrap=wrap)

        self._out = (
            outp(r.corrected_tensions),
            outp(r.channel_status),
            outp(r.gateway_heartbeat, wrap=True),
            outp(r.gateway_state),
            outp(r.wrench),
        )
        self._wdata_at23 = MBAP + 10
        self._wdata_at16 = MBAP + 6
        # the cycle decodes and encodes every field in one compiled call (compiled now)
        self._in_group = FieldGroup(
            (self._raw, self._vel, self._len, self._pose, self._hb), raw=(False,) * 4 + (True,)
        )
        self._hb_value = np.zeros(1)
        self._hb_int = r.plc_heartbeat.type != "float32"
        self._out_group = FieldGroup(self._out)
        self._decode(Inputs.allocate(self.cables))
        self._encode(Outputs.allocate(self.cables))

    def _frame(self, fc: int, fields: bytes, nbytes: int) -> bytearray:
        pdu = bytes((fc,)) + fields
        frame = bytearray(MBAP + len(pdu) + nbytes)
        _HEADER.pack_into(frame, 0, 0, 0, len(pdu) + nbytes + 1, self.mb.unit_id)
        frame[MBAP : MBAP + len(pdu)] = pdu
        return frame

    # --- connection (non-blocking; the base class paces the attempts) -----------------
    def _open_begin(self) -> bool:
        self._close()
        self._connect_deadline = time.monotonic() + self.mb.connect_timeout_s
        try:
            info = socket.getaddrinfo(self.mb.host, self.mb.port, type=socket.SOCK_STREAM)[0]
            sock = socket.socket(info[0], info[1], info[2])
        except OSError as exc:
            raise DriverInitError(f"{self.where}: cannot connect: {exc}") from exc
        sock.setblocking(False)
        self._pending = sock
        rc = sock.connect_ex(info[4])
        if rc not in (0, errno.EINPROGRESS, errno.EWOULDBLOCK):
            self._abandon()
            raise DriverInitError(f"{self.where}: cannot connect: {os.strerror(rc)}")
        return False

    def _open_advance(self, budget_s: float) -> bool:
        sock = self._pending
        if sock is None:
            raise DriverInitError(f"{self.where}: no connection attempt in progress")
        if not self._handshaking:
            _, writable, _ = select.select([], [sock], [], max(budget_s, 0.0))
            if not writable:
                self._check_connect_deadline("connect")
                return False
            rc = sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
            if rc:
                self._abandon()
                raise DriverInitError(f"{self.where}: cannot connect: {os.strerror(rc)}")
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if self._ssl is not None:
                self._pending = self._ssl.wrap_socket(
                    sock, server_hostname=self.mb.host, do_handshake_on_connect=False
                )
                self._handshaking = True
        if self._handshaking and not self._handshake(budget_s):
            return False
        self._connected()
        return True

    def _handshake(self, budget_s: float) -> bool:
        """Advance the TLS handshake for at most ``budget_s``; True when done."""
        sock = self._pending
        assert isinstance(sock, ssl.SSLSocket)
        end = time.monotonic() + max(budget_s, 0.0)
        while True:
            try:
                sock.do_handshake()
                return True
            except ssl.SSLWantReadError:
                wait_read = True
            except ssl.SSLWantWriteError:
                wait_read = False
            except (OSError, ssl.SSLError) as exc:
                self._abandon()
                raise DriverInitError(f"{self.where}: TLS handshake: {_tls_reason(exc)}") from exc
            remaining = end - time.monotonic()
            ready = select.select(
                [sock] if wait_read else [], [] if wait_read else [sock], [], max(remaining, 0)
            )
            if not (ready[0] or ready[1]):
                self._check_connect_deadline("TLS handshake")
                return False

    def _check_connect_deadline(self, what: str) -> None:
        if time.monotonic() > self._connect_deadline:
            self._abandon()
            raise DriverTimeoutError(
                f"{self.where}: {what} timed out after {self.mb.connect_timeout_s} s"
            )

    def _abandon(self) -> None:
        if self._pending is not None:
            self._pending.close()
        self._pending = None
        self._handshaking = False

    def _connected(self) -> None:
        sock, self._pending, self._handshaking = self._pending, None, False
        assert sock is not None
        sock.settimeout(self.mb.timeout_s)
        self._sock = sock
        self._sock_timeout = self.mb.timeout_s
        self._have = self._consumed = 0
        self._timeouts_in_a_row = 0

    def _drop(self) -> None:
        """Forget the connection: every call fails until the loop reconnects."""
        if self._sock is not None:
            self._sock.close()
        self._sock = None
        self._timeouts_in_a_row = 0

    def _close(self) -> None:
        self._drop()
        self._abandon()

    # --- transactions -----------------------------------------------------------------
    def _recv_more(self, sock: socket.socket, deadline: float) -> None:
        """Append what the socket has to the receive buffer (at least one byte)."""
        remaining = deadline - time.perf_counter()
        if remaining <= 0:
            raise TimeoutError
        sock.settimeout(remaining)  # this wait ends at the transaction's own deadline
        self._sock_timeout = remaining
        k = sock.recv_into(self._rxv[self._have :])
        if k == 0:
            raise ConnectionResetError("connection closed by the server")
        self._have += k

    def _receive(self, sock: socket.socket, tid: int, deadline: float) -> int:
        """Read frames until the one answering ``tid``; return its PDU length.

        Frames are parsed from ``_rx`` (``_have`` bytes); usually one ``recv_into`` brings
        exactly the reply. Bytes after it are kept; dropped frames are shifted out.
        """
        while True:
            while self._have < MBAP:
                self._recv_more(sock, deadline)
            rtid, proto, length, unit = _HEADER.unpack_from(self._rx, 0)
            size = MBAP - 1 + length
            if length < 2 or size > RX_FRAME_MAX:  # framing is lost: drop the connection
                self.dropped_replies += 1
                raise ConnectionResetError(f"malformed reply (MBAP length {length})")
            while self._have < size:
                self._recv_more(sock, deadline)
            if rtid == tid and proto == 0 and unit == self.mb.unit_id:
                self._consumed = size
                return length - 1
            if unit != self.mb.unit_id:
                self.foreign_unit_replies += 1
            self.dropped_replies += 1
            self._shift(size)

    def _shift(self, size: int) -> None:
        rest = self._have - size
        if rest:
            self._rx[:rest] = self._rx[size : self._have]
        self._have = rest

    def _transact(self, frame: bytearray, fc: int, address: int) -> int:
        """Send ``frame`` (its header gets a fresh transaction id) and await its reply."""
        sock = self._sock
        if sock is None:
            raise DriverIOError(f"{self.where}: not connected")
        if self._consumed:  # the previous reply has been decoded: drop it from the buffer
            self._shift(self._consumed)
            self._consumed = 0
        self._tid = (self._tid + 1) & 0xFFFF
        struct.pack_into(">H", frame, 0, self._tid)
        deadline = time.perf_counter() + self.mb.timeout_s
        late = False
        try:
            if self._sock_timeout < 0.5 * self.mb.timeout_s:
                sock.settimeout(self.mb.timeout_s)
                self._sock_timeout = self.mb.timeout_s
            self._last_look(frame)
            sock.sendall(frame)
            n = self._receive(sock, self._tid, deadline)
            if time.perf_counter() > deadline:  # read late (this process was held up):
                late = True  # the reply is dropped, its data is no good
                raise TimeoutError
        except TimeoutError as exc:
            self._timeouts_in_a_row += 1
            if self._timeouts_in_a_row >= MAX_TIMEOUTS_IN_A_ROW:
                self._drop()
            what = "reply read after its deadline" if late else "no reply within"
            raise DriverTimeoutError(
                f"{self.where}: function {fc} at register {address}: {what} {self.mb.timeout_s} s"
            ) from exc
        except (OSError, ssl.SSLError) as exc:
            self._drop()
            raise DriverIOError(
                f"{self.where}: function {fc} at register {address}: {exc}"
            ) from exc
        self._timeouts_in_a_row = 0
        self._check_reply(fc, address, n)  # an exception reply is no good reply
        return n

    def _last_look(self, frame: bytearray) -> None:
        """The output gate once more right before the frame leaves: a frame that went
        stale since it was encoded (this process held up in between) goes out invalid."""
        outgoing = self._outgoing
        if outgoing is None:
            return
        outputs, at = outgoing
        if self._gate_frame(outputs):
            self._encode(outputs)
            frame[at:] = self._wdata

    def _check_reply(self, fc: int, address: int, n: int) -> None:
        rfc = self._rx[MBAP]
        if rfc == fc | 0x80:
            code = self._rx[MBAP + 1] if n >= 2 else 0
            name = EXCEPTION_NAMES.get(code, "unknown exception")
            raise DriverIOError(
                f"{self.where}: function {fc} at register {address}: exception {code} ({name})"
            )
        if rfc != fc:
            raise DriverIOError(
                f"{self.where}: function {fc} at register {address}: reply has function {rfc}"
            )

    def _read_span(self, frame: bytearray, fc: int, span: Span) -> None:
        n = self._transact(frame, fc, span.start)
        if n != 2 + 2 * span.count or self._rx[MBAP + 1] != 2 * span.count:
            raise DriverIOError(
                f"{self.where}: function {fc} at register {span.start}: reply of {n} bytes "
                f"for {span.count} registers"
            )

    # --- hooks ------------------------------------------------------------------------
    def _exchange(self, outputs: Outputs | None, inputs: Inputs) -> None:
        if outputs is None:
            self._read_span(self._fc3, FC_READ, self.layout.read_span)
        elif self.mb.use_fc23:
            self._encode(outputs)
            self._fc23[self._wdata_at23 :] = self._wdata
            self._outgoing = (outputs, self._wdata_at23)
            try:
                self._read_span(self._fc23, FC_READ_WRITE, self.layout.read_span)
            finally:
                self._outgoing = None
        else:  # the 3 + 16 fallback
            self._write(outputs)
            self._read_span(self._fc3, FC_READ, self.layout.read_span)
        self._decode(inputs)

    def _read(self, inputs: Inputs) -> None:
        self._exchange(None, inputs)

    def _decode(self, inputs: Inputs) -> None:
        hb = self._hb_value
        i = inputs
        self._in_group.decode((i.tension_raw_n, i.velocity_m_s, i.length_m, i.pose, hb))
        inputs.plc_heartbeat = int(hb[0]) if self._hb_int else float(hb[0])
        if self._mass is not None:
            inputs.platform_mass_kg = float(self._mass.decode(self._mass_value)[0])

    def _encode(self, outputs: Outputs) -> None:
        o = outputs
        hb, state = int(o.gateway_heartbeat), int(o.gateway_state)
        self._out_group.encode((o.tension_corrected_n, o.channel_status, hb, state, o.wrench))

    def _write(self, outputs: Outputs) -> None:
        self._encode(outputs)
        self._fc16[self._wdata_at16 :] = self._wdata
        ws = self.layout.write_span
        self._outgoing = (outputs, self._wdata_at16)
        try:
            n = self._transact(self._fc16, FC_WRITE, ws.start)
        finally:
            self._outgoing = None
        if n != 5 or struct.unpack_from(">HH", self._rx, MBAP + 1) != (ws.start, ws.count):
            raise DriverIOError(f"{self.where}: function 16 at register {ws.start}: bad echo")


def _tls_reason(exc: BaseException) -> str:
    """The TLS failure as an operator reads it: the verification reason when there is one."""
    reason = getattr(exc, "verify_message", None)
    if reason:
        return f"certificate verify failed: {reason}"
    return str(getattr(exc, "reason", None) or exc)
