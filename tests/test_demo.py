"""``cdpr-gateway run`` and ``cdpr-gateway demo --offline`` end to end (bounded)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import yaml

from gateway.cli import main
from gateway.config import DEFAULT_CONFIG_PATH

ROOT = Path(__file__).resolve().parent.parent


def write_config(tmp_path: Path, **sections) -> Path:
    data = yaml.safe_load(DEFAULT_CONFIG_PATH.read_text())
    data["bus"]["driver"] = "virtual"
    data["metrics"]["port"] = 0
    for key, value in sections.items():
        data[key] = {**data.get(key, {}), **value}
    path = tmp_path / "gateway.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_run_bounded_cycles_exits_zero(tmp_path, capsys):
    path = write_config(tmp_path)
    assert main(["run", "--config", str(path), "--cycles", "50"]) == 0
    assert "cycles 50" in capsys.readouterr().err


def test_run_unknown_driver_names_the_key(tmp_path, capsys):
    path = write_config(tmp_path, bus={"driver": "profinet"})
    assert main(["run", "--config", str(path), "--cycles", "5"]) == 2
    err = capsys.readouterr().err
    assert "bus.driver" in err and "profinet" in err and str(path) in err


def test_run_bad_value_names_the_key(tmp_path, capsys):
    path = write_config(tmp_path, loop={"period_s": -1})
    assert main(["run", "--config", str(path)]) == 2
    assert re.search(r"loop\W+period_s", capsys.readouterr().err)


def test_run_sigterm_stops_cleanly(tmp_path):
    path = write_config(tmp_path)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "gateway.cli", "run", "--config", str(path)],
        stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT,
    )  # fmt: skip
    lines: list[str] = []
    ready = threading.Event()

    def reader() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            lines.append(line)
            if "connected to" in line:
                ready.set()

    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    try:
        assert ready.wait(60), "".join(lines)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    thread.join(timeout=10)
    assert proc.stderr is not None
    proc.stderr.close()
    text = "".join(lines)
    assert re.search(r"metrics on http://127\.0\.0\.1:\d+/metrics", text)
    assert "stopped: cycles" in text
    # issue 14: timestamps and logger names, the start-up banner, the state change
    stamp = r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} (INFO|WARNING) cdpr_gateway(\.loop)?: "
    assert re.search(stamp + r"cdpr-gateway \S+ starting; config " + re.escape(str(path)), text,
                     re.MULTILINE), text  # fmt: skip
    assert re.search(stamp + r"bus: virtual \(bus\.virtual\)", text, re.MULTILINE)
    assert re.search(stamp + r"model: dahl, 3 pulleys", text, re.MULTILINE)
    assert re.search(stamp + r"loop: period 1 ms, .*real-time scheduling", text, re.MULTILINE)
    assert re.search(stamp + r"connected to the PLC at virtual", text, re.MULTILINE)


@pytest.mark.slow
def test_demo_offline_corrected_beats_raw(capsys):
    assert main(["demo", "--offline", "--stand-in", "--seconds", "2"]) == 0
    out, err = capsys.readouterr()
    assert "demo (offline):" in err  # progress lines
    mean = re.search(r"mean\s+([\d.]+)\s+([\d.]+)", out)
    assert mean, out
    raw, corrected = float(mean.group(1)), float(mean.group(2))
    assert corrected < 0.25 * raw
    assert re.search(r"cycles\s+\d+", out) and "jitter p50 / p99" in out


@pytest.mark.slow
def test_demo_offline_with_the_plant(capsys):
    assert main(["demo", "--offline", "--seconds", "2"]) == 0
    out = capsys.readouterr().out
    mean = re.search(r"mean\s+([\d.]+)\s+([\d.]+)", out)
    assert mean, out
    assert float(mean.group(2)) < 0.5 * float(mean.group(1))
    assert "plant in process" in out
