"""The fault-injecting proxy against a Modbus-like echo server: each fault does what it says.

No assertion on wall time: a delayed or dropped reply is checked by the absence of a
reply within a window shorter than the delay, then (where it must come) by its arrival
within a generous timeout.
"""

from __future__ import annotations

import socket
import struct
from collections.abc import Iterator

import pytest

from evaluation.faultproxy import FaultProxy
from tests.reliability_helpers import (
    EchoModbusServer,
    connect,
    echo_server,
    mbap,
    no_reply_within,
    read_pdu,
    recv_exact,
    recv_frame,
    transact,
)

pytestmark = pytest.mark.loopback


@pytest.fixture
def echo() -> Iterator[EchoModbusServer]:
    with echo_server() as server:
        yield server


@pytest.fixture
def proxy(echo: EchoModbusServer) -> Iterator[FaultProxy]:
    with FaultProxy("127.0.0.1", echo.port, seed=7) as p:
        yield p


def _frame(tid: int) -> bytes:
    return mbap(tid, read_pdu(100 + tid % 50, 8))


def test_passes_frames_unchanged(proxy: FaultProxy, echo: EchoModbusServer) -> None:
    with connect(proxy.port) as sock:
        for tid in range(20):
            assert transact(sock, _frame(tid)) == _frame(tid)
    assert echo.requests == 20
    assert proxy.counters["replies"] == 20
    assert proxy.counters["connections"] == 1


def test_reply_delay(proxy: FaultProxy) -> None:
    proxy.set_fault("delay", seconds=0.6, direction="reply", count=1)
    with connect(proxy.port) as sock:
        sock.sendall(_frame(1))
        assert no_reply_within(sock, 0.15)
        assert recv_frame(sock) == _frame(1)
        assert transact(sock, _frame(2)) == _frame(2)  # count=1: the fault has expired
    assert proxy.counters["delay"] == 1
    assert proxy.active_faults() == []


def test_request_delay_holds_the_request_back(proxy: FaultProxy, echo: EchoModbusServer) -> None:
    proxy.set_fault("delay", seconds=0.6, direction="request")
    with connect(proxy.port) as sock:
        sock.sendall(_frame(3))
        assert no_reply_within(sock, 0.15)
        assert echo.requests == 0  # still held by the proxy
        assert recv_frame(sock) == _frame(3)
    assert echo.requests == 1


def test_drop_next_n(proxy: FaultProxy, echo: EchoModbusServer) -> None:
    proxy.set_fault("drop", count=2)
    with connect(proxy.port) as sock:
        for tid in (1, 2):
            sock.sendall(_frame(tid))
            assert no_reply_within(sock, 0.2)
        assert transact(sock, _frame(3)) == _frame(3)
    assert echo.requests == 3
    assert proxy.counters["drop"] == 2


def _drop_pattern(echo: EchoModbusServer, seed: int) -> list[int]:
    with FaultProxy("127.0.0.1", echo.port, seed=seed) as p:
        p.set_fault("drop", probability=0.5)
        with connect(p.port) as sock:
            for tid in range(40):
                sock.sendall(_frame(tid))
            got: list[int] = []
            while not no_reply_within(sock, 0.3):  # bounded: at most 40 replies come
                got.append(struct.unpack(">H", recv_frame(sock)[:2])[0])
                assert len(got) <= 40
        assert p.counters["drop"] == 40 - len(got)
    return got


def test_drop_probability_is_seeded(echo: EchoModbusServer) -> None:
    first = _drop_pattern(echo, seed=3)
    assert 0 < len(first) < 40
    assert first == sorted(first)  # order kept
    assert _drop_pattern(echo, seed=3) == first
    assert _drop_pattern(echo, seed=4) != first


def test_split_sends_pieces(proxy: FaultProxy) -> None:
    proxy.set_fault("split", pieces=3, pause_s=0.3, count=1)
    frame = mbap(9, read_pdu(0, 8) + bytes(range(16)))
    with connect(proxy.port) as sock:
        sock.sendall(frame)
        first = sock.recv(4096)
        assert 0 < len(first) < len(frame)  # the rest is still 0.3 s away
        rest = recv_exact(sock, len(frame) - len(first))
        assert first + rest == frame
    assert proxy.counters["split"] == 1


@pytest.mark.parametrize(("where", "lo", "hi"), [("header", 0, 9), ("data", 9, 30)])
def test_corrupt_changes_bytes_where_asked(proxy: FaultProxy, where: str, lo: int, hi: int) -> None:
    proxy.set_fault("corrupt", nbytes=1, where=where, count=1)
    frame = mbap(5, read_pdu(0, 8) + bytes(range(1, 18)))
    with connect(proxy.port) as sock:
        sock.sendall(frame)
        got = recv_exact(sock, len(frame))  # length may be corrupted: read by size
    diff = [i for i in range(len(frame)) if got[i] != frame[i]]
    assert len(diff) == 1
    assert lo <= diff[0] < hi
    assert proxy.counters["corrupt"] == 1


