"""`record --out` (issue 31 item 5): a name that is not a recording format is refused in one
line, exit 2, before anything is simulated or written."""

from __future__ import annotations

from pathlib import Path

import pytest

from gateway.cli import main


@pytest.mark.parametrize("name", ["r.txt", "r.gz", "r.csv.bz2", "r", "r.csvx", "r.parquet.tmp"])
def test_record_refuses_an_out_that_is_not_a_recording(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str
) -> None:
    out = tmp_path / name
    assert main(["record", "--seconds", "600", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--out {out}: not a recording format" in err[0]
    assert ".csv, .csv.gz, .parquet" in err[0]
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_record_progress_is_labelled_from_the_start(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "r.csv"
    assert main(["record", "--seconds", "2", "--out", str(out)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0] == "record: simulating the plant:   0 % (0 of 2 s)"  # before any work
    assert "record: simulating the plant: 100 % (2 of 2 s)" in err
    assert err[-1].startswith("record: 2000 samples x ") and str(out) in err[-1]
