"""Modbus TCP client driver: the gateway's side of the PLC's MB_SERVER.

One transaction per cycle. With ``use_fc23`` the outputs given to :meth:`write_from` are
staged and sent with the next :meth:`read_into` in one function-23 read/write
transaction (write the outputs span, read the inputs span); :meth:`flush` sends a staged
write alone with function 16. Without ``use_fc23`` a cycle is a function-3 read and a
function-16 write. The simulation truth block is read in the same transaction when it
fits one read (<= 125 registers with the inputs), else by :meth:`read_truth`.

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
(a late reply to a request that timed out, or garbage) is read whole and dropped
(``dropped_replies``). Read and connect timeouts raise :class:`DriverTimeoutError`;
three timeouts in a row, a closed or broken connection drop the socket. Reconnects never
block the cycle for long: a connect is started non-blocking and polled for at most
``timeout_s`` per call, attempts are spaced with exponential backoff between
``reconnect_min_s`` and ``reconnect_max_s`` and every failed call raises
:class:`DriverIOError` quickly. ``reconnects`` counts connections re-established after a
loss. Exception replies raise :class:`DriverIOError` naming the function, the register
and the exception. Optional TLS (Modbus/TCP Security, port 802) with the ``ssl`` module.
"""

from __future__ import annotations

import errno
import select
import socket
import ssl
import struct
import time
from typing import Any

import numpy as np

