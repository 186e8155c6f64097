"""One contract every fieldbus driver keeps (style.md: python-can's back2back tests).

Drivers join by adding a harness to ``tests/driver_contract_helpers.HARNESSES``.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from drivers.base import (
    ChannelStatus,
    DriverState,
    GatewayState,
    Inputs,
    Outputs,
    driver_class,
)
from gateway.errors import DriverError, DriverInitError
from tests.driver_contract_helpers import HARNESSES, DriverHarness

pytestmark = pytest.mark.loopback

MAX_FAILING_CALLS = 50  # a broken link must raise within this many calls


@pytest.fixture(params=sorted(HARNESSES))
def harness(request: pytest.FixtureRequest) -> Iterator[DriverHarness]:
    with HARNESSES[request.param]() as h:
        try:
            yield h
        finally:
            h.driver.close()


def _outputs(m: int) -> Outputs:
    out = Outputs.allocate(m)
    out.tension_corrected_n[:] = 150.0 + 2.5 * np.arange(m)
    out.channel_status[:] = [int(ChannelStatus(k % 3)) for k in range(m)]
    out.wrench[:] = (1.0, -2.0, 490.5, 0.25, -0.125, 0.5)
    out.gateway_heartbeat = 321
    out.gateway_state = int(GatewayState.ACTIVE)
    return out


class TestDriverContract:
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
        expect = img.raw_counts.astype(float) * 500.0 / 27648
        expect[-1] = np.nan
        assert_allclose(inputs.tension_raw_n, expect, rtol=1e-9)
        assert inputs.plc_heartbeat == 4711
        assert inputs.read_time_s > 0
        assert d.roundtrip_s.count >= 1

    def test_write_from_lands_at_the_plc(self, harness: DriverHarness) -> None:
        img = harness.image
        with harness.driver as d:
            out = _outputs(d.cables)
            d.write_from(out)
            d.flush()
            harness.propagate()
            with img.lock:
                assert_allclose(img.corrected_n, out.tension_corrected_n, rtol=1e-6)
                assert_array_equal(img.channel_status, out.channel_status)
                assert img.gateway_heartbeat == 321
                assert img.gateway_state == int(GatewayState.ACTIVE)

    def test_state_transitions(self, harness: DriverHarness) -> None:
        d = harness.driver
        inputs, out = Inputs.allocate(d.cables), _outputs(d.cables)
        assert d.state is DriverState.UNCONFIGURED
        d.open()
        assert d.state is DriverState.CONNECTED
        d.read_into(inputs)
        assert d.state is DriverState.CONNECTED
        d.write_from(out)
        assert d.state is DriverState.ACTIVE
        d.flush()
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


def _fail_io(d, inputs: Inputs, out: Outputs) -> DriverError:
    """Cycle until the broken link raises; return the error (a DriverError)."""
    for _ in range(MAX_FAILING_CALLS):
        try:
            d.read_into(inputs)
            d.write_from(out)
            d.flush()
        except DriverError as exc:
            return exc
    raise AssertionError(f"{d.name}: no DriverError in {MAX_FAILING_CALLS} cycles")


def test_unknown_driver_name_is_an_init_error() -> None:
    with pytest.raises(DriverInitError, match="unknown driver 'nope'"):
        driver_class("nope")
