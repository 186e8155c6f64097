"""The Modbus TCP client driver against the soft PLC server and scripted fake servers."""

from __future__ import annotations

import dataclasses
import socket
import struct
import time

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from drivers.base import DriverState, Inputs, Outputs, make_driver
from drivers.modbus_tcp import ModbusTcpDriver
from gateway.core.config import load_config
from gateway.core.registermap import RegisterField
from gateway.errors import (
    ConfigError,
    DriverError,
    DriverInitError,
    DriverIOError,
    DriverTimeoutError,
)
from tests.loop_helpers import fresh
from tests.modbus_helpers import (
    LOCALHOST,
    FakeServer,
    config_for,
    exception_reply,
    fc3_reply,
    mbap,
    plc_server,
)

pytestmark = pytest.mark.loopback

HEARTBEAT_OFFSET = 52  # in the default read span 0..52


def _outputs(cables: int = 8) -> Outputs:
    out = Outputs.allocate(cables)
    out.tension_corrected_n[:] = np.linspace(120.0, 190.0, cables)
    out.channel_status[:] = [0, 1, 2, 0, 1, 2, 0, 0][:cables]
    out.wrench[:] = (1.0, 2.0, 490.0, 0.5, -0.5, 0.25)
    out.gateway_heartbeat = 65537  # wraps to 1 on the wire
    out.gateway_state = 2
    return out


def test_registered_by_name() -> None:
    assert isinstance(make_driver(load_config(), "modbus_tcp"), ModbusTcpDriver)


@pytest.mark.parametrize("use_fc23", [True, False])
def test_reads_and_writes_against_the_soft_plc(use_fc23: bool) -> None:
    with plc_server() as (_server, img, cfg):
        img.raw_counts[2] = 32767  # overflow -> NaN
        drv = ModbusTcpDriver(config_for(cfg.bus.modbus_tcp.port, cfg, use_fc23=use_fc23))
        inputs = Inputs.allocate(8)
        with drv:
            drv.read_into(inputs)
            expect = img.raw_counts * 500.0 / 27648
            expect[2] = np.nan
            assert_allclose(inputs.tension_raw_n, expect, rtol=1e-12)
            assert_allclose(inputs.velocity_m_s, img.velocity_m_s, rtol=1e-7)
            assert_allclose(inputs.length_m, img.length_m, rtol=1e-7)
            assert_allclose(inputs.pose, img.pose, rtol=1e-7)
            assert inputs.plc_heartbeat == img.plc_heartbeat
            out = _outputs()
            drv.write_from(fresh(out, drv))  # always at once (function 16)
            assert drv.state is DriverState.ACTIVE
            assert img.gateway_writes == 1
            img.gateway_heartbeat = 0
            drv.exchange(fresh(out, drv), inputs)  # fc23: one transaction; else 16 then 3
            assert img.gateway_writes == 2
            assert_allclose(img.corrected_n, out.tension_corrected_n, rtol=1e-7)
            assert_array_equal(img.channel_status, out.channel_status)
            assert_allclose(img.wrench, out.wrench, rtol=1e-7)
            assert (img.gateway_heartbeat, img.gateway_state) == (1, 2)
            assert inputs.plc_heartbeat == img.plc_heartbeat
            assert drv.combines_write_and_read is use_fc23


@pytest.mark.parametrize(("use_fc23", "functions"), [(True, [23, 3]), (False, [16, 3, 3])])
def test_exchange_is_one_function_23_transaction(use_fc23: bool, functions: list[int]) -> None:
    """With function 23 an exchange is ONE request; the fallback is 16 then 3."""

    def respond(req: bytes, k: int) -> list[tuple[float, bytes]]:
        if req[7] == 16:
            return [(0.0, mbap(req[7:12], struct.unpack(">H", req[:2])[0]))]
        return [(0.0, fc3_reply(req, regs={HEARTBEAT_OFFSET: 7}))]

    with FakeServer(respond) as fake:
        with ModbusTcpDriver(config_for(fake.port, use_fc23=use_fc23)) as drv:
            inputs = Inputs.allocate(8)
            drv.exchange(fresh(_outputs(), drv), inputs)
            assert inputs.plc_heartbeat == 7
            drv.exchange(None, inputs)
        assert [r[7] for r in fake.requests] == functions


def test_open_fails_cleanly_without_a_server() -> None:
    with socket.create_server((LOCALHOST, 0)) as s:
        port = s.getsockname()[1]  # a free port nobody listens on after this block
    drv = ModbusTcpDriver(config_for(port))
    with pytest.raises(DriverInitError, match=f"{port}"):
        drv.open()
    assert drv.state is DriverState.FAULT
    drv.close()
    drv.close()


