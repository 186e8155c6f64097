"""``cdpr-gateway fleet RECORDINGS... --model MODEL.yaml --out DIR [--per-robot]
[--scheduler ADDRESS] [--workers N] [--columns MAP]``: every recording diagnosed as a task on
dask.distributed (``--columns``: every recording's columns renamed the same way, as
``diagnose`` does).

``--per-robot``: one task per robot instead, its recordings diagnosed jointly for one set
of findings, as ``diagnose REC REC ... --model MODEL`` does (:mod:`gateway.diagnose.sessions`;
the robot of each recording as :func:`gateway.fleet.task.recording_identity` tells it: the
metadata's ``robot``, else the Hive folder ``robot=R``, else the parent folder's name; its
recordings in order of start, then path). One report per robot
(``DIR/reports/NNN-robot-R.json``, the bytes ``diagnose --json`` writes for those
recordings), one row per robot x finding x cable in the table (``recording``: the
recordings joined by `` + ``; ``start``: the earliest), one point per robot in its plot; a
robot's task is sized as its recordings joined (:func:`gateway.fleet.sizing.joined`).

RECORDINGS are files (``.csv``, ``.csv.gz``, ``.parquet``), globs (``'runs/*.parquet'``,
``**`` recursive) or folders (a Hive tree ``robot=R/date=D/part-N.parquet``: every
recording under it). Writes ``DIR/reports/NNN-NAME.json`` (each the bytes ``diagnose
--json`` writes for that recording alone), ``DIR/fleet.parquet`` and ``DIR/fleet.csv``
(:mod:`gateway.fleet.table`), ``DIR/plots/robot-R.png`` and ``DIR/fleet.md``
(:mod:`gateway.fleet.plots`). A line per finished recording on stderr; a recording that
fails is listed and the job goes on; the exit status is 0 when the job ran (1 when every
recording failed), 2 on bad arguments or a missing ``fleet`` extra.
"""

from __future__ import annotations

import argparse
import glob
import sys
import time
from pathlib import Path

from gateway.core.config import output_path
from gateway.errors import GatewayError
from gateway.fleet.task import TaskResult
from gateway.recordings.columns import add_columns_option, column_map

SUFFIXES = (".csv", ".csv.gz", ".parquet")
MAX_RECORDINGS = 100_000


def configure_parser(command: str, parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "recordings", nargs="+", help="recording files, globs or folders (a Hive tree)"
    )
    parser.add_argument("--model", type=Path, required=True, help="nominal model YAML")
    parser.add_argument("--out", type=Path, required=True, help="output folder (created)")
    parser.add_argument(
        "--per-robot",
        action="store_true",
        help="one task per robot: its recordings diagnosed jointly (as diagnose REC REC ...), "
        "one report and one set of findings per robot",
    )
    parser.add_argument(
        "--scheduler",
        help="address of a running dask scheduler (tcp://HOST:8786) instead of a local "
        "cluster; its workers need cdpr-gateway installed and must see the recordings and "
        "the model at the paths given here",
    )
    parser.add_argument(
        "--workers", type=int, default=2, help="local cluster: worker processes (default 2)"
    )
    add_columns_option(parser)


def expand(args: list[str]) -> list[str]:
    """Absolute paths of the recordings named (files, globs, folders), sorted, unique."""
    found: dict[str, None] = {}
    for arg in args:
        path = Path(arg)
        if path.is_dir():
            hits = [p for p in path.rglob("*") if p.is_file() and p.name.endswith(SUFFIXES)]
        elif glob.has_magic(arg):
            hits = [Path(p) for p in glob.glob(arg, recursive=True)]
            hits = [p for p in hits if p.is_file() and p.name.endswith(SUFFIXES)]
        elif path.is_file():
            hits = [path]
        else:
            raise GatewayError(f"{arg}: no such recording")
        if not hits:
            raise GatewayError(f"{arg}: no recordings ({', '.join(SUFFIXES)}) there")
        for p in sorted(hits):
            found[str(p.resolve())] = None
        if len(found) > MAX_RECORDINGS:
            raise GatewayError(f"more than {MAX_RECORDINGS} recordings")
    return list(found)


def by_robot(recordings: list[str]) -> list[list[str]]:
    """The recordings grouped by robot (:func:`gateway.fleet.task.recording_identity`, from
    each file's metadata), robots in order of name, each robot's recordings in order of
    start, then path. A file whose metadata cannot be read is grouped by its path (its
    task then says what is wrong with it)."""
    from gateway.fleet.task import recording_identity
    from gateway.recordings.reader import read_metadata

    groups: dict[str, list[tuple[str, str]]] = {}
    for rec in recordings:
        try:
            meta = read_metadata(rec)
        except GatewayError:
            meta = {}
        robot, start = recording_identity(Path(rec), meta)
        groups.setdefault(robot, []).append((start, rec))
    return [[rec for _, rec in sorted(groups[robot])] for robot in sorted(groups)]


