"""One contract every fieldbus driver keeps (the house style: python-can's back2back tests).

:class:`DriverContract` holds the tests; each driver joins with one subclass naming its
harness factory from ``tests/driver_contract_helpers.HARNESSES``.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from drivers.base import (
    ChannelStatus,
    Driver,
    DriverState,
    GatewayState,
    Inputs,
    Outputs,
    driver_class,
)
from gateway.errors import DriverError, DriverInitError
from tests.driver_contract_helpers import HARNESSES, DriverHarness
from tests.loop_helpers import fresh

pytestmark = pytest.mark.loopback

MAX_FAILING_CALLS = 50  # a broken link must raise within this many calls
NEWTONS_PER_COUNT = 500.0 / 27648
# the one S7 reading (drivers/s7.py): the window -4864..32511 is a number, the rest NaN
S7_CASES = {
    0: 0.0,
    27648: 500.0,
    32511: 32511 * NEWTONS_PER_COUNT,  # top of the overrange
    -4864: -4864 * NEWTONS_PER_COUNT,  # bottom of the underrange
    32767: math.nan,  # overflow
    -32768: math.nan,  # underflow
    32600: math.nan,  # no S7 module sends this: not a measurement
    -5000: math.nan,
}


def _outputs(m: int) -> Outputs:
    out = Outputs.allocate(m)
    out.tension_corrected_n[:] = 150.0 + 2.5 * np.arange(m)
    out.channel_status[:] = [int(ChannelStatus(k % 3)) for k in range(m)]
    out.wrench[:] = (1.0, -2.0, 490.5, 0.25, -0.125, 0.5)
    out.gateway_heartbeat = 321
    out.gateway_state = int(GatewayState.ACTIVE)
    return out


def _fail_io(d: Driver, inputs: Inputs, out: Outputs) -> DriverError:
    """Cycle until the broken link raises; return the error (a DriverError)."""
    for _ in range(MAX_FAILING_CALLS):
        try:
            d.read_into(inputs)
            d.write_from(fresh(out, d))
        except DriverError as exc:
            return exc
    raise AssertionError(f"{d.name}: no DriverError in {MAX_FAILING_CALLS} cycles")


class DriverContract:
    """The contract; subclasses set ``driver_name`` (a key of ``HARNESSES``)."""

    driver_name = ""

    @pytest.fixture
    def harness(self) -> Iterator[DriverHarness]:
        with HARNESSES[self.driver_name]() as h:
            try:
                yield h
            finally:
                h.driver.close()

    def test_declares_the_contract(self, harness: DriverHarness) -> None:
        d = harness.driver
        assert d.name == self.driver_name
        assert isinstance(d.paced_by_bus, bool)
        assert isinstance(d.combines_write_and_read, bool)
        assert (d.syncs, d.reconnects, d.reconnect_attempts, d.dropped_replies) == (0, 0, 0, 0)
        assert d.last_sync_timestamp == 0.0
        assert 0 < d.backoff.min_s <= d.backoff.max_s

    def test_open_close_twice_and_reopen(self, harness: DriverHarness) -> None:
        d = harness.driver
        assert d.state is DriverState.UNCONFIGURED
        d.open()
        assert d.connected
        d.close()
        d.close()
        assert d.state is DriverState.UNCONFIGURED
        d.open()  # a closed driver can be opened again
        d.read_into(Inputs.allocate(d.cables))
        assert d.reconnects == 1
        d.close()

    def test_context_manager(self, harness: DriverHarness) -> None:
        with harness.driver as d:
            assert d is harness.driver
            assert d.state is DriverState.CONNECTED
        assert d.state is DriverState.UNCONFIGURED

    def test_read_into_fills_inputs(self, harness: DriverHarness) -> None:
        img = harness.image
        with img.lock:
            img.raw_counts[:] = np.arange(img.cables) * 2000 + 500
            img.raw_counts[-1] = 32767  # overflow code -> NaN
            img.plc_heartbeat = 4711
        harness.propagate()
        with harness.driver as d:
            inputs = Inputs.allocate(d.cables)
            inputs.tension_raw_n[:] = -1.0
            d.read_into(inputs)
        expect = img.raw_counts.astype(float) * NEWTONS_PER_COUNT
        expect[-1] = np.nan
        assert_allclose(inputs.tension_raw_n, expect, rtol=1e-9)
        assert inputs.plc_heartbeat == 4711
        assert inputs.read_time_s > 0
        assert d.roundtrip_s.count >= 1

    def test_one_s7_reading(self, harness: DriverHarness) -> None:
        """Every driver decodes the same counts to the same newtons (or NaN)."""
        img = harness.image
        cases = list(S7_CASES.items())[: img.cables]
        with img.lock:
            img.raw_counts[: len(cases)] = [c for c, _ in cases]
        harness.propagate()
        with harness.driver as d:
            inputs = Inputs.allocate(d.cables)
            d.read_into(inputs)
        assert_allclose(inputs.tension_raw_n[: len(cases)], [n for _, n in cases], rtol=1e-9)

    def test_write_from_lands_at_the_plc(self, harness: DriverHarness) -> None:
        img = harness.image
        with harness.driver as d:
            out = _outputs(d.cables)
            d.write_from(fresh(out, d))
            assert d.state is DriverState.ACTIVE
            harness.propagate()
            with img.lock:
                assert_allclose(img.corrected_n, out.tension_corrected_n, rtol=1e-6)
                assert_array_equal(img.channel_status, out.channel_status)
                assert img.gateway_heartbeat == 321
                assert img.gateway_state == int(GatewayState.ACTIVE)

    def test_exchange_writes_and_reads(self, harness: DriverHarness) -> None:
        img = harness.image
        with img.lock:
            img.plc_heartbeat = 999
        harness.propagate()
        with harness.driver as d:
            out, inputs = _outputs(d.cables), Inputs.allocate(d.cables)
            d.exchange(fresh(out, d), inputs)
            assert inputs.plc_heartbeat == 999
            assert d.state is DriverState.ACTIVE
            harness.propagate()
            with img.lock:
                assert img.gateway_heartbeat == 321
                assert_allclose(img.corrected_n, out.tension_corrected_n, rtol=1e-6)
            d.exchange(None, inputs)  # nothing to write: a read
            assert inputs.plc_heartbeat == 999

    def test_state_transitions(self, harness: DriverHarness) -> None:
        d = harness.driver
        inputs, out = Inputs.allocate(d.cables), _outputs(d.cables)
        assert d.state is DriverState.UNCONFIGURED
        d.open()
        assert d.state is DriverState.CONNECTED
        d.read_into(inputs)
        assert d.state is DriverState.CONNECTED
        d.write_from(fresh(out, d))
        assert d.state is DriverState.ACTIVE
        harness.stop()
        _fail_io(d, inputs, out)
        assert d.state is DriverState.FAULT
        assert not d.connected
        d.close()
        assert d.state is DriverState.UNCONFIGURED

    def test_errors_are_driver_errors(self, harness: DriverHarness) -> None:
        d = harness.driver
        d.open()
        harness.stop()
        err = _fail_io(d, Inputs.allocate(d.cables), _outputs(d.cables))
        assert isinstance(err, DriverError)
        assert d.name in str(err)

    def test_backoff_is_reset_only_by_a_good_reply(self, harness: DriverHarness) -> None:
        d = harness.driver
        d.open()
        d.close()
        d.open()  # two attempts and no data yet: the interval has grown
        assert d.backoff.interval_s == pytest.approx(min(4 * d.backoff.min_s, d.backoff.max_s))
        assert not d.ready_to_connect(d.backoff.next_at - 1e-3)
        d.read_into(Inputs.allocate(d.cables))
        assert d.backoff.interval_s == d.backoff.min_s
        assert d.ready_to_connect(0.0)
        assert d.poll_connect(0.0)  # connected: nothing to do


class TestModbusTcpContract(DriverContract):
    driver_name = "modbus_tcp"


class TestCanopenContract(DriverContract):
    driver_name = "canopen"


class TestVirtualContract(DriverContract):
    driver_name = "virtual"


def test_every_registered_driver_runs_the_contract() -> None:
    from drivers.base import DRIVERS

    enrolled = {c.driver_name for c in DriverContract.__subclasses__()}
    assert enrolled == set(DRIVERS) == set(HARNESSES)


def test_unknown_driver_name_is_an_init_error() -> None:
    with pytest.raises(DriverInitError, match="unknown driver 'nope'"):
        driver_class("nope")
