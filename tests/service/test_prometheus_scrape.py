"""A real Prometheus server on loopback scrapes the gateway; its query API sees the metrics."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import threading
import time
import urllib.parse
import urllib.request
from pathlib import Path

import pytest

from drivers.virtual import VirtualDriver
from gateway.core.config import MetricsConfig
from gateway.runtime.loop import CyclicService
from gateway.service.exporter import MetricsServer
from gateway.service.metrics import make_registry
from tests.loop_helpers import Wobble, config, free_port, live_image

pytestmark = [pytest.mark.external, pytest.mark.loopback, pytest.mark.long]  # ~6 s
WAIT_S = 90.0


def prometheus_binary() -> str:
    path = shutil.which("prometheus")
    if path is None:
        if os.environ.get("CDPR_REQUIRE_EXTERNAL") == "1":
            pytest.fail("prometheus not installed but CDPR_REQUIRE_EXTERNAL=1")
        pytest.skip("prometheus (Debian package 'prometheus') not installed")
    return path


def query(port: int, expr: str) -> list[dict]:
    url = f"http://127.0.0.1:{port}/api/v1/query?" + urllib.parse.urlencode({"query": expr})
    with urllib.request.urlopen(url, timeout=5) as reply:
        body = json.load(reply)
    assert body["status"] == "success", body
    return list(body["data"]["result"])


def wait_for(port: int, expr: str, proc: subprocess.Popen, deadline: float) -> list[dict]:
    while time.monotonic() < deadline:
        assert proc.poll() is None, "prometheus exited"
        try:
            result = query(port, expr)
        except OSError:
            result = []
        if result:
            return result
        time.sleep(0.5)
    pytest.fail(f"prometheus never returned {expr} within {WAIT_S} s")


def test_prometheus_scrapes_the_gateway(tmp_path: Path):
    binary = prometheus_binary()
    cfg = config(period_s=0.01, busy_wait_s=0.0)
    img = live_image(cfg)
    service = CyclicService(cfg, VirtualDriver(cfg, image=img, step=Wobble(img)), history=1024)
    exporter = MetricsServer(MetricsConfig(host="127.0.0.1", port=0), make_registry(service))
    worker = threading.Thread(target=service.run, daemon=True)
    worker.start()
    web_port = free_port()
    (tmp_path / "prometheus.yml").write_text(
        "global: {scrape_interval: 1s}\n"
        "scrape_configs:\n"
        "  - job_name: cdpr-gateway\n"
        "    scrape_interval: 1s\n"
        "    scrape_timeout: 1s\n"
        f"    static_configs: [{{targets: ['127.0.0.1:{exporter.port}']}}]\n"
    )
    proc = subprocess.Popen(
        [
            binary,
            f"--config.file={tmp_path / 'prometheus.yml'}",
            f"--storage.tsdb.path={tmp_path / 'data'}",
            f"--web.listen-address=127.0.0.1:{web_port}",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + WAIT_S
        buckets = wait_for(web_port, "cdpr_gateway_cycle_seconds_bucket", proc, deadline)
        assert {r["metric"]["le"] for r in buckets} >= {"5e-05", "0.005", "+Inf"}
        corrected = wait_for(web_port, "cdpr_gateway_tension_corrected_newtons", proc, deadline)
        assert sorted(int(r["metric"]["cable"]) for r in corrected) == list(range(1, 9))
        assert all(190 < float(r["value"][1]) < 260 for r in corrected)
        status = wait_for(web_port, "cdpr_gateway_channel_status", proc, deadline)
        assert len(status) == 8
        up = wait_for(web_port, 'up{job="cdpr-gateway"}', proc, deadline)
        assert float(up[0]["value"][1]) == 1.0
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)
        service.stop()
        worker.join(timeout=20)
        exporter.close()
    assert not worker.is_alive()
