"""Malformed Modbus/TCP traffic against the soft PLC's server over raw sockets.

For every case: the server does not crash or hang (every socket operation has a timeout),
answers with the exception the Modbus application protocol (v1.1b3) requires where it
requires one, and a second client connection (the witness, a background thread doing a
known read every few ms) keeps being served correctly throughout the module.

Register areas of the default map (sim_plc.modbus_server): inputs 0..55 read-only,
outputs 100..137 writable, truth 200..215 read-only; everything else is illegal.
"""

from __future__ import annotations

import socket
import struct
import threading
from collections.abc import Iterator

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.reliability_helpers import (
    connect,
    mbap,
    read_pdu,
    recv_frame,
    rw_pdu,
    soft_plc,
    transact,
    write_pdu,
)

pytestmark = pytest.mark.loopback
pytest.importorskip("sim_plc.modbus_server", reason="the soft PLC's Modbus server")

ILLEGAL_FUNCTION, ILLEGAL_ADDRESS, ILLEGAL_VALUE = 1, 2, 3
QUIET_S = 0.15  # how long "no reply" is waited for
WITNESS_READ = mbap(0, read_pdu(0, 53))


class Witness:
    """A second client: reads registers 0..52 every ``period_s`` and checks the reply."""

    def __init__(self, port: int, expected: bytes, period_s: float = 0.005) -> None:
        self.port, self.expected, self.period_s = port, expected, period_s
        self.ok = 0
        self.failures: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="witness")

    def _run(self) -> None:
        with connect(self.port, timeout_s=5.0) as sock:  # a loaded machine stalls the server
            tid = 0
            while not self._stop.wait(self.period_s):
                tid = (tid + 1) & 0xFFFF
                try:
                    reply = transact(sock, mbap(tid, read_pdu(0, 53)))
                except (OSError, EOFError) as exc:
                    self.failures.append(f"tid {tid}: {exc!r}")
                    return
                if reply[:2] != struct.pack(">H", tid) or reply[2:] != self.expected[2:]:
                    self.failures.append(f"tid {tid}: wrong reply {reply.hex()}")
                else:
                    self.ok += 1

    def start(self) -> Witness:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(3.0)


@pytest.fixture(scope="module")
def plc() -> Iterator[tuple[int, Witness]]:
    with soft_plc() as (server, _image, _cfg):
        with connect(server.port) as sock:
            expected = transact(sock, WITNESS_READ)
        assert expected[7] == 3 and expected[8] == 2 * 53
        witness = Witness(server.port, expected).start()
        try:
            yield server.port, witness
        finally:
            witness.stop()
        assert witness.failures == []
        assert witness.ok > 10


@pytest.fixture
def port(plc: tuple[int, Witness]) -> Iterator[int]:
    """The server's port; after each test the witness must still be served."""
    port, witness = plc
    before = witness.ok
    yield port
    with connect(port) as sock:  # and a fresh connection is served too
        assert transact(sock, mbap(77, read_pdu(0, 1)))[7] == 3
    assert witness.failures == []
    assert witness.ok >= before


def _reply_after(port: int, raw: bytes) -> bytes | None:
    """Send ``raw`` on a fresh connection; the first reply frame, or None if none came."""
    with connect(port) as sock:
        sock.sendall(raw)
        sock.settimeout(QUIET_S)
        try:
            return recv_frame(sock)
        except (TimeoutError, EOFError, ConnectionResetError):
            return None


def _exception(reply: bytes | None, function: int) -> int:
    assert reply is not None, "no reply where an exception reply is required"
    assert reply[7] == 0x80 | function, f"reply {reply.hex()} is not an exception to {function}"
    assert struct.unpack_from(">H", reply, 4)[0] == 3  # unit + function + code
    return reply[8]


# --- exception replies the spec requires ---------------------------------------------
@pytest.mark.parametrize("function", [0x00, 0x09, 0x41, 0x64, 0x7F, 0x01, 0x02])
def test_unsupported_function_is_illegal_function(port: int, function: int) -> None:
    reply = _reply_after(port, mbap(1, bytes((function,)) + struct.pack(">HH", 0, 1)))
    assert _exception(reply, function) == ILLEGAL_FUNCTION


@pytest.mark.parametrize(
    ("pdu", "function"),
    [
        (read_pdu(0, 0, 3), 3),
        (read_pdu(0, 0, 4), 4),
        (read_pdu(0, 126, 3), 3),
        (read_pdu(0, 126, 4), 4),
        (struct.pack(">BHHB", 16, 100, 0, 0), 16),
        (write_pdu(100, [0] * 124), 16),
        (rw_pdu(0, 0, 116, [0]), 23),
        (rw_pdu(0, 126, 116, [0]), 23),
        (rw_pdu(0, 8, 100, [0] * 122), 23),
    ],
    ids=[
        "fc3-0",
        "fc4-0",
        "fc3-126",
        "fc4-126",
        "fc16-0",
        "fc16-124",
        "fc23-r0",
        "fc23-r126",
        "fc23-w122",
    ],
)
def test_count_out_of_range_is_illegal_value(port: int, pdu: bytes, function: int) -> None:
    assert _exception(_reply_after(port, mbap(2, pdu)), function) == ILLEGAL_VALUE


