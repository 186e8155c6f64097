"""deploy/: the dashboard and alerts only use metrics the gateway exports and keep robots
apart; the alerts pass `promtool test rules`; the unit is hardened, supervised and verified."""

from __future__ import annotations

import configparser
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from gateway.core.config import load_config
from gateway.service.metrics import make_registry
from tests.service.test_metrics import ran_service

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"

PROMQL_WORDS = {
    # functions and aggregations used (or plausibly used) in the dashboard and alerts
    "histogram_quantile",
    "rate",
    "irate",
    "increase",
    "sum",
    "max",
    "min",
    "avg",
    "count",
    "max_over_time",
    "min_over_time",
    "avg_over_time",
    "delta",
    "deriv",
    "abs",
    "topk",
    "bottomk",
    "clamp_min",
    "clamp_max",
    "changes",
    "resets",
    "time",
    "vector",
    "label_replace",
    # keywords
    "by",
    "without",
    "on",
    "ignoring",
    "group_left",
    "group_right",
    "and",
    "or",
    "unless",
    "offset",
    "bool",
}
LABELS = {"le", "bus", "kind", "cable", "version", "instance", "job"}
BUILTIN_SERIES = {"up"}


def metric_names(expr: str) -> set[str]:
    """Series names an expression selects: identifiers that are not functions/labels."""
    expr = re.sub(r'"(?:[^"\\]|\\.)*"', '""', expr)  # label values
    expr = re.sub(r"\[[^\]]*\]", "", expr)  # range selectors [1m]
    expr = re.sub(r"\{[^}]*\}", "", expr)  # label matchers
    expr = re.sub(r"\b(by|without|on|ignoring)\s*\([^)]*\)", "", expr)  # grouping labels
    names = set()
    for match in re.finditer(r"[A-Za-z_:][A-Za-z0-9_:]*", expr):
        token = match.group(0)
        rest = expr[match.end() :].lstrip()
        if token in PROMQL_WORDS or rest.startswith("(") or re.fullmatch(r"\d+[smhdwy]", token):
            continue
        names.add(token)
    return names


def exported_series() -> set[str]:
    registry = make_registry(ran_service(10))
    return {s.name for family in registry.collect() for s in family.samples}


def dashboard() -> dict:
    return json.loads((DEPLOY / "grafana-dashboard.json").read_text())


def dashboard_exprs() -> list[str]:
    exprs = [t["expr"] for p in dashboard()["panels"] for t in p.get("targets", [])]
    assert len(exprs) >= 10
    return exprs


def alert_exprs() -> list[str]:
    rules = yaml.safe_load((DEPLOY / "alerts.yml").read_text())
    return [r["expr"] for g in rules["groups"] for r in g["rules"]]


def test_the_parser_finds_metric_names():
    expr = 'histogram_quantile(0.99, sum by (le) (rate(foo_bucket{bus="x"}[1m]))) / bar_total'
    assert metric_names(expr) == {"foo_bucket", "bar_total"}


def test_every_dashboard_query_uses_exported_metrics():
    exported = exported_series() | BUILTIN_SERIES
    used: set[str] = set()
    for expr in dashboard_exprs():
        names = metric_names(expr)
        assert names, expr
        assert names <= exported, f"{expr}: {names - exported} not exported"
        used |= names
    families = {n.removesuffix("_bucket").removesuffix("_sum").removesuffix("_count") for n in used}
    # the dashboard shows every family of the design table
    assert {n.removesuffix("_total") for n in families} >= {
        "cdpr_gateway_cycle_seconds",
        "cdpr_gateway_jitter_seconds",
        "cdpr_gateway_overruns",
        "cdpr_gateway_bus_roundtrip_seconds",
        "cdpr_gateway_errors",
        "cdpr_gateway_reconnects",
        "cdpr_gateway_connected",
        "cdpr_gateway_tension_raw_newtons",
        "cdpr_gateway_tension_corrected_newtons",
        "cdpr_gateway_friction_newtons",
        "cdpr_gateway_channel_status",
        "cdpr_gateway_build_info",
        "cdpr_gateway_state",
        "cdpr_gateway_plc_heartbeat_age_seconds",
        "cdpr_gateway_sample_age_seconds",
    }


