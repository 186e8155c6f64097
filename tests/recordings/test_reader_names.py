"""Regressions: recording headers that read as something else.

``velocity_١`` (Arabic-Indic digit) and ``velocity_１`` (fullwidth) were read as cable 1,
``velocity_01`` next to ``velocity_1`` was accepted (one silently replaced the other), and
988 metadata lines of 1 MiB each (a 1.54 MB .csv.gz) were accepted at a 1175 MiB peak.
"""

from __future__ import annotations

import gzip
from pathlib import Path

import pytest

from gateway.errors import RecordingError
from gateway.recordings.reader import MAX_METADATA_CHARS, read_recording

BODY = "".join(f"{k * 0.001},0.1,{100 + k % 7},{99 + k % 7}\n" for k in range(50))


def _write(tmp_path: Path, header: str, meta: str = "") -> Path:
    path = tmp_path / "rec.csv"
    path.write_text(meta + header + "\n" + BODY, encoding="utf-8")
    return path


@pytest.mark.parametrize(
    "name",
    ["velocity_١", "velocity_１", "velocity_01", "velocity_0", "velocity_+1", "velocity_1 "],
)
def test_a_cable_index_is_ascii_digits_without_leading_zeros(tmp_path, name):
    path = _write(tmp_path, f"t,{name},tension_sensor_1,tension_platform_1")
    if name.endswith(" "):  # surrounding blanks are the CSV's, not the name's: accepted
        assert read_recording(path).cables == 1
        return
    with pytest.raises(
        RecordingError,
        match=r"rec.csv:1: column .*cable indices .* ASCII digits without leading zeros",
    ):
        read_recording(path)


def test_velocity_01_next_to_velocity_1_is_refused(tmp_path):
    path = tmp_path / "rec.csv"
    head = "t,velocity_1,velocity_01,tension_sensor_1,tension_platform_1\n"
    path.write_text(head + "0,0.1,0.2,100,99\n0.001,0.1,0.2,101,100\n")
    with pytest.raises(RecordingError, match="velocity_01"):
        read_recording(path)


def test_metadata_is_capped_in_total_bytes_not_only_in_lines(tmp_path):
    path = tmp_path / "rec.csv.gz"
    line = "# note: " + "x" * ((1 << 20) - 100) + "\n"  # just under the line cap
    with gzip.open(path, "wt", encoding="utf-8") as fh:
        for _ in range(40):  # 40 MiB of metadata in 40 lines (the cap on lines is 1000)
            fh.write(line)
        fh.write("t,velocity_1,tension_sensor_1,tension_platform_1\n" + BODY)
    assert path.stat().st_size < 1 << 20
    with pytest.raises(RecordingError, match=rf"metadata of more than {MAX_METADATA_CHARS}"):
        read_recording(path)
