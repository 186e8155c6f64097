"""What one worker does with one recording: its diagnosis, never an exception.

:func:`diagnose_task` runs in a Dask worker (imported there by name: the worker must have
this package installed, and the recording and model must be at paths it sees). Whatever
goes wrong with one recording -- a malformed file, a diagnosis that fails -- comes back as
an ``error`` in the result instead of an exception, so the job lists it and goes on (an
exception would make Dask retry the task or fail the gather). With ``fleet --per-robot`` a
task is one robot's recordings, diagnosed jointly as ``diagnose REC REC ...`` does (one
report, :mod:`gateway.diagnose.sessions`).
"""

from __future__ import annotations

import datetime
import os
import re
import resource
import socket
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

from gateway.errors import GatewayError

_HIVE = re.compile(r"^(robot|date)=(.+)$")


@dataclass(frozen=True)
class TaskResult:
    """One recording's outcome: the report's text (``diagnose --json``'s bytes) or an
    error line; robot and start time from the metadata (or the Hive path, or the file)."""

    recording: str
    robot: str
    start: str  # ISO 8601, UTC
    report_json: str | None
    error: str | None
    seconds: float  # wall time of the diagnosis
    worker: str  # the Dask worker's address (tcp://HOST:PORT), or host:pid outside one
    peak_rss_mb: float  # the worker process's peak RSS so far
    recordings: tuple[str, ...] = ()
    """A joined task's recordings (``fleet --per-robot``; ``recording`` is then their names
    joined by `` + ``); empty for one recording."""


def recording_identity(path: Path, meta: dict[str, str]) -> tuple[str, str]:
    """(robot, start): metadata ``robot`` / ``started``, else the Hive folders
    ``robot=R`` / ``date=D``, else the parent folder's name / the file's time."""
    hive = {m.group(1): m.group(2) for part in path.parts if (m := _HIVE.match(part))}
    robot = meta.get("robot") or hive.get("robot") or path.parent.name or "unknown"
    start = meta.get("started") or hive.get("date")
    if not start:
        try:
            mtime = path.stat().st_mtime
        except OSError:
            mtime = 0.0
        start = datetime.datetime.fromtimestamp(mtime, datetime.UTC).isoformat(timespec="seconds")
    return robot, start


JOIN = " + "
"""What separates a joined task's recordings in its ``recording`` (as in a joined report's
``source``)."""


def group_identity(paths: list[Path], metas: list[dict[str, str]]) -> tuple[str, str]:
    """(robot, start) of recordings diagnosed as one: the first's robot, the earliest start."""
    ids = [recording_identity(p, m) for p, m in zip(paths, metas, strict=True)]
    return ids[0][0], min(start for _, start in ids)


def _worker() -> str:
    """The address of the Dask worker running this task (which host of a fleet spread over
    several ran it), or ``host:pid`` when no worker runs it."""
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):  # ValueError: not in a worker
        return f"{socket.gethostname()}:{os.getpid()}"


def diagnose_task(
    recording: str | list[str], model: str, columns: dict[str, str] | None = None
) -> TaskResult:
    """Diagnose ``recording`` against ``model`` as ``diagnose [--columns]`` does (a list:
    one robot's recordings jointly, as ``diagnose REC REC ...``); never raises."""
    from gateway.diagnose.cli import report_json
    from gateway.diagnose.fromfiles import diagnose_file
    from gateway.recordings.reader import read_metadata

    several = isinstance(recording, list)
    paths = [Path(r) for r in recording] if isinstance(recording, list) else [Path(recording)]
    t0 = time.perf_counter()
    report: str | None = None
    error: str | None = None
    robot, start = group_identity(paths, [{} for _ in paths])
    try:
        robot, start = group_identity(paths, [read_metadata(p) for p in paths])
        what: Path | list[Path] = paths if several else paths[0]
        report = report_json(diagnose_file(what, Path(model), columns=columns).report)
    except GatewayError as exc:
        error = str(exc)
    except Exception as exc:  # a bug shows its place, but one recording never ends the job
        where = traceback.extract_tb(exc.__traceback__)[-1]
        error = f"{type(exc).__name__}: {exc} ({Path(where.filename).name}:{where.lineno})"
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return TaskResult(
        recording=JOIN.join(recording) if isinstance(recording, list) else recording,
        robot=robot,
        start=start,
        report_json=report,
        error=error,
        seconds=time.perf_counter() - t0,
        worker=_worker(),
        peak_rss_mb=peak,
        recordings=tuple(recording) if isinstance(recording, list) else (),
    )
