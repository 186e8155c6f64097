"""``check`` answers every config with exit 0 or one line per problem and exit 2, never a
traceback (``plc_heartbeat`` with count 2 gave one), and files it is told to
read must be regular and bounded (``check --config /dev/zero``, an EDS symlinked to
/dev/zero, ``diagnose --model /dev/zero`` were read until killed at 1.5 GB; a FIFO hung).
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gateway.cli import main
from gateway.core.config import DEFAULT_CONFIG_PATH
from gateway.core.configtypes import read_yaml
from gateway.core.resources import data_dir

FIXTURES = sorted(data_dir().rglob("*.yaml"))
OUTPUTS = ("corrected_tensions", "channel_status", "gateway_heartbeat", "gateway_state", "wrench")
INPUTS = ("raw_tensions", "setpoint_velocities", "setpoint_lengths", "pose", "plc_heartbeat")


def _check(capsys, path: Path, *extra: str) -> tuple[int, list[str]]:
    status = main(["check", "--config", str(path), *extra])
    captured = capsys.readouterr()
    err = [ln for ln in captured.err.splitlines() if ln.strip()]
    assert "Traceback" not in captured.err and "Traceback" not in captured.out
    return status, err


def _one_line_each(status: int, err: list[str]) -> None:
    assert status in (0, 2), err
    problems = [ln for ln in err if ln.startswith("cdpr-gateway check: error:")]
    warnings = [ln for ln in err if ln.startswith("warning:")]
    assert len(problems) + len(warnings) == len(err), err  # nothing but those lines
    assert (status == 2) == bool(problems), err


@pytest.mark.parametrize("path", FIXTURES, ids=[p.name for p in FIXTURES])
def test_every_shipped_config_passes_check(capsys, path: Path) -> None:
    status, err = _check(capsys, path)
    _one_line_each(status, err)
    assert status == 0, err


FIELD = st.fixed_dictionaries(
    {
        "address": st.one_of(st.integers(0, 160), st.integers(-5, 70000)),
        "count": st.one_of(st.sampled_from([1, 2, 6, 8]), st.integers(-1, 130)),
        "type": st.sampled_from(["int16", "uint16", "int32", "uint32", "float32", "int8"]),
    },
    optional={
        "word_order": st.sampled_from(["high_first", "low_first", "middle"]),
        "scale": st.sampled_from([1.0, 0.1, 0.01, -1.0, 0.0, 1e-12, 1e12, 1e300]),
        "format": st.sampled_from(["plain", "s7_analog", "bcd"]),
        "invalid": st.integers(-(2**33), 2**33),
    },
)


@settings(
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(st.dictionaries(st.sampled_from(INPUTS + OUTPUTS + ("platform_mass",)), FIELD))
def test_any_register_map_gets_one_line_per_problem(tmp_path_factory, capsys, fields) -> None:
    data = read_yaml(DEFAULT_CONFIG_PATH)
    data["bus"]["modbus_tcp"]["registers"].update(fields)
    path = tmp_path_factory.mktemp("map") / "map.yaml"
    path.write_text(yaml.safe_dump(data))
    status, err = _check(capsys, path)
    _one_line_each(status, err)


def test_plc_heartbeat_of_two_registers_is_one_line(tmp_path, capsys) -> None:
    data = read_yaml(DEFAULT_CONFIG_PATH)
    data["bus"]["modbus_tcp"]["registers"]["plc_heartbeat"] = {"address": 60, "count": 2}
    path = tmp_path / "hb.yaml"
    path.write_text(yaml.safe_dump(data))
    status, err = _check(capsys, path)
    assert status == 2 and len(err) == 1, err
    assert "registers.plc_heartbeat: count 2, need 1" in err[0]


def _fifo(tmp_path: Path) -> Path:
    path = tmp_path / "fifo.yaml"
    os.mkfifo(path)
    return path


@pytest.mark.parametrize("target", ["/dev/zero", "fifo", "dir"])
def test_check_refuses_what_is_not_a_regular_file_at_once(tmp_path, capsys, target) -> None:
    path = {"/dev/zero": Path("/dev/zero"), "fifo": None, "dir": tmp_path}[target]
    path = path if path is not None else _fifo(tmp_path)
    done: list[tuple[int, list[str]]] = []
    worker = threading.Thread(target=lambda: done.append(_check(capsys, path)), daemon=True)
    worker.start()
    worker.join(timeout=30)  # a FIFO must not hang the open
    assert done, "check hung"
    status, err = done[0]
    assert status == 2 and len(err) == 1, err
    assert str(path) in err[0] and "not a regular" in err[0], err


def test_an_eds_symlinked_to_dev_zero_is_refused(tmp_path, capsys) -> None:
    eds = tmp_path / "gateway.eds"
    eds.symlink_to("/dev/zero")
    data = read_yaml(DEFAULT_CONFIG_PATH)
    data["bus"]["driver"] = "canopen"
    data["bus"]["canopen"] = {"gateway_eds": str(eds)}
    path = tmp_path / "can.yaml"
    path.write_text(yaml.safe_dump(data))
    status, err = _check(capsys, path)
    assert status == 2 and len(err) == 1, err
    assert "bus.canopen.gateway_eds" in err[0] and "character device" in err[0], err


def test_a_huge_config_is_refused_before_it_is_read(tmp_path, capsys) -> None:
    path = tmp_path / "huge.yaml"
    with path.open("wb") as fh:
        fh.truncate(64 << 20)  # sparse: 64 MiB of zeros costs no disk
    status, err = _check(capsys, path)
    assert status == 2 and len(err) == 1 and "more than" in err[0], err


def test_diagnose_refuses_a_model_that_is_not_a_regular_file(tmp_path, capsys) -> None:
    rec = tmp_path / "rec.csv"
    rec.write_text("t,velocity_1,tension_sensor_1,tension_platform_1\n0,0,1,1\n0.001,0,1,1\n")
    status = main(["diagnose", str(rec), "--model", "/dev/zero", "--json", str(tmp_path / "r")])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1 and "/dev/zero" in err[0], err