def _robot_name(i: int, robot: str) -> str:
    return f"{i:03d}-robot-{''.join(c if c.isalnum() or c in '-_.=' else '_' for c in robot)}.json"


def _name(i: int, recording: str) -> str:
    stem = Path(recording).name
    for suffix in SUFFIXES[::-1]:
        stem = stem.removesuffix(suffix)
    parent = Path(recording).parent.name
    label = f"{parent}-{stem}" if parent.startswith("date=") or stem.startswith("part-") else stem
    return f"{i:03d}-{''.join(c if c.isalnum() or c in '-_.=' else '_' for c in label)}.json"


def _verdict(res: TaskResult) -> tuple[str, str]:
    """(verdict, 'RMSE before -> after') of one result, for the terminal and fleet.md."""
    import json

    if res.report_json is None:
        return "FAILED", ""
    rep = json.loads(res.report_json)
    verdict = ", ".join(f["effect"] for f in rep["findings"]) or "none"
    return verdict, f"{rep['baseline']['rmse_n']:.3f} -> {rep['final']['rmse_n']:.3f}"


def run_command(command: str, args: argparse.Namespace) -> int:
    from gateway.fleet.run import import_distributed, run_tasks

    if not 1 <= args.workers <= 256:
        raise GatewayError("--workers must be in 1..256")
    import_distributed()  # a missing extra is one line, before anything else
    columns = column_map(args.columns)
    recordings = expand(args.recordings)
    tasks: list[str] | list[list[str]] = by_robot(recordings) if args.per_robot else recordings
    model = args.model.resolve()
    if not model.is_file():
        raise GatewayError(f"--model {args.model}: no such file")
    args.out.mkdir(parents=True, exist_ok=True)
    output_path(args.out / "fleet.md", "--out")
    (args.out / "reports").mkdir(exist_ok=True)
    t0 = time.perf_counter()

    def progress(done: int, res: TaskResult) -> None:
        if not args.quiet:
            verdict, rmse = _verdict(res)
            what = f"{verdict} (RMSE {rmse} N)" if res.report_json else f"FAILED: {res.error}"
            print(
                f"[{done:{len(str(len(tasks)))}d}/{len(tasks)}] {_what(res)}: "
                f"{what}, {res.seconds:.1f} s",
                file=sys.stderr,
                flush=True,
            )

    results, where = run_tasks(
        tasks,  # type: ignore[arg-type]
        str(model),
        args.scheduler,
        args.workers,
        progress,
        args.out / "dask.log",
        columns,
    )
    wall = time.perf_counter() - t0
    return _write_outputs(args.out, results, where, wall, str(args.model), args.per_robot)


def _what(res: TaskResult) -> str:
    """The task on the terminal: the recording, or the robot and its recordings' count."""
    if not res.recordings:
        return res.recording
    from gateway.fleet.plots import plural

    return f"robot {res.robot} ({plural(len(res.recordings), 'recording')})"


def _write_outputs(
    out: Path,
    results: list[TaskResult],
    where: str,
    wall: float,
    model: str,
    per_robot: bool = False,
) -> int:
    from gateway.fleet.plots import plural, write_plots, write_summary
    from gateway.fleet.table import table_rows, write_table

    named = [
        (res, _robot_name(i, res.robot) if per_robot else _name(i, res.recording))
        for i, res in enumerate(results)
    ]
    for res, name in named:
        if res.report_json is not None:
            (out / "reports" / name).write_text(res.report_json, encoding="utf-8")
    rows = table_rows([(res, name if res.report_json else "") for res, name in named])
    write_table(rows, out)
    plots = write_plots(rows, out / "plots")
    summary = []
    for res, name in named:
        verdict, rmse = _verdict(res)
        summary.append(
            {
                "robot": res.robot,
                "start": res.start,
                "recording": res.recording,
                "verdict": verdict,
                "rmse": rmse,
                "error": res.error,
                "report": f"reports/{name}" if res.report_json else "",
            }
        )
    summary.sort(key=lambda r: (r["robot"], r["start"], r["recording"]))
    info = {"cluster": where, "wall": f"{wall:.1f} s", "model": model}
    if per_robot:
        info["recordings"] = str(sum(len(r.recordings) for r in results))
    write_summary(out / "fleet.md", summary, plots, info)
    failed = sum(1 for r in results if r.error)
    what = plural(len(results), "recording")
    if per_robot:
        what = f"{plural(len(results), 'robot')} ({info['recordings']} recordings)"
    print(
        f"fleet: {what}, {failed} failed, {wall:.1f} s on {where}; "
        f"table, fleet.md and plots in {out}"
    )
    for res in results:
        if res.error:
            print(f"  failed: {_what(res)}: {res.error}")
    return 1 if failed == len(results) else 0
