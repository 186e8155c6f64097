"""Recordings from other loggers (issue 31 item 4; docs/recording-format.md, "Recordings
from other loggers"): ``--columns`` renames a file's columns to the format's, the delimiter
(comma, semicolon, tab) is the header's, a semicolon- or tab-separated file may write the
decimal comma, a missing column is refused listing the columns found and expected, and a
plain CSV's last line cut short is dropped with one warning, as a ``.csv.gz``'s cut member
is (tests/recordings/test_gzip_members.py)."""

from __future__ import annotations

import gzip
import logging
import string
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from gateway.cli import main
from gateway.errors import ConfigError, RecordingError
from gateway.recordings.columns import column_map, is_format_column
from gateway.recordings.reader import (
    Recording,
    detect_delimiter,
    read_recording,
    write_recording,
)

ROOT = Path(__file__).resolve().parents[2]
MODEL = ROOT / "config" / "default.yaml"
FUNCTION_SCOPED = [HealthCheck.function_scoped_fixture]
NAME_CHARS = string.ascii_letters + string.digits + "_-[]()/ .:µ°"


def file_names(count: int) -> st.SearchStrategy[list[str]]:
    """``count`` distinct column names as another logger writes them: no delimiter, no
    quote, no '#' first, no surrounding blanks, none a name of the format."""
    name = (
        st.text(NAME_CHARS, min_size=1, max_size=14)
        .map(str.strip)
        .filter(lambda s: bool(s) and not is_format_column(s))
    )
    return st.lists(name, min_size=count, max_size=count, unique=True)


def table(rows: int, cables: int, seed: int) -> tuple[list[str], np.ndarray]:
    """Format names and values (rows, columns): t, then per cable velocity, sensor and
    platform tension; a few empty (NaN) optional values would change the kept rows, so
    every value is present."""
    rng = np.random.default_rng(seed)
    names = ["t"]
    for i in range(1, cables + 1):
        names += [f"velocity_{i}", f"tension_sensor_{i}", f"tension_platform_{i}"]
    data = rng.uniform(-500, 500, (rows, len(names))).round(rng.integers(0, 8))
    data[:, 0] = np.cumsum(rng.uniform(1e-3, 2e-2, rows))
    return names, data


def number(x: float, decimal_comma: bool) -> str:
    text = repr(float(x))
    return text.replace(".", ",") if decimal_comma else text


@settings(max_examples=120, deadline=None, suppress_health_check=FUNCTION_SCOPED)
@given(
    cables=st.integers(1, 3),
    rows=st.integers(10, 40),
    seed=st.integers(0, 2**16),
    delimiter=st.sampled_from([",", ";", "\t"]),
    decimal_comma=st.booleans(),
    quoted=st.booleans(),
    crlf=st.booleans(),
    gz=st.booleans(),
    data=st.data(),
)
def test_columns_renamed_in_any_order_and_delimiter_read_back_the_same(
    tmp_path, cables, rows, seed, delimiter, decimal_comma, quoted, crlf, gz, data
):
    assume(not (decimal_comma and delimiter == ","))  # the decimal comma needs another
    names, values = table(rows, cables, seed)
    theirs = data.draw(file_names(len(names)), label="file names")
    order = data.draw(st.permutations(range(len(names))), label="column order")
    mapping = {names[c]: theirs[c] for c in range(len(names))}
    newline = "\r\n" if crlf else "\n"
    head = [f'"{theirs[c]}"' if quoted else theirs[c] for c in order]
    lines = ["# logger: someone else's", delimiter.join(head)]
    for row in values:
        lines.append(delimiter.join(number(row[c], decimal_comma) for c in order))
    text = newline.join(lines) + newline
    path = tmp_path / ("r.txt.gz" if gz else "r.txt")
    path.write_bytes(gzip.compress(text.encode()) if gz else text.encode())

    assert detect_delimiter(lines[1]) == delimiter
    rec = read_recording(path, min_samples=1, columns=mapping)
    assert rec.cables == cables and rec.samples == rows and rec.metadata["logger"]
    np.testing.assert_array_equal(rec.t, values[:, 0])
    for i in range(cables):
        for kind in ("velocity", "tension_sensor", "tension_platform"):
            got = getattr(rec, kind)[:, i]
            np.testing.assert_array_equal(got, values[:, names.index(f"{kind}_{i + 1}")])
    # the same mapping written as a YAML file of the project's one loader
    yaml_file = tmp_path / "map.yaml"
    yaml_file.write_text("".join(f"{k}: {v!r}\n" for k, v in mapping.items()), encoding="utf-8")
    assert column_map(str(yaml_file)) == mapping


