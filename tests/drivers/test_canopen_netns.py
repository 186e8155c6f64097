"""CANopen across processes: the soft PLC and the gateway driver in two processes on
python-can's ``udp_multicast`` bus, inside a private network namespace this test creates
(loopback only). Skipped when not root, without ``ip netns`` or without msgpack."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parents[1]  # tests/
GROUP = "239.74.163.2"
RUN_S = 20.0


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=10)


@pytest.fixture
def netns() -> Iterator[str]:
    pytest.importorskip("msgpack", reason="python-can's udp_multicast needs msgpack")
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root")
    if shutil.which("ip") is None:
        pytest.skip("iproute2 'ip' not installed")
    name = f"cdpr-canopen-{uuid.uuid4().hex[:8]}"
    try:
        _ip("netns", "add", name)
    except subprocess.CalledProcessError as exc:
        pytest.skip(f"ip netns add failed: {exc.stderr.decode().strip()}")
    try:
        _ip("netns", "exec", name, "ip", "link", "set", "lo", "up", "multicast", "on")
        _ip("netns", "exec", name, "ip", "route", "add", "224.0.0.0/4", "dev", "lo")
        yield name
    finally:
        _ip("netns", "del", name)


def _free_udp_port(ns: str) -> int:
    code = "import socket; s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); "
    code += "s.bind(('127.0.0.1', 0)); print(s.getsockname()[1])"
    out = subprocess.run(
        ["ip", "netns", "exec", ns, sys.executable, "-c", code],
        check=True,
        capture_output=True,
        timeout=30,
    )
    return int(out.stdout)


def _spawn(ns: str, role: str, port: int) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(HERE.parent), str(HERE)])}
    cmd = ["ip", "netns", "exec", ns, sys.executable, str(HERE / "canopen_helpers.py")]
    return subprocess.Popen(
        [*cmd, role, GROUP, str(port), str(RUN_S)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


def _result(proc: subprocess.Popen[str]) -> dict:
    try:
        out, err = proc.communicate(timeout=RUN_S + 30)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
    assert proc.returncode == 0, err[-2000:]
    return json.loads(out.strip().splitlines()[-1])


@pytest.mark.loopback
def test_plc_and_gateway_in_two_processes(netns: str) -> None:
    from tests.canopen_helpers import NETNS_CYCLES, expected_counts

    port = _free_udp_port(netns)
    gateway = _spawn(netns, "gateway", port)  # listening before the first SYNC
    plc = _spawn(netns, "plc", port)
    plc_out, gw_out = _result(plc), _result(gateway)
    expected_n = expected_counts(8) * 500.0 / 27648
    assert gw_out["good"] == NETNS_CYCLES
    np.testing.assert_allclose(gw_out["tension_raw_n"], expected_n, atol=1e-9)
    assert plc_out["gateway_writes"] >= NETNS_CYCLES - 5
    np.testing.assert_allclose(plc_out["corrected_n"], expected_n, atol=0.01 + 1e-9)
    assert plc_out["gateway_heartbeat"] == NETNS_CYCLES  # its last write arrived