def test_the_dashboard_works_with_file_provisioning_and_keeps_robots_apart():
    dash = dashboard()
    text = json.dumps(dash)
    assert "DS_PROMETHEUS" not in text and "__inputs" not in dash  # import-UI only
    variables = {v["name"]: v for v in dash["templating"]["list"]}
    assert variables["datasource"]["type"] == "datasource"
    assert variables["datasource"]["query"] == "prometheus"
    assert variables["instance"]["includeAll"] and variables["instance"]["multi"]
    assert "instance" in variables["instance"]["definition"]
    for panel in dash["panels"]:
        assert panel["datasource"]["uid"] == "${datasource}", panel["title"]
        for target in panel["targets"]:
            expr = target["expr"]
            assert target["datasource"]["uid"] == "${datasource}"
            assert 'instance=~"$instance"' in expr, expr  # the chosen robots only
            # an aggregation keeps the instance label: robots are never summed together
            for agg in re.finditer(r"\b(sum|avg|max|min|count)\b\s*(by\s*\(([^)]*)\))?", expr):
                assert agg.group(3) and "instance" in agg.group(3), expr
            assert "{{instance}}" in target["legendFormat"], target


def test_the_dashboard_shows_state_and_tensions_in_newtons():
    panels = dashboard()["panels"]
    by_metric = {}
    for panel in panels:
        for target in panel["targets"]:
            for name in metric_names(target["expr"]):
                by_metric.setdefault(name, panel)
    state = by_metric["cdpr_gateway_state"]
    mapping = state["fieldConfig"]["defaults"]["mappings"][0]["options"]
    assert {k: v["text"] for k, v in mapping.items()} == {
        "0": "stopped",
        "1": "connected",
        "2": "active",
        "3": "fault",
    }
    assert "cdpr_gateway_plc_heartbeat_age_seconds" in by_metric
    assert "cdpr_gateway_sample_age_seconds" in by_metric
    for name in ("tension_raw_newtons", "tension_corrected_newtons", "friction_newtons"):
        assert by_metric[f"cdpr_gateway_{name}"]["fieldConfig"]["defaults"]["unit"] == "forceN"


def test_every_alert_uses_exported_metrics():
    exported = exported_series() | BUILTIN_SERIES
    for expr in alert_exprs():
        names = metric_names(expr)
        assert names and names <= exported, f"{expr}: {names - exported} not exported"


def test_the_alerts_cover_what_issue_14_lists_and_never_sum_robots():
    rules = yaml.safe_load((DEPLOY / "alerts.yml").read_text())
    by_name = {r["alert"]: r["expr"] for g in rules["groups"] for r in g["rules"]}
    assert re.search(r"\bup\{job=\"cdpr-gateway\"\} == 0", by_name["CdprGatewayDown"])
    assert by_name["CdprGatewayAbsent"].startswith("absent(up{")
    assert "cdpr_gateway_connected == 0" in by_name["CdprGatewayBusDisconnected"]
    assert "cdpr_gateway_channel_status == 2" in by_name["CdprGatewayChannelInvalid"]
    assert "cdpr_gateway_plc_heartbeat_age_seconds" in by_name["CdprGatewayPlcHeartbeatStalled"]
    overrun = by_name["CdprGatewayOverrunBudget"]
    assert "cdpr_gateway_overruns_total" in overrun and "cycle_seconds_count" in overrun
    for expr in by_name.values():
        assert not re.search(r"\b(sum|avg|max|min|count)\b", expr), expr
    prom = yaml.safe_load((DEPLOY / "prometheus.yml").read_text())
    assert [job["job_name"] for job in prom["scrape_configs"]] == ["cdpr-gateway"]
    assert "alerts.yml" in prom["rule_files"]


def test_scrape_config_targets_the_default_exporter():
    prom = yaml.safe_load((DEPLOY / "prometheus.yml").read_text())
    cfg = load_config()
    targets = [
        t for job in prom["scrape_configs"] for sc in job["static_configs"] for t in sc["targets"]
    ]
    assert targets == [f"{cfg.metrics.host}:{cfg.metrics.port}"] == ["127.0.0.1:9109"]


