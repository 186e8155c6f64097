"""The Modbus driver and the loop against a hostile PLC (tests/hostile_modbus.py).

Regression tests for the hostile-PLC probe: a reply from another unit id is dropped and
counted, never decoded; an erroring PLC is reconnected to at a growing interval, not in
a storm; each wait for reply bytes ends at the transaction's own deadline (no ratcheting
socket timeout); a PLC that accepts no connection never stalls the cycle.
"""

from __future__ import annotations

import shutil
import socket
import threading
import time
from pathlib import Path

import pytest

from drivers.base import Inputs, make_driver
from drivers.modbus_tcp import ModbusTcpDriver
from gateway.core.config import Config, TlsConfig
from gateway.errors import DriverInitError, DriverIOError, DriverTimeoutError
from gateway.runtime.loop import CyclicService
from tests.hostile_modbus import LOCALHOST, HostileServer, make_tls_pair
from tests.hostile_modbus import gateway_config as _config

pytestmark = pytest.mark.loopback


def test_reply_from_another_unit_is_dropped_and_counted() -> None:
    with (
        HostileServer("foreign_unit", then_good=True, heartbeat=1234) as server,
        ModbusTcpDriver(_config(server.port, timeout_s=1.0)) as drv,
    ):
        inputs = Inputs.allocate(8)
        drv.read_into(inputs)
        assert inputs.plc_heartbeat == 1234  # the foreign reply said 1235
        assert drv.foreign_unit_replies == 1
        assert drv.dropped_replies == 1


def test_only_foreign_replies_are_a_timeout_never_data() -> None:
    with (
        HostileServer("foreign_unit", heartbeat=1234) as server,
        ModbusTcpDriver(_config(server.port, timeout_s=0.1)) as drv,
    ):
        inputs = Inputs.allocate(8)
        inputs.plc_heartbeat = 7
        with pytest.raises(DriverTimeoutError):
            drv.read_into(inputs)
        assert inputs.plc_heartbeat == 7  # nothing decoded
        assert drv.foreign_unit_replies == 1


@pytest.mark.parametrize("mode", ["exception", "malformed", "accept_drop", "reset_mid_frame"])
def test_an_erroring_plc_is_retried_at_a_growing_interval(mode: str) -> None:
    """The real loop, 0.8 s against a PLC that errors: attempts at 0, 0.05, 0.15, 0.35,
    0.75 s (backoff 0.05 s doubling, reset only by a good data reply). Before the fix the
    same run opened ~100-150 connections per second."""
    with HostileServer(mode, max_seconds=20) as server:
        cfg = _config(server.port, reconnect_min_s=0.05, reconnect_max_s=2.0)
        service = CyclicService(cfg, make_driver(cfg))
        service.run(cycles=800)
        assert 2 <= server.connections <= 7
        assert service.driver.backoff.interval_s >= 0.4  # it grew and was never reset


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl command not found")
def test_a_plc_refusing_the_client_certificate_is_retried_at_a_growing_interval(
    tmp_path: Path,
) -> None:
    pki = make_tls_pair(str(tmp_path))
    opts = {"tls_cert": pki["server_cert"], "tls_key": pki["server_key"], "max_seconds": 20}
    with HostileServer("tls_refuse", **opts) as server:
        tls = TlsConfig(pki["client_cert"], pki["client_key"], pki["server_cert"])
        cfg = _config(server.port, tls=tls)
        service = CyclicService(cfg, make_driver(cfg))
        service.run(cycles=800)
        assert 2 <= server.connections <= 7  # before the fix: ~60 handshakes per second


def test_a_malformed_reply_is_counted_and_drops_the_connection() -> None:
    with HostileServer("malformed") as server, ModbusTcpDriver(_config(server.port)) as drv:
        with pytest.raises(DriverIOError, match="malformed reply"):
            drv.read_into(Inputs.allocate(8))
        assert drv.dropped_replies == 1
        with pytest.raises(DriverIOError, match="not connected"):
            drv.read_into(Inputs.allocate(8))


def test_each_wait_ends_at_its_own_deadline() -> None:
    """A reply whose pieces came late must not shorten the next transaction's wait."""
    with (
        HostileServer("split", latency_s=0.15, pieces=3) as server,
        ModbusTcpDriver(_config(server.port, timeout_s=0.25)) as drv,
    ):
        inputs = Inputs.allocate(8)
        drv.read_into(inputs)  # pieces at 50, 100, 150 ms
        server.cfg.mode, server.cfg.latency_s = "latency", 0.15
        drv.read_into(inputs)  # whole, 150 ms late: well inside 250 ms
        assert inputs.plc_heartbeat == server.cfg.heartbeat


def _cycles_per_second_while_connecting(cfg: Config) -> int:
    """Cycles the real loop runs in 1 s (after its first cycle) against ``cfg``'s PLC."""
    service = CyclicService(cfg, make_driver(cfg))
    worker = threading.Thread(target=service.run, daemon=True)
    worker.start()
    end = time.monotonic() + 10.0
    while service.stats.cycles == 0 and time.monotonic() < end:  # start-up (bounded)
        time.sleep(0.01)
    first = service.stats.cycles
    time.sleep(1.0)
    cycles = service.stats.cycles - first
    service.stop()
    worker.join(timeout=10)
    assert not worker.is_alive()
    assert not service.bus_up
    return cycles


def test_a_plc_that_accepts_no_connection_never_stalls_the_cycle() -> None:
    """Connect attempts to a listener whose backlog is full (SYNs dropped) are advanced
    half a period at a time: the loop keeps cycling while the attempt hangs. Before the
    fix the loop blocked ``connect_timeout_s`` per attempt (8 cycles in 3 s)."""
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.bind((LOCALHOST, 0))
    listener.listen(0)
    port = listener.getsockname()[1]
    fillers = []
    for _ in range(4):  # fill the accept queue; later SYNs get no answer
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setblocking(False)
        s.connect_ex((LOCALHOST, port))
        fillers.append(s)
    time.sleep(0.05)
    try:
        cycles = _cycles_per_second_while_connecting(_config(port, connect_timeout_s=1.0))
        assert cycles >= 300, cycles  # ~1000 expected at 1 ms; a blocking connect: ~1
    finally:
        for s in fillers:
            s.close()
        listener.close()


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl command not found")
def test_a_tls_handshake_with_a_plaintext_plc_never_stalls_the_cycle(tmp_path: Path) -> None:
    """The PLC speaks plain Modbus and never answers the ClientHello: the handshake is
    advanced across cycles until ``connect_timeout_s``, never blocking one."""
    pki = make_tls_pair(str(tmp_path))
    with HostileServer("good", max_seconds=20) as server:
        tls = TlsConfig(pki["client_cert"], pki["client_key"], pki["server_cert"])
        cfg = _config(server.port, tls=tls, connect_timeout_s=1.0)
        cycles = _cycles_per_second_while_connecting(cfg)
        assert cycles >= 300, cycles


def test_refused_connect_names_the_cause() -> None:
    with socket.create_server((LOCALHOST, 0)) as s:
        port = s.getsockname()[1]
    drv = ModbusTcpDriver(_config(port))
    with pytest.raises(DriverInitError, match="Connection refused"):
        drv.open()
    drv.close()
