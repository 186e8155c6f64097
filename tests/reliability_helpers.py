"""Shared helpers of the reliability tests: raw Modbus/TCP frames over bounded sockets,
and a tiny Modbus-like echo server on 127.0.0.1 (a free port).

Every socket operation here has a timeout; every loop is bounded.
"""

from __future__ import annotations

import contextlib
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

import numpy as np

from gateway.core.config import Config, load_config
from sim_plc.image import ProcessImage

if TYPE_CHECKING:
    from sim_plc.modbus_server import ModbusPlcServer

# a reply that must come, comes within this on loopback: 2 s was not enough with both cores
# busy (make test beside other jobs: the fuzz fixture's fresh-connection check timed out
# twice in full runs at load 6-8); a reply that must not come is waited for apart (QUIET_S)
IO_TIMEOUT_S = 5.0


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
    image: ProcessImage | None = None, cfg: Config | None = None, tls: Any = None
) -> Iterator[tuple[ModbusPlcServer, ProcessImage, Config]]:
    """The soft PLC's Modbus server on a free loopback port: (server, image, config);
    with ``tls`` (a TlsConfig) it speaks Modbus/TCP Security."""
    from sim_plc.modbus_server import ModbusPlcServer

    cfg = cfg or load_config()
    image = image if image is not None else static_image(cfg.cables)
    server = ModbusPlcServer(cfg, image, host="127.0.0.1", port=0, tls=tls)
    server.start()
    try:
        yield server, image, cfg
    finally:
        server.stop()


# --- gateway -> fault proxy -> soft PLC ------------------------------------------------
class PlcHeartbeat:
    """The soft PLC's cycle counter: +1 every ``period_s`` (a thread; ``stop()`` joins)."""

    def __init__(self, image: ProcessImage, period_s: float = 0.001) -> None:
        self.image, self.period_s = image, period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="plc-heartbeat")

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            with self.image.lock:
                self.image.plc_heartbeat = (self.image.plc_heartbeat + 1) & 0xFFFF

    def start(self) -> PlcHeartbeat:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(2.0)


class WriteOracle:
    """Checks every write the gateway makes to the soft PLC (hooked into the server).

    The soft PLC's inputs are constant, so every good read gives the same inputs and the
    model (at rest: setpoint velocities 0) the same corrected tensions and wrench. After
    :meth:`freeze` has taken them from the clean warm-up, a written channel must be: status
    GOOD or SUBSTITUTED with exactly that value, or INVALID with NaN; the wrench exactly
    the expected one while no channel is invalid, else NaN. Anything else is a value
    computed from a bad read reaching the PLC (``bad_values``, the first 100 in ``bad``).
    """

    def __init__(self, image: ProcessImage, cycles: Callable[[], int]) -> None:
        self.image = image
        self.cycles = cycles  # the gateway's cycle counter, read when a write arrives
        self.expected: np.ndarray | None = None
        self.writes = 0
        self.all_good_writes = 0
        self.flagged_writes = 0
        self.bad: list[str] = []  # the first 100 violations
        self.bad_values = 0  # every violating channel value
        self.expected_wrench: np.ndarray | None = None
        self.last_corrected = np.full(image.cables, np.nan)
        self.last_status = np.zeros(image.cables, dtype=np.uint16)
        self.last_wrench = np.full(6, np.nan)
        self._watch_from: int | None = None
        self.recovered_at: int | None = None  # gateway cycle of the first good write

    def hook(self, write: Callable[[int, list[int]], None]) -> Callable[[int, list[int]], None]:
        def checked(address: int, values: list[int]) -> None:
            write(address, values)
            with self.image.lock:
                self.last_corrected[:] = self.image.corrected_n
                self.last_status[:] = self.image.channel_status
                self.last_wrench[:] = self.image.wrench
            self._check(self.last_corrected, self.last_status)

        return checked

    def _check(self, corrected: np.ndarray, status: np.ndarray) -> None:
        self.writes += 1
        all_good = bool(np.all(status == 0))
        self.all_good_writes += all_good
        self.flagged_writes += not all_good
        if all_good and self._watch_from is not None and self.recovered_at is None:
            self.recovered_at = self.cycles()
        if self.expected is None or self.expected_wrench is None:
            return
        wrench_ok = (
            np.array_equal(self.last_wrench, self.expected_wrench)
            if np.all(status < 2)
            else bool(np.all(np.isnan(self.last_wrench)))
        )
        if not wrench_ok:
            self.bad_values += 1
            if len(self.bad) < 100:
                self.bad.append(f"write {self.writes}: wrench {self.last_wrench}")
        for i, (value, st) in enumerate(zip(corrected, status, strict=True)):
            ok = (st in (0, 1) and value == self.expected[i]) or (st == 2 and np.isnan(value))
            if ok:
                continue
            self.bad_values += 1
            if len(self.bad) < 100:
                self.bad.append(f"write {self.writes}: cable {i + 1} status {st} value {value}")

    def freeze(self) -> None:
        """Take the expected corrected tensions from the last (all-good) write."""
        assert self.all_good_writes > 0 and np.all(self.last_status == 0)
        self.expected = self.last_corrected.copy()
        self.expected_wrench = self.last_wrench.copy()
        assert np.all(np.isfinite(self.expected)) and np.all(np.isfinite(self.expected_wrench))

    def watch_recovery(self) -> None:
        """Note the gateway cycle of the next all-good write (``recovered_at``)."""
        self.recovered_at = None
        self._watch_from = self.cycles()


