"""The collector yields exactly the metric names, types and labels of docs/metrics.md."""

from __future__ import annotations

import urllib.request

import numpy as np
import pytest

from drivers.virtual import VirtualDriver, VirtualFaults
from gateway import __version__
from gateway.core.config import MetricsConfig
from gateway.errors import ConfigError, TemporaryError
from gateway.runtime.loop import CyclicService
from gateway.service.exporter import MetricsServer
from gateway.service.metrics import make_registry
from tests.loop_helpers import FakeClock, config, live_image
from tests.tls_helpers import self_signed

# docs/metrics.md's table: name -> (type, labels)
DESIGN_TABLE = {
    "cdpr_gateway_cycle_seconds": ("histogram", set()),
    "cdpr_gateway_jitter_seconds": ("histogram", set()),
    "cdpr_gateway_overruns": ("counter", set()),
    "cdpr_gateway_record_dropped": ("counter", set()),  # gateway.service.recorder
    "cdpr_gateway_bus_roundtrip_seconds": ("histogram", {"bus"}),
    "cdpr_gateway_errors": ("counter", {"kind"}),
    "cdpr_gateway_gated": ("counter", {"reason"}),  # the output gate (drivers/gate.py)
    "cdpr_gateway_reconnects": ("counter", {"bus"}),
    "cdpr_gateway_connected": ("gauge", {"bus"}),
    "cdpr_gateway_tension_raw_newtons": ("gauge", {"cable"}),
    "cdpr_gateway_tension_corrected_newtons": ("gauge", {"cable"}),
    "cdpr_gateway_friction_newtons": ("gauge", {"cable"}),
    "cdpr_gateway_channel_status": ("gauge", {"cable"}),
    "cdpr_gateway_build_info": ("gauge", {"version", "bus"}),
    # the operator's view
    "cdpr_gateway_state": ("gauge", set()),
    "cdpr_gateway_plc_heartbeat_age_seconds": ("gauge", set()),
    "cdpr_gateway_sample_age_seconds": ("gauge", set()),
}


def ran_service(cycles: int = 100, faults: VirtualFaults | None = None) -> CyclicService:
    cfg = config(busy_wait_s=0.0)
    clock = FakeClock()
    drv = VirtualDriver(cfg, image=live_image(cfg), faults=faults)
    svc = CyclicService(cfg, drv, clock=clock, sleep=clock.sleep, history=1024)
    svc.run(cycles=cycles)
    return svc


def label_names(metric) -> set[str]:
    names: set[str] = set()
    for s in metric.samples:
        names |= set(s.labels) - {"le"}
    return names


def test_names_types_and_labels_are_exactly_the_design_table():
    registry = make_registry(ran_service())
    found = {m.name: (m.type, label_names(m)) for m in registry.collect()}
    assert {k: v for k, v in found.items() if k.startswith("cdpr_")} == DESIGN_TABLE
    assert {k for k in found if not k.startswith("cdpr_")} == PROCESS_METRICS


# the process collector (docs/realtime.md watches process_resident_memory_bytes)
PROCESS_METRICS = {
    "process_virtual_memory_bytes",
    "process_resident_memory_bytes",
    "process_start_time_seconds",
    "process_cpu_seconds",
    "process_open_fds",
    "process_max_fds",
}


def test_process_metrics_are_this_process():
    import resource

    registry = make_registry(ran_service(5))
    rss = registry.get_sample_value("process_resident_memory_bytes")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    assert rss is not None and 10e6 < rss <= peak * 1.01
    assert registry.get_sample_value("process_open_fds") >= 3


