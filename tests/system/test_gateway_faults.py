"""The gateway through a fault-injecting proxy to the soft PLC, on loopback.

gateway (CyclicService + ModbusTcpDriver) -> FaultProxy -> soft PLC (ModbusPlcServer) with
constant inputs and a running heartbeat. For each fault the gateway

* keeps cycling (its cycle counter advances while the fault lasts);
* flags the channels (``cdpr_gateway_channel_status`` > 0 while no read succeeds);
* writes no value computed from a bad read: every write arriving at the PLC is checked by
  :class:`tests.reliability_helpers.WriteOracle` (GOOD/SUBSTITUTED with the value the
  clean inputs give, or INVALID with NaN);
* recovers within ``RECOVERY_CYCLES`` executed cycles once the fault is cleared (the
  first all-good write at the PLC);
* counts it: ``cdpr_gateway_errors_total{kind}``, and ``cdpr_gateway_reconnects_total``
  where the connection had to be re-established.

Stated recovery bound: a failed read leaves nothing written and the channels flagged;
the driver drops a broken connection (or one with three timeouts in a row) and
reconnects with backoff, and the loop reopens the driver after a few failed cycles. The
proxy accepts at once, so a cleared fault is over after at most a connect and one
transaction; RECOVERY_CYCLES leaves room for a reply still in flight (measured: at most
6 cycles in the 60 s soak).

Corruption is injected in the frame header only (MBAP, function code, byte count): a
corrupted data word inside a well-formed Modbus/TCP reply is not detectable by the
protocol (no checksum above TCP's; TLS adds one), see docs/security.md.
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("sim_plc.modbus_server", reason="the soft PLC's Modbus server")
pytest.importorskip("drivers.modbus_tcp", reason="the Modbus TCP driver")
pytest.importorskip("gateway.service.metrics", reason="the loop and its metrics")

from tests.reliability_helpers import GatewayRig, wait_for

pytestmark = [pytest.mark.loopback, pytest.mark.slow]

RECOVERY_CYCLES = 100
FAULT_ERRORS = 5  # errors to see before the fault is cleared
WAIT_S = 20.0  # bound of every wait (generous: two shared cores)


@pytest.fixture
def rig() -> Iterator[GatewayRig]:
    with GatewayRig(seed=11) as r:
        r.warm_up()
        yield r
        assert r.oracle.bad == []


def _total(errors: dict[str, float], kinds: tuple[str, ...]) -> float:
    return sum(errors.get(k, 0.0) for k in kinds)


def _fault_and_recover(
    rig: GatewayRig,
    kind: str,
    params: dict[str, Any],
    error_kinds: tuple[str, ...],
    reconnect: bool,
) -> dict[str, float]:
    """Inject, watch the gateway through it, clear, measure the recovery. Figures back."""
    errors0, reconnects0 = rig.errors(), rig.reconnects()
    rig.proxy.set_fault(kind, **params)
    cycles0, status_max = rig.cycles, [0.0]

    def seen_enough() -> bool:
        status_max[0] = max(status_max[0], rig.channel_status_max())
        return _total(rig.errors(), error_kinds) - _total(errors0, error_kinds) >= FAULT_ERRORS

    assert wait_for(seen_enough, WAIT_S), f"{kind}: errors {rig.errors()}"
    assert rig.cycles > cycles0  # kept cycling
    assert status_max[0] >= 1  # channels flagged (substituted or invalid)
    rig.proxy.clear()
    rig.oracle.watch_recovery()
    cleared_at = rig.cycles
    assert wait_for(lambda: rig.oracle.recovered_at is not None, WAIT_S), f"{kind}: no recovery"
    recovery = rig.oracle.recovered_at - cleared_at  # type: ignore[operator]
    assert recovery <= RECOVERY_CYCLES, f"{kind}: recovered after {recovery} cycles"
    if reconnect:
        assert rig.reconnects() > reconnects0
    assert rig.proxy.counters.get(kind, 0) >= 1
    assert rig.oracle.bad == []
    return {"recovery_cycles": recovery, "fault_cycles": cleared_at - cycles0}


@pytest.mark.parametrize(
    ("kind", "params", "error_kinds", "reconnect"),
    [
        ("delay", {"seconds": 0.2, "direction": "reply"}, ("timeout",), True),
        ("delay", {"seconds": 0.2, "direction": "request"}, ("timeout",), True),
        ("drop", {}, ("timeout",), True),
        ("drop", {"probability": 0.5}, ("timeout",), False),
        ("corrupt", {"where": "header", "nbytes": 2}, ("timeout", "io"), False),
        ("wrong_tid", {}, ("timeout",), True),
        ("reset", {"after_bytes": 5}, ("io",), True),
        ("reset", {"after_bytes": 0}, ("io",), True),
        ("silent", {}, ("timeout",), True),
        ("exception", {"code": 6}, ("io",), False),  # server busy
        ("exception", {"code": 2}, ("io",), False),  # illegal data address
    ],
    ids=[
        "delay-reply",
        "delay-request",
        "drop",
        "drop-half",
        "corrupt-header",
        "wrong-tid",
        "reset-mid-frame",
        "reset-at-start",
        "silent",
        "busy",
        "illegal-address",
    ],
)
def test_fault_flagged_counted_recovered(
    rig: GatewayRig,
    kind: str,
    params: dict[str, Any],
    error_kinds: tuple[str, ...],
    reconnect: bool,
) -> None:
    """``reconnect``: the fault breaks the connection or leaves it unusable (a reset, or
    replies that never come), so the driver must reconnect; a lone lost reply, an
    exception reply or a corrupted frame may be survived on the same connection."""
    _fault_and_recover(rig, kind, params, error_kinds, reconnect)


@pytest.mark.parametrize(
    ("kind", "params", "good"),
    [
        ("split", {"pieces": 3, "pause_s": 0.0005}, True),
        # below the data's age limit (loop.stale_after_s, 10 ms): late, not stale, good
        ("delay", {"seconds": 0.005, "direction": "reply"}, True),
        # below the 50 ms timeout, but above the age limit: the output gate writes those
        # values invalid (reason "age"), and good ones come back after
        ("delay", {"seconds": 0.015, "direction": "reply"}, False),
    ],
    ids=["split", "short-delay", "long-delay"],
)
def test_tolerated_fault_keeps_values_good(
    rig: GatewayRig, kind: str, params: dict[str, Any], good: bool
) -> None:
    errors0, writes0 = rig.errors(), rig.oracle.all_good_writes
    aged0 = rig.metric("cdpr_gateway_gated_total", reason="age")
    rig.proxy.set_fault(kind, **params)
    assert wait_for(lambda: rig.proxy.counters.get(kind, 0) >= 100, WAIT_S)
    during = rig.oracle.all_good_writes
    aged = rig.metric("cdpr_gateway_gated_total", reason="age") - aged0
    rig.proxy.clear()
    if good:  # frames keep coming: good, or (a late cycle on a loaded machine) stopped by
        assert during - writes0 + aged / 8 >= 50  # the gate for age alone, never bad
    else:
        assert aged >= 8 * 50  # whole frames of 8 channels
    assert wait_for(lambda: rig.oracle.all_good_writes >= during + 50, WAIT_S)
    assert _total(rig.errors(), ("timeout", "io", "connect", "write")) == _total(
        errors0, ("timeout", "io", "connect", "write")
    )
    assert rig.oracle.bad == []


def test_silent_plc_gets_no_writes_and_heartbeat_freezes(rig: GatewayRig) -> None:
    """While nothing is answered the PLC receives nothing: its gateway heartbeat stops."""
    rig.proxy.set_fault("silent")
    assert wait_for(lambda: rig.errors().get("timeout", 0) >= 3, WAIT_S)
    writes, heartbeat = rig.oracle.writes, rig.image.gateway_heartbeat
    cycles = rig.cycles
    assert wait_for(lambda: rig.cycles >= cycles + 20, WAIT_S)
    assert rig.oracle.writes == writes
    assert rig.image.gateway_heartbeat == heartbeat
    assert rig.metric("cdpr_gateway_connected", bus="modbus_tcp") in (0.0, 1.0)
    rig.proxy.clear()
    assert wait_for(lambda: rig.image.gateway_heartbeat != heartbeat, WAIT_S)


def test_plc_refusing_the_map_is_never_written() -> None:
    """A gateway whose outputs lie outside the PLC's writable area (the real soft PLC
    answers exception 2): it keeps cycling, counts io errors, the PLC receives nothing."""
    import dataclasses

    from gateway.core.registermap import RegisterField, RegisterMap

    shifted = RegisterMap(
        corrected_tensions=RegisterField(1100, 8, "float32"),
        channel_status=RegisterField(1116, 8, "uint16"),
        gateway_heartbeat=RegisterField(1124, 1, "uint16"),
        gateway_state=RegisterField(1125, 1, "uint16"),
        wrench=RegisterField(1126, 6, "float32"),
    )
    assert dataclasses.is_dataclass(shifted)
    with GatewayRig(registers=shifted) as rig:
        assert wait_for(lambda: rig.errors().get("io", 0) >= 10, WAIT_S), rig.errors()
        cycles = rig.cycles
        assert wait_for(lambda: rig.cycles >= cycles + 10, WAIT_S)
        assert rig.image.gateway_writes == 0
        assert rig.oracle.writes == 0


def test_corrupted_data_word_passes_undetected() -> None:
    """The residual risk of docs/security.md (FR3), and a check that the oracle can fail:
    a data byte corrupted inside a well-formed reply is decoded as a good value, and a
    wrong value reaches the PLC. Only TLS (or a checksum in the PLC's data) catches it."""
    with GatewayRig(seed=5) as rig:
        rig.warm_up()
        rig.proxy.set_fault("corrupt", where="data", nbytes=1)
        assert wait_for(lambda: rig.oracle.bad_values > 0, WAIT_S), rig.proxy.counters
        rig.proxy.clear()
        assert _total(rig.errors(), ("timeout", "io")) == 0  # nothing the driver can see


# --- Modbus/TCP Security: TLS both ways, through the proxy ------------------------------
def make_certificates(directory: Path) -> dict[str, Path]:
    """A CA, a server certificate for IP 127.0.0.1 and a client certificate, signed by the
    CA, plus a second CA with its own client certificate (a stranger). PEM files made with
    the ``openssl`` command; keys are EC P-256. Returns the paths by name."""

    def run(*args: str) -> None:
        subprocess.run(["openssl", *args], check=True, capture_output=True, timeout=30)

    p = {
        n: directory / f"{n}.pem"
        for n in (
            "ca",
            "ca_key",
            "server",
            "server_key",
            "client",
            "client_key",
            "other_ca",
            "other_ca_key",
            "stranger",
            "stranger_key",
        )
    }
    ec = ("-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes")
    for ca in ("ca", "other_ca"):
        run(
            "req",
            "-x509",
            *ec,
            "-keyout",
            str(p[f"{ca}_key"]),
            "-out",
            str(p[ca]),
            "-days",
            "2",
            "-subj",
            f"/CN=cdpr test {ca}",
        )
    ext = directory / "server.ext"
    ext.write_text("subjectAltName=IP:127.0.0.1\n")
    for name, ca, extra in (
        ("server", "ca", ("-extfile", str(ext))),
        ("client", "ca", ()),
        ("stranger", "other_ca", ()),
    ):
        csr = directory / f"{name}.csr"
        run(
            "req",
            "-new",
            *ec,
            "-keyout",
            str(p[f"{name}_key"]),
            "-out",
            str(csr),
            "-subj",
            f"/CN=cdpr test {name}",
        )
        run(
            "x509",
            "-req",
            "-in",
            str(csr),
            "-CA",
            str(p[ca]),
            "-CAkey",
            str(p[f"{ca}_key"]),
            "-CAcreateserial",
            "-out",
            str(p[name]),
            "-days",
            "2",
            *extra,
        )
    return p


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    if shutil.which("openssl") is None:
        pytest.skip("the openssl command makes the test certificates")
    return make_certificates(tmp_path_factory.mktemp("certs"))


def _client_tls(certs: dict[str, Path], client: str = "client", ca: str = "ca") -> Any:
    from gateway.core.config import TlsConfig

    return TlsConfig(
        certfile=str(certs[client]), keyfile=str(certs[f"{client}_key"]), cafile=str(certs[ca])
    )


def _plc_tls(certs: dict[str, Path]) -> Any:
    from gateway.core.config import TlsConfig

    return TlsConfig(
        certfile=str(certs["server"]), keyfile=str(certs["server_key"]), cafile=str(certs["ca"])
    )


def test_tls_both_ways_detects_corruption(certs: dict[str, Path]) -> None:
    """gateway -TLS-> proxy (raw bytes) -TLS-> soft PLC (client certificate required).
    A byte corrupted anywhere in the TLS stream fails the record's integrity check: the
    driver sees an error, the PLC gets no wrong value, the gateway reconnects."""
    with GatewayRig(seed=3, tls=_client_tls(certs), plc_tls=_plc_tls(certs)) as rig:
        rig.warm_up()
        errors0 = _total(rig.errors(), ("timeout", "io"))
        rig.proxy.set_fault("corrupt", where="any", nbytes=1, probability=0.3)
        assert wait_for(
            lambda: _total(rig.errors(), ("timeout", "io")) >= errors0 + FAULT_ERRORS, WAIT_S
        ), rig.errors()
        rig.proxy.clear()
        rig.oracle.watch_recovery()
        assert wait_for(lambda: rig.oracle.recovered_at is not None, WAIT_S)
        assert rig.reconnects() >= 1
        assert rig.oracle.bad == []
        assert rig.proxy.counters["connections"] >= 2


@pytest.mark.parametrize(
    ("client", "ca"), [("stranger", "ca"), ("client", "other_ca")], ids=["client", "server"]
)
def test_tls_certificate_from_another_ca_is_refused(
    certs: dict[str, Path], client: str, ca: str
) -> None:
    """A client certificate the PLC does not trust, or a PLC certificate the gateway does
    not trust: no session, nothing written, the failures counted; the loop keeps trying."""
    with GatewayRig(tls=_client_tls(certs, client, ca), plc_tls=_plc_tls(certs)) as rig:
        assert wait_for(
            lambda: (
                _total(rig.errors(), ("connect", "io", "timeout")) >= 2
                and rig.proxy.counters.get("connections", 0) >= 2
            ),
            WAIT_S,
        ), rig.errors()
        assert rig.image.gateway_writes == 0
        assert rig.oracle.writes == 0
