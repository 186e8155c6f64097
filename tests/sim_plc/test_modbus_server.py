"""The soft PLC's Modbus TCP server against independent clients (pymodbus, raw sockets,
mbpoll) over loopback."""

from __future__ import annotations

import os
import shutil
import socket
import struct
import subprocess
from collections.abc import Iterator

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal
from pymodbus.client import ModbusTcpClient

from gateway.core.config import load_config
from sim_plc.image import ProcessImage
from sim_plc.modbus_server import ModbusPlcServer
from tests.modbus_helpers import (
    LOCALHOST,
    filled_image,
    from_words,
    plc_server,
    raw_transaction,
    words,
)

pytestmark = pytest.mark.loopback

OUTPUT_WORDS = 38  # 100..137


@pytest.fixture
def served() -> Iterator[tuple[ModbusPlcServer, ProcessImage]]:
    with plc_server() as (server, image, _cfg):
        yield server, image


@pytest.fixture
def client(served: tuple[ModbusPlcServer, ProcessImage]) -> Iterator[ModbusTcpClient]:
    c = ModbusTcpClient(LOCALHOST, port=served[0].port, timeout=2, retries=0)
    assert c.connect()
    yield c
    c.close()


def _outputs_words(
    tensions: np.ndarray, status: list[int], heartbeat: int, state: int, wrench: np.ndarray
) -> list[int]:
    regs = words(tensions, ">f4") + status + [heartbeat, state] + words(wrench, ">f4")
    assert len(regs) == OUTPUT_WORDS
    return regs


def test_reads_documented_registers(served, client) -> None:
    _, img = served
    regs = client.read_holding_registers(0, count=56, device_id=1).registers
    assert_array_equal(np.asarray(regs[0:8], np.uint16).view(np.int16), img.raw_counts)
    assert_allclose(from_words(regs[8:24], ">f4"), img.velocity_m_s, rtol=1e-7)
    assert_allclose(from_words(regs[24:40], ">f4"), img.length_m, rtol=1e-7)
    assert_allclose(from_words(regs[40:52], ">f4"), img.pose, rtol=1e-7)
    assert regs[52] == img.plc_heartbeat
    assert regs[53:56] == [0, 0, 0]  # reserved
    truth = client.read_holding_registers(200, count=16, device_id=1).registers
    assert_allclose(from_words(truth, ">f4"), img.true_tension_n, rtol=1e-7)


def test_reads_follow_the_image(served, client) -> None:
    _, img = served
    with img.lock:
        img.raw_counts[3] = 32767
        img.plc_heartbeat = 65535
    regs = client.read_input_registers(0, count=53, device_id=1).registers  # function 4
    assert regs[3] == 32767
    assert regs[52] == 65535


def test_fc23_reads_inputs_and_writes_outputs_in_one_transaction(served, client) -> None:
    _, img = served
    tensions = np.linspace(150, 220, 8)
    wrench = np.array([1.5, -2.0, 490.5, 0.25, -0.5, 0.125])
    values = _outputs_words(tensions, [0, 1, 2, 0, 0, 0, 1, 2], 17, 2, wrench)
    rr = client.readwrite_registers(
        read_address=0, read_count=56, write_address=100, values=values, device_id=1
    )
    assert not rr.isError()
    assert rr.registers[52] == img.plc_heartbeat
    assert_allclose(img.corrected_n, tensions, rtol=1e-7)
    assert_array_equal(img.channel_status, [0, 1, 2, 0, 0, 0, 1, 2])
    assert (img.gateway_heartbeat, img.gateway_state) == (17, 2)
    assert_allclose(img.wrench, wrench, rtol=1e-7)
    assert img.gateway_writes == 1


def test_separate_write_and_read_back(served, client) -> None:
    _, img = served
    values = _outputs_words(np.full(8, 99.5), [2] * 8, 3, 1, np.zeros(6))
    assert not client.write_registers(100, values, device_id=1).isError()
    assert not client.write_register(124, 4, device_id=1).isError()  # function 6
    back = client.read_holding_registers(100, count=OUTPUT_WORDS, device_id=1).registers
    assert back[:24] == values[:24]
    assert back[24] == 4
    assert img.gateway_heartbeat == 4
    assert img.gateway_writes == 2
    # half of a float32 written with function 6: the other half keeps its value
    assert not client.write_register(100, 0x4000, device_id=1).isError()
    assert img.corrected_n[0] == pytest.approx(
        float(np.array([0x4000, values[1]], ">u2").view(">f4")[0])
    )


