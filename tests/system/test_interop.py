"""Interoperability with a Modbus TCP stack this project did not write.

The gateway's client (drivers/modbus_tcp.py) and the soft PLC's server are both
hand-written here: a bug they share would pass every loopback test. pyModbusTCP's server
(pure Python, independent of pymodbus and of this code) is started on loopback holding
the default register map; the PLC side of every value is encoded and decoded in this
test with ``struct`` alone (not the project's codec). Checked: the values read, the
function-23 path (one write/read transaction), the function-16 path (16 then 3), both
word orders of the 32-bit types, and the whole loop writing good frames.
"""

from __future__ import annotations

import dataclasses
import importlib
import struct
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from drivers.base import Inputs, Lifecycle, Outputs
from drivers.modbus_tcp import ModbusTcpDriver
from gateway.core.config import Config, load_config
from gateway.core.registermap import RegisterField
from gateway.runtime.loop import CyclicService
from tests.loop_helpers import free_port, fresh

pyModbusTCP = importlib.import_module("pyModbusTCP.server")  # a dev dependency: never skipped
pytestmark = pytest.mark.loopback

RAW_COUNTS = [0, 3000, 6000, 13824, 20000, 27648, 30000, -400]
VELOCITY = [-0.5, -0.25, -0.125, 0.0, 0.0625, 0.125, 0.25, 0.5]
LENGTH = [1.0, 1.25, 1.5, 1.75, 2.0, 2.25, 2.5, 2.75]
POSE = [0.125, -0.25, 1.5, 0.0625, -0.03125, 0.5]
MASS = 40.0


def _words(values: list[float], code: str, low_first: bool) -> list[int]:
    """Registers of ``values`` (struct ``code`` per value), 32-bit words swapped if asked."""
    out: list[int] = []
    for v in values:
        raw = struct.pack(">" + code, v)
        words = list(struct.unpack(f">{len(raw) // 2}H", raw))
        out += words[::-1] if low_first and len(words) == 2 else words
    return out


def _values(words: list[int], code: str, low_first: bool) -> list[float]:
    size = struct.calcsize(code) // 2
    out = []
    for k in range(0, len(words), size):
        w = words[k : k + size]
        w = w[::-1] if low_first and size == 2 else w
        out.append(struct.unpack(">" + code, struct.pack(f">{size}H", *w))[0])
    return out


class ForeignPlc:
    """pyModbusTCP's server on 127.0.0.1 with the PLC's inputs of one register map."""

    def __init__(self, cfg: Config, low_first: bool, port: int) -> None:
        self.bank = pyModbusTCP.DataBank()
        self.port = port
        self.server = pyModbusTCP.ModbusServer(
            host="127.0.0.1", port=self.port, no_block=True, data_bank=self.bank
        )
        self.low_first = low_first
        self.regs = cfg.bus.modbus_tcp.registers
        self.heartbeat = 4242

    def fill(self) -> None:
        r, lf = self.regs, self.low_first
        put = self.bank.set_holding_registers
        put(r.raw_tensions.address, [c & 0xFFFF for c in RAW_COUNTS])
        put(r.setpoint_velocities.address, _words(VELOCITY, "f", lf))
        put(r.setpoint_lengths.address, _words(LENGTH, "f", lf))
        put(r.pose.address, _words(POSE, "f", lf))
        put(r.plc_heartbeat.address, [self.heartbeat & 0xFFFF])
        if r.platform_mass is not None:
            put(r.platform_mass.address, _words([MASS], "f", lf))

    def beat(self) -> None:
        self.heartbeat += 1
        self.bank.set_holding_registers(self.regs.plc_heartbeat.address, [self.heartbeat & 0xFFFF])

    def read(self, field: RegisterField, code: str) -> list[float]:
        words = self.bank.get_holding_registers(field.address, field.words)
        return _values(words, code, self.low_first and field.words == 2 * field.count)


@pytest.fixture(params=[False, True], ids=["high_first", "low_first"])
def plc(request) -> Iterator[tuple[ForeignPlc, Config]]:
    low_first: bool = request.param
    cfg = load_config()
    regs = cfg.bus.modbus_tcp.registers
    if low_first:  # every 32-bit field low word first, the wrench as int32 at 0.01 N
        names = ("setpoint_velocities", "setpoint_lengths", "pose", "platform_mass")
        swapped = {
            n: dataclasses.replace(getattr(regs, n), word_order="low_first")
            for n in (*names, "corrected_tensions")
        }
        wrench = RegisterField(126, 6, "int32", word_order="low_first", scale=0.01)
        regs = dataclasses.replace(regs, **swapped, wrench=wrench)
    port = free_port()
    mb = dataclasses.replace(cfg.bus.modbus_tcp, port=port, registers=regs, timeout_s=1.0)
    cfg = dataclasses.replace(cfg, bus=dataclasses.replace(cfg.bus, modbus_tcp=mb))
    foreign = ForeignPlc(cfg, low_first, port)
    foreign.fill()
    foreign.server.start()
    try:
        yield foreign, cfg
    finally:
        foreign.server.stop()