def honest_csv(tmp_path: Path, rows: int = 40, name: str = "r.csv") -> tuple[Path, Recording]:
    rng = np.random.default_rng(7)
    rec = Recording(
        t=np.arange(rows) * 1e-3,
        velocity=rng.normal(0, 0.05, (rows, 2)),
        tension_sensor=rng.uniform(100, 200, (rows, 2)),
        tension_platform=rng.uniform(100, 200, (rows, 2)),
        metadata={"robot": "r"},
    )
    path = tmp_path / name
    write_recording(path, rec)
    return path, read_recording(path, min_samples=1)  # the values as written (%.10g)


@settings(max_examples=150, deadline=None, suppress_health_check=FUNCTION_SCOPED)
@given(cut=st.floats(0.0, 1.0), crlf=st.booleans())
def test_a_plain_csv_cut_at_any_byte_reads_its_whole_rows_or_is_refused(
    tmp_path, caplog, cut, crlf
):
    path, whole = honest_csv(tmp_path)
    data = path.read_bytes()
    if crlf:
        data = data.replace(b"\n", b"\r\n")
    at = int(cut * len(data))
    kept = data[:at]
    path.write_bytes(kept)
    lines = kept.replace(b"\r\n", b"\n").replace(b"\r", b"\n")  # a lone CR ends a line too
    header_at = lines.find(b"\nt,")
    complete_rows = lines[header_at + 1 :].count(b"\n") - 1 if header_at >= 0 else -1
    caplog.clear()
    try:
        with caplog.at_level(logging.WARNING, logger="cdpr_gateway.recordings"):
            rec = read_recording(path, min_samples=1)
    except RecordingError as exc:  # cut before the header's end or the first whole row
        assert "\n" not in str(exc) and str(path) in str(exc)
        assert complete_rows <= 0
        return
    n = rec.samples
    assert n == complete_rows  # every whole row, and nothing of the cut one
    np.testing.assert_array_equal(rec.tension_sensor, whole.tension_sensor[:n])
    np.testing.assert_array_equal(rec.t, whole.t[:n])
    warnings = [r.getMessage() for r in caplog.records]
    cut_line = lines.rsplit(b"\n", 1)[-1].strip()
    if cut_line:
        (line,) = warnings
        assert f"ends after an unclean stop: {n} rows to t = {rec.t[-1]:.3f} s" in line
        assert "the last partial line" in line and str(path) in line
    else:
        assert warnings == []