def test_wrong_transaction_id(proxy: FaultProxy) -> None:
    proxy.set_fault("wrong_tid", offset=0x1000, count=1)
    with connect(proxy.port) as sock:
        got = transact(sock, _frame(0xF123))
        assert got[:2] == struct.pack(">H", 0x0123)  # wraps at 16 bits
        assert got[2:] == _frame(0xF123)[2:]
        assert transact(sock, _frame(4)) == _frame(4)
    assert proxy.counters["wrong_tid"] == 1


def test_reset_mid_frame(proxy: FaultProxy) -> None:
    proxy.set_fault("reset", after_bytes=5, count=1)
    frame = _frame(6)
    got = bytearray()
    reset = False
    with connect(proxy.port) as sock:
        sock.sendall(frame)
        for _ in range(len(frame) + 1):
            try:
                chunk = sock.recv(4096)
            except ConnectionResetError:
                reset = True
                break
            if not chunk:
                break
            got += chunk
    assert reset
    assert len(got) <= 5
    assert bytes(got) == frame[: len(got)]
    assert proxy.counters["reset"] == 1
    with connect(proxy.port) as sock:  # the proxy keeps accepting
        assert transact(sock, _frame(7)) == _frame(7)


def test_silent_then_recovers(proxy: FaultProxy, echo: EchoModbusServer) -> None:
    proxy.set_fault("silent")
    with connect(proxy.port) as sock, connect(proxy.port) as other:
        sock.sendall(_frame(1))
        other.sendall(_frame(2))
        assert no_reply_within(sock, 0.3)
        assert no_reply_within(other, 0.05)
        assert echo.requests == 0  # read and discarded: the target never saw them
        proxy.clear()
        assert transact(sock, _frame(3)) == _frame(3)  # same connection serves again
        assert transact(other, _frame(4)) == _frame(4)
    assert proxy.counters["silent"] == 2


def test_faults_combine_and_clear(proxy: FaultProxy) -> None:
    proxy.set_fault("wrong_tid", offset=1)
    proxy.set_fault("split", pieces=2, pause_s=0.01)
    assert proxy.active_faults() == ["split", "wrong_tid"]
    with connect(proxy.port) as sock:
        got = transact(sock, _frame(10))
        assert got[:2] == struct.pack(">H", 11)
        proxy.clear("wrong_tid")
        assert transact(sock, _frame(12)) == _frame(12)
        proxy.clear()
        assert transact(sock, _frame(13)) == _frame(13)
    assert proxy.counters["split"] == 2


def test_connections_are_independent(proxy: FaultProxy) -> None:
    with connect(proxy.port) as a, connect(proxy.port) as b:
        for tid in range(10):
            a.sendall(_frame(tid))
            b.sendall(_frame(1000 + tid))
            assert recv_frame(b) == _frame(1000 + tid)
            assert recv_frame(a) == _frame(tid)


def test_unreachable_target_resets_client() -> None:
    dead = socket.create_server(("127.0.0.1", 0))
    port = dead.getsockname()[1]
    dead.close()  # nothing listens there now
    with FaultProxy("127.0.0.1", port) as p:
        # the reset may reach the client before its connect() has returned
        with pytest.raises((ConnectionResetError, EOFError)), connect(p.port) as sock:
            recv_frame(sock)
        assert p.counters["upstream_failures"] == 1


def test_bad_arguments_and_stop_twice(echo: EchoModbusServer) -> None:
    p = FaultProxy("127.0.0.1", echo.port).start()
    with pytest.raises(ValueError, match="unknown fault"):
        p.set_fault("explode")
    with pytest.raises(ValueError, match="no parameter"):
        p.set_fault("drop", seconds=1)
    with pytest.raises(ValueError, match="probability"):
        p.set_fault("drop", probability=2.0)
    p.stop()
    p.stop()
    with pytest.raises(OSError), connect(p.port, timeout_s=0.5):
        pass


@pytest.mark.parametrize("code", [2, 6])
def test_exception_answered_by_the_proxy(
    proxy: FaultProxy, echo: EchoModbusServer, code: int
) -> None:
    proxy.set_fault("exception", code=code, count=1)
    with connect(proxy.port) as sock:
        got = transact(sock, mbap(0x0102, read_pdu(0, 8), unit=9))
        assert got == struct.pack(">HHHBBB", 0x0102, 0, 3, 9, 0x83, code)
        assert echo.requests == 0  # refused, not forwarded
        assert transact(sock, _frame(5)) == _frame(5)
    assert proxy.counters["exception"] == 1


def test_requests_split_by_the_client_are_reassembled(proxy: FaultProxy) -> None:
    frame = _frame(8)
    with connect(proxy.port) as sock:
        sock.sendall(frame[:4])
        assert no_reply_within(sock, 0.1)
        sock.sendall(frame[4:] + _frame(9))  # the rest and a second request, one segment
        assert recv_frame(sock) == frame
        assert recv_frame(sock) == _frame(9)
    assert proxy.counters["requests"] == 2