def wait_for(predicate: Callable[[], bool], timeout_s: float, poll_s: float = 0.005) -> bool:
    """Poll ``predicate`` until true or ``timeout_s`` is over (bounded); its last value."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(poll_s)
    return predicate()


class GatewayRig:
    """The gateway (cyclic service + Modbus driver) -> :class:`FaultProxy` -> soft PLC.

    Everything on 127.0.0.1, free ports; the PLC's inputs are constant (``static_image``)
    with a running heartbeat; ``oracle`` checks every write. ``start()``/``stop()``
    (``stop`` safe twice), or use it as a context manager.
    """

    def __init__(
        self,
        seed: int = 0,
        period_s: float = 0.001,
        timeout_s: float = 0.05,
        registers: Any = None,
        tls: Any = None,
        plc_tls: Any = None,
    ) -> None:
        self.seed, self.period_s, self.timeout_s = seed, period_s, timeout_s
        self.registers = registers  # the gateway's register map (None: the default)
        self.tls = tls  # the gateway's TlsConfig (None: plain Modbus/TCP)
        self.plc_tls = plc_tls  # the soft PLC's TlsConfig (the proxy then relays raw bytes)
        self._stack = contextlib.ExitStack()
        self._thread: threading.Thread | None = None

    def start(self) -> GatewayRig:
        from drivers.modbus_tcp import ModbusTcpDriver
        from evaluation.faultproxy import FaultProxy
        from gateway.runtime.loop import CyclicService
        from gateway.service.metrics import make_registry

        plc_cfg = load_config()
        self.server, self.image, _ = self._stack.enter_context(
            soft_plc(cfg=plc_cfg, tls=self.plc_tls)
        )
        self._stack.callback(PlcHeartbeat(self.image).start().stop)
        framing = "raw" if self.plc_tls is not None else "mbap"  # TLS records, not MBAP
        self.proxy = FaultProxy("127.0.0.1", self.server.port, seed=self.seed, framing=framing)
        self.proxy.start()
        self._stack.callback(self.proxy.stop)
        self.cfg = gateway_config(
            plc_cfg, self.proxy.port, self.period_s, self.timeout_s, self.registers, self.tls
        )
        self.service = CyclicService(self.cfg, ModbusTcpDriver(self.cfg), history=4096)
        self.registry = make_registry(self.service)
        self.oracle = WriteOracle(self.image, lambda: self.service.stats.cycles)
        regs = self.server.registers
        regs.write = self.oracle.hook(regs.write)  # type: ignore[method-assign]
        self._thread = threading.Thread(target=self.service.run, daemon=True, name="gateway")
        self._thread.start()
        return self

    def stop(self) -> None:
        thread, self._thread = self._thread, None
        if thread is not None:
            self.service.stop()
            thread.join(10.0)
        self._stack.close()

    def __enter__(self) -> GatewayRig:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def cycles(self) -> int:
        return int(self.service.stats.cycles)

    def metric(self, name: str, **labels: str) -> float:
        value = self.registry.get_sample_value(name, labels)
        return float("nan") if value is None else float(value)

    def errors(self) -> dict[str, float]:
        """cdpr_gateway_errors_total by kind."""
        out: dict[str, float] = {}
        for family in self.registry.collect():
            for s in family.samples:
                if s.name == "cdpr_gateway_errors_total":
                    out[s.labels["kind"]] = s.value
        return out

    def reconnects(self) -> float:
        return self.metric("cdpr_gateway_reconnects_total", bus=self.cfg.bus.driver)

    def channel_status_max(self) -> float:
        return max(
            self.metric("cdpr_gateway_channel_status", cable=str(i + 1))
            for i in range(self.cfg.cables)
        )

    def warm_up(self, good_writes: int = 100, timeout_s: float = 20.0) -> None:
        """Wait for ``good_writes`` all-good writes, then freeze the oracle."""
        assert wait_for(lambda: self.oracle.all_good_writes >= good_writes, timeout_s), (
            f"no warm-up: {self.oracle.all_good_writes} good writes, cycles {self.cycles}, "
            f"errors {self.errors()}"
        )
        self.oracle.freeze()


def gateway_config(
    plc_cfg: Config,
    port: int,
    period_s: float,
    timeout_s: float,
    registers: Any = None,
    tls: Any = None,
) -> Config:
    """The gateway's config: the Modbus driver at ``port``, short backoff, no metrics
    server, no busy-wait (the tests share two cores)."""
    import dataclasses

    mb = dataclasses.replace(
        plc_cfg.bus.modbus_tcp,
        host="127.0.0.1",
        port=port,
        timeout_s=timeout_s,
        reconnect_min_s=0.01,
        reconnect_max_s=0.2,
        tls=tls,
        registers=registers if registers is not None else plc_cfg.bus.modbus_tcp.registers,
    )
    return dataclasses.replace(
        plc_cfg,
        bus=dataclasses.replace(plc_cfg.bus, driver="modbus_tcp", modbus_tcp=mb),
        loop=dataclasses.replace(plc_cfg.loop, period_s=period_s, busy_wait_s=0.0),
        metrics=dataclasses.replace(plc_cfg.metrics, enabled=False),
    )
