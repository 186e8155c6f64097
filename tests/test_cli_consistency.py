"""One command line: every command takes --log-level and --quiet,
--config is required where a bundled default would point at the wrong machine and says
its default elsewhere, and bad output paths fail up front in one line, never a traceback."""

from __future__ import annotations

import importlib
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gateway.cli import COMMANDS, main

ROOT = Path(__file__).resolve().parents[1]
REQUIRED_CONFIG = {"run", "check", "calibrate"}


def help_text(command: str, capsys) -> str:
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    return " ".join(capsys.readouterr().out.split())


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_command_has_the_common_options(command: str, capsys) -> None:
    text = help_text(command, capsys)
    assert "--log-level" in text and "--quiet" in text, text
    if command in ("examples", "diagnose", "export", "fleet"):
        return  # no config: bundled configs, a model file, a recording
    assert "--config" in text
    if command in REQUIRED_CONFIG:
        assert "--config FILE" in text and "(required" in text, text
    else:
        assert "default: the bundled" in text, text


def test_run_without_config_is_refused(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["run"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--config" in err[0]


def test_modules_do_not_define_the_common_options_twice() -> None:
    import argparse

    for name, (module_name, _) in COMMANDS.items():
        parser = argparse.ArgumentParser()
        importlib.import_module(module_name).configure_parser(name, parser)
        assert "--quiet" not in parser._option_string_actions, name
        assert "--log-level" not in parser._option_string_actions, name


def cli(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "gateway", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_replicate_into_an_impossible_directory_is_one_line_up_front() -> None:
    t0 = time.monotonic()
    res = cli("replicate", "--out", "/proc/nope", "--seconds", "1")
    assert res.returncode == 2, res.stderr
    assert "Traceback" not in res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "--out /proc/nope" in lines[0], res.stderr
    assert time.monotonic() - t0 < 60


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("rec") / "rec.csv"
    res = cli("record", "--seconds", "3", "--out", str(out), "--quiet")
    assert res.returncode == 0, res.stderr
    return out


def test_diagnose_report_onto_an_existing_file_fails_before_the_work(recording, tmp_path):
    existing = tmp_path / "taken"
    existing.write_text("x")
    res = cli(
        "diagnose",
        str(recording),
        "--model",
        "config/default.yaml",
        "--json",
        str(tmp_path / "r.json"),
        "--report",
        str(existing),
    )
    assert res.returncode == 2, res.stderr
    assert "Traceback" not in res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and f"--report {existing}" in lines[0], res.stderr
    assert not (tmp_path / "r.json").exists()  # refused before the diagnosis ran


def test_diagnose_needs_no_json_when_a_report_is_wanted(recording, tmp_path):
    res = cli(
        "diagnose",
        str(recording),
        "--model",
        "config/default.yaml",
        "--report",
        str(tmp_path / "rep"),
        "--quiet",
    )
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "rep" / "summary.md").is_file()
    assert res.stdout.startswith("verdict: ")
    assert res.stderr == ""  # --quiet


def test_replicate_takes_seconds_like_every_other_command(capsys) -> None:
    text = help_text("replicate", capsys)
    assert "--seconds SECONDS" in text and "--seconds-limit" not in text
