"""The README's commands run as written from a wheel install in an empty directory: the
wheel is built and installed into a fresh venv by .ci/wheel-check, whole (the demo on both
buses outside the tree, `fleet` without its extra: CI's wheel check, run here once and not
again by .ci/run), then every ``cdpr-gateway ...`` line of the README's ``sh`` blocks runs,
in order, in an empty directory with that venv first on PATH and no PYTHONPATH. The
README's ``calibrate`` is CI's end-to-end calibration: its result is checked as
tests/sim_plc/test_calibrate.py states it (:func:`check_calibration`)."""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.sim_plc.test_calibrate import check_calibration

ROOT = Path(__file__).resolve().parents[2]
pytestmark = [pytest.mark.long]


def readme_commands(text: str) -> list[str]:
    """Every ``cdpr-gateway`` command of the README's ``sh`` blocks, and every install of
    an extra (``pip install 'cdpr-gateway[EXTRA]'``), continuation lines joined, comments
    dropped, in order."""
    commands: list[str] = []
    for block in re.findall(r"```sh\n(.*?)```", text, re.S):
        joined = re.sub(r"\\\n\s*", " ", block)
        for line in joined.splitlines():
            line = line.split(" #", 1)[0].strip()
            if line.startswith(("cdpr-gateway ", "pip install 'cdpr-gateway[")):
                commands.append(line)
    return commands


def extra_requirements(extra: str) -> list[str]:
    """The requirements of an optional dependency group of pyproject.toml."""
    import tomllib

    data = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return list(data["project"]["optional-dependencies"][extra])


def test_the_readme_lists_the_commands_a_wheel_user_needs() -> None:
    commands = readme_commands((ROOT / "README.md").read_text())
    assert commands[0] == "cdpr-gateway examples config", commands  # before any --config
    used = {c.split()[1] for c in commands if c.startswith("cdpr-gateway ")}
    assert {"examples", "record", "diagnose", "calibrate"} <= used, commands


@pytest.mark.timeout(1800)  # a wheel installed into a fresh venv, two demos, calibrate's 4 x 30 s
def test_readme_commands_run_from_a_wheel_in_an_empty_directory(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "NOTIFY_SOCKET")}
    install = tmp_path / "install"
    res = subprocess.run(
        [str(ROOT / ".ci" / "wheel-check"), sys.executable],
        env={**env, "WHEEL_CHECK_VENV": str(install)},
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert res.returncode == 0, res.stdout + res.stderr
    assert "wheel-check: OK" in res.stdout and "demo runs skipped" not in res.stdout, res.stdout
    empty = tmp_path / "empty"
    empty.mkdir()
    env["PATH"] = f"{install / 'venv' / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    calibrated = False
    for command in readme_commands((ROOT / "README.md").read_text()):
        print(f"README: {command}", flush=True)  # with -s: where a slow run is
        argv = shlex.split(command)
        if argv[0] == "pip":  # the extra's requirements into the wheel's venv (the wheel
            # itself is not on the package index here)
            extra = re.fullmatch(r"cdpr-gateway\[(\w+)\]", argv[2]).group(1)  # type: ignore[union-attr]
            argv = [
                str(install / "venv" / "bin" / "python"),
                "-m",
                "pip",
                "install",
                "-q",
                *extra_requirements(extra),
            ]
        run = subprocess.run(argv, cwd=empty, env=env, capture_output=True, text=True, timeout=600)
        assert run.returncode == 0, f"{command}\n{run.stdout}\n{run.stderr}"
        assert "Traceback" not in run.stderr, command
        if command.startswith("cdpr-gateway diagnose"):
            assert run.stdout.startswith("verdict: viscous"), run.stdout
        if command.startswith("cdpr-gateway calibrate --config config/calibrate/viscous.yaml"):
            out = empty / argv[argv.index("--out") + 1]
            check_calibration(out, run.stdout, run.stderr)
            calibrated = True
    assert calibrated, "the README no longer calibrates viscous.yaml: CI's one calibration"
    # the README's service command wrote the unit for the wheel's venv, as docs/service.md
    # installs it: systemd accepts it as written (the binary it runs exists)
    unit = empty / "service" / "cdpr-gateway.service"
    exec_start = next(
        line for line in unit.read_text().splitlines() if line.startswith("ExecStart=")
    )
    assert exec_start.startswith(f"ExecStart={install / 'venv' / 'bin' / 'cdpr-gateway'} run")
    assert (empty / "service" / "gateway.yaml").is_file()
    analyze = shutil.which("systemd-analyze")
    if analyze is not None or os.environ.get("CDPR_REQUIRE_EXTERNAL") == "1":
        assert analyze is not None, "systemd-analyze not installed but CDPR_REQUIRE_EXTERNAL=1"
        res = subprocess.run(
            [analyze, "verify", str(unit)], capture_output=True, text=True, timeout=60
        )
        assert res.returncode == 0 and "ignoring" not in res.stderr, res.stderr
