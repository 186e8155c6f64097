"""A recording as MCAP (the ``mcap`` library): what Foxglove and PlotJuggler open natively.

One JSON channel per kind, each with a JSON Schema (``jsonschema`` encoding, units in the
schema's descriptions): ``/tensions`` (``sensor``, and where recorded ``platform`` and
``corrected``, N per cable), ``/setpoints`` (``velocity`` m/s, ``length`` m per cable),
``/pose`` (``x y z`` m, ``rx ry rz`` rad, ``mass`` kg) and ``/status`` (per cable, 0
good, 1 substituted, 2 invalid). A value the recording lacks (NaN) is ``null``. Every
message of a row has the same log and publish time in ns: ``round(t * 1e9)`` plus the
recording's start (metadata ``started``, UTC) when it has one, so the players show wall
time; ``t`` itself is in every message too. The recording's metadata is an MCAP metadata
record named ``recording`` (with ``time_offset_ns``).
"""

from __future__ import annotations

import datetime
import json
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path

import numpy as np

from gateway.errors import GatewayError
from gateway.recordings.reader import POSE_COLUMNS, Recording, read_recording

CHANNELS = ("/tensions", "/setpoints", "/pose", "/status")
_UNITS = {
    "sensor": "N",
    "platform": "N",
    "corrected": "N",
    "velocity": "m/s",
    "length": "m",
    "x": "m",
    "y": "m",
    "z": "m",
    "rx": "rad",
    "ry": "rad",
    "rz": "rad",
    "mass": "kg",
    "status": "0 good, 1 substituted, 2 invalid",
}


def _cable_columns(rec: Recording, prefix: str) -> np.ndarray | None:
    names = [f"{prefix}_{i + 1}" for i in range(rec.cables)]
    if not all(n in rec.extra for n in names):
        return None
    return np.column_stack([rec.extra[n] for n in names])


def channel_arrays(rec: Recording) -> dict[str, dict[str, np.ndarray]]:
    """Per channel, field name -> (N,) or (N, m) array; channels without data left out."""
    out: dict[str, dict[str, np.ndarray]] = {"/tensions": {"sensor": rec.tension_sensor}}
    for name, arr in (
        ("platform", rec.tension_platform),
        ("corrected", _cable_columns(rec, "tension_corrected")),
    ):
        if arr is not None:
            out["/tensions"][name] = arr
    out["/setpoints"] = {"velocity": rec.velocity}
    if rec.length is not None:
        out["/setpoints"]["length"] = rec.length
    pose: dict[str, np.ndarray] = {}
    if rec.pose is not None:
        pose = {n: rec.pose[:, k] for k, n in enumerate(POSE_COLUMNS)}
    if rec.mass is not None:
        pose["mass"] = rec.mass
    if pose:
        out["/pose"] = pose
    status = _cable_columns(rec, "status")
    if status is not None:
        out["/status"] = {"status": status}
    return out


def schema(topic: str, fields: dict[str, np.ndarray]) -> dict:
    number = {"type": ["number", "null"]}
    props: dict[str, dict] = {"t": {"type": "number", "description": "s since the start"}}
    for name, arr in fields.items():
        desc = f"{name} ({_UNITS.get(name, '')})"
        if arr.ndim == 2:
            props[name] = {"type": "array", "items": number, "description": desc + ", per cable"}
        else:
            props[name] = {**number, "description": desc}
    return {
        "title": f"cdpr-gateway {topic}",
        "type": "object",
        "properties": props,
        "required": ["t", *fields],
    }


def _values(arr: np.ndarray) -> list:
    """JSON-safe list (NaN -> None) of every row of ``arr`` as Python values."""
    rows = arr.tolist()
    if not np.isnan(arr).any():
        return rows
    if arr.ndim == 1:
        return [None if x != x else x for x in rows]
    return [[None if x != x else x for x in r] for r in rows]


