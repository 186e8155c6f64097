"""Packaging: the shipped configs are found wherever the package is installed, EDS paths
resolve beside their config file, plain ``pytest`` works, the daemon loads no sim_plc, and
``replicate`` fails when one of its own goals is missed."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from gateway.core.config import DEFAULT_CONFIG_PATH, load_config
from gateway.core.configtypes import read_yaml
from gateway.core.resources import data_dir, data_file

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = ("default.yaml", "replicate.yaml", "gateway.eds", "analog_in_401.eds", "plc_master.eds")


def test_the_shipped_files_are_found_through_the_package():
    assert {p.name for p in data_dir().iterdir()} >= set(SHIPPED)
    for name in SHIPPED:
        assert data_file(name).is_file(), name
    assert data_file("default.yaml") == DEFAULT_CONFIG_PATH
    # the wheel maps config/ to gateway/data/ (setup.py): every shipped file matches it
    patterns = {p.suffix for p in (ROOT / "config").rglob("*") if p.is_file()}
    assert patterns <= {".yaml", ".eds"}, patterns


def test_eds_paths_resolve_beside_the_config_file(tmp_path):
    data = read_yaml(DEFAULT_CONFIG_PATH)
    data["bus"]["canopen"] = {
        "gateway_eds": "nodes/my_gateway.eds",
        "plc_eds": str(data_file("plc_master.eds")),
    }
    path = tmp_path / "site" / "gateway.yaml"
    path.parent.mkdir()
    path.write_text(yaml.safe_dump(data))
    can = load_config(path).bus.canopen
    assert can.gateway_eds == str(tmp_path / "site" / "nodes" / "my_gateway.eds")  # stated
    assert can.plc_eds == str(data_file("plc_master.eds"))  # absolute: as given
    assert can.analog_eds == str(data_file("analog_in_401.eds"))  # left out: shipped


def test_a_config_copied_elsewhere_still_finds_the_shipped_eds(tmp_path):
    from drivers.canopen_pdo import load_pdo_layouts

    copy = tmp_path / "gateway.yaml"
    copy.write_text(DEFAULT_CONFIG_PATH.read_text())
    can = load_config(copy).bus.canopen
    tpdos, rpdos = load_pdo_layouts(can.gateway_eds, can.gateway_node_id)
    assert tpdos and rpdos


def test_plain_pytest_finds_the_tests_package(tmp_path):
    """`pytest` (not `python -m pytest`) imports tests.* helpers: pythonpath in pyproject."""
    pytest_bin = Path(sys.executable).with_name("pytest")
    if not pytest_bin.exists():
        pytest.skip("no pytest script beside this interpreter")
    res = subprocess.run(
        [
            str(pytest_bin),
            "-q",
            "-p",
            "no:cacheprovider",
            "--collect-only",
            "tests/service/test_deploy.py",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    assert "No module named 'tests'" not in res.stdout


def test_the_daemon_modules_load_no_sim_plc():
    """gateway.cli reaches sim_plc's subcommands only by name (importlib), at the time the
    subcommand runs: importing the daemon's modules and running `run --help` loads none."""
    code = (
        "import sys, contextlib, io\n"
        "import gateway.cli, gateway.service.daemon, gateway.service.metrics\n"
        "import gateway.service.exporter, gateway.runtime.loop\n"
        "with contextlib.suppress(SystemExit), contextlib.redirect_stdout(io.StringIO()):\n"
        "    gateway.cli.main(['run', '--help'])\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'sim_plc'))\n"
    )
    res = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.strip() == "[]"


def test_replicate_exits_1_naming_a_missed_goal(monkeypatch, capsys, tmp_path):
    from sim_plc import replicate

    goals = {
        "improvement_at_least_85pct": {"value": 0.9, "target": ">= 0.85", "met": True},
        "hysteresis_after_at_most_2n": {"value": 3.5, "target": "<= 2 N", "met": False},
    }
    monkeypatch.setattr(replicate, "replicate", lambda *a, **k: {"goals": goals})
    args = argparse.Namespace(
        config=str(DEFAULT_CONFIG_PATH), out=str(tmp_path), seconds=1.0, no_plots=True
    )
    assert replicate.run_command("replicate", args) == 1
    err = capsys.readouterr().err
    assert "goal missed: hysteresis_after_at_most_2n" in err
    goals["hysteresis_after_at_most_2n"]["met"] = True
    assert replicate.run_command("replicate", args) == 0


def test_building_the_package_warns_about_nothing(tmp_path):
    """A wheel built from setup.py's package map: no 'Package ... is absent' (the 40-line
    warning every fresh install printed for gateway.data.calibrate), and every shipped
    config lands under gateway/data/, the calibrate examples included, and so do the
    service files (gateway/data/deploy/) and the documents (gateway/data/docs/)."""
    import zipfile

    res = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-w", str(tmp_path), str(ROOT)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode == 0, res.stderr
    out = res.stdout + res.stderr
    assert "is absent" not in out and "would be ignored" not in out, out
    (wheel,) = tmp_path.glob("cdpr_gateway-*.whl")
    prefix = "gateway/data/"
    built = {n[len(prefix) :] for n in zipfile.ZipFile(wheel).namelist() if n.startswith(prefix)}
    shipped = {
        p.relative_to(ROOT / "config").as_posix()
        for p in (ROOT / "config").rglob("*")
        if p.is_file()
    }
    assert shipped <= built, shipped - built
    # the evaluation (suites, sealed draws, real-data converters, baseline, fault proxy) is
    # the tests' and benchmarks', not the product's
    names = zipfile.ZipFile(wheel).namelist()
    assert not [n for n in names if n.startswith(("evaluation/", "tests/", "bench/"))]
    # `examples deploy` writes the service files and points the unit at the documents:
    # both come from the wheel
    for folder in ("deploy", "docs"):
        files = {
            f"{folder}/{p.relative_to(ROOT / folder).as_posix()}"
            for p in (ROOT / folder).rglob("*")
            if p.is_file() and p.suffix in (".yml", ".json", ".service", ".md")
        }
        assert files and files <= built, files - built


def test_every_runtime_dependency_is_imported_by_the_shipped_code():
    """[project] dependencies hold what the installed package imports (gateway, drivers,
    sim_plc); a library only the tests use (pymodbus' client) belongs to ``dev``."""
    import ast
    import re
    import tomllib

    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    names = {re.split(r"[<>=!~ \[;]", d, maxsplit=1)[0].lower() for d in deps}
    module_of = {"pyyaml": "yaml", "python-can": "can", "prometheus-client": "prometheus_client"}
    imported: set[str] = set()
    for package in ("gateway", "drivers", "sim_plc"):
        for path in (ROOT / package).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Import):
                    imported |= {a.name.split(".")[0] for a in node.names}
                elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                    imported.add(node.module.split(".")[0])
    unused = sorted(n for n in names if module_of.get(n, n.replace("-", "_")) not in imported)
    assert unused == [], f"runtime dependencies nothing shipped imports: {unused}"
