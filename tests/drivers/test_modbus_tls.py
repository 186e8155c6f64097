"""Modbus/TCP Security: TLS with certificates verified both ways, on loopback.

The test makes its own throw-away CA, server and client certificates with the openssl
command line (Debian's openssl, present wherever Python's ssl module is).
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from drivers.base import Inputs, Outputs
from drivers.modbus_tcp import ModbusTcpDriver
from gateway.core.config import TlsConfig, load_config
from gateway.errors import DriverError
from sim_plc.modbus_server import ModbusPlcServer
from tests.loop_helpers import fresh
from tests.modbus_helpers import LOCALHOST, config_for, filled_image

pytestmark = [
    pytest.mark.loopback,
    pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl command not found"),
]


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=60)


def _ca(d: Path, name: str) -> None:
    _openssl(
        "req",
        "-x509",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-days",
        "2",
        "-keyout",
        f"{name}.key",
        "-out",
        f"{name}.pem",
        "-subj",
        f"/CN={name}",
        "-addext",
        "basicConstraints=critical,CA:TRUE",
        "-addext",
        "keyUsage=critical,keyCertSign,cRLSign",
        cwd=d,
    )


def _leaf(d: Path, name: str, ca: str, ext: str) -> None:
    (d / f"{name}.ext").write_text(ext)
    _openssl(
        "req",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-keyout",
        f"{name}.key",
        "-out",
        f"{name}.csr",
        "-subj",
        f"/CN={name}",
        cwd=d,
    )
    _openssl(
        "x509",
        "-req",
        "-in",
        f"{name}.csr",
        "-CA",
        f"{ca}.pem",
        "-CAkey",
        f"{ca}.key",
        "-CAcreateserial",
        "-days",
        "2",
        "-out",
        f"{name}.pem",
        "-extfile",
        f"{name}.ext",
        cwd=d,
    )


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("pki")
    _ca(d, "ca")
    _ca(d, "rogue_ca")
    _leaf(d, "server", "ca", "subjectAltName=IP:127.0.0.1\nextendedKeyUsage=serverAuth\n")
    _leaf(d, "client", "ca", "extendedKeyUsage=clientAuth\n")
    _leaf(d, "intruder", "rogue_ca", "extendedKeyUsage=clientAuth\n")
    return d


def _tls(d: Path, name: str, ca: str) -> TlsConfig:
    return TlsConfig(str(d / f"{name}.pem"), str(d / f"{name}.key"), str(d / f"{ca}.pem"))


@pytest.fixture()
def tls_server(pki: Path):
    image = filled_image()
    server = ModbusPlcServer(load_config(), image, LOCALHOST, 0, tls=_tls(pki, "server", "ca"))
    server.start()
    yield server, image
    server.stop()


def test_mutual_tls_round_trip(pki: Path, tls_server) -> None:
    server, image = tls_server
    cfg = config_for(server.port, tls=_tls(pki, "client", "ca"))
    inputs, outputs = Inputs.allocate(8), Outputs.allocate(8)
    outputs.tension_corrected_n[:] = np.arange(8) + 200.0
    outputs.channel_status[:] = 0
    with ModbusTcpDriver(cfg) as drv:
        drv.read_into(inputs)
        drv.exchange(fresh(outputs, drv), inputs)
    assert inputs.plc_heartbeat == image.plc_heartbeat
    assert_allclose(inputs.velocity_m_s, image.velocity_m_s, rtol=1e-6)
    assert_allclose(image.corrected_n, np.arange(8) + 200.0, rtol=1e-6)


@pytest.mark.parametrize(
    ("client", "ca", "reason"),
    [
        ("intruder", "ca", "connection closed by the server"),
        # the cause is in the message: the verification reason, as the loop logs it
        ("client", "rogue_ca", "TLS handshake: certificate verify failed: self-signed"),
    ],
    ids=["server-refuses-unknown-client", "client-refuses-unknown-server"],
)
def test_unverified_peers_are_refused(
    pki: Path, tls_server, client: str, ca: str, reason: str
) -> None:
    server, image = tls_server
    cfg = config_for(server.port, tls=_tls(pki, client, ca), timeout_s=0.5)
    drv = ModbusTcpDriver(cfg)
    with pytest.raises(DriverError, match=reason):
        drv.open()
        drv.read_into(Inputs.allocate(8))
    drv.close()
    assert image.gateway_writes == 0


def test_plain_tcp_client_gets_nothing_from_tls_server(tls_server) -> None:
    server, _ = tls_server
    drv = ModbusTcpDriver(config_for(server.port, timeout_s=0.3))
    with pytest.raises(DriverError, match=r"connection closed|timed out|no reply"):
        drv.open()
        drv.read_into(Inputs.allocate(8))
    drv.close()