def _messages(t: np.ndarray, fields: dict[str, np.ndarray], block: int) -> Iterator[bytes]:
    for start in range(0, t.size, block):
        stop = min(start + block, t.size)
        cols = {name: _values(arr[start:stop]) for name, arr in fields.items()}
        for k, tk in enumerate(t[start:stop].tolist()):
            msg = {"t": tk, **{name: col[k] for name, col in cols.items()}}
            yield json.dumps(msg, separators=(",", ":"), allow_nan=False).encode()


def time_offset_ns(rec: Recording) -> int:
    started = rec.metadata.get("started")
    if not started:
        return 0
    try:
        when = datetime.datetime.fromisoformat(started)
    except ValueError:
        return 0
    when = when if when.tzinfo else when.replace(tzinfo=datetime.UTC)
    try:
        return int(when.timestamp()) * 1_000_000_000  # before 1970: negative, refused later
    except (OverflowError, OSError, ValueError):  # year 1 or 9999 on some platforms
        return -1 if when.year < 1970 else MAX_NS + 1


MAX_NS = 2**64 - 1  # MCAP's log and publish times: unsigned 64-bit ns since 1970 (to 2554)


def mcap_stamps(recording: Path, t: np.ndarray, offset_ns: int, started: str = "") -> list[int]:
    """Each row's time in ns, exactly (Python integers: ``t`` of 1e10 s overflowed int64
    silently), or one line when one lies outside what MCAP can hold."""
    if t.size and not (np.isfinite(t[0]) and np.isfinite(t[-1])):
        raise GatewayError(f"{recording}: t is not finite; MCAP needs a time for every row")
    stamps = [round(x * 1e9) + offset_ns for x in t.tolist()]
    bad = next((k for k, s in enumerate(stamps) if not 0 <= s <= MAX_NS), None)
    if bad is not None:
        when = f"t = {t[bad]:g} s" + (f" after the start {started}" if started else "")
        raise GatewayError(
            f"{recording}: row {bad + 1}: {when} is outside what MCAP can hold "
            "(0 to 2^64 ns after 1970-01-01, up to the year 2554)"
        )
    return stamps


def export_mcap(
    recording: Path,
    out: Path,
    progress: Callable[[float], None] | None = None,
    columns: Mapping[str, str] | None = None,
):
    """Write ``recording`` (any format the reader takes; ``columns``: its columns renamed,
    ``--columns``) to ``out`` as MCAP; returns the number of messages written."""
    from mcap.writer import Writer

    from gateway import __version__

    if out.exists() and not out.is_file():  # /dev/stdout, a pipe: the writer seeks back
        raise GatewayError(f"{out}: not a regular file; MCAP is written to a file (it seeks)")
    rec = read_recording(recording, min_samples=1, columns=columns)
    offset = time_offset_ns(rec)
    stamps = mcap_stamps(
        recording, rec.t, offset, rec.metadata.get("started", "") if offset else ""
    )
    channels = channel_arrays(rec)
    count = 0
    try:
        fh = open(out, "wb")  # noqa: SIM115 - closed below
    except OSError as exc:
        raise GatewayError(f"{out}: cannot write: {exc.strerror or exc}") from exc
    with fh:
        writer = Writer(fh)
        writer.start(profile="", library=f"cdpr-gateway {__version__}")
        writer.add_metadata(
            "recording",
            {**rec.metadata, "source_file": str(recording), "time_offset_ns": str(offset)},
        )
        for n, (topic, fields) in enumerate(channels.items()):
            sid = writer.register_schema(
                topic.strip("/"), "jsonschema", json.dumps(schema(topic, fields)).encode()
            )
            cid = writer.register_channel(topic, "json", sid)
            for k, data in enumerate(_messages(rec.t, fields, 8192)):
                writer.add_message(
                    cid, log_time=stamps[k], data=data, publish_time=stamps[k], sequence=k
                )
                count += 1
            if progress is not None:
                progress((n + 1) / len(channels))
        writer.finish()
    return count
