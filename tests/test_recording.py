"""Recordings (spec/recording.md): round trips, skipped rows, malformed files refused."""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from gateway.errors import RecordingError
from gateway.recording import Recording, read_recording, write_recording

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
    rec = sample(10)
    rec.tension_platform[3, 1] = np.nan  # required: row skipped
    rec.length[5, 0] = np.nan  # optional: kept as NaN
    write_recording(tmp_path / "r.csv", rec)
    back = read_recording(tmp_path / "r.csv")
    assert back.samples == 9 and back.skipped_rows == 1
    assert np.isnan(back.length).sum() == 1


def test_hand_written_file_with_metadata_blank_lines_and_extra_columns(tmp_path: Path) -> None:
    path = tmp_path / "hand.csv"
    path.write_text(
        "# source: logger\n# anything: kept\n"
        "t,velocity_1,tension_sensor_1,tension_platform_1,temperature\n"
        "0.0,0.1,100,101,20\n\n0.002,-0.1,102,100,\n"
    )
    rec = read_recording(path)
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
        read_recording(path)


def test_pose_and_mass_stand_in_for_platform_tension(tmp_path: Path) -> None:
    path = tmp_path / "pose.csv"
    path.write_text("t,velocity_1,tension_sensor_1,x,y,z,rx,ry,rz,mass\n0,0,1,0,0,1,0,0,0,50\n")
    rec = read_recording(path)
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
    rec = read_recording(path)
    assert rec.metadata == {"source": "excel"}
    assert rec.samples == 2 and rec.cables == 1
    assert_allclose(rec.tension_sensor[:, 0], [100.0, 100.5])
