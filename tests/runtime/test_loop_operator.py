"""The operator's view of the loop: log lines, systemd notifications."""

from __future__ import annotations

import contextlib
import logging
import re
import socket
from pathlib import Path

import pytest

from drivers.virtual import VirtualDriver, VirtualFaults
from gateway.core.cliopts import FOREIGN_LOGGERS, setup_logging
from gateway.runtime.loop import CyclicService
from gateway.runtime.sdnotify import Notifier
from tests.loop_helpers import FakeClock, config, live_image


def make(faults=None, notifier=None, **loop):
    cfg = config(busy_wait_s=0.0, **loop)
    clock = FakeClock()
    drv = VirtualDriver(cfg, image=live_image(cfg), faults=faults)
    svc = CyclicService(cfg, drv, clock=clock, sleep=clock.sleep, history=4096, notifier=notifier)
    return svc, drv, clock


def messages(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "cdpr_gateway.loop"]


def test_each_state_change_is_logged_once_with_its_cause(caplog):
    # a summary at ~0.5 s (channels stuck on the static image) holds the next one back
    # for 10 s; the outage at read 1000 must not leave it unsaid that the bus recovered
    svc, _, _ = make(VirtualFaults(drop_on_read=1000))
    with caplog.at_level(logging.INFO, logger="cdpr_gateway.loop"):
        svc.run(cycles=1500)
    lines = messages(caplog)
    connected = [m for m in lines if m.startswith("connected to the PLC at virtual")]
    lost = [m for m in lines if m.startswith("disconnected from the PLC")]
    recovered = [m for m in lines if m.startswith("recovered:")]
    assert len(connected) == 1 and len(lost) == 1 and len(recovered) == 1, lines
    assert "connection dropped (fault injection)" in lost[0]  # the driver's cause
    assert lines.index(lost[0]) < lines.index(recovered[0])
    after = lines[lines.index(recovered[0]) + 1 :]
    summaries = [m for m in after if m.startswith("gateway: ")]
    assert len(summaries) == 1 and "reconnects +1" in summaries[0], lines
    assert summaries[0].endswith("(state active)")


def test_unreachable_plc_at_start_says_why(caplog):
    svc, drv, _ = make(VirtualFaults(fail_opens=2))
    with caplog.at_level(logging.INFO, logger="cdpr_gateway.loop"):
        svc.run(cycles=400)
    lines = messages(caplog)
    first = [m for m in lines if m.startswith("cannot reach the PLC yet:")]
    assert len(first) == 1, lines
    assert "open" in first[0] and "fault injection" in first[0]
    assert sum(m.startswith("recovered:") for m in lines) == 1
    assert drv.opens == 3


def test_heartbeat_fault_and_recovery_are_logged(caplog):
    faults = VirtualFaults(freeze_heartbeat_from=10, freeze_heartbeat_until=200)
    svc, _, _ = make(faults, heartbeat_timeout_s=0.05)
    with caplog.at_level(logging.INFO, logger="cdpr_gateway.loop"):
        svc.run(cycles=300)
    lines = messages(caplog)
    assert sum("PLC heartbeat has not changed for 0.05 s" in m for m in lines) == 1, lines
    assert sum(m.startswith("recovered:") for m in lines) == 1


def test_foreign_loggers_are_quiet_unless_debug():
    saved = {n: logging.getLogger(n).level for n in (*FOREIGN_LOGGERS, "")}
    try:
        setup_logging("INFO")
        assert all(logging.getLogger(n).level == logging.WARNING for n in FOREIGN_LOGGERS)
        assert logging.getLogger().level == logging.INFO
        setup_logging("DEBUG")
        assert all(logging.getLogger(n).level == logging.DEBUG for n in FOREIGN_LOGGERS)
    finally:
        for name, level in saved.items():
            logging.getLogger(name).setLevel(level)


# --- sd_notify ---------------------------------------------------------------------------


@pytest.fixture
def notify_socket(tmp_path: Path):
    path = str(tmp_path / "notify")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.setblocking(False)
    yield path, sock
    sock.close()


def test_no_notify_socket_no_notifier():
    assert Notifier.from_env({}) is None
    assert Notifier.from_env({"NOTIFY_SOCKET": ""}) is None


def test_watchdog_interval_is_half_of_watchdog_usec(notify_socket):
    path, _ = notify_socket
    n = Notifier.from_env({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "200000"})
    assert n is not None and n.watchdog_interval_s == pytest.approx(0.1)
    n.close()


