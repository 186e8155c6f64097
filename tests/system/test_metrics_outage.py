"""A gauge of an invalid channel carries no value: the PLC is killed, and at
every scrape from then on each cable whose status is 2 (invalid) has NaN tension gauges.

NaN rather than an absent series (Prometheus' instrumentation guide, "avoid missing
metrics": a series that comes and goes breaks ``rate``, ``for:`` clauses and dashboards;
NaN where a number would mislead). The registers hold NaN for such a channel too."""

from __future__ import annotations

import math
import time

import pytest

from tests.reliability_helpers import GatewayRig, wait_for

pytestmark = [pytest.mark.loopback]

PER_CABLE = (
    "cdpr_gateway_tension_corrected_newtons",
    "cdpr_gateway_tension_raw_newtons",
    "cdpr_gateway_friction_newtons",
)


def scrape(rig: GatewayRig) -> dict[tuple[str, str], float]:
    """One collection of the registry: (name, cable) -> value."""
    out = {}
    for family in rig.registry.collect():
        for s in family.samples:
            if "cable" in s.labels:
                out[(s.name, s.labels["cable"])] = s.value
    return out


def test_killing_the_plc_turns_every_invalid_channels_tensions_nan() -> None:
    with GatewayRig(seed=3) as rig:
        rig.warm_up()
        cables = [str(i + 1) for i in range(rig.cfg.cables)]
        before = scrape(rig)
        assert all(math.isfinite(before[(n, c)]) for n in PER_CABLE for c in cables), before
        rig.server.stop()  # the PLC is gone: reads fail, channels go stale then invalid
        invalid_seen: set[str] = set()
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and invalid_seen != set(cables):
            now = scrape(rig)
            for c in cables:
                if now[("cdpr_gateway_channel_status", c)] == 2:
                    invalid_seen.add(c)
                    values = {n: now[(n, c)] for n in PER_CABLE}
                    assert all(math.isnan(v) for v in values.values()), (c, values)
            time.sleep(0.01)
        assert invalid_seen == set(cables)
        assert wait_for(lambda: rig.metric("cdpr_gateway_connected", bus="modbus_tcp") == 0, 5)
        later = scrape(rig)  # long after: still no flat line of the last good value
        assert all(math.isnan(later[(n, c)]) for n in PER_CABLE for c in cables), later
