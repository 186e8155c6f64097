"""Recordings (docs/recording-format.md): round trips, skipped rows, malformed files refused."""

from __future__ import annotations

import gzip
import re
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from gateway.core.config import DEFAULT_CONFIG_PATH
from gateway.errors import RecordingError
from gateway.recordings.reader import Recording, read_recording, write_recording

HEADER = "t,velocity_1,tension_sensor_1,tension_platform_1"


def sample(n: int = 50, m: int = 2) -> Recording:
    rng = np.random.default_rng(0)
    return Recording(
        t=np.cumsum(rng.uniform(0.5e-3, 1.5e-3, n)),  # uneven sampling
        velocity=rng.normal(0, 0.05, (n, m)),
        tension_sensor=rng.uniform(-50, 400, (n, m)),
        tension_platform=rng.uniform(-50, 400, (n, m)),
        length=rng.uniform(1, 3, (n, m)),
        metadata={"source": "test", "operator": "x"},
    )


@pytest.mark.parametrize("name", ["rec.csv", "rec.csv.gz"])
def test_round_trip(tmp_path: Path, name: str) -> None:
    rec = sample()
    write_recording(tmp_path / name, rec)
    back = read_recording(tmp_path / name)
    assert back.cables == 2 and back.samples == 50 and back.skipped_rows == 0
    for field in ("t", "velocity", "tension_sensor", "tension_platform", "length"):
        assert_allclose(getattr(back, field), getattr(rec, field), rtol=1e-9)
    assert back.metadata == {"source": "test", "operator": "x"}


def test_missing_required_value_skips_row_and_optional_is_nan(tmp_path: Path) -> None:
    rec = sample(20)
    rec.tension_platform[3, 1] = np.nan  # required: row skipped
    rec.length[5, 0] = np.nan  # optional: kept as NaN
    write_recording(tmp_path / "r.csv", rec)
    back = read_recording(tmp_path / "r.csv")
    assert back.samples == 19 and back.skipped_rows == 1
    assert np.isnan(back.length).sum() == 1


def test_hand_written_file_with_metadata_blank_lines_and_extra_columns(tmp_path: Path) -> None:
    path = tmp_path / "hand.csv"
    path.write_text(
        "# source: logger\n# anything: kept\n"
        "t,velocity_1,tension_sensor_1,tension_platform_1,temperature\n"
        "0.0,0.1,100,101,20\n\n0.002,-0.1,102,100,\n"
    )
    rec = read_recording(path, min_samples=1)
    assert rec.metadata["anything"] == "kept"
    assert rec.samples == 2 and rec.cables == 1
    assert np.isnan(rec.extra["temperature"][1])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("velocity_1,tension_sensor_1,tension_platform_1\n1,2,3\n", r":1: no 't' column"),
        (f"{HEADER}\n0,1,2,3\n0.1,1,abc,3\n", r":3: column 'tension_sensor_1': 'abc' is not"),
        (f"{HEADER}\n0,1,2,3\n0,1,2,3\n", r":3: column 't': 0.0 does not increase"),
        (f"{HEADER}\n0,1,2,3\n0.1,1,2\n", r":3: 3 fields, header has 4"),
        ("t,velocity_1,tension_platform_1\n0,1,2\n", r"cable 1 has no column 'tension_sensor_1'"),
        (
            "t,velocity_1,tension_sensor_1,velocity_2,tension_sensor_2,tension_platform_1\n"
            "0,1,2,3,4,5\n",
            r"'tension_platform_2' is missing",
        ),
        ("t,velocity_1,tension_sensor_1\n0,1,2\n", r"no tension_platform_i columns"),
        (f"{HEADER}\n", r"no data rows"),
        (f"{HEADER}\n0,1,inf,3\n", r"value is not finite"),
        ("t,t,velocity_1\n", r"column 't' appears twice"),
    ],
)
def test_malformed_files_are_refused_with_line_and_column(
    tmp_path: Path, text: str, message: str
) -> None:
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(RecordingError, match=message):
        read_recording(path, min_samples=1)


def test_pose_and_mass_stand_in_for_platform_tension(tmp_path: Path) -> None:
    path = tmp_path / "pose.csv"
    path.write_text("t,velocity_1,tension_sensor_1,x,y,z,rx,ry,rz,mass\n0,0,1,0,0,1,0,0,0,50\n")
    rec = read_recording(path, min_samples=1)
    assert rec.tension_platform is None
    assert rec.pose is not None and rec.pose.shape == (1, 6)
    assert rec.mass is not None and rec.mass[0] == 50