def test_damage_before_the_last_line_is_still_refused(tmp_path):
    path, _ = honest_csv(tmp_path)
    lines = path.read_text().split("\n")
    lines[10] = lines[10][: len(lines[10]) // 2]  # a line cut short, more follow
    path.write_text("\n".join(lines))
    with pytest.raises(RecordingError, match=r"r.csv:11: \d fields, header has 7$"):
        read_recording(path, min_samples=1)


def test_decimal_commas_in_a_comma_separated_file_are_refused_naming_the_line(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text(
        "t,velocity_1,tension_sensor_1,tension_platform_1\n"
        + "".join(f"0.{k:03d},0,1,100,5,99\n" for k in range(20))
    )
    with pytest.raises(RecordingError, match=r"r.csv:2: 6 fields, header has 4$"):
        read_recording(path)


def test_a_semicolon_file_with_a_thousands_separator_is_refused_not_misread(tmp_path):
    path = tmp_path / "r.csv"
    rows = "".join(f"0,{k:03d};0;1.234,5;99\n" for k in range(20))
    path.write_text("t;velocity_1;tension_sensor_1;tension_platform_1\n" + rows)
    with pytest.raises(RecordingError, match=r"r.csv:2: column 'tension_sensor_1': '1.234,5'"):
        read_recording(path)


@pytest.mark.parametrize(
    ("spec", "says"),
    [
        ("t=time,tension_sensr_1=F1", "'tension_sensr_1' is not a column of the recording format"),
        ("t=time,velocity_0=v", "'velocity_0' is not a column of the recording format"),
        ("t=time,velocity_1025=v", "'velocity_1025' is not a column"),
        ("t=time,velocity_1", "'velocity_1' is not NAME=COLUMN"),
        ("t=time,t=other", "'t' is given twice"),
        ("t=time,velocity_1=time", "velocity_1: the file's column 'time' is already 't'"),
        ("t=", "t: no file column named"),
        ("time", "--columns time: no such file, and not NAME=COLUMN pairs"),
    ],
)
def test_a_bad_mapping_is_one_line_naming_the_key(spec, says):
    with pytest.raises(ConfigError, match=r"^--columns") as exc:
        column_map(spec)
    assert says in str(exc.value) and "\n" not in str(exc.value)


def test_a_mapping_file_names_the_file_and_the_key(tmp_path):
    path = tmp_path / "map.yaml"
    path.write_text("t: time\nforce_1: F1\n")
    with pytest.raises(ConfigError, match=r"map.yaml: 'force_1' is not a column"):
        column_map(str(path))
    path.write_text("t: time\nvelocity_1: [v1]\n")
    with pytest.raises(ConfigError, match=r"map.yaml: velocity_1: the value must be a column"):
        column_map(str(path))
    path.write_text("t: time\nt: again\n")  # the loader refuses a key given twice
    with pytest.raises(ConfigError, match=r"map.yaml:2: duplicate key 't'"):
        column_map(str(path))
    path.write_text("t: 7\n")  # a number as a column name: the header's text
    assert column_map(str(path)) == {"t": "7"}


def test_a_mapping_against_the_file_is_checked_on_its_header(tmp_path):
    path, _ = honest_csv(tmp_path)
    with pytest.raises(
        RecordingError,
        match=r"r.csv:2: --columns t=time: the file has no column 'time' \(columns found: t, ",
    ):
        read_recording(path, columns={"t": "time"})
    with pytest.raises(RecordingError, match=r"the file has a column 't' of its own"):
        read_recording(path, columns={"t": "velocity_2"})
    swapped = read_recording(path, columns={"velocity_1": "velocity_2", "velocity_2": "velocity_1"})
    plain = read_recording(path)
    np.testing.assert_array_equal(swapped.velocity, plain.velocity[:, ::-1])


def test_a_parquet_file_is_renamed_the_same_way(tmp_path):
    _, whole = honest_csv(tmp_path)
    path = tmp_path / "r.parquet"
    write_recording(path, whole)
    swap = {"tension_sensor_1": "tension_sensor_2", "tension_sensor_2": "tension_sensor_1"}
    rec = read_recording(path, min_samples=1, columns=swap)
    np.testing.assert_array_equal(rec.tension_sensor, whole.tension_sensor[:, ::-1])
    np.testing.assert_array_equal(rec.velocity, whole.velocity)
    with pytest.raises(RecordingError, match=r"r.parquet: schema: --columns t=time: the file"):
        read_recording(path, columns={"t": "time"})


def test_a_missing_column_lists_the_columns_found_and_expected(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text("time;F1;v1\n" + "".join(f"{k};1;2\n" for k in range(20)))
    with pytest.raises(RecordingError) as exc:
        read_recording(path)
    text = str(exc.value)
    assert text.startswith(f"{path}:1: no 't' column (columns found: time, F1, v1; expected: t")
    assert "--columns t=COLUMN" in text and "\n" not in text


def cli(argv: list[str], capsys) -> tuple[int, list[str]]:
    status = main(argv)
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    return status, err


def test_export_with_columns_from_a_semicolon_logger(tmp_path, capsys):
    path = tmp_path / "logger.txt"
    rows = "".join(
        f"{k / 1000:.3f};{k % 5 / 10:.1f};{100 + k % 7:.2f};{99 + k:.2f}\n" for k in range(30)
    )
    path.write_text("Zeit;v1;F1;Fp1\n" + rows.replace(".", ","))
    spec = "t=Zeit,velocity_1=v1,tension_sensor_1=F1,tension_platform_1=Fp1"
    out = tmp_path / "o.mcap"
    status, err = cli(["export", str(path), "--to", "mcap", str(out), "--columns", spec], capsys)
    assert status == 0 and out.stat().st_size > 0, err
    rec = read_recording(path, columns=column_map(spec))
    np.testing.assert_array_equal(rec.tension_platform[:, 0], 99 + np.arange(30))


@pytest.mark.parametrize(
    ("extra", "says"),
    [
        (["--columns", "t=Zeit,force_1=F1"], "--columns: 'force_1' is not a column"),
        (["--columns", "t=time"], "logger.txt:1: --columns t=time: the file has no column"),
        ([], "logger.txt:1: no 't' column (columns found: Zeit, v1, F1, Fp1; expected:"),
        (["--columns", "t=Zeit"], "logger.txt:1: no cable columns"),
    ],
)
def test_cli_errors_are_one_line_and_status_2(tmp_path, capsys, extra, says):
    path = tmp_path / "logger.txt"
    path.write_text("Zeit\tv1\tF1\tFp1\n" + "".join(f"{k}\t1\t2\t3\n" for k in range(20)))
    status, err = cli(
        ["export", str(path), "--to", "mcap", str(tmp_path / "o.mcap"), *extra], capsys
    )
    assert status == 2 and len(err) == 1, err
    assert says in err[0] and err[0].startswith("cdpr-gateway export: error: "), err


def test_export_refuses_an_output_name_of_another_format(tmp_path, capsys):
    path, _ = honest_csv(tmp_path)
    status, err = cli(["export", str(path), "--to", "mcap", str(tmp_path / "o.csv")], capsys)
    assert status == 2 and len(err) == 1 and "the name must end in .mcap" in err[0], err
    assert not (tmp_path / "o.csv").exists()


def test_export_warns_once_of_a_cut_last_line_and_exits_0(tmp_path, capsys, caplog):
    path, _ = honest_csv(tmp_path)
    path.write_bytes(path.read_bytes()[:-7])
    with caplog.at_level(logging.WARNING, logger="cdpr_gateway.recordings"):
        status, err = cli(["export", str(path), "--to", "mcap", str(tmp_path / "o.mcap")], capsys)
    assert status == 0, err
    (line,) = [r.getMessage() for r in caplog.records]
    assert "ends after an unclean stop: 39 rows to t = 0.038 s, the last partial line" in line


@pytest.mark.parametrize("command", ["diagnose", "fleet"])
def test_diagnose_and_fleet_refuse_a_bad_mapping_before_any_work(tmp_path, capsys, command):
    path, _ = honest_csv(tmp_path)
    argv = [command, str(path), "--model", str(MODEL), "--columns", "t=a,t=b"]
    argv += ["--out", str(tmp_path / "f")] if command == "fleet" else []
    status, err = cli(argv, capsys)
    assert status == 2 and err == [f"cdpr-gateway {command}: error: --columns: 't' is given twice"]


def test_diagnose_of_a_foreign_file_with_columns_is_the_diagnosis_of_the_original(tmp_path):
    """The same recording as a semicolon-separated file with decimal commas, its own column
    names in another order and no final line end: ``diagnose --columns MAP.yaml`` gives the
    report the original gives, number for number (one warning for the cut line: a row
    fewer, so the original is cut the same)."""
    import json
    from dataclasses import replace

    from evaluation.scenarios import Scenario
    from tests.diagnose_helpers import write_scenario

    sc = Scenario("byo", {"viscous": {"c_ns_m": 8.0}}, cables=1, seconds=12.0)
    rec, model = write_scenario(tmp_path, replace(sc, seed=5))
    text = rec.read_text().rstrip("\n")
    meta = [ln for ln in text.split("\n") if ln.startswith("#")]
    head, *rows = [ln for ln in text.split("\n") if not ln.startswith("#")]
    names = head.split(",")
    theirs = {n: f"Kanal {k} [{n[:3]}]" for k, n in enumerate(names)}
    order = names[::-1]
    body = [";".join(dict(zip(names, r.split(","), strict=True))[n] for n in order) for r in rows]
    foreign = tmp_path / "logger.txt"
    foreign.write_text(
        "\n".join([*meta, ";".join(theirs[n] for n in order), *(b.replace(".", ",") for b in body)])
    )  # no final line end: its last row is dropped with a warning
    rec.write_text("\n".join([*meta, head, *rows[:-1]]) + "\n")
    mapping = tmp_path / "map.yaml"
    mapping.write_text("".join(f"{n}: '{theirs[n]}'\n" for n in names))
    reports = []
    for path, extra in ((rec, []), (foreign, ["--columns", str(mapping)])):
        out = tmp_path / f"{path.stem}.json"
        argv = ["diagnose", str(path), "--model", str(model), "--json", str(out), "--quiet"]
        assert main(argv + extra) == 0
        reports.append(json.loads(out.read_text()))
    assert reports[0] == reports[1]
    assert [f["effect"] for f in reports[0]["findings"]] == ["viscous"]


@pytest.mark.parametrize("name", ["r.txt", "r.csv.bak", "r", "r.gz", "r.parq"])
def test_run_record_refuses_a_name_of_no_recording_format(tmp_path, name):
    """``run --record r.txt`` wrote CSV under that name; refused before the bus connects
    (start_recorder runs before the service configures the driver)."""
    from gateway.core.config import load_config
    from gateway.service.daemon import start_recorder

    cfg = load_config(MODEL)
    with pytest.raises(RecordingError, match=rf"^--record {tmp_path / name}: not a recording"):
        start_recorder(cfg, str(tmp_path / name))
    assert not (tmp_path / name).exists()