@pytest.mark.parametrize(
    ("name", "pdu", "reply"),
    [
        ("unknown function", b"\x63\x00\x00\x00\x01", b"\xe3\x01"),
        ("coils are not served", b"\x01\x00\x00\x00\x08", b"\x81\x01"),
        ("count 0", b"\x03\x00\x00\x00\x00", b"\x83\x03"),
        ("count 126", b"\x03\x00\x00\x00\x7e", b"\x83\x03"),
        ("unmapped address", b"\x03\x00\x3c\x00\x02", b"\x83\x02"),
        ("span into a gap", b"\x03\x00\x30\x00\x10", b"\x83\x02"),
        ("past the truth block", b"\x03\x00\xd4\x00\x08", b"\x83\x02"),
        ("fc16 into inputs", b"\x10\x00\x00\x00\x01\x02\x00\x05", b"\x90\x02"),
        ("fc6 into inputs", b"\x06\x00\x34\x00\x05", b"\x86\x02"),
        ("fc6 into the truth", b"\x06\x00\xc8\x00\x05", b"\x86\x02"),
        ("fc23 writing inputs", b"\x17\x00\x00\x00\x01\x00\x00\x00\x01\x02\x00\x05", b"\x97\x02"),
    ],
)
def test_bad_requests_get_exceptions_and_serving_goes_on(served, name, pdu, reply) -> None:
    server, img = served
    before = img.raw_counts.copy()
    with socket.create_connection((LOCALHOST, server.port), timeout=2) as a:
        assert raw_transaction(a, pdu, tid=7) == reply, name
        ok = raw_transaction(a, b"\x03\x00\x00\x00\x02", tid=8)  # same connection
        assert ok == b"\x03\x04" + struct.pack(">hh", *img.raw_counts[:2])
    with socket.create_connection((LOCALHOST, server.port), timeout=2) as b:
        assert raw_transaction(b, b"\x03\x00\x34\x00\x01", tid=9) == b"\x03\x02" + struct.pack(
            ">H", img.plc_heartbeat
        )
    assert_array_equal(img.raw_counts, before)
    assert img.gateway_writes == 0


def test_other_connections_unaffected_by_a_broken_one(served, client) -> None:
    server, img = served
    with socket.create_connection((LOCALHOST, server.port), timeout=2) as bad:
        bad.sendall(b"\x00\x01\x00\x00\x00\xff\x01\x03")  # a truncated frame, left hanging
        regs = client.read_holding_registers(52, count=1, device_id=1).registers
    assert regs == [img.plc_heartbeat]


def test_start_binds_a_free_port_and_stop_is_safe_twice() -> None:
    img = filled_image()
    with plc_server(img) as (server, _, _):
        assert server.port > 0
        server.stop()
        server.stop()
        with pytest.raises(OSError):
            socket.create_connection((LOCALHOST, server.port), timeout=1).close()


def _mbpoll() -> str | None:
    path = shutil.which("mbpoll")
    if path is None and os.environ.get("CDPR_REQUIRE_EXTERNAL") == "1":
        pytest.fail("mbpoll is not installed but CDPR_REQUIRE_EXTERNAL=1")
    if path is None:
        pytest.skip("mbpoll not installed (Debian package mbpoll)")
    return path


def _mbpoll_values(path: str, port: int, ref: int, count: int, kind: str) -> list[float]:
    cmd = [path, "-m", "tcp", "-a", "1", "-0", "-1", "-B", "-o", "2", "-p", str(port)]
    cmd += ["-t", kind, "-r", str(ref), "-c", str(count), LOCALHOST]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=20, check=True).stdout
    values = [line.split(":", 1)[1].split()[0] for line in out.splitlines() if line.startswith("[")]
    assert len(values) == count, out
    return [float(v) for v in values]


@pytest.mark.external
def test_mbpoll_reads_what_the_gateway_wrote(served, client) -> None:
    path = _mbpoll()
    server, img = served
    tensions = np.array([101.25, 202.5, 303.75, 55.5, 66.0, 77.125, 88.0, 99.5])
    values = _outputs_words(tensions, [0, 0, 1, 2, 0, 0, 0, 1], 9, 2, np.ones(6))
    assert not client.write_registers(100, values, device_id=1).isError()
    got_t = _mbpoll_values(path, server.port, 100, 8, "4:float")
    got_s = _mbpoll_values(path, server.port, 116, 8, "4")
    with img.lock:
        assert_allclose(got_t, img.corrected_n, rtol=1e-6)
        assert_array_equal(got_s, img.channel_status)


def test_connections_beyond_the_limit_are_closed_and_counted() -> None:
    limited = ModbusPlcServer(load_config(), filled_image(), LOCALHOST, 0, max_connections=2)
    with limited:
        socks = [socket.create_connection((LOCALHOST, limited.port), timeout=2) for _ in range(3)]
        try:
            for s in socks[:2]:  # the first two are served
                assert raw_transaction(s, b"\x03\x00\x34\x00\x01", tid=3)[:2] == b"\x03\x02"
            assert socks[2].recv(1) == b""  # the third: closed at once
            assert limited.refused == 1
            assert len(limited.connections) == 2
        finally:
            for s in socks:
                s.close()


def test_bad_header_is_counted() -> None:
    with plc_server() as (server, _, _):
        with socket.create_connection((LOCALHOST, server.port), timeout=2) as s:
            s.sendall(struct.pack(">HHHB", 1, 7, 6, 1) + b"\x03\x00\x00\x00\x01")
            assert s.recv(1) == b""
        assert server.bad_frames == 1