def test_values_come_from_the_loop_statistics():
    svc = ran_service(120, VirtualFaults(drop_on_read=50))
    reg = make_registry(svc)
    # 120 wake-ups: 3 failed reads and 1 reconnect are not cycles of the service (no data)
    assert svc.stats.cycles == 120
    assert reg.get_sample_value("cdpr_gateway_cycle_seconds_count") == 116
    assert reg.get_sample_value("cdpr_gateway_jitter_seconds_count") == 116
    assert reg.get_sample_value(
        "cdpr_gateway_cycle_seconds_bucket", {"le": "+Inf"}
    ) == pytest.approx(116)
    assert reg.get_sample_value("cdpr_gateway_cycle_seconds_bucket", {"le": "5e-05"}) == 116
    assert reg.get_sample_value("cdpr_gateway_overruns_total") == 0
    assert reg.get_sample_value("cdpr_gateway_errors_total", {"kind": "io"}) == 3
    assert reg.get_sample_value("cdpr_gateway_errors_total", {"kind": "timeout"}) == 0
    assert reg.get_sample_value("cdpr_gateway_reconnects_total", {"bus": "virtual"}) == 1
    assert (
        reg.get_sample_value("cdpr_gateway_bus_roundtrip_seconds_count", {"bus": "virtual"})
        == svc.driver.roundtrip_s.count
    )
    assert reg.get_sample_value("cdpr_gateway_connected", {"bus": "virtual"}) == 0  # closed
    assert (
        reg.get_sample_value("cdpr_gateway_build_info", {"version": __version__, "bus": "virtual"})
        == 1
    )


def test_per_cable_gauges():
    svc = ran_service()
    reg = make_registry(svc)
    for i in range(8):
        cable = {"cable": str(i + 1)}
        raw = reg.get_sample_value("cdpr_gateway_tension_raw_newtons", cable)
        corrected = reg.get_sample_value("cdpr_gateway_tension_corrected_newtons", cable)
        friction = reg.get_sample_value("cdpr_gateway_friction_newtons", cable)
        assert raw == pytest.approx(200.0, abs=0.02)
        assert corrected == svc.comp.corrected_n[i]
        assert friction == pytest.approx(corrected - raw)
        assert reg.get_sample_value("cdpr_gateway_channel_status", cable) == 0
    assert np.all(svc.comp.corrected_n > svc.comp.raw_n)


def test_http_exporter_serves_on_loopback_and_reports_a_busy_port():
    reg = make_registry(ran_service(10))
    server = MetricsServer(MetricsConfig(host="127.0.0.1", port=0), reg)
    try:
        assert server.port > 0
        url = f"http://127.0.0.1:{server.port}/metrics"
        with urllib.request.urlopen(url, timeout=5) as reply:
            body = reply.read().decode()
        assert 'cdpr_gateway_cycle_seconds_bucket{le="+Inf"} 10.0' in body
        assert "cdpr_gateway_tension_corrected_newtons" in body
        # a busy port may free up: a temporary error (exit 75), not a config error (exit 2)
        with pytest.raises(TemporaryError, match=r"x\.yaml: metrics\.port: .*in use"):
            MetricsServer(MetricsConfig(host="127.0.0.1", port=server.port), reg, "x.yaml")
    finally:
        server.close()
        server.close()


def test_connected_follows_the_bus():
    cfg = config(busy_wait_s=0.0)
    clock = FakeClock()
    drv = VirtualDriver(cfg, image=live_image(cfg), faults=VirtualFaults(fail_on_read=3))
    svc = CyclicService(cfg, drv, clock=clock, sleep=clock.sleep, history=64)
    reg = make_registry(svc)
    assert reg.get_sample_value("cdpr_gateway_connected", {"bus": "virtual"}) == 0
    svc.configure()
    assert reg.get_sample_value("cdpr_gateway_connected", {"bus": "virtual"}) == 1
    svc._loop(3)  # the third read fails
    assert reg.get_sample_value("cdpr_gateway_connected", {"bus": "virtual"}) == 0
    svc._loop(1)
    assert reg.get_sample_value("cdpr_gateway_connected", {"bus": "virtual"}) == 1