@pytest.mark.parametrize(
    ("pdu", "function"),
    [
        (read_pdu(0, 125, 3), 3),  # count at the limit, crosses into unmapped registers
        (write_pdu(100, [0] * 123), 16),  # at the limit, beyond the output area
        (rw_pdu(0, 8, 100, [0] * 121), 23),  # fc23 write limit, beyond the output area
        (write_pdu(0, [1, 2]), 16),  # the PLC's inputs are read-only
        (struct.pack(">BHH", 6, 52, 1), 6),  # the PLC heartbeat is read-only
        (read_pdu(60, 1, 3), 3),  # a hole in the map
        (read_pdu(65535, 1, 3), 3),
    ],
    ids=["fc3-125", "fc16-123", "fc23-w121", "fc16-inputs", "fc6-heartbeat", "hole", "top"],
)
def test_count_at_limit_or_bad_address_is_illegal_address(
    port: int, pdu: bytes, function: int
) -> None:
    assert _exception(_reply_after(port, mbap(3, pdu)), function) == ILLEGAL_ADDRESS


@pytest.mark.parametrize("byte_count", [0, 2, 6, 255])
def test_write_byte_count_mismatch_is_illegal_value(port: int, byte_count: int) -> None:
    pdu = struct.pack(">BHHB", 16, 116, 2, byte_count) + bytes(4)
    assert _exception(_reply_after(port, mbap(4, pdu)), 16) == ILLEGAL_VALUE
    pdu23 = struct.pack(">BHHHHB", 23, 0, 4, 116, 2, byte_count) + bytes(4)
    assert _exception(_reply_after(port, mbap(5, pdu23)), 23) == ILLEGAL_VALUE


def test_valid_requests_at_the_limits_are_served(port: int) -> None:
    with connect(port) as sock:
        reply = transact(sock, mbap(6, read_pdu(0, 56)))
        assert reply[7:9] == bytes((3, 112))
        reply = transact(sock, mbap(7, write_pdu(100, [0] * 38)))  # the whole output area
        assert reply[7:] == struct.pack(">BHH", 16, 100, 38)
        reply = transact(sock, mbap(8, rw_pdu(0, 56, 100, [0] * 38)))
        assert reply[7:9] == bytes((23, 112))


# --- framing: MBAP header, truncation, pipelining ------------------------------------
@pytest.mark.parametrize(
    "raw",
    [
        mbap(9, read_pdu(0, 2), protocol=1),
        mbap(9, read_pdu(0, 2), protocol=0xFFFF),
        mbap(9, read_pdu(0, 2), length=0),
        mbap(9, b"", length=1),
        mbap(9, read_pdu(0, 2), length=0xFFFF),
        mbap(9, read_pdu(0, 2), length=200),
        mbap(9, read_pdu(0, 2))[:5],
        mbap(9, read_pdu(0, 2))[:9],
        mbap(9, write_pdu(100, [1, 2, 3]))[:14],
    ],
    ids=["proto1", "protoffff", "len0", "len1", "lenffff", "len200", "hdr5", "pdu2", "write14"],
)
def test_bad_header_or_truncated_frame_gets_no_data_reply(port: int, raw: bytes) -> None:
    """No register data for a frame that is not a valid request (the spec: discard it);
    an exception reply is tolerated, a data reply is not."""
    reply = _reply_after(port, raw)
    assert reply is None or reply[7] & 0x80


def test_truncated_frame_then_silence_does_not_block_others(port: int) -> None:
    with connect(port) as stuck, connect(port) as other:
        stuck.sendall(mbap(10, read_pdu(0, 2))[:8])  # never completed
        for tid in range(20):
            assert transact(other, mbap(tid, read_pdu(0, 2)))[:2] == struct.pack(">H", tid)


def test_short_mbap_length_gets_illegal_value(port: int) -> None:
    """Length 3 cuts a function-3 request to 2 PDU bytes: a malformed request."""
    reply = _reply_after(port, mbap(11, read_pdu(0, 2), length=3))
    assert _exception(reply, 3) == ILLEGAL_VALUE


def test_several_requests_in_one_segment_all_answered(port: int) -> None:
    """Was a strict xfail under pymodbus 3.16 (its transport cleared the receive buffer)."""
    frames = b"".join(mbap(40 + k, read_pdu(k, 2)) for k in range(3))
    with connect(port) as sock:
        sock.sendall(frames)
        sock.settimeout(0.5)
        tids = [struct.unpack(">H", recv_frame(sock)[:2])[0] for _ in range(3)]
    assert tids == [40, 41, 42]


