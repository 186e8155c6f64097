"""``cdpr-gateway examples deploy DIR``: the service files written for this installation.

The unit's ``ExecStart`` runs the installing environment's console script (not the
``/opt`` path of the shipped template), its ``Documentation=`` names documents that exist,
the config it reads is written beside it, nothing is overwritten, and ``systemd-analyze
verify`` accepts the result as written (the binary it names exists). The wheel-installed
form runs in tests/system/test_readme_commands.py (the README's service command).
"""

from __future__ import annotations

import configparser
import os
import shutil
import subprocess
from pathlib import Path
from urllib.parse import unquote, urlparse

import pytest
import yaml

from gateway.cli import main
from gateway.core.resources import deploy_dir
from gateway.service import examples


def _unit(path: Path) -> configparser.SectionProxy:
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str  # type: ignore[assignment,method-assign]
    unit.read(path)
    return unit["Service"]


def _documentation(path: Path) -> list[str]:
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str  # type: ignore[assignment,method-assign]
    unit.read(path)
    return unit["Unit"]["Documentation"].split()


def test_deploy_writes_the_unit_for_this_installation(tmp_path, capsys):
    out = tmp_path / "service"
    assert main(["examples", "deploy", str(out)]) == 0
    written = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()}
    shipped = {p.as_posix() for p in examples.bundled_deploy()}
    assert shipped <= written and "gateway.yaml" in written, written
    assert {"cdpr-gateway.service", "alerts.yml", "alertmanager.yml"} <= shipped
    assert {"grafana-dashboard.json", "site/gateways.yml"} <= shipped
    exec_start = _unit(out / "cdpr-gateway.service")["ExecStart"].split()
    script = Path(exec_start[0])
    assert script == examples.console_script() and os.access(script, os.X_OK), exec_start
    assert "/opt/" not in exec_start[0] or script.is_file()
    assert exec_start[1:] == ["run", "--config", "/etc/cdpr-gateway/gateway.yaml"]
    pre = _unit(out / "cdpr-gateway.service")["ExecStartPre"].split()
    assert pre == [str(script), "warmup", "--config", "/etc/cdpr-gateway/gateway.yaml"], pre
    docs = _documentation(out / "cdpr-gateway.service")
    assert docs and all(urlparse(u).scheme == "file" for u in docs), docs
    assert all(Path(unquote(urlparse(u).path)).is_file() for u in docs), docs
    # every other file is the shipped one, byte for byte; gateway.yaml is the default config
    for rel in shipped - {"cdpr-gateway.service"}:
        assert (out / rel).read_bytes() == (deploy_dir() / rel).read_bytes(), rel
    assert yaml.safe_load((out / "gateway.yaml").read_text())["bus"]
    line = capsys.readouterr().out.strip()
    assert f"ExecStart {script}" in line and "service.md" in line, line


def test_deploy_never_overwrites_and_needs_a_dir(tmp_path, capsys):
    out = tmp_path / "service"
    out.mkdir()
    (out / "alerts.yml").write_text("mine\n")
    assert main(["examples", "deploy", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "alerts.yml: exists; nothing copied" in err[0], err
    assert (out / "alerts.yml").read_text() == "mine\n"
    assert sorted(p.name for p in out.iterdir()) == ["alerts.yml"]
    assert main(["examples", "deploy"]) == 2
    assert "needs DIR" in capsys.readouterr().err
    assert main(["examples", "a", "b"]) == 2
    assert "takes DIR or 'deploy DIR'" in capsys.readouterr().err


def test_the_listing_names_the_service_files(capsys):
    assert main(["examples"]) == 0
    out = capsys.readouterr().out
    assert "'cdpr-gateway examples deploy DIR' writes them" in out
    assert "cdpr-gateway.service" in out and "alertmanager.yml" in out


def test_a_unit_without_its_exec_line_is_refused():
    with pytest.raises(Exception, match="ExecStart"):
        examples.unit_text("[Service]\nExecStart=/bin/true\n", Path("/x/cdpr-gateway"), Path("/d"))


@pytest.mark.external
def test_systemd_accepts_the_written_unit_as_is(tmp_path):
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        if os.environ.get("CDPR_REQUIRE_EXTERNAL") == "1":
            pytest.fail("systemd-analyze not installed but CDPR_REQUIRE_EXTERNAL=1")
        pytest.skip("systemd-analyze not installed")
    out = tmp_path / "service"
    assert main(["examples", "deploy", str(out)]) == 0
    unit = out / "cdpr-gateway.service"
    res = subprocess.run([analyze, "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "Unknown key" not in res.stderr and "ignoring" not in res.stderr, res.stderr
    # ... and it would say so: a unit naming a binary that does not exist is refused
    text = unit.read_text().replace(str(examples.console_script()), "/nonexistent/cdpr-gateway")
    unit.write_text(text)
    bad = subprocess.run([analyze, "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert bad.returncode != 0 and "nonexistent" in bad.stderr, bad.stderr
