"""Regressions: output register maps that cannot carry the contract are refused, integer
maps write a sentinel (never a plausible number) for "no value", heartbeats of any width
wrap, a float PLC heartbeat may be NaN, a reply read after its deadline is no good reply.
"""

from __future__ import annotations

import dataclasses
import math
import struct
import time
import types

import numpy as np
import pytest

from drivers.base import ChannelStatus, Inputs, Outputs
from drivers.modbus_tcp import MBAP, ModbusTcpDriver
from gateway.core.config import Config, load_config
from gateway.core.registermap import RegisterField
from gateway.errors import ConfigError, DriverTimeoutError
from gateway.service.daemon import build_driver
from tests.modbus_helpers import FakeServer, config_for, fc3_reply


def _with_map(cfg: Config | None = None, **fields: RegisterField) -> Config:
    cfg = cfg or load_config()
    regs = dataclasses.replace(cfg.bus.modbus_tcp.registers, **fields)
    mb = dataclasses.replace(cfg.bus.modbus_tcp, registers=regs)
    return dataclasses.replace(cfg, bus=dataclasses.replace(cfg.bus, modbus_tcp=mb))


def _written(drv: ModbusTcpDriver, field: RegisterField) -> np.ndarray:
    """The values ``field`` holds in the driver's request data (after ``_encode``)."""
    start = 2 * (field.address - drv.layout.write_span.start)
    code = {"int16": "h", "uint16": "H", "int32": "i", "uint32": "I", "float32": "f"}[field.type]
    raw = bytes(drv._wdata[start : start + 2 * field.words])
    return np.array(struct.unpack(f">{field.count}{code}", raw))


def test_int16_tensions_at_a_scale_that_clips_the_sensor_range_are_refused():
    """Int16 at scale 0.01 tops out at 327.67 N: 400 N was written as
    327.67 N with status 0. Refused at check and start, naming the key."""
    cfg = _with_map(corrected_tensions=RegisterField(100, 8, "int16", scale=0.01))
    with pytest.raises(ConfigError, match=r"registers\.corrected_tensions: .*500"):
        build_driver(cfg)


def test_integer_tensions_write_a_sentinel_for_no_value():
    """Int16 at scale 0.1: an invalid channel (and the stopped frame) was
    written as 0.0 N, a plausible value. Now the map's sentinel (-32768 by default)."""
    field = RegisterField(100, 8, "int16", scale=0.1)
    drv = build_driver(_with_map(corrected_tensions=field))
    assert isinstance(drv, ModbusTcpDriver)
    out = Outputs.allocate(8)
    out.tension_corrected_n[:] = np.linspace(10.0, 480.0, 8)
    out.tension_corrected_n[3] = math.nan
    out.channel_status[:] = int(ChannelStatus.GOOD)
    out.channel_status[3] = int(ChannelStatus.INVALID)
    drv._encode(out)
    raw = _written(drv, field)
    assert raw[3] == -32768
    good = np.delete(out.tension_corrected_n, 3)
    np.testing.assert_array_equal(np.delete(raw, 3), np.rint(good / 0.1))


def test_the_integer_sentinel_is_configurable_but_never_plausible():
    ok = RegisterField(100, 8, "int16", scale=0.1, invalid=32767)
    drv = build_driver(_with_map(corrected_tensions=ok))
    out = Outputs.allocate(8)
    out.tension_corrected_n[:] = math.nan
    drv._encode(out)
    assert np.all(_written(drv, ok) == 32767)
    plausible = RegisterField(100, 8, "int16", scale=0.1, invalid=-100)  # -10 N: noise at 0
    with pytest.raises(ConfigError, match=r"corrected_tensions.*invalid"):
        build_driver(_with_map(corrected_tensions=plausible))


def test_canopen_refuses_a_sensor_range_its_pdo_cannot_carry():
    """Range_n 1000 N over CANopen: 800 N went out as 655.32 N (the PDO's
    clamp) with status 0. Refused, naming sensor.range_n."""
    cfg = load_config()
    cfg = dataclasses.replace(
        cfg,
        sensor=dataclasses.replace(cfg.sensor, range_n=1000.0),
        bus=dataclasses.replace(cfg.bus, driver="canopen"),
    )
    with pytest.raises(ConfigError, match=r"sensor\.range_n: .*655"):
        build_driver(cfg)