def test_loop_sends_ready_once_configured_watchdog_while_cycling_and_stopping(notify_socket):
    path, sock = notify_socket
    msgs: list[str] = []

    class Draining(Notifier):
        """Reads what it sent right away: the loop runs on a fake clock, faster than a
        receiving thread is scheduled, and a unix datagram queue holds only a few."""

        def notify(self, message: str) -> bool:
            ok = super().notify(message)
            with contextlib.suppress(BlockingIOError):
                while True:
                    msgs.append(sock.recv(4096).decode())
            return ok

    notifier = Draining(path, watchdog_interval_s=0.1)
    svc, _, _ = make(VirtualFaults(drop_on_read=1000), notifier=notifier)
    svc.run(cycles=2500)  # 2.5 s of loop time on the fake clock
    notifier.close()
    assert notifier.failed == 0
    assert msgs.count("READY=1") == 1
    assert msgs.index("READY=1") < msgs.index("STATUS=active")  # ready before the PLC answered
    pings = msgs.count("WATCHDOG=1")
    assert 24 <= pings <= 27, pings  # every 0.1 s of a 2.5 s run
    assert any(m.startswith("STATUS=disconnected from the PLC") for m in msgs)
    assert msgs[-1] == "STOPPING=1"


def test_abstract_namespace_address():
    name = f"cdpr-test-{id(object())}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    try:
        notifier = Notifier.from_env({"NOTIFY_SOCKET": "@" + name})
        assert notifier is not None and notifier.notify("READY=1")
        assert sock.recv(64) == b"READY=1"
        notifier.close()
    finally:
        sock.close()


def test_unreachable_notify_socket_never_raises(tmp_path: Path):
    notifier = Notifier(str(tmp_path / "nobody-listens"))
    assert notifier.notify("WATCHDOG=1") is False and notifier.failed == 1
    notifier.close()


def test_a_flapping_bus_is_one_outage_said_twice(caplog):
    """A read timing out every 20th cycle for 1 s (a CANopen bus missing SYNCs on a loaded
    machine said 205 'recovered' WARNINGs and 153 summaries in 5 s): one WARNING when it
    starts, one INFO line when the loop has stayed active SETTLED_S, counting them."""
    from gateway.errors import DriverTimeoutError
    from gateway.runtime.loop import SETTLED_S

    def flap(n: int) -> None:
        if 100 <= n < 1100 and n % 20 == 0:
            raise DriverTimeoutError(f"no SYNC within 2.5 ms (read {n})")

    cfg = config(busy_wait_s=0.0)
    clock = FakeClock()
    drv = VirtualDriver(cfg, image=live_image(cfg), on_read=flap)
    svc = CyclicService(cfg, drv, clock=clock, sleep=clock.sleep, history=4096)
    with caplog.at_level(logging.DEBUG, logger="cdpr_gateway.loop"):
        svc.run(cycles=2000)
    records = [r for r in caplog.records if r.name == "cdpr_gateway.loop"]
    said = [r for r in records if r.levelno >= logging.INFO]
    lost = [r for r in said if r.getMessage().startswith("disconnected from the PLC")]
    back = [r for r in said if r.getMessage().startswith("recovered:")]
    assert len(lost) == 1 and lost[0].levelno == logging.WARNING, [r.getMessage() for r in said]
    assert len(back) == 1 and back[0].levelno == logging.INFO, [r.getMessage() for r in said]
    assert "no SYNC within 2.5 ms (read 100)" in lost[0].getMessage()
    n = int(re.search(r"\((\d+) interruptions, the longest", back[0].getMessage()).group(1))
    assert n == 50, back[0].getMessage()  # reads 100, 120, ..., 1080
    assert said.index(lost[0]) < said.index(back[0])
    summaries = [r for r in said if r.getMessage().startswith("gateway: ")]
    assert len(summaries) <= 3, [r.getMessage() for r in summaries]
    # each interruption is still in the log at DEBUG, for whoever asks
    assert sum(r.getMessage().startswith("disconnected") for r in records) == 50
    assert SETTLED_S < 1.0


def test_a_heartbeat_fault_recovers_without_claiming_a_connection(caplog):
    faults = VirtualFaults(freeze_heartbeat_from=10, freeze_heartbeat_until=200)
    svc, _, _ = make(faults, heartbeat_timeout_s=0.05)
    with caplog.at_level(logging.INFO, logger="cdpr_gateway.loop"):
        svc.run(cycles=1000)
    (back,) = [r for r in caplog.records if r.getMessage().startswith("recovered:")]
    assert back.levelno == logging.INFO
    assert "heartbeat changes again" in back.getMessage() and "connected" not in back.getMessage()