def test_timeout_when_the_server_does_not_answer() -> None:
    with FakeServer(lambda req, k: []) as fake:
        drv = ModbusTcpDriver(config_for(fake.port, timeout_s=0.05))
        with drv:
            inputs = Inputs.allocate(8)
            for _ in range(3):
                with pytest.raises(DriverTimeoutError, match="function 3 at register 0"):
                    drv.read_into(inputs)
            assert drv.state is DriverState.FAULT
            assert len(fake.requests) == 3  # one request per call, never two in flight
            # three timeouts in a row drop the connection: the next call reconnects first
            with pytest.raises(DriverIOError, match="not connected"):
                drv.read_into(inputs)


def test_wrong_transaction_id_is_dropped() -> None:
    def respond(req: bytes, k: int) -> list[tuple[float, bytes]]:
        tid = struct.unpack(">H", req[:2])[0]
        wrong = fc3_reply(req, tid=(tid + 100) & 0xFFFF, regs={HEARTBEAT_OFFSET: 111})
        return [(0.0, wrong), (0.0, fc3_reply(req, regs={HEARTBEAT_OFFSET: 222}))]

    with FakeServer(respond) as fake, ModbusTcpDriver(config_for(fake.port)) as drv:
        inputs = Inputs.allocate(8)
        drv.read_into(inputs)
        assert inputs.plc_heartbeat == 222
        assert drv.dropped_replies == 1


def test_late_reply_is_dropped_never_used() -> None:
    late: list[bytes] = []

    def respond(req: bytes, k: int) -> list[tuple[float, bytes]]:
        if k == 0:  # answer too late: the driver has given up by then
            late.append(fc3_reply(req, regs={HEARTBEAT_OFFSET: 111}))
            return []
        return [(0.0, late[0]), (0.0, fc3_reply(req, regs={HEARTBEAT_OFFSET: 222}))]

    with FakeServer(respond) as fake, ModbusTcpDriver(config_for(fake.port, timeout_s=0.05)) as drv:
        inputs = Inputs.allocate(8)
        with pytest.raises(DriverTimeoutError):
            drv.read_into(inputs)
        drv.read_into(inputs)
        assert inputs.plc_heartbeat == 222
        assert drv.dropped_replies == 1
        assert drv.state is DriverState.CONNECTED  # recovered from the fault


def test_exception_reply_names_function_and_register() -> None:
    reply = lambda req, k: [(0.0, exception_reply(req, 2))]  # noqa: E731
    with FakeServer(reply) as fake, ModbusTcpDriver(config_for(fake.port)) as drv:
        with pytest.raises(DriverIOError, match=r"function 23 at register 0: exception 2 "):
            drv.exchange(_outputs(), Inputs.allocate(8))
        with pytest.raises(DriverIOError, match=r"function 3 .*\(illegal data address\)"):
            drv.read_into(Inputs.allocate(8))
        assert drv.state is DriverState.FAULT


def _poll_until_connected(drv: ModbusTcpDriver, seconds: float) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:  # bounded
        try:
            if drv.poll_connect(budget_s=0.001):
                return True
        except DriverError:
            pass
        time.sleep(0.002)
    return False


def test_reconnects_after_the_server_restarts() -> None:
    with plc_server() as (server, img, cfg):
        port = server.port
        drv = ModbusTcpDriver(config_for(port, cfg, reconnect_min_s=0.01, reconnect_max_s=0.04))
        inputs = Inputs.allocate(8)
        drv.open()
        drv.read_into(inputs)
    # the server is gone: the read fails, later calls say so until a reconnect
    with pytest.raises(DriverIOError):
        drv.read_into(inputs)
    with pytest.raises(DriverIOError, match="not connected"):
        drv.read_into(inputs)
    drv.close()
    attempts = drv.reconnect_attempts
    with pytest.raises(DriverInitError, match="Connection refused"):  # the cause, errno text
        drv.poll_connect(budget_s=0.05)
    assert drv.reconnect_attempts == attempts + 1
    assert not drv.poll_connect(budget_s=0.0)  # within the backoff: no new attempt
    assert drv.reconnect_attempts == attempts + 1
    img.plc_heartbeat = 777
    with plc_server(img, port=port) as (_server, _img, _cfg):
        assert _poll_until_connected(drv, 2.0)
        drv.read_into(inputs)
        assert inputs.plc_heartbeat == 777
        assert drv.reconnects == 1
        assert drv.state is DriverState.CONNECTED
    drv.close()


def test_map_counts_must_match_the_cables() -> None:
    cfg = load_config()
    regs = dataclasses.replace(cfg.bus.modbus_tcp.registers, pose=RegisterField(40, 5, "float32"))
    cfg = config_for(5020, cfg, registers=regs)
    with pytest.raises(ConfigError, match=r"registers\.pose: count 5, need 6"):
        ModbusTcpDriver(cfg)
