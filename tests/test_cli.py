"""The command line: commands listed, errors end with status 2 and one line."""

from __future__ import annotations

import pytest

from gateway.cli import COMMANDS, main
from tests.config_helpers import edited_config


def test_help_lists_every_command(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for name in COMMANDS:
        assert name in out


def test_unknown_command_is_an_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["frobnicate"])
    assert exc.value.code == 2
    assert "invalid choice" in capsys.readouterr().err


def test_every_command_module_exists() -> None:
    import importlib

    for module_name, _ in COMMANDS.values():
        module = importlib.import_module(module_name)
        assert callable(module.configure_parser) and callable(module.run_command)


# --- cdpr-gateway check ---------------------------------------------------------------


from gateway.core.config import DEFAULT_CONFIG_PATH  # noqa: E402
from tests.modbus_helpers import plc_server  # noqa: E402


def write_config(tmp_path, edit=None) -> str:
    return str(edited_config(tmp_path, edit))


def test_check_accepts_the_default_config(capsys) -> None:
    assert main(["check", "--config", str(DEFAULT_CONFIG_PATH)]) == 0
    out = capsys.readouterr().out
    assert "valid; 8 cables" in out and "plausible setpoints" in out


def test_check_register_count_mismatch_names_file_and_key(tmp_path, capsys) -> None:
    def six_channels(d):
        d["bus"]["modbus_tcp"]["registers"] = {
            "raw_tensions": {"address": 0, "count": 6, "type": "int16", "format": "s7_analog"}
        }

    path = write_config(tmp_path, six_channels)
    assert main(["check", "--config", path]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert f"{path}: bus.modbus_tcp.registers.raw_tensions: count 6, need 8" in err[0]


def test_check_register_overlap_names_the_file(tmp_path, capsys) -> None:
    def overlap(d):
        d["bus"]["modbus_tcp"]["registers"] = {
            "wrench": {"address": 120, "count": 6, "type": "float32"}
        }

    path = write_config(tmp_path, overlap)
    assert main(["check", "--config", path]) == 2
    err = capsys.readouterr().err
    assert f"{path}: bus.modbus_tcp.registers: " in err and "overlaps" in err


def test_check_missing_tls_file_names_the_key(tmp_path, capsys) -> None:
    def tls(d):
        d["bus"]["modbus_tcp"]["tls"] = {
            "certfile": str(tmp_path / "nope.pem"),
            "keyfile": str(tmp_path / "nope.key"),
        }

    path = write_config(tmp_path, tls)
    assert main(["check", "--config", path]) == 2
    err = capsys.readouterr().err
    assert f"{path}: bus.modbus_tcp.tls.certfile: " in err and "no such file" in err


def test_check_warns_about_max_tension_above_the_sensor_range(tmp_path, capsys) -> None:
    def high(d):
        d["tension"]["max_n"] = 900.0

    assert main(["check", "--config", write_config(tmp_path, high)]) == 0
    err = capsys.readouterr().err
    assert "warning:" in err and "tension.max_n" in err and "sensor range" in err


@pytest.mark.parametrize(
    ("section", "key", "value", "message"),
    [
        ("loop", "stale_after_s", -1, r"loop.stale_after_s: must be in 0.0001..60, got -1"),
        ("metrics", "port", 99999, r"metrics.port: must be in 0..65535"),
        ("limits", "max_cable_speed_m_s", 0, r"limits.max_cable_speed_m_s: must be in 1e-06"),
    ],
)
def test_impossible_values_are_refused_in_one_line(
    tmp_path, capsys, section, key, value, message
) -> None:
    def bad(d):
        d.setdefault(section, {})[key] = value

    path = write_config(tmp_path, bad)
    for command in ("check", "run"):
        assert main([command, "--config", path]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and path in err[0], err
        assert __import__("re").search(message, err[0]), err


def test_bad_log_level_is_one_line_and_status_2(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["run", "--config", str(DEFAULT_CONFIG_PATH), "--log-level", "LOUD"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'LOUD' is not a log level" in err[0]


def test_check_connect_reads_once_and_writes_nothing(tmp_path, capsys) -> None:
    with plc_server() as (server, img, _cfg):

        def point(d):
            d["bus"]["modbus_tcp"]["port"] = server.port

        path = write_config(tmp_path, point)
        assert main(["check", "--config", path, "--connect"]) == 0
        assert img.gateway_writes == 0  # nothing written
    out = capsys.readouterr().out
    assert "nothing written" in out
    assert f"PLC heartbeat     {img.plc_heartbeat}" in out
    first = float(out.split("tensions N")[1].split()[0])
    assert first == pytest.approx(img.raw_counts[0] * 500.0 / 27648, abs=0.01)


def test_check_connect_says_why_it_cannot_read(tmp_path, capsys) -> None:
    import socket

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]

    def point(d):
        d["bus"]["modbus_tcp"]["port"] = port
        d["bus"]["modbus_tcp"]["connect_timeout_s"] = 0.5

    assert main(["check", "--config", write_config(tmp_path, point), "--connect"]) == 1
    err = capsys.readouterr().err
    assert "cannot read from the PLC" in err and "refused" in err.lower()


def test_record_into_a_missing_directory_fails_before_simulating(tmp_path, capsys) -> None:
    import time

    out = tmp_path / "missing" / "x.csv"
    t0 = time.perf_counter()
    assert main(["record", "--seconds", "600", "--out", str(out), "--quiet"]) == 2
    assert time.perf_counter() - t0 < 60  # 600 s of plant were not simulated first
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--out {out}: directory" in err[0] and "does not exist" in err[0]
    assert not out.parent.exists()


def test_diagnose_json_into_a_missing_directory_is_refused(tmp_path, capsys) -> None:
    target = tmp_path / "nonexistent" / "x.json"
    argv = [
        "diagnose",
        str(tmp_path / "rec.csv"),
        "--model",
        str(DEFAULT_CONFIG_PATH),
        "--json",
        str(target),
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"--json {target}: directory" in err
    assert not target.parent.exists()


def test_the_daemons_modules_never_import_sim_plc() -> None:
    """sim_plc (soft PLC, demo, record) is on top of everything: the daemon never loads it."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    code = (
        "import sys, gateway.cli, gateway.service.daemon, gateway.service.metrics, "
        "gateway.service.check, gateway.runtime; "
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'sim_plc'))"
    )
    res = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=root, timeout=120
    )
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "[]"


def test_the_stopped_line_has_a_timestamp_like_every_log_line(tmp_path) -> None:
    """The final ``stopped: ...`` line was the one line without a time."""
    import re
    import subprocess
    import sys
    from pathlib import Path

    def virtual(data):
        data["bus"]["driver"] = "virtual"
        data["metrics"]["enabled"] = False

    path = edited_config(tmp_path, virtual, "virtual.yaml")
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run(
        [sys.executable, "-m", "gateway.cli", "run", "--config", str(path), "--cycles", "20"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=root,
    )
    assert done.returncode == 0, done.stderr
    lines = [ln for ln in done.stderr.splitlines() if "stopped: cycles" in ln]
    assert len(lines) == 1, done.stderr
    stamp = r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} INFO cdpr_gateway: stopped: cycles 20"
    assert re.match(stamp, lines[0]), lines[0]