@pytest.mark.parametrize("n", [2, 3, 20, 50, 200])
def test_pipelined_requests_in_one_segment_all_answered_in_order(port: int, n: int) -> None:
    """pymodbus 3.16 answered only the first of 1-20 and none of 50 or more."""
    frames = b"".join(mbap(40 + k, read_pdu(k % 50, 2)) for k in range(n))
    with connect(port) as sock:
        sock.sendall(frames)
        replies = [recv_frame(sock) for _ in range(n)]
        assert transact(sock, mbap(30, read_pdu(0, 2)))[:2] == struct.pack(">H", 30)
    assert [struct.unpack_from(">H", r)[0] for r in replies] == [40 + k for k in range(n)]
    assert all(r[7] == 3 and r[8] == 4 for r in replies)


def test_pipelined_mix_of_good_and_bad_requests_answered_in_order(port: int) -> None:
    pdus = [
        read_pdu(0, 2),
        read_pdu(60, 1),
        write_pdu(0, [1]),
        bytes((0x41, 0, 0)),
        read_pdu(0, 126),
        rw_pdu(0, 1, 100, [7]),
    ]
    with connect(port) as sock:
        sock.sendall(b"".join(mbap(50 + k, p) for k, p in enumerate(pdus)))
        replies = [recv_frame(sock) for _ in pdus]
    assert [r[:2] for r in replies] == [struct.pack(">H", 50 + k) for k in range(len(pdus))]
    assert [r[7] for r in replies] == [3, 0x83, 0x90, 0xC1, 0x83, 23]
    assert [r[8] for r in replies[1:5]] == [
        ILLEGAL_ADDRESS,
        ILLEGAL_ADDRESS,
        ILLEGAL_FUNCTION,
        ILLEGAL_VALUE,
    ]


@pytest.mark.parametrize("cut", [1, 6, 7, 9, 11])
def test_pipelined_frames_split_anywhere_all_answered(port: int, cut: int) -> None:
    """Two whole frames and part of a third, then the rest: three replies, in order."""
    frames = b"".join(mbap(60 + k, read_pdu(k, 2)) for k in range(3))
    split = 2 * 12 + cut
    with connect(port) as sock:
        sock.sendall(frames[:split])
        first = [recv_frame(sock) for _ in range(2)]
        sock.sendall(frames[split:])
        third = recv_frame(sock)
    assert [r[:2] for r in (*first, third)] == [struct.pack(">H", 60 + k) for k in range(3)]


def _closed_after(sock: socket.socket) -> bool:
    """True when the server closes ``sock`` (EOF or reset) within the I/O timeout."""
    try:
        return sock.recv(1) == b""
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False


@pytest.mark.parametrize(
    "bad",
    [
        mbap(9, read_pdu(0, 2), protocol=1),
        mbap(9, read_pdu(0, 2), protocol=0xFFFF),
        mbap(9, read_pdu(0, 2), length=0),
        mbap(9, b"", length=1),
        mbap(9, read_pdu(0, 2), length=0xFFFF),
        mbap(9, read_pdu(0, 2), length=267),
    ],
    ids=["proto1", "protoffff", "len0", "len1", "lenffff", "len267"],
)
def test_frame_not_served_closes_connection_after_due_replies(port: int, bad: bytes) -> None:
    """The replies to the good frames before it arrive, then EOF (not a silent socket)."""
    good = mbap(70, read_pdu(0, 2)) + mbap(71, read_pdu(2, 2))
    with connect(port) as sock:
        sock.sendall(good + bad + mbap(72, read_pdu(0, 2)))
        assert [recv_frame(sock)[:2] for _ in range(2)] == [b"\x00\x46", b"\x00\x47"]
        assert _closed_after(sock)


def test_frame_not_served_alone_closes_connection(port: int) -> None:
    with connect(port) as sock:
        sock.sendall(mbap(9, read_pdu(0, 2), protocol=1)[:6])  # the header is enough
        assert _closed_after(sock)


def test_many_connections_opened_and_dropped(port: int) -> None:
    socks = [connect(port) for _ in range(30)]
    for k, s in enumerate(socks):
        if k % 3 == 0:
            s.sendall(mbap(k, read_pdu(0, 2))[:9])
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        s.close()  # RST, some of them mid-frame


# --- generated frames ------------------------------------------------------------------
def _check_reply(reply: bytes | None, tid: int) -> None:
    if reply is None:
        return
    assert reply[:2] == struct.pack(">H", tid)
    assert reply[2:4] == b"\x00\x00"
    assert struct.unpack_from(">H", reply, 4)[0] == len(reply) - 6


frames = st.builds(
    lambda tid, unit, function, body: (tid, mbap(tid, bytes((function,)) + body, unit=unit)),
    st.integers(0, 0xFFFF),
    st.integers(0, 255),
    st.one_of(st.sampled_from([3, 4, 6, 16, 23]), st.integers(0, 255)),
    st.binary(min_size=0, max_size=40),
)


@settings(
    max_examples=80,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(frame=frames)
def test_generated_frames(port: int, frame: tuple[int, bytes]) -> None:
    tid, raw = frame
    _check_reply(_reply_after(port, raw), tid)


@settings(
    max_examples=40,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(raw=st.binary(min_size=1, max_size=300))
def test_random_bytes(port: int, raw: bytes) -> None:
    reply = _reply_after(port, raw)
    if reply is not None:
        assert reply[2:4] == b"\x00\x00"
