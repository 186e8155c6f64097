"""The gateway as a real CANopen node: boot-up, 1017h heartbeat, NMT commands, SDO.

One process, a private python-can virtual channel; a second bus on it plays the master.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator

import can
import pytest

from drivers.base import Inputs, Outputs
from drivers.canopen import CanopenDriver
from gateway.errors import DriverTimeoutError
from tests.canopen_helpers import canopen_config

GW = 0x20
HEARTBEAT_COB = 0x700 + GW
HEARTBEAT_MS = 100  # 1017h in config/gateway.eds


@pytest.fixture
def node() -> Iterator[tuple[CanopenDriver, can.BusABC]]:
    cfg = canopen_config()
    master = can.Bus(interface="virtual", channel=cfg.bus.canopen.channel)
    driver = CanopenDriver(cfg, timeout_s=0.005)
    try:
        yield driver, master
    finally:
        driver.close()
        master.shutdown()


def _frames(bus: can.BusABC, seconds: float, cob_id: int) -> list[bytes]:
    out, end = [], time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:  # bounded by ``seconds``
        msg = bus.recv(left)
        if msg is not None and msg.arbitration_id == cob_id:
            out.append(bytes(msg.data))
    return out


def _nmt(master: can.BusABC, driver: CanopenDriver, command: int) -> None:
    master.send(can.Message(arbitration_id=0, data=bytes((command, GW)), is_extended_id=False))
    with pytest.raises(DriverTimeoutError):  # no PLC: the read only takes the command in
        driver.read_into(Inputs.allocate(driver.cables))


def test_boot_up_then_heartbeat_operational(node) -> None:
    driver, master = node
    driver.open()
    frames = _frames(master, 3.5 * HEARTBEAT_MS / 1000, HEARTBEAT_COB)
    assert frames[0] == b"\x00"  # boot-up
    # (at most one heartbeat says pre-operational, 0x7F, before the node starts itself)
    assert frames[-3:] == [b"\x05"] * 3  # operational heartbeats every 1017h ms
    assert driver.nmt_state == "OPERATIONAL"


def test_nmt_stop_silences_pdos_and_start_resumes(node) -> None:
    driver, master = node
    driver.open()
    _nmt(master, driver, 0x02)  # stop
    assert driver.nmt_state == "STOPPED"
    _frames(master, 0.01, -1)  # drain what was sent so far
    driver.write_from(Outputs.allocate(driver.cables))
    frames = _frames(master, 0.25, HEARTBEAT_COB)
    assert b"\x04" in frames  # the heartbeat says stopped
    _nmt(master, driver, 0x01)  # start
    assert driver.nmt_state == "OPERATIONAL"
    _frames(master, 0.01, -1)
    driver.write_from(Outputs.allocate(driver.cables))
    tpdo1 = _frames(master, 0.05, 0x180 + GW)
    assert len(tpdo1) == 1


def test_stopped_node_sends_no_pdo(node) -> None:
    driver, master = node
    driver.open()
    _nmt(master, driver, 0x02)
    _frames(master, 0.01, -1)
    driver.write_from(Outputs.allocate(driver.cables))
    assert _frames(master, 0.05, 0x180 + GW) == []


def test_reset_communication_sends_boot_up_again(node) -> None:
    driver, master = node
    driver.open()
    _frames(master, 0.01, -1)
    _nmt(master, driver, 0x82)
    frames = _frames(master, 0.25, HEARTBEAT_COB)
    assert frames[0] == b"\x00"
    assert driver.nmt_state == "OPERATIONAL"


def test_sdo_upload_of_the_heartbeat_time(node) -> None:
    driver, master = node
    driver.open()
    _frames(master, 0.01, -1)
    # expedited upload request of 1017h sub 0
    req = bytes((0x40, 0x17, 0x10, 0x00, 0, 0, 0, 0))
    master.send(can.Message(arbitration_id=0x600 + GW, data=req, is_extended_id=False))
    with pytest.raises(DriverTimeoutError):
        driver.read_into(Inputs.allocate(driver.cables))
    reply = _frames(master, 0.05, 0x580 + GW)
    assert len(reply) == 1
    assert reply[0][1:4] == b"\x17\x10\x00"
    assert int.from_bytes(reply[0][4:6], "little") == HEARTBEAT_MS


def test_virtual_interface_says_it_only_connects_one_process(node, caplog) -> None:
    driver, _ = node
    with caplog.at_level(logging.WARNING, logger="cdpr_gateway.canopen"):
        driver.open()
    assert any("ONE process" in r.getMessage() for r in caplog.records)