def _outputs() -> Outputs:
    out = Outputs.allocate(8)
    out.tension_corrected_n[:] = [10.5, 120.25, 250.0, 333.5, 400.0, 480.75, 499.5, 0.5]
    out.channel_status[:] = [0, 0, 1, 0, 0, 1, 0, 0]
    out.wrench[:] = [12.34, -56.78, 900.5, 1.25, -2.5, 0.75]
    out.gateway_heartbeat = 77
    out.gateway_state = int(Lifecycle.ACTIVE)
    return out


def _check_written(foreign: ForeignPlc, out: Outputs) -> None:
    r = foreign.regs
    assert_allclose(foreign.read(r.corrected_tensions, "f"), out.tension_corrected_n, rtol=1e-6)
    status = foreign.bank.get_holding_registers(r.channel_status.address, 8)
    assert_array_equal(status, out.channel_status)
    (hb,) = foreign.bank.get_holding_registers(r.gateway_heartbeat.address, 1)
    (state,) = foreign.bank.get_holding_registers(r.gateway_state.address, 1)
    assert (hb, state) == (out.gateway_heartbeat, out.gateway_state)
    if r.wrench.type == "float32":
        wrench = foreign.read(r.wrench, "f")
        assert_allclose(wrench, out.wrench, rtol=1e-6)
    else:
        wrench = np.array(foreign.read(r.wrench, "i")) * r.wrench.scale
        assert_allclose(wrench, out.wrench, atol=0.005 + 1e-9)


@pytest.mark.parametrize("use_fc23", [True, False], ids=["fc23", "fc16+3"])
def test_the_gateway_reads_and_writes_a_foreign_modbus_server(plc, use_fc23: bool) -> None:
    foreign, cfg = plc
    mb = dataclasses.replace(cfg.bus.modbus_tcp, use_fc23=use_fc23)
    cfg = dataclasses.replace(cfg, bus=dataclasses.replace(cfg.bus, modbus_tcp=mb))
    inputs = Inputs.allocate(8)
    with ModbusTcpDriver(cfg) as drv:
        drv.read_into(inputs)  # function 3
        assert_allclose(inputs.tension_raw_n, np.array(RAW_COUNTS) * 500.0 / 27648, rtol=1e-12)
        assert_allclose(inputs.velocity_m_s, VELOCITY, rtol=1e-7)
        assert_allclose(inputs.length_m, LENGTH, rtol=1e-7)
        assert_allclose(inputs.pose, POSE, rtol=1e-7)
        assert inputs.plc_heartbeat == 4242
        assert inputs.platform_mass_kg == pytest.approx(MASS)
        out = _outputs()
        foreign.beat()
        drv.exchange(fresh(out, drv), inputs)  # fc23: one transaction; else 16 then 3
        _check_written(foreign, out)
        assert inputs.plc_heartbeat == 4243  # read in the same exchange
        out.gateway_heartbeat = 78
        out.tension_corrected_n[0] = 11.5
        drv.write_from(fresh(out, drv))  # function 16 at once
        _check_written(foreign, out)
        assert drv.dropped_replies == 0 and drv.gated.sum() == 0


def test_the_gateway_loop_against_a_foreign_modbus_server(plc) -> None:
    foreign, cfg = plc
    cfg = dataclasses.replace(
        cfg, loop=dataclasses.replace(cfg.loop, busy_wait_s=0.0, max_input_age_s=0.05)
    )
    # on the shared test machine the pure-Python server's round trip is ~1 ms: a larger
    # age limit for this test; the gate's age check itself is tested elsewhere
    service = CyclicService(cfg, ModbusTcpDriver(cfg), history=1024)
    stop = threading.Event()

    def plc_cycle() -> None:  # the PLC's heartbeat, +1 per ms, until stopped
        for _ in range(20_000):
            if stop.wait(0.001):
                return
            foreign.beat()

    beater = threading.Thread(target=plc_cycle, daemon=True)
    worker = threading.Thread(target=service.run, kwargs={"cycles": 1500}, daemon=True)
    beater.start()
    worker.start()
    seen_good = False
    deadline = time.monotonic() + 60
    while worker.is_alive() and time.monotonic() < deadline:
        status = foreign.bank.get_holding_registers(foreign.regs.channel_status.address, 8)
        if status and all(s == 0 for s in status):
            tensions = foreign.read(foreign.regs.corrected_tensions, "f")
            assert np.all(np.isfinite(tensions)) and np.all(np.abs(tensions) < 600), tensions
            seen_good = True
        time.sleep(0.01)
    worker.join(timeout=30)
    stop.set()
    beater.join(timeout=5)
    assert not worker.is_alive()
    assert seen_good, f"no all-good frame seen; gated {service.driver.gated}"
    assert service.stats.written > 500, service.stats.errors
    (state,) = foreign.bank.get_holding_registers(foreign.regs.gateway_state.address, 1)
    assert state == Lifecycle.STOPPED  # the last frame