from drivers.base import Driver, DriverState, Inputs, Outputs
from drivers.registers import FieldCodec, Span, layout_map
from gateway.config import ModbusTcpConfig
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
        self.where = f"modbus_tcp {self.mb.host}:{self.mb.port} unit {self.mb.unit_id}"
        self.layout = layout_map(self.mb.registers)
        self._check_counts()
        try:
            self._ssl = _tls_context(self.mb)
        except (OSError, ssl.SSLError) as exc:
            raise DriverInitError(f"{self.where}: TLS setup: {exc}") from exc
        self._sock: socket.socket | None = None
        self._connecting: socket.socket | None = None
        self._connect_deadline = 0.0
        self._next_attempt = 0.0
        self._backoff_s = self.mb.reconnect_min_s
        self._ever_connected = False
        self._tid = 0
        self._timeouts_in_a_row = 0
        self._staged = False
        self.dropped_replies = 0
        self.reconnect_attempts = 0
        self._build_frames(config)

    # --- setup ------------------------------------------------------------------------
    def _check_counts(self) -> None:
        r = self.mb.registers
        expect = {
            "raw_tensions": (r.raw_tensions, self.cables),
            "setpoint_velocities": (r.setpoint_velocities, self.cables),
            "setpoint_lengths": (r.setpoint_lengths, self.cables),
            "pose": (r.pose, 6),
            "corrected_tensions": (r.corrected_tensions, self.cables),
            "channel_status": (r.channel_status, self.cables),
            "wrench": (r.wrench, 6),
        }
        if r.true_tensions is not None:
            expect["true_tensions"] = (r.true_tensions, self.cables)
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
        ts = self.layout.truth_span
        self._fc3_truth = (
            self._frame(FC_READ, struct.pack(">HH", ts.start, ts.count), 0) if ts else None
        )
        sensor = config.sensor
        r = self.mb.registers
        off = MBAP + 2

        def inp(f: Any, base: Span = rs) -> FieldCodec:
            return FieldCodec(f, self._rx, base.start, off, sensor)

        self._raw = inp(r.raw_tensions)
        self._vel = inp(r.setpoint_velocities)
        self._len = inp(r.setpoint_lengths)
        self._pose = inp(r.pose)
        self._hb = inp(r.plc_heartbeat)
        self._mass = inp(r.platform_mass) if r.platform_mass is not None else None
        self._mass_value = np.zeros(1)
        self._truth_in_read = inp(r.true_tensions) if self.layout.truth_in_read else None
        self._truth_alone = inp(r.true_tensions, ts) if ts is not None else None

        def outp(f: Any) -> FieldCodec:
            return FieldCodec(f, self._wdata, ws.start, 0, sensor)

        self._out = (
            outp(r.corrected_tensions),
            outp(r.channel_status),
            outp(r.gateway_heartbeat),
            outp(r.gateway_state),
            outp(r.wrench),
        )
        self._wdata_at23 = MBAP + 10
        self._wdata_at16 = MBAP + 6

    def _frame(self, fc: int, fields: bytes, nbytes: int) -> bytearray:
        pdu = bytes((fc,)) + fields
        frame = bytearray(MBAP + len(pdu) + nbytes)
        _HEADER.pack_into(frame, 0, 0, 0, len(pdu) + nbytes + 1, self.mb.unit_id)
        frame[MBAP : MBAP + len(pdu)] = pdu
        return frame

    # --- connection -------------------------------------------------------------------
    def _open(self) -> None:
        self._staged = False
        self._backoff_s = self.mb.reconnect_min_s
        try:
            sock = socket.create_connection(
                (self.mb.host, self.mb.port), timeout=self.mb.connect_timeout_s
            )
        except TimeoutError as exc:
            raise DriverTimeoutError(f"{self.where}: connect timed out") from exc
        except OSError as exc:
            raise DriverInitError(f"{self.where}: cannot connect: {exc}") from exc
        self._sock = self._finish(sock)
        self._ever_connected = True

    def _finish(self, sock: socket.socket) -> socket.socket:
        """TCP_NODELAY, the TLS handshake, the read timeout; a fresh receive buffer."""
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._have = self._consumed = 0
        if self._ssl is not None:
            sock.settimeout(self.mb.connect_timeout_s)
            try:
                sock = self._ssl.wrap_socket(sock, server_hostname=self.mb.host)
            except (OSError, ssl.SSLError) as exc:
                sock.close()
                raise DriverInitError(f"{self.where}: TLS handshake: {exc}") from exc
        sock.settimeout(self.mb.timeout_s)
        self._sock_timeout = self.mb.timeout_s
        return sock

    def _drop(self) -> None:
        """Forget the connection; the next call reconnects (after the backoff)."""
        for s in (self._sock, self._connecting):
            if s is not None:
                s.close()
        self._sock = self._connecting = None
        self._staged = False
        self._timeouts_in_a_row = 0
        self._next_attempt = time.monotonic() + self._backoff_s
        # grows until a good reply resets it (a link that keeps dropping backs off)
        self._backoff_s = min(2 * self._backoff_s, self.mb.reconnect_max_s)

    def _failed_attempt(self, why: str, exc: BaseException | None = None) -> DriverIOError:
        if self._connecting is not None:
            self._connecting.close()
            self._connecting = None
        self._next_attempt = time.monotonic() + self._backoff_s
        wait = self._backoff_s
        self._backoff_s = min(2 * self._backoff_s, self.mb.reconnect_max_s)
        err = DriverIOError(f"{self.where}: reconnect failed: {why} (next try in {wait:.3f} s)")
        err.__cause__ = exc
        return err

    def _ensure_connected(self) -> socket.socket:
        """The connected socket, or a quick DriverIOError while (re)connecting."""
        if self._sock is not None:
            return self._sock
        now = time.monotonic()
        if self._connecting is None:
            if now < self._next_attempt:
                raise DriverIOError(
                    f"{self.where}: not connected (next try in {self._next_attempt - now:.3f} s)"
                )
            self._start_connect(now)
        return self._poll_connect()

    def _start_connect(self, now: float) -> None:
        self.reconnect_attempts += 1
        try:
            info = socket.getaddrinfo(self.mb.host, self.mb.port, type=socket.SOCK_STREAM)[0]
            sock = socket.socket(info[0], info[1], info[2])
        except OSError as exc:
            raise self._failed_attempt(str(exc), exc) from exc
        sock.setblocking(False)
        self._connecting = sock
        self._connect_deadline = now + self.mb.connect_timeout_s
        rc = sock.connect_ex(info[4])
        if rc not in (0, errno.EINPROGRESS, errno.EWOULDBLOCK):
            raise self._failed_attempt(errno.errorcode.get(rc, str(rc)))

    def _poll_connect(self) -> socket.socket:
        sock = self._connecting
        assert sock is not None
        _, writable, _ = select.select([], [sock], [], self.mb.timeout_s)
        if not writable:
            if time.monotonic() > self._connect_deadline:
                raise self._failed_attempt("connect timed out")
            raise DriverIOError(f"{self.where}: connecting")
        rc = sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
        if rc:
            raise self._failed_attempt(errno.errorcode.get(rc, str(rc)))
        self._connecting = None
        try:
            self._sock = self._finish(sock)
        except DriverInitError as exc:
            raise self._failed_attempt(str(exc), exc) from exc
        if self._ever_connected:
            self.reconnects += 1
        self._ever_connected = True
        # the backoff is reset by the first good reply, not here: a PLC that accepts and
        # then drops every connection must not be reconnected to at full rate
        return self._sock

    def _close(self) -> None:
        for s in (self._sock, self._connecting):
            if s is not None:
                s.close()
        self._sock = self._connecting = None
        self._staged = False

    # --- transactions -----------------------------------------------------------------
    def _recv_more(self, sock: socket.socket, deadline: float) -> None:
        """Append what the socket has to the receive buffer (at least one byte)."""
        remaining = deadline - time.perf_counter()
        if remaining <= 0:
            raise TimeoutError
        if remaining < self._sock_timeout - 0.001:  # settimeout only when it matters
            sock.settimeout(remaining)
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
            rtid, proto, length, _unit = _HEADER.unpack_from(self._rx, 0)
            size = MBAP - 1 + length
            if length < 2 or size > RX_FRAME_MAX:
                raise ConnectionResetError(f"malformed reply (MBAP length {length})")
            while self._have < size:
                self._recv_more(sock, deadline)
            if rtid == tid and proto == 0:
                self._consumed = size
                return length - 1
            self.dropped_replies += 1
            self._shift(size)

    def _shift(self, size: int) -> None:
        rest = self._have - size
        if rest:
            self._rx[:rest] = self._rx[size : self._have]
        self._have = rest

    def _transact(self, frame: bytearray, fc: int, address: int) -> int:
        """Send ``frame`` (its header gets a fresh transaction id) and await its reply."""
        sock = self._ensure_connected()
        if self._consumed:  # the previous reply has been decoded: drop it from the buffer
            self._shift(self._consumed)
            self._consumed = 0
        self._tid = (self._tid + 1) & 0xFFFF
        struct.pack_into(">H", frame, 0, self._tid)
        deadline = time.perf_counter() + self.mb.timeout_s
        try:
            sock.sendall(frame)
            n = self._receive(sock, self._tid, deadline)
        except TimeoutError as exc:
            self._timeouts_in_a_row += 1
            if self._timeouts_in_a_row >= MAX_TIMEOUTS_IN_A_ROW:
                self._drop()
            raise DriverTimeoutError(
                f"{self.where}: function {fc} at register {address}: no reply within "
                f"{self.mb.timeout_s} s"
            ) from exc
        except (OSError, ssl.SSLError) as exc:
            self._drop()
            raise DriverIOError(
                f"{self.where}: function {fc} at register {address}: {exc}"
            ) from exc
        self._timeouts_in_a_row = 0
        self._backoff_s = self.mb.reconnect_min_s  # a good reply: the link works
        self._check_reply(fc, address, n)
        return n

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
    def _read(self, inputs: Inputs) -> None:
        if self._staged:
            self._fc23[self._wdata_at23 :] = self._wdata
            self._staged = False
            self._read_span(self._fc23, FC_READ_WRITE, self.layout.read_span)
        else:
            self._read_span(self._fc3, FC_READ, self.layout.read_span)
        self._raw.decode(inputs.tension_raw_n)
        self._vel.decode(inputs.velocity_m_s)
        self._len.decode(inputs.length_m)
        self._pose.decode(inputs.pose)
        inputs.plc_heartbeat = self._hb.decode_int()
        if self._mass is not None:
            inputs.platform_mass_kg = float(self._mass.decode(self._mass_value)[0])
        if self._truth_in_read is not None and inputs.true_tension_n is not None:
            self._truth_in_read.decode(inputs.true_tension_n)
        if self.state is DriverState.FAULT or self.state is DriverState.UNCONFIGURED:
            self.state = DriverState.CONNECTED

    def _write(self, outputs: Outputs) -> None:
        tension, status, heartbeat, state, wrench = self._out
        tension.encode(outputs.tension_corrected_n)
        status.encode(outputs.channel_status)
        heartbeat.encode(outputs.gateway_heartbeat & 0xFFFF)
        state.encode(outputs.gateway_state)
        wrench.encode(outputs.wrench)
        if self.mb.use_fc23:
            self._staged = True
        else:
            self._send_write()

    def _send_write(self) -> None:
        self._fc16[self._wdata_at16 :] = self._wdata
        ws = self.layout.write_span
        n = self._transact(self._fc16, FC_WRITE, ws.start)
        if n != 5 or struct.unpack_from(">HH", self._rx, MBAP + 1) != (ws.start, ws.count):
            raise DriverIOError(f"{self.where}: function 16 at register {ws.start}: bad echo")

    # --- extras -----------------------------------------------------------------------
    def flush(self) -> None:
        """Send a staged write now (function 16)."""
        if not self._staged:
            return
        self._staged = False
        try:
            self._send_write()
        except DriverIOError:
            self.state = DriverState.FAULT
            raise

    def read_truth(self, inputs: Inputs) -> None:
        """Read the simulation truth block into ``inputs.true_tension_n`` (own transaction).

        A no-op when the map has no truth block or ``inputs`` has no truth array; when the
        truth block fits the cycle's read, :meth:`read_into` fills it already.
        """
        if self._truth_alone is None or inputs.true_tension_n is None:
            return
        ts = self.layout.truth_span
        assert ts is not None and self._fc3_truth is not None
        try:
            self._read_span(self._fc3_truth, FC_READ, ts)
        except DriverIOError:
            self.state = DriverState.FAULT
            raise
        self._truth_alone.decode(inputs.true_tension_n)

    @property
    def staged(self) -> bool:
        """True while a write waits for the next read (function-23 mode)."""
        return self._staged
