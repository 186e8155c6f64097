"""CANopen on python-can's virtual bus in one process: EDS files, PDO round trips between
the soft PLC's nodes and the gateway driver, timeouts and recovery."""

from __future__ import annotations

import math

import numpy as np
import pytest

import drivers.canopen as co
import drivers.canopen_pdo as pdo
from drivers.base import ChannelStatus, DriverState, make_driver
from drivers.s7 import S7Analog
from gateway.errors import DriverInitError, DriverTimeoutError
from tests.canopen_helpers import CanopenRig, canopen_config, fill_image, rig  # noqa: F401
from tests.loop_helpers import fresh

EDS_FILES = {
    "config/analog_in_401.eds": 0x10,
    "config/gateway.eds": 0x20,
    "config/plc_master.eds": co.PLC_NODE_ID,
}


@pytest.mark.parametrize("path", sorted(EDS_FILES))
def test_eds_loads_with_byte_aligned_pdos(path: str) -> None:
    tpdos, rpdos = pdo.load_pdo_layouts(path, EDS_FILES[path])
    assert tpdos, f"{path}: no TPDO"
    for layout in [*tpdos.values(), *rpdos.values()]:
        assert 1 <= layout.codec.size <= 8


def test_analog_module_is_cia401() -> None:
    import canopen

    od = canopen.import_od(str(pdo.resolve_path("config/analog_in_401.eds")), 0x10)
    assert od[0x1000].default & 0xFFFF == 401
    assert [od[0x6401][s].data_type for s in range(1, 9)] == [
        canopen.objectdictionary.INTEGER16
    ] * 8
    tpdos, _ = pdo.load_pdo_layouts("config/analog_in_401.eds", 0x10)
    assert [(t.cob_id, t.trans_type) for t in tpdos.values()] == [(0x190, 1), (0x290, 1)]
    assert tpdos[1].entries == tuple((0x6401, s) for s in range(1, 5))
    assert tpdos[2].entries == tuple((0x6401, s) for s in range(5, 9))


def test_producers_and_consumers_agree() -> None:
    """Every TPDO of the master and the gateway is consumed by an RPDO with the same
    COB-ID and the same mapping; the analog TPDOs match the gateway's RPDO1/2 formats."""
    gw_tx, gw_rx = pdo.load_pdo_layouts("config/gateway.eds", 0x20)
    plc_tx, plc_rx = pdo.load_pdo_layouts("config/plc_master.eds", co.PLC_NODE_ID)
    analog_tx, _ = pdo.load_pdo_layouts("config/analog_in_401.eds", 0x10)
    consumers = {lay.cob_id: lay for lay in [*gw_rx.values(), *plc_rx.values()]}
    for producer in [*gw_tx.values(), *plc_tx.values()]:
        consumer = consumers[producer.cob_id]
        assert consumer.entries == producer.entries
        assert consumer.codec.format == producer.codec.format
    for n in (1, 2):
        assert gw_rx[n].cob_id == analog_tx[n].cob_id
        assert gw_rx[n].codec.format == analog_tx[n].codec.format


def test_scaling_round_trip_within_resolution() -> None:
    for value in (-655.0, -1.234, 0.0, 0.01, 123.456, 655.3):
        assert abs(pdo.decode_tension(pdo.encode_tension(value)) - value) <= 0.01 + 1e-12
    assert math.isnan(pdo.decode_tension(pdo.encode_tension(math.nan)))
    assert pdo.decode_tension(pdo.encode_tension(1e6)) == pytest.approx(655.32)
    assert pdo.to_int16(1.0, pdo.VELOCITY_M_S_PER_COUNT) == 32767  # clamped
    status = np.array([0, 1, 2, 0, 2, 2, 1, 0], dtype=np.uint16)
    out = np.zeros(8, dtype=np.uint16)
    pdo.unpack_status(pdo.pack_status(status), out)
    np.testing.assert_array_equal(out, status)
    analog = S7Analog(500.0)  # the one S7 codec the driver decodes with
    assert math.isnan(analog.decode_count(32767))
    assert math.isnan(analog.decode_count(-32768))
    assert analog.decode_count(27648) == pytest.approx(500.0)


def test_registered_by_name() -> None:
    driver = make_driver(canopen_config())
    assert isinstance(driver, co.CanopenDriver)


def test_stepped_cycles_deliver_the_image(rig: CanopenRig) -> None:  # noqa: F811
    fill_image(rig.image, seed=3)
    syncs = rig.driver.syncs
    for _ in range(co.SLOW_PERIOD_CYCLES):  # all slow PDOs go out once per 10 cycles
        rig.cycle()
    img, inp = rig.image, rig.inputs
    k = rig.cfg.sensor.range_n / rig.cfg.sensor.adc_full_scale
    np.testing.assert_allclose(inp.tension_raw_n, img.raw_counts * k, rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        inp.velocity_m_s, img.velocity_m_s, rtol=0, atol=pdo.VELOCITY_M_S_PER_COUNT / 2 + 1e-15
    )
    np.testing.assert_allclose(
        inp.length_m, img.length_m, rtol=0, atol=pdo.LENGTH_M_PER_COUNT / 2 + 1e-12
    )
    np.testing.assert_allclose(
        inp.pose, img.pose, rtol=0, atol=pdo.POSITION_M_PER_COUNT / 2 + 1e-12
    )
    assert inp.plc_heartbeat == img.plc_heartbeat
    assert rig.driver.syncs == syncs + co.SLOW_PERIOD_CYCLES


