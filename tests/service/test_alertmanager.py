"""deploy/alertmanager.yml against a real Alertmanager on loopback: one PLC
outage's alerts arrive as one group per robot, and only the cause is left active."""

from __future__ import annotations

import contextlib
import json
import subprocess
import time
import urllib.request
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import pytest

from tests.loop_helpers import free_port
from tests.service.test_deploy import DEPLOY, _require

pytestmark = [pytest.mark.external, pytest.mark.loopback]
CONFIG = DEPLOY / "alertmanager.yml"


def test_amtool_accepts_the_config_and_groups_by_robot() -> None:
    amtool = _require("amtool")
    check = subprocess.run(
        [amtool, "check-config", str(CONFIG)], capture_output=True, text=True, timeout=60
    )
    assert check.returncode == 0 and "SUCCESS" in check.stdout, check.stdout + check.stderr
    assert "4 inhibit rules" in check.stdout


@contextlib.contextmanager
def alertmanager(tmp_path: Path) -> Iterator[str]:
    binary = _require("prometheus-alertmanager")
    port = free_port()
    proc = subprocess.Popen(
        [
            binary,
            f"--config.file={CONFIG}",
            f"--storage.path={tmp_path}",
            f"--web.listen-address=127.0.0.1:{port}",
            "--cluster.listen-address=",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    url = f"http://127.0.0.1:{port}/api/v2"
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            with contextlib.suppress(OSError):
                urllib.request.urlopen(f"{url}/status", timeout=2).close()
                break
            assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
            time.sleep(0.1)
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)
        if proc.stderr is not None:
            proc.stderr.close()


def outage(instance: str, cables: int) -> list[dict]:
    """What deploy/alerts.yml fires for one PLC outage on one robot."""
    names = [
        "CdprGatewayBusDisconnected",
        "CdprGatewayFault",
        "CdprGatewayPlcHeartbeatStalled",
        "CdprGatewayErrors",
    ]
    labels = [{"alertname": n, "severity": "critical"} for n in names]
    labels += [
        {"alertname": "CdprGatewayChannelInvalid", "severity": "critical", "cable": str(c + 1)}
        for c in range(cables)
    ]
    start = datetime.now(UTC).isoformat()
    return [
        {"labels": {**lab, "job": "cdpr-gateway", "instance": instance}, "startsAt": start}
        for lab in labels
    ]


def test_one_outage_leaves_only_its_cause_active_per_robot(tmp_path) -> None:
    with alertmanager(tmp_path) as url:
        alerts = outage("robot-a:9109", 8)  # a PLC outage on robot a
        alerts += [{**outage("robot-b:9109", 1)[-1]}]  # robot b: one bad channel, alone
        request = urllib.request.Request(
            f"{url}/alerts",
            data=json.dumps(alerts).encode(),
            headers={"Content-Type": "application/json"},
        )
        urllib.request.urlopen(request, timeout=5).close()
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            with urllib.request.urlopen(f"{url}/alerts", timeout=5) as reply:
                seen = json.load(reply)
            if len(seen) == len(alerts) and all(
                a["status"]["state"] != "unprocessed" for a in seen
            ):
                break
            time.sleep(0.2)
        active = sorted(
            (a["labels"]["instance"], a["labels"]["alertname"])
            for a in seen
            if a["status"]["state"] == "active"
        )
        assert active == [
            ("robot-a:9109", "CdprGatewayBusDisconnected"),
            ("robot-b:9109", "CdprGatewayChannelInvalid"),
        ], active
        suppressed = [a for a in seen if a["status"]["state"] == "suppressed"]
        assert len(suppressed) == len(alerts) - 2
        assert all(a["status"]["inhibitedBy"] for a in suppressed)
        with urllib.request.urlopen(f"{url}/alerts/groups", timeout=5) as reply:
            groups = json.load(reply)
        robots = sorted(g["labels"].get("instance") for g in groups)
        assert robots == ["robot-a:9109", "robot-b:9109"], groups  # one group per robot
