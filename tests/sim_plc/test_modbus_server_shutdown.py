"""The soft PLC server's shutdown leaves no socket behind (regression: a flaky
ResourceWarning in tests/drivers/test_driver_contract.py).

A connection the kernel completed just before ``stop()`` is accepted by asyncio in the
same loop turn that delivers the stop, and its transport is made one turn later. The
server used to close its listener first, so that transport failed to attach (asyncio's
``Server._attach`` asserts on a closed listener) and was dropped with its socket open.
The test stages exactly that loop turn: it holds the server's loop, connects, queues
the stop, and releases the loop.
"""

from __future__ import annotations

import contextlib
import gc
import socket
import threading

import pytest

from tests.modbus_helpers import LOCALHOST, plc_server

pytestmark = pytest.mark.loopback

HOLD_TIMEOUT_S = 5.0
EOF_TIMEOUT_S = 2.0


def test_a_connection_accepted_as_the_server_stops_is_closed() -> None:
    with plc_server() as (server, _image, _cfg):
        loop, stopping = server._loop, server._stopping  # white box: stage the loop turn
        assert loop is not None and stopping is not None
        held, release = threading.Event(), threading.Event()

        def hold() -> None:
            held.set()
            release.wait(HOLD_TIMEOUT_S)

        loop.call_soon_threadsafe(hold)
        assert held.wait(HOLD_TIMEOUT_S)
        # the kernel completes the handshake while the loop is held
        client = socket.create_connection((LOCALHOST, server.port), timeout=EOF_TIMEOUT_S)
        with client:
            loop.call_soon_threadsafe(stopping.set)  # queued ahead of the accept
            release.set()
            server.stop()
            assert server.thread is None
            # the server side is closed (EOF or reset), not left to the garbage collector
            with contextlib.suppress(ConnectionResetError):
                assert client.recv(1) == b""
    gc.collect()  # a leaked transport or socket would warn here (warnings are errors)