@pytest.mark.parametrize(
    ("type_", "expect"),
    [
        ("int16", [32766, 32767, -32768, -32767, -1, 0, 1]),
        ("uint16", [32766, 32767, 32768, 32769, 65535, 0, 1]),
        ("int32", [32766, 32767, 32768, 32769, 65535, 65536, 65537]),
    ],
)
def test_gateway_heartbeat_wraps_modulo_its_register(type_: str, expect: list[int]):
    """An int16 gateway heartbeat stuck at 32767 for half of every 65 s."""
    field = RegisterField(124, 1, type_)  # type: ignore[arg-type]
    regs = {"gateway_heartbeat": field}
    if type_ == "int32":  # two registers: move the state out of its way
        regs["gateway_state"] = RegisterField(138, 1)
    drv = build_driver(_with_map(**regs))
    out = Outputs.allocate(8)
    seen = []
    for hb in (32766, 32767, 32768, 32769, 65535, 65536, 65537):
        out.gateway_heartbeat = hb
        drv._encode(out)
        seen.append(int(_written(drv, field)[0]))
    assert seen == expect


def test_a_float_plc_heartbeat_may_be_nan():
    """A float32 PLC heartbeat carrying NaN: ``int(NaN)`` ended the gateway."""
    field = RegisterField(55, 1, "float32")  # 53..54: the platform mass
    drv = build_driver(_with_map(plc_heartbeat=field))
    assert isinstance(drv, ModbusTcpDriver)
    at = MBAP + 2 + 2 * (field.address - drv.layout.read_span.start)
    drv._rx[at : at + 4] = struct.pack(">f", math.nan)
    inputs = Inputs.allocate(8)
    drv._decode(inputs)
    assert math.isnan(inputs.plc_heartbeat)


def test_a_reply_read_after_its_deadline_is_a_timeout():
    """The receive path checked its deadline only before receiving, so a
    reply read 2 s late (the gateway stopped inside recv) was decoded as fresh data."""

    def reply(frame: bytes, k: int):
        return [(0.0, fc3_reply(frame, regs={52: k + 1}))]

    with FakeServer(reply) as server:
        drv = ModbusTcpDriver(config_for(server.port, timeout_s=0.5))
        drv.open()
        inputs = Inputs.allocate(8)
        drv.read_into(inputs)  # on time
        offset = {"s": 0.0}
        clock = types.SimpleNamespace(
            perf_counter=lambda: time.perf_counter() + offset["s"], monotonic=time.monotonic
        )
        recv_more = drv._recv_more

        def late(sock, deadline):
            recv_more(sock, deadline)
            offset["s"] = 2.0  # the recv returned 2 s after it began

        drv._recv_more = late  # type: ignore[method-assign]
        original = ModbusTcpDriver.__module__
        import drivers.modbus_tcp as mod

        real_time = mod.time
        mod.time = clock  # type: ignore[assignment]
        try:
            with pytest.raises(DriverTimeoutError, match="after its deadline"):
                drv.read_into(inputs)
        finally:
            mod.time = real_time
            drv.close()
        assert original == "drivers.modbus_tcp"


def test_a_frame_held_up_after_encoding_is_gated_again_before_it_leaves():
    """The driver re-checks right before sending: a frame encoded, then held up (this
    process stopped between the gate and the send), goes out invalid."""

    def reply(frame: bytes, k: int):
        return [(0.0, fc3_reply(frame, regs={52: k + 1}))]

    with FakeServer(reply) as server:
        drv = ModbusTcpDriver(config_for(server.port, timeout_s=0.5))
        drv.open()
        offset = {"s": 0.0}
        drv.clock = lambda: time.monotonic() + offset["s"]  # type: ignore[method-assign]
        encode = drv._encode

        def encode_then_stall(outputs):
            encode(outputs)
            offset["s"] += 0.05  # held up for 50 ms after encoding

        drv._encode = encode_then_stall  # type: ignore[method-assign]
        out = Outputs.allocate(8)
        out.tension_corrected_n[:] = 200.0
        out.channel_status[:] = int(ChannelStatus.GOOD)
        now = drv.clock()
        drv.exchange(out.stamp(now, now), Inputs.allocate(8))
        drv.close()
    request = server.requests[-1]
    assert request[7] == 23
    data = request[7 + 10 :]  # after function, addresses, counts, byte count
    tension = struct.unpack(">8f", data[:32])
    status = struct.unpack(">8H", data[32:48])
    assert all(math.isnan(x) for x in tension) and set(status) == {2}
    assert drv.gated[list(drv.GATE_REASONS).index("age")] == 8
