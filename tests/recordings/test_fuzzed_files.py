"""Every CLI entry point that reads a recording, on fuzzed files (issue 30 item 4): the
file read whole (exit 0) or refused in one line of the project's own (exit 2), never a
traceback, whatever was cut, flipped or inserted, in CSV, CSV.gz and Parquet. In process
(gateway.cli.main): an exception that is not the project's fails the test with its
traceback."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from gateway.cli import main
from gateway.recordings.reader import Recording, write_recording

ROOT = Path(__file__).resolve().parents[2]
MODEL = ROOT / "config" / "default.yaml"
N = 60


def _honest(suffix: str, tmp: Path) -> bytes:
    rng = np.random.default_rng(3)
    t = np.arange(N) * 1e-3
    rec = Recording(
        t=t,
        velocity=rng.normal(0, 0.05, (N, 2)),
        tension_sensor=rng.uniform(100, 200, (N, 2)),
        tension_platform=rng.uniform(100, 200, (N, 2)),
        metadata={"robot": "fuzz", "started": "2026-11-28T10:00:00+00:00"},
    )
    path = tmp / f"honest{suffix}"
    write_recording(path, rec)
    return path.read_bytes()


@pytest.fixture(scope="module")
def honest(tmp_path_factory) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("honest")
    out = {}
    for suffix in (".csv", ".csv.gz", ".parquet"):
        path = tmp / f"data{suffix}"
        path.write_bytes(_honest(suffix, tmp))
        out[suffix] = path
    return out


def mutate(data: bytes, kind: str, at: float, noise: bytes) -> bytes:
    i = int(at * len(data))
    if kind == "cut":
        return data[:i]
    if kind == "flip":
        b = bytearray(data)
        for k, x in enumerate(noise[:8]):
            b[(i + 997 * k) % len(b)] ^= x or 0xFF
        return bytes(b)
    return data[:i] + noise + data[i:]  # insert


def run(argv: list[str], capsys) -> tuple[int, list[str]]:
    status = main(argv)
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    return status, err


FUZZ = {
    "suffix": st.sampled_from([".csv", ".csv.gz", ".parquet"]),
    "kind": st.sampled_from(["cut", "flip", "insert"]),
    "at": st.floats(0.0, 1.0),
    "noise": st.binary(min_size=1, max_size=64),
}


@settings(
    max_examples=120,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(**FUZZ)
def test_export_reads_whole_or_refuses_in_one_line(
    tmp_path, capsys, honest, suffix, kind, at, noise
):
    path = tmp_path / f"fuzzed{suffix}"
    path.write_bytes(mutate(honest[suffix].read_bytes(), kind, at, noise))
    status, err = run(["export", str(path), "--to", "mcap", str(tmp_path / "o.mcap")], capsys)
    assert status in (0, 2), (status, err)
    if status == 2:
        errors = [e for e in err if "error:" in e]
        assert len(errors) == 1 and str(path) in errors[0], err
    assert not any("Traceback" in e for e in err), err


@settings(
    max_examples=12,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(**FUZZ)
@example(suffix=".csv", kind="cut", at=0.46484375, noise=b"\x00")  # 27 rows: a bin fit of none
def test_diagnose_reads_whole_or_refuses_in_one_line(
    tmp_path, capsys, honest, suffix, kind, at, noise
):
    path = tmp_path / f"fuzzed{suffix}"
    path.write_bytes(mutate(honest[suffix].read_bytes(), kind, at, noise))
    status, err = run(
        [
            "diagnose",
            str(path),
            "--model",
            str(MODEL),
            "--json",
            str(tmp_path / "r.json"),
            "--quiet",
        ],
        capsys,
    )
    assert status in (0, 2), (status, err)
    if status == 2:
        errors = [e for e in err if "error:" in e]
        assert len(errors) == 1 and str(path) in errors[0], err


def test_a_schema_name_that_is_not_utf8_is_refused_in_one_line(honest, tmp_path, capsys) -> None:
    """The fuzz's first find (a flipped byte in a column name of the footer: pyarrow's
    UnicodeDecodeError as it opened the file), kept as an example."""
    data = honest[".parquet"].read_bytes()
    name = b"tension_sensor_1"
    at = data.rindex(name)  # the footer's schema
    bad = tmp_path / "bad.parquet"
    bad.write_bytes(data[:at] + b"\xa0" + data[at + 1 :])
    status, err = run(["export", str(bad), "--to", "mcap", str(tmp_path / "o.mcap")], capsys)
    assert status == 2
    assert len(err) == 1 and "not UTF-8" in err[0] and str(bad) in err[0], err
