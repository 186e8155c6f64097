"""deploy/: the dashboard and alerts only use metrics the gateway exports; unit hardening."""

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

from gateway.config import load_config
from gateway.metrics import make_registry
from tests.test_metrics import ran_service

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"

PROMQL_WORDS = {
    # functions and aggregations used (or plausibly used) in the dashboard and alerts
    "histogram_quantile", "rate", "irate", "increase", "sum", "max", "min", "avg", "count",
    "max_over_time", "min_over_time", "avg_over_time", "delta", "deriv", "abs", "topk",
    "bottomk", "clamp_min", "clamp_max", "changes", "resets", "time", "vector", "label_replace",
    # keywords
    "by", "without", "on", "ignoring", "group_left", "group_right", "and", "or", "unless",
    "offset", "bool",
}  # fmt: skip
LABELS = {"le", "bus", "kind", "cable", "version"}
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


def dashboard_exprs() -> list[str]:
    dash = json.loads((DEPLOY / "grafana-dashboard.json").read_text())
    exprs = [t["expr"] for p in dash["panels"] for t in p.get("targets", [])]
    assert len(exprs) >= 10
    return exprs


def alert_exprs() -> list[str]:
    rules = yaml.safe_load((DEPLOY / "alerts.yml").read_text())
    return [r["expr"] for g in rules["groups"] for r in g["rules"]]


def test_the_parser_finds_metric_names():
    expr = 'histogram_quantile(0.99, sum by (le) (rate(foo_bucket{bus="x"}[1m]))) / bar_total'
    assert metric_names(expr) == {"foo_bucket", "bar_total"}


def test_every_dashboard_query_uses_exported_metrics():
    exported = exported_series()
    used: set[str] = set()
    for expr in dashboard_exprs():
        names = metric_names(expr)
        assert names, expr
        assert names <= exported, f"{expr}: {names - exported} not exported"
        used |= names
    families = {n.removesuffix("_bucket").removesuffix("_sum").removesuffix("_count") for n in used}
    # the dashboard shows every family of the design table
    assert {n.removesuffix("_total") for n in families} >= {
        "cdpr_gateway_cycle_seconds", "cdpr_gateway_jitter_seconds", "cdpr_gateway_overruns",
        "cdpr_gateway_bus_roundtrip_seconds", "cdpr_gateway_errors", "cdpr_gateway_reconnects",
        "cdpr_gateway_connected", "cdpr_gateway_tension_raw_newtons",
        "cdpr_gateway_tension_corrected_newtons", "cdpr_gateway_friction_newtons",
        "cdpr_gateway_channel_status", "cdpr_gateway_build_info",
    }  # fmt: skip


def test_every_alert_uses_exported_metrics():
    exported = exported_series() | BUILTIN_SERIES
    for expr in alert_exprs():
        names = metric_names(expr)
        assert names and names <= exported, expr


def test_scrape_config_targets_the_default_exporter():
    prom = yaml.safe_load((DEPLOY / "prometheus.yml").read_text())
    cfg = load_config()
    targets = [t for job in prom["scrape_configs"] for sc in job["static_configs"]
               for t in sc["targets"]]  # fmt: skip
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
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert res.returncode == 0, res.stdout + res.stderr
    assert "SUCCESS: 4 rules found" in res.stdout, res.stdout


def test_systemd_accepts_the_unit(tmp_path):
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze not installed")
    text = (DEPLOY / "cdpr-gateway.service").read_text()
    unit = tmp_path / "cdpr-gateway-check.service"
    unit.write_text(re.sub(r"(?m)^ExecStart=.*$", "ExecStart=/bin/true", text))
    res = subprocess.run([analyze, "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "Unknown key" not in res.stderr, res.stderr