def test_basic_auth_guards_the_exporter():
    import base64
    import hashlib
    import urllib.error

    reg = make_registry(ran_service(5))
    digest = hashlib.sha256(b"s3cret").hexdigest()
    cfg = MetricsConfig(
        host="127.0.0.1", port=0, basic_auth_user="prom", basic_auth_password_sha256=digest
    )
    server = MetricsServer(cfg, reg)
    url = f"http://127.0.0.1:{server.port}/metrics"
    try:
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(url, timeout=5)
        assert err.value.code == 401
        err.value.close()
        for password, ok in ((b"wrong", False), (b"s3cret", True)):
            token = base64.b64encode(b"prom:" + password).decode()
            request = urllib.request.Request(url, headers={"Authorization": f"Basic {token}"})
            if ok:
                with urllib.request.urlopen(request, timeout=5) as reply:
                    assert b"cdpr_gateway_cycle_seconds_count 5.0" in reply.read()
            else:
                with pytest.raises(urllib.error.HTTPError) as bad:
                    urllib.request.urlopen(request, timeout=5)
                assert bad.value.code == 401
                bad.value.close()
    finally:
        server.close()


def test_half_configured_basic_auth_is_a_config_error():
    reg = make_registry(ran_service(1))
    with pytest.raises(ConfigError, match="basic_auth"):
        MetricsServer(MetricsConfig(host="127.0.0.1", port=0, basic_auth_user="x"), reg)


def test_tls_exporter(tmp_path):
    import shutil
    import ssl

    openssl = shutil.which("openssl")
    if openssl is None:
        pytest.skip("openssl not installed")
    cert, key = self_signed(tmp_path, "server")
    reg = make_registry(ran_service(3))
    cfg = MetricsConfig(host="127.0.0.1", port=0, certfile=str(cert), keyfile=str(key))
    server = MetricsServer(cfg, reg)
    import socket

    idle = socket.create_connection(("127.0.0.1", server.port), timeout=5)  # never handshakes
    try:
        context = ssl.create_default_context(cafile=str(cert))
        url = f"https://127.0.0.1:{server.port}/metrics"
        # an idle client holding a connection must not stall the scrape behind it
        with urllib.request.urlopen(url, timeout=3, context=context) as reply:
            assert b"cdpr_gateway_cycle_seconds_count 3.0" in reply.read()
    finally:
        idle.close()
        server.close()
    with pytest.raises(ConfigError, match=r"metrics\.certfile"):
        MetricsServer(MetricsConfig(host="127.0.0.1", port=0, certfile=str(key)), reg)


def test_state_and_ages_follow_the_loop():
    """state is the wire code of register 125; the ages grow while nothing arrives."""
    cfg = config(busy_wait_s=0.0, heartbeat_timeout_s=0.05)
    clock = FakeClock()
    img = live_image(cfg)
    faults = VirtualFaults(freeze_heartbeat_from=20)
    drv = VirtualDriver(cfg, image=img, faults=faults)
    svc = CyclicService(cfg, drv, clock=clock, sleep=clock.sleep, history=256)
    reg = make_registry(svc)
    assert reg.get_sample_value("cdpr_gateway_state") == 0  # stopped: not started
    assert np.isnan(reg.get_sample_value("cdpr_gateway_sample_age_seconds"))
    assert np.isnan(reg.get_sample_value("cdpr_gateway_plc_heartbeat_age_seconds"))
    svc.configure()
    assert reg.get_sample_value("cdpr_gateway_state") == 1  # connected, nothing written
    svc._loop(10)
    assert reg.get_sample_value("cdpr_gateway_state") == 2 == img.gateway_state
    assert reg.get_sample_value("cdpr_gateway_sample_age_seconds") < 0.001
    # a change is dated at the read that last showed the old value: one period back
    assert reg.get_sample_value("cdpr_gateway_plc_heartbeat_age_seconds") < 0.0015
    svc._loop(100)  # the heartbeat froze at read 20: ~90 ms ago, > 50 ms timeout
    assert reg.get_sample_value("cdpr_gateway_state") == 3 == img.gateway_state
    age = reg.get_sample_value("cdpr_gateway_plc_heartbeat_age_seconds")
    assert age == pytest.approx(0.090, abs=0.003)
    assert reg.get_sample_value("cdpr_gateway_sample_age_seconds") < 0.001  # reads go on
    clock.advance(2.0)  # nothing read for 2 s
    assert reg.get_sample_value("cdpr_gateway_sample_age_seconds") == pytest.approx(2.0, abs=0.01)
    svc.stop()
    svc.run()
    assert reg.get_sample_value("cdpr_gateway_state") == 0