def test_unit_is_hardened_and_runs_the_daemon():
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str  # type: ignore[assignment,method-assign]
    unit.read(DEPLOY / "cdpr-gateway.service")
    svc = unit["Service"]
    assert svc["DynamicUser"] == "yes"
    assert svc["NoNewPrivileges"] == "yes"
    assert svc["ProtectSystem"] == "strict"
    assert svc["RestrictAddressFamilies"].split() == ["AF_INET", "AF_INET6", "AF_UNIX", "AF_CAN"]
    assert svc["KillSignal"] == "SIGTERM"
    assert re.search(r"cdpr-gateway run --config \S+", svc["ExecStart"])
    assert "MemoryDenyWriteExecute" not in svc  # numba JIT needs W+X pages
    # supervised: sd_notify READY/WATCHDOG, no restart loop on a config error (exit 2)
    assert svc["Type"] == "notify"
    assert svc["WatchdogSec"].rstrip("s").isdigit() and int(svc["WatchdogSec"].rstrip("s")) > 0
    assert svc["RestartPreventExitStatus"].split() == ["2"]
    assert svc["Restart"] == "on-failure"
    # TLS keys reach the dynamic user only as credentials
    assert svc["LoadCredential"] == "tls:/etc/cdpr-gateway/tls"
    # room for the exporter's bounded connections plus its fd reserve for the bus
    assert int(svc["LimitNOFILE"]) >= 4096
    # real time granted
    assert svc["CPUSchedulingPolicy"] == "fifo"
    assert int(svc["LimitRTPRIO"]) >= int(svc["CPUSchedulingPriority"]) > 0
    assert svc["LimitMEMLOCK"] == "infinity"
    assert svc["RestrictRealtime"] == "no"


def _require(binary: str) -> str:
    path = shutil.which(binary)
    if path is None:
        if os.environ.get("CDPR_REQUIRE_EXTERNAL") == "1":
            pytest.fail(f"{binary} not installed but CDPR_REQUIRE_EXTERNAL=1")
        pytest.skip(f"{binary} not installed")
    return path


@pytest.mark.external
def test_promtool_accepts_the_scrape_config_and_rules(tmp_path):
    promtool = _require("promtool")
    shutil.copy(DEPLOY / "prometheus.yml", tmp_path)
    shutil.copy(DEPLOY / "alerts.yml", tmp_path)
    res = subprocess.run(
        [promtool, "check", "config", str(tmp_path / "prometheus.yml")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 0, res.stdout + res.stderr
    assert "SUCCESS: 8 rules found" in res.stdout, res.stdout


@pytest.mark.external
def test_promtool_checks_and_unit_tests_the_alerts(tmp_path):
    promtool = _require("promtool")
    check = subprocess.run(
        [promtool, "check", "rules", str(DEPLOY / "alerts.yml")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert check.returncode == 0, check.stdout + check.stderr
    res = subprocess.run(
        [promtool, "test", "rules", "alerts.test.yml"],
        cwd=DEPLOY,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stdout + res.stderr
    assert "SUCCESS" in res.stdout, res.stdout
    # the test file can fail: a budget below robot-a's 0.5 % makes it fire where it must not
    shutil.copy(DEPLOY / "alerts.test.yml", tmp_path)
    strict = (DEPLOY / "alerts.yml").read_text().replace("[5m]) > 0.02", "[5m]) > 0.001")
    assert strict != (DEPLOY / "alerts.yml").read_text()
    (tmp_path / "alerts.yml").write_text(strict)
    bad = subprocess.run(
        [promtool, "test", "rules", "alerts.test.yml"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bad.returncode != 0 and "CdprGatewayOverrunBudget" in bad.stdout + bad.stderr


@pytest.mark.external
def test_systemd_accepts_the_unit(tmp_path):
    analyze = _require("systemd-analyze")
    text = (DEPLOY / "cdpr-gateway.service").read_text()
    unit = tmp_path / "cdpr-gateway-check.service"
    unit.write_text(re.sub(r"(?m)^(ExecStart(?:Pre)?=).*$", r"\1/bin/true", text))
    res = subprocess.run([analyze, "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stdout + res.stderr
    # systemd ignores a key it does not know or cannot parse, with a line ending "ignoring"
    assert "Unknown key" not in res.stderr and "ignoring" not in res.stderr, res.stderr
    # ... which this check sees: a bad value makes it complain
    unit.write_text(unit.read_text().replace("WatchdogSec=5s", "WatchdogSec=banana"))
    bad = subprocess.run([analyze, "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert "ignoring" in bad.stderr, bad.stderr