def test_new_values_arrive_in_the_next_cycle(rig: CanopenRig) -> None:  # noqa: F811
    for cycle in range(5):
        with rig.image.lock:
            rig.image.raw_counts[:] = np.arange(8) * 1000 + cycle
            rig.image.raw_counts[cycle] = 32767  # overflow code
        rig.cycle()
        assert math.isnan(rig.inputs.tension_raw_n[cycle])
        ok = np.arange(8) != cycle
        expected = (np.arange(8) * 1000 + cycle) * 500.0 / 27648
        np.testing.assert_allclose(rig.inputs.tension_raw_n[ok], expected[ok], atol=1e-12)


def test_driver_writes_land_in_the_image(rig: CanopenRig) -> None:  # noqa: F811
    out = rig.outputs
    out.tension_corrected_n[:] = [10.0, 250.5, 499.99, 0.0, -3.0, 600.0, math.nan, 77.7]
    out.channel_status[:] = [0, 0, 1, 0, 0, 0, 2, 1]
    out.gateway_heartbeat = 0x1234
    out.gateway_state = 2
    rig.cycle()
    rig.driver.write_from(fresh(out, rig.driver))
    assert rig.driver.state is DriverState.ACTIVE
    assert rig.plc.poll() == 3
    img = rig.image
    np.testing.assert_allclose(
        img.corrected_n, out.tension_corrected_n, atol=pdo.TENSION_N_PER_COUNT / 2 + 1e-9
    )
    assert math.isnan(img.corrected_n[6])
    np.testing.assert_array_equal(img.channel_status, out.channel_status)
    assert (img.gateway_heartbeat, img.gateway_state, img.gateway_writes) == (0x1234, 2, 1)
    assert img.channel_status[6] == ChannelStatus.INVALID


def test_missing_sync_times_out_then_recovers(rig: CanopenRig) -> None:  # noqa: F811
    rig.cycle()
    with pytest.raises(DriverTimeoutError, match="no SYNC"):
        rig.driver.read_into(rig.inputs)  # nothing sent: no SYNC
    assert rig.driver.state is DriverState.FAULT
    rig.plc.sync_enabled = False
    rig.plc.step()
    with pytest.raises(DriverTimeoutError, match="no SYNC"):
        rig.driver.read_into(rig.inputs)
    rig.plc.sync_enabled = True
    with rig.image.lock:
        rig.image.raw_counts[:] = 1234
    rig.cycle()
    np.testing.assert_allclose(rig.inputs.tension_raw_n, 1234 * 500.0 / 27648)


def test_silent_analog_module_times_out_then_recovers(rig: CanopenRig) -> None:  # noqa: F811
    rig.cycle()
    assert rig.plc.analog is not None
    rig.plc.analog.enabled = False
    rig.plc.step()
    with pytest.raises(DriverTimeoutError, match="0x190, 0x290"):
        rig.driver.read_into(rig.inputs)
    rig.plc.analog.enabled = True
    with rig.image.lock:
        rig.image.raw_counts[:] = 2000
    rig.cycle()
    np.testing.assert_allclose(rig.inputs.tension_raw_n, 2000 * 500.0 / 27648)


def test_a_late_reader_gets_the_newest_set(rig: CanopenRig) -> None:  # noqa: F811
    for value in (100, 200, 300):
        with rig.image.lock:
            rig.image.raw_counts[:] = value
        rig.plc.step()
    rig.driver.read_into(rig.inputs)
    np.testing.assert_allclose(rig.inputs.tension_raw_n, 300 * 500.0 / 27648)
    with pytest.raises(DriverTimeoutError):  # that set was consumed; no new SYNC
        rig.driver.read_into(rig.inputs)


def test_short_frame_is_an_io_error(rig: CanopenRig) -> None:  # noqa: F811
    import can

    from gateway.errors import DriverIOError

    bus = can.Bus(interface="virtual", channel=rig.cfg.bus.canopen.channel)
    try:
        bus.send(can.Message(arbitration_id=0x190, data=b"\x01\x02", is_extended_id=False))
        with pytest.raises(DriverIOError, match="0x190: 2 data bytes"):
            rig.driver.read_into(rig.inputs)
    finally:
        bus.shutdown()


def test_close_twice_and_bad_eds(tmp_path) -> None:
    cfg = canopen_config()
    driver = co.CanopenDriver(cfg)
    driver.open()  # creates its own virtual bus from the config
    driver.close()
    driver.close()
    bad = tmp_path / "bad.eds"
    bad.write_text("[1000]\nParameterName=x\nObjectType=0x7\nDataType=0x9999\n")
    import dataclasses

    can_cfg = dataclasses.replace(cfg.bus.canopen, gateway_eds=str(bad))
    cfg2 = dataclasses.replace(cfg, bus=dataclasses.replace(cfg.bus, canopen=can_cfg))
    with pytest.raises(DriverInitError, match=r"bad\.eds: cannot load EDS"):
        co.CanopenDriver(cfg2).open()


def test_real_time_thread_serves_the_driver(rig: CanopenRig) -> None:  # noqa: F811
    """The PLC's own 1 kHz thread against a reading/writing gateway thread (this one)."""
    rig.plc.start(realtime=True)
    with rig.image.lock:
        rig.image.raw_counts[:] = np.arange(8) * 100
    good = 0
    for _ in range(2000):  # bounded; a loaded machine may time a few reads out
        try:
            rig.driver.read_into(rig.inputs)
        except DriverTimeoutError:
            continue
        rig.outputs.gateway_heartbeat = good
        rig.driver.write_from(fresh(rig.outputs, rig.driver))
        good += 1
        if good == 50:
            break
    assert good == 50
    np.testing.assert_allclose(rig.inputs.tension_raw_n, np.arange(8) * 100 * 500.0 / 27648)
    rig.plc.stop()  # joins the thread, which took the gateway's PDOs in before each SYNC
    rig.plc.stop()
    assert rig.image.gateway_writes >= 40
    assert rig.plc.cycles >= 50