def test_corrupt_gzip_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "x.csv.gz"
    path.write_bytes(gzip.compress(b"t,velocity_1\n")[:10])
    with pytest.raises(RecordingError, match="cannot read"):
        read_recording(path)


def test_spreadsheet_csv_with_bom_and_quoted_header(tmp_path: Path) -> None:
    path = tmp_path / "excel.csv"
    text = '# source: excel\r\n"t","velocity_1","tension_sensor_1","tension_platform_1"\r\n'
    text += "0,0.1,100,101\r\n1e-3,0.1,100.5,101.5\r\n"
    path.write_bytes(b"\xef\xbb\xbf" + text.encode())
    rec = read_recording(path, min_samples=1)
    assert rec.metadata == {"source": "excel"}
    assert rec.samples == 2 and rec.cables == 1
    assert_allclose(rec.tension_sensor[:, 0], [100.0, 100.5])


# --- hostile and tiny inputs ----------------------------------------------------------------
def _rows(n: int, t0: float = 0.0, dt: float = 1e-3) -> str:
    return "".join(f"{t0 + k * dt!r},0.1,{100 + k},{101 + k}\n" for k in range(n))


@pytest.mark.parametrize(
    ("text", "message"),
    [
        # an 81-byte file naming cable 100000000: refused before any per-cable list exists
        (
            "t,velocity_100000000,tension_sensor_100000000,tension_platform_100000000\n0,1,2,3\n",
            r"cable indices must be contiguous 1..m with m <= 1024",
        ),
        ("t,velocity_0,tension_sensor_0,tension_platform_0\n0,1,2,3\n", r"contiguous 1..m"),
        (
            "t,velocity_1,tension_sensor_1,tension_platform_1,velocity_3,tension_sensor_3,"
            "tension_platform_3\n",
            r"cable 2 has no column 'velocity_2'",
        ),
        (f"{HEADER}\n" + _rows(5, dt=1e-300), r":3: column 't': time step 1e-300 s is below"),
        (f"{HEADER}\n" + _rows(20) + "1,0.1,1e300,3\n", r":22: column 'tension_sensor_1': 1e\+300"),
        (
            f"{HEADER}\n" + _rows(20) + "1,0.1,-inf,3\n",
            r":22: column 'tension_sensor_1': value is not",
        ),
        (f"{HEADER}\n" + _rows(1), r"too short: 1 samples, at least 10"),
        (f"{HEADER}\n" + _rows(2), r"too short: 2 samples"),
        ("# " + "x" * (1 << 20) + "\n", r":1: line longer than"),
        (f"{HEADER}\n" + _rows(20) + "1" * (1 << 21) + "\n" + _rows(3), r":22: line longer than"),
    ],
)
def test_hostile_and_tiny_inputs_are_refused(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(RecordingError, match=message):
        read_recording(path)


def test_huge_cable_index_is_refused_without_memory(tmp_path: Path) -> None:
    import resource

    path = tmp_path / "tiny.csv"
    path.write_text("t,velocity_100000000,tension_sensor_100000000\n0,1,2\n")
    assert path.stat().st_size < 100
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(RecordingError, match="contiguous"):
        read_recording(path)
    grown_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before
    assert grown_kb < 50_000  # the old reader built 1e8-long lists here (> 3 GB)


def test_max_samples_limit(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import gateway.recordings.reader as recording

    path = tmp_path / "long.csv.gz"
    with gzip.open(path, "wt") as fh:
        fh.write(f"{HEADER}\n" + _rows(500))
    assert read_recording(path, max_samples=500).samples == 500
    with pytest.raises(RecordingError, match=r"more than 499 samples"):
        read_recording(path, max_samples=499)
    monkeypatch.setattr(recording, "MAX_VALUES", 4 * 300)  # the memory bound: values
    with pytest.raises(RecordingError, match=r"more than 300 samples of 4 columns"):
        read_recording(path)


def test_chunks_join_seamlessly(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Across chunk borders: values, skipped rows and the time check are the same."""
    import gateway.recordings.reader as recording

    monkeypatch.setattr(recording, "CHUNK_ROWS", 7)
    monkeypatch.setattr(recording, "READ_BLOCK_CHARS", 333)  # blocks end mid-line
    rec = sample(100, 3)
    rec.tension_sensor[13, 2] = np.nan  # required: skipped
    rec.extra["status_1"] = np.arange(100.0)
    rec.extra["status_1"][40] = np.nan
    write_recording(tmp_path / "r.csv", rec)
    back = read_recording(tmp_path / "r.csv")
    keep = np.ones(100, dtype=bool)
    keep[13] = False
    assert back.samples == 99 and back.skipped_rows == 1
    assert_allclose(back.t, rec.t[keep], rtol=1e-9)
    assert_allclose(back.tension_platform, rec.tension_platform[keep], rtol=1e-9)
    assert_allclose(back.extra["status_1"], rec.extra["status_1"][keep], rtol=1e-9)
    text = (tmp_path / "r.csv").read_text().splitlines()
    text[60] = text[60].replace(text[60].split(",")[0], "0", 1)  # t falls back mid-file
    (tmp_path / "r.csv").write_text("\n".join(text) + "\n")
    with pytest.raises(RecordingError, match=r":61: column 't': 0.0 does not increase"):
        read_recording(tmp_path / "r.csv")


def test_writer_writes_missing_and_non_finite_as_empty_fields(tmp_path: Path) -> None:
    rec = sample(12, 1)
    rec.length[2, 0] = np.nan
    rec.length[3, 0] = np.inf
    rec.length[4, 0] = -np.inf
    write_recording(tmp_path / "r.csv", rec)
    lines = (tmp_path / "r.csv").read_text().splitlines()
    assert all("nan" not in x and "inf" not in x for x in lines)
    assert lines[3 + 2].endswith(",")  # metadata (2 lines), header, then rows
    back = read_recording(tmp_path / "r.csv")
    assert np.isnan(back.length[2:5, 0]).all() and back.samples == 12


# --- hostile YAML (config for run, model file for diagnose) ---------------------------------
def _alias_bomb(levels: int = 9) -> str:
    lines = ["a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    for k in range(1, levels):
        lines.append(f"a{k}: &a{k} [" + ", ".join([f"*a{k - 1}"] * 9) + "]")
    return "\n".join(lines) + f"\nloop:\n  period_s: *a{levels - 1}\n"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (_alias_bomb(), r"line \d+, column \d+: not valid YAML: aliases expand to more than"),
        ("loop: " + "[" * 50_000 + "]" * 50_000 + "\n", r"nested deeper than 100 levels"),
        ("BOMB6", r"loop.period_s: expected a number, got \[\[1, 1, 1, 1, \.\.\.\], \[\["),
    ],
)
def test_hostile_yaml_is_one_line_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, message: str
) -> None:
    from gateway.cli import main

    path = tmp_path / "bomb.yaml"
    if text == "BOMB6":  # 531441 values where a number is expected, in a full config
        chain = ["&b0 [" + ", ".join(["1"] * 9) + "]"]
        chain += [f"&b{k} [" + ", ".join([f"*b{k - 1}"] * 9) + "]" for k in range(1, 6)]
        bomb = "[" + ", ".join(chain) + "]"
        text = DEFAULT_CONFIG_PATH.read_text()
        text = text.replace("\nloop:\n  period_s: 0.001\n", f"\nloop:\n  period_s: {bomb}\n", 1)
        assert bomb in text
    path.write_text(text)
    assert main(["run", "--config", str(path), "--cycles", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and len(err) < 400
    assert re.search(message, err), err
    if "period_s: [" in text:
        return  # a full config whose loop section the diagnosis does not read
    rec = tmp_path / "ok.csv"
    rec.write_text(f"{HEADER}\n" + _rows(30))
    assert main(["diagnose", str(rec), "--model", str(path), "--json", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and len(err) < 400
    assert re.search(message, err), err


def test_small_alias_use_is_still_accepted(tmp_path: Path) -> None:
    from gateway.core.config import load_friction

    path = tmp_path / "ok.yaml"
    path.write_text(
        "friction:\n  pulleys:\n    - &p {wrap_deg: 90.0, mu: 0.015}\n    - *p\n    - *p\n"
    )
    assert len(load_friction(path).pulleys) == 3
