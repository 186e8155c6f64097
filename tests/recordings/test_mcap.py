"""``export --to mcap``: every value and time stamp read back equal with the mcap reader;
each message valid against its channel's JSON Schema."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader

from gateway.cli import main
from gateway.recordings.reader import POSE_COLUMNS, Recording, write_recording


def gateway_like(n: int = 700, m: int = 3) -> Recording:
    rng = np.random.default_rng(4)
    rec = Recording(
        t=np.cumsum(rng.uniform(0.8e-3, 1.2e-3, n)),
        velocity=rng.normal(0, 0.1, (n, m)),
        tension_sensor=rng.uniform(10, 400, (n, m)),
        length=rng.uniform(1, 4, (n, m)),
        pose=rng.normal(0, 0.5, (n, 6)),
        mass=40 - 1e-3 * np.arange(n),
        metadata={"robot": "r9", "started": "2026-03-01T12:00:00+00:00", "source": "test"},
        extra={
            **{f"tension_corrected_{i + 1}": rng.uniform(10, 400, n) for i in range(m)},
            **{f"status_{i + 1}": rng.integers(0, 3, n).astype(float) for i in range(m)},
        },
    )
    rec.length[5, 1] = np.nan  # type: ignore[index]  # missing values: null in the export
    rec.extra["tension_corrected_2"][5] = np.nan
    return rec


def _expect(rec: Recording) -> dict[str, dict[str, np.ndarray]]:
    corrected = np.column_stack([rec.extra[f"tension_corrected_{i + 1}"] for i in range(3)])
    status = np.column_stack([rec.extra[f"status_{i + 1}"] for i in range(3)])
    pose = {n: rec.pose[:, k] for k, n in enumerate(POSE_COLUMNS)}  # type: ignore[index]
    return {
        "/tensions": {"sensor": rec.tension_sensor, "corrected": corrected},
        "/setpoints": {"velocity": rec.velocity, "length": rec.length},  # type: ignore[dict-item]
        "/pose": {**pose, "mass": rec.mass},  # type: ignore[dict-item]
        "/status": {"status": status},
    }


def test_the_export_reads_back_equal(tmp_path: Path, capsys) -> None:
    rec = gateway_like()
    write_recording(tmp_path / "g.parquet", rec)
    out = tmp_path / "g.mcap"
    assert main(["export", str(tmp_path / "g.parquet"), "--to", "mcap", str(out)]) == 0
    offset = 1772366400 * 10**9  # 2026-03-01T12:00:00Z
    stamps = np.round(rec.t * 1e9).astype(np.int64) + offset
    expect = _expect(rec)
    got: dict[str, list[dict]] = {topic: [] for topic in expect}
    validators: dict[str, jsonschema.protocols.Validator] = {}
    with open(out, "rb") as fh:
        reader = make_reader(fh)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert meta["recording"]["robot"] == "r9"
        assert meta["recording"]["time_offset_ns"] == str(offset)
        for schema, channel, message in reader.iter_messages():
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            body = json.loads(message.data)
            if channel.topic not in validators:
                spec = json.loads(schema.data)
                validators[channel.topic] = jsonschema.validators.validator_for(spec)(spec)
            validators[channel.topic].validate(body)
            k = len(got[channel.topic])
            assert message.log_time == message.publish_time == stamps[k]
            assert body["t"] == rec.t[k]
            got[channel.topic].append(body)
    for topic, fields in expect.items():
        assert len(got[topic]) == rec.samples, topic
        for name, values in fields.items():
            back = np.array(
                [[np.nan if x is None else x for x in np.atleast_1d(b[name])] for b in got[topic]],
                dtype=float,
            )
            np.testing.assert_array_equal(back.reshape(values.shape), values, err_msg=name)
    assert "export: 2800 messages" in capsys.readouterr().err


def test_a_recording_without_pose_has_no_pose_channel(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    rec = Recording(
        t=np.arange(20) * 1e-3,
        velocity=rng.normal(size=(20, 1)),
        tension_sensor=rng.normal(size=(20, 1)),
        tension_platform=rng.normal(size=(20, 1)),
    )
    write_recording(tmp_path / "p.csv", rec)
    assert (
        main(
            ["export", str(tmp_path / "p.csv"), "--to", "mcap", str(tmp_path / "p.mcap"), "--quiet"]
        )
        == 0
    )
    with open(tmp_path / "p.mcap", "rb") as fh:
        topics = [c.topic for _, c, _ in make_reader(fh).iter_messages()]
    assert sorted(set(topics)) == ["/setpoints", "/tensions"] and len(topics) == 40


def test_a_bad_recording_is_one_line_and_status_2(tmp_path: Path, capsys) -> None:
    (tmp_path / "bad.csv").write_text("t,x\n1,2\n")
    code = main(["export", str(tmp_path / "bad.csv"), "--to", "mcap", str(tmp_path / "o.mcap")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "bad.csv:1: no cable columns" in err


@pytest.mark.parametrize(
    ("t0", "started", "says"),
    [
        (2e10, "", "row 1: t = 2e+10 s is outside what MCAP can hold"),
        (-1.0, "", "row 1: t = -0.99"),
        (0.0, "1960-01-01T00:00:00+00:00", "after the start 1960-01-01"),
        (0.0, "0001-01-01T00:00:00+00:00", "after the start 0001-01-01"),
        (0.0, "9999-12-31T00:00:00+00:00", "after the start 9999-12-31"),
    ],
)
def test_times_mcap_cannot_hold_are_refused_in_one_line(tmp_path, capsys, t0, started, says):
    """Each gave a struct.error or OverflowError traceback (issue 30 item 4)."""
    rec = gateway_like(20, 2)
    rec = dataclasses.replace(rec, t=rec.t + t0, metadata={**rec.metadata, "started": started})
    write_recording(tmp_path / "r.parquet", rec)
    out = tmp_path / "r.mcap"
    assert main(["export", str(tmp_path / "r.parquet"), "--to", "mcap", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0], err
    assert not out.exists() or out.stat().st_size == 0


def test_an_output_that_cannot_seek_is_refused_up_front(tmp_path, capsys):
    write_recording(tmp_path / "r.csv", gateway_like(20, 2))
    assert main(["export", str(tmp_path / "r.csv"), "--to", "mcap", "/dev/null"]) == 2
    err = capsys.readouterr().err.strip()
    assert "/dev/null: not a regular file" in err and "\n" not in err, err


def test_times_int64_cannot_hold_but_mcap_can_are_exported(tmp_path, capsys):
    """t = 1e10 s (the year 2286) overflowed int64 ns and gave a traceback; MCAP's u64
    holds it."""
    rec = gateway_like(20, 2)
    rec = dataclasses.replace(rec, t=rec.t + 1e10, metadata={**rec.metadata, "started": ""})
    write_recording(tmp_path / "r.parquet", rec)
    out = tmp_path / "r.mcap"
    assert main(["export", str(tmp_path / "r.parquet"), "--to", "mcap", str(out)]) == 0
    with out.open("rb") as fh:
        times = [m.log_time for _, _, m in make_reader(fh).iter_messages()]
    assert min(times) == round(rec.t[0] * 1e9) and min(times) > 2**63
