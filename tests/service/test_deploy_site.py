"""deploy/site/: many gateways in one Prometheus (one for the site, or an agent per robot
cell writing to a central one): promtool accepts every file; a real agent scraping two
gateways on loopback forwards their series, each with its `instance` and `robot`, to a
real central Prometheus; the dashboard selects by robot."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import time
from pathlib import Path

import pytest
import yaml

from gateway.core.config import MetricsConfig
from gateway.service.exporter import MetricsServer
from gateway.service.metrics import make_registry
from tests.loop_helpers import free_port
from tests.service.test_deploy import _require
from tests.service.test_metrics import ran_service
from tests.service.test_prometheus_scrape import query

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
SITE = DEPLOY / "site"
CELLS = sorted(SITE.glob("prometheus-cell-*.yml"))
WAIT_S = 90.0


def load(path: Path):
    return yaml.safe_load(path.read_text())


def test_every_gateway_has_a_robot_and_a_cell_and_each_agent_keeps_its_own():
    gateways = load(SITE / "gateways.yml")
    robots = [g["labels"]["robot"] for g in gateways]
    assert len(robots) == len(set(robots)) >= 2  # a robot label names one gateway
    cells = {g["labels"]["cell"] for g in gateways}
    assert {f"cell-{p.stem.rsplit('-', 1)[1]}" for p in CELLS} == cells
    kept: list[str] = []
    for path in CELLS:
        cfg = load(path)
        (job,) = cfg["scrape_configs"]
        assert job["job_name"] == "cdpr-gateway"  # the alerts select this job
        assert job["file_sd_configs"][0]["files"] == ["gateways.yml"]
        (rule,) = job["relabel_configs"]
        assert rule["action"] == "keep" and rule["source_labels"] == ["cell"]
        kept += [
            g["labels"]["robot"]
            for g in gateways
            if re.fullmatch(rule["regex"], g["labels"]["cell"])
        ]
        assert cfg["remote_write"][0]["url"].endswith("/api/v1/write")
        assert "rule_files" not in cfg  # an agent evaluates no rules
    assert sorted(kept) == sorted(robots)  # every gateway scraped by exactly one agent
    central = load(SITE / "prometheus-central.yml")
    assert central["rule_files"] == ["../alerts.yml"] and "scrape_configs" not in central
    site = load(SITE / "prometheus-site.yml")
    assert site["rule_files"] == ["../alerts.yml"]
    assert site["scrape_configs"][0]["file_sd_configs"][0]["files"] == ["gateways.yml"]


def test_the_dashboard_selects_robots_and_never_merges_them():
    dash = json.loads((DEPLOY / "grafana-dashboard.json").read_text())
    variables = {v["name"]: v for v in dash["templating"]["list"]}
    assert variables["robot"]["definition"] == "label_values(cdpr_gateway_build_info, robot)"
    assert variables["robot"]["multi"] and variables["robot"]["includeAll"]
    assert 'robot=~"$robot"' in variables["instance"]["definition"]  # gateways of those robots
    names = [v["name"] for v in dash["templating"]["list"]]
    assert names.index("robot") < names.index("instance")
    for panel in dash["panels"]:
        for target in panel["targets"]:
            expr = target["expr"]
            assert 'robot=~"$robot", instance=~"$instance"' in expr, expr
            for agg in re.finditer(r"\bby\s*\(([^)]*)\)", expr):
                assert "robot" in agg.group(1), expr  # the legend can name the robot
            assert "{{robot}}" in target["legendFormat"]


@pytest.mark.external
def test_promtool_accepts_the_site_central_and_agent_configs(tmp_path):
    promtool = _require("promtool")
    site = tmp_path / "site"
    shutil.copytree(SITE, site)
    shutil.copy(DEPLOY / "alerts.yml", tmp_path)
    checks = [["prometheus-site.yml"], ["prometheus-central.yml"]]
    checks += [["--agent", p.name] for p in CELLS]
    for args in checks:
        res = subprocess.run(
            [promtool, "check", "config", *args],
            cwd=site,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert res.returncode == 0, res.stdout + res.stderr
        assert "SUCCESS" in res.stdout
        if "--agent" not in args:
            assert "SUCCESS: 8 rules found" in res.stdout  # the alerts, per robot
    # the check can fail: an agent config with a rule file is refused in agent mode
    bad = site / CELLS[0].name
    bad.write_text(bad.read_text() + "\nrule_files: [../alerts.yml]\n")
    res = subprocess.run(
        [promtool, "check", "config", "--agent", bad.name],
        cwd=site,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode != 0


def _start_prometheus(binary: str, args: list[str], log: Path) -> subprocess.Popen[bytes]:
    with open(log, "wb") as fh:
        return subprocess.Popen([binary, *args], stdout=fh, stderr=subprocess.STDOUT)


def _stop(procs: list[subprocess.Popen[bytes]]) -> None:
    for p in procs:
        p.terminate()
    for p in procs:
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=10)


@pytest.mark.long  # ~27 s: the agent's first remote write takes its time
@pytest.mark.external
@pytest.mark.loopback
def test_an_agent_forwards_two_gateways_to_the_central_prometheus(tmp_path):
    """The shipped cell-a agent and central configs, with the gateways on loopback and
    the centre's URL on loopback: the centre sees each gateway's series with its own
    instance, robot and cell, and `up` per robot for the alerts."""
    binary = _require("prometheus")
    exporters = [
        MetricsServer(MetricsConfig(host="127.0.0.1", port=0), make_registry(ran_service(10)))
        for _ in range(2)
    ]
    central_port, agent_port = free_port(), free_port()
    site = tmp_path / "site"
    shutil.copytree(SITE, site)
    shutil.copy(DEPLOY / "alerts.yml", tmp_path)
    gateways = [
        {"targets": [f"127.0.0.1:{e.port}"], "labels": {"robot": f"r-{i}", "cell": "cell-a"}}
        for i, e in enumerate(exporters)
    ]
    gateways.append({"targets": ["127.0.0.1:9"], "labels": {"robot": "other", "cell": "cell-b"}})
    (site / "gateways.yml").write_text(yaml.safe_dump(gateways))
    agent_cfg = (SITE / "prometheus-cell-a.yml").read_text()
    url = re.search(r"url: (\S+)", agent_cfg).group(1)  # type: ignore[union-attr]
    agent_cfg = agent_cfg.replace(url, f"http://127.0.0.1:{central_port}/api/v1/write")
    agent_cfg = agent_cfg.replace("batch_send_deadline: 5s", "batch_send_deadline: 1s")
    (site / "prometheus-cell-a.yml").write_text(agent_cfg)
    procs = [
        _start_prometheus(
            binary,
            [
                f"--config.file={site / 'prometheus-central.yml'}",
                "--web.enable-remote-write-receiver",
                f"--storage.tsdb.path={tmp_path / 'central'}",
                f"--web.listen-address=127.0.0.1:{central_port}",
            ],
            tmp_path / "central.log",
        ),
        _start_prometheus(
            binary,
            [
                f"--config.file={site / 'prometheus-cell-a.yml'}",
                "--enable-feature=agent",
                f"--storage.agent.path={tmp_path / 'agent'}",
                f"--web.listen-address=127.0.0.1:{agent_port}",
            ],
            tmp_path / "agent.log",
        ),
    ]
    try:
        deadline = time.monotonic() + WAIT_S
        series: list[dict] = []
        while time.monotonic() < deadline and len(series) < 2:
            for p, name in zip(procs, ("central", "agent"), strict=True):
                assert p.poll() is None, (tmp_path / f"{name}.log").read_text()[-2000:]
            try:
                series = query(central_port, "cdpr_gateway_build_info")
            except OSError:
                series = []
            time.sleep(0.5)
        labels = sorted(
            (s["metric"]["robot"], s["metric"]["instance"], s["metric"]["cell"]) for s in series
        )
        assert labels == [
            (f"r-{i}", f"127.0.0.1:{e.port}", "cell-a") for i, e in enumerate(exporters)
        ], series
        up = query(central_port, 'up{job="cdpr-gateway"}')
        assert sorted(s["metric"]["robot"] for s in up) == ["r-0", "r-1"]  # not cell-b's
    finally:
        _stop(procs)
        for e in exporters:
            e.close()
