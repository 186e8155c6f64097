"""``cdpr-gateway diagnose RECORDING [RECORDING ...] --model MODEL.yaml [--json REPORT.json]
[--report DIR] [--validate OTHER] [--write-model FITTED.yaml] [--columns MAP]``: see
docs/recording-format.md, :mod:`gateway.diagnose.engine`, (several recordings of one
machine) :mod:`gateway.diagnose.sessions` and (the model file's fitted effects)
:mod:`gateway.diagnose.writemodel`."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING

from gateway.core.cliopts import output_dir
from gateway.core.config import (
    Config,
    FrictionConfig,
    config_from_mapping,
    load_friction,
    output_path,
)
from gateway.core.configtypes import read_yaml
from gateway.diagnose import heldout
from gateway.errors import GatewayError
from gateway.recordings.columns import add_columns_option, column_map
from gateway.recordings.reader import Recording, read_recording

# The diagnosis proper (engine, statics, warm-up, model writer) loads numba and the compiled
# kernels: imported where a file is diagnosed, never for --help (tests/test_cli_lazy.py).
if TYPE_CHECKING:
    from gateway.diagnose.engine import Diagnosis


def configure_parser(command: str, parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "recording",
        type=Path,
        nargs="+",
        help="recording (.csv, .csv.gz or .parquet); several: recordings of one machine, "
        "diagnosed together for one set of findings",
    )
    parser.add_argument(
        "--model",
        type=Path,
        required=True,
        help="nominal model YAML: a friction: mapping, or a full config",
    )
    parser.add_argument("--json", type=Path, help="write the JSON report here")
    parser.add_argument("--report", type=Path, help="write PNG pictures and summary.md here")
    parser.add_argument(
        "--validate",
        type=Path,
        help="a second recording of the same machine, scored but never fitted",
    )
    parser.add_argument(
        "--write-model",
        type=Path,
        help="write the model plus every fitted effect here (friction.effects)",
    )
    add_columns_option(parser)  # the recording's and --validate's


def load_model(path: Path) -> tuple[object, Config | None]:
    """The friction config and, if the file is a full config with a geometry, the config."""
    data = read_yaml(path)
    friction = load_friction(path)
    cfg = config_from_mapping(data, str(path)) if "geometry" in data else None
    return friction, cfg


def _tensions(rec: Recording, cfg: Config | None, say):
    """Platform tensions (N, m) and dT_p/dm (N, m) or None."""
    from gateway.diagnose import pose_statics

    if rec.tension_platform is not None:
        tp = rec.tension_platform
    else:
        say(f"{rec.source}: platform tensions from pose and mass (statics)")
        tp = pose_statics.platform_tensions(rec, cfg)
    return tp, pose_statics.mass_sensitivity(rec, cfg, say)


def _read(
    path: Path,
    friction: FrictionConfig,
    cfg: Config | None = None,
    columns: Mapping[str, str] | None = None,
) -> tuple[Recording, FrictionConfig]:
    """A recording relative to the model's fitted effects (``friction.effects``) and the
    nominal friction (:func:`relative_to_model`). Without effects, only the first row of
    the cable lengths is read: the diagnosis reads none of them, the model writer the
    first (the eccentricity's phase); undoing effects needs all of them."""
    from gateway.diagnose.writemodel import relative_to_model

    first_only = () if friction.effects else ("length",)
    rec = read_recording(path, first_row_only=first_only, columns=columns)
    return relative_to_model(rec, friction, cfg)


def _unchanged(rec: Recording) -> Recording:
    return rec


def _slim(rec: Recording) -> tuple[Recording, Callable[[Recording], Recording]]:
    """The recording without its cable lengths, which the diagnosis does not read (64
    bytes per sample of 8 cables when they were read whole), and a function that gives the
    model writer back what it reads of them (the first lengths, for the eccentricity's
    phase). Pose and mass go too once the platform tensions and dT_p/dm exist
    (:func:`_without_pose`)."""
    first = None if rec.length is None else rec.length[:1].copy()

    def keep_for_model(r: Recording) -> Recording:
        return dataclasses.replace(r, length=first)  # one row: write_model reads length[0]

    return dataclasses.replace(rec, length=None), keep_for_model


def _without_pose(rec: Recording) -> Recording:
    """``rec`` without pose and mass (56 bytes per sample), read by :func:`_tensions` only."""
    return dataclasses.replace(rec, pose=None, mass=None)


@dataclasses.dataclass
class _Run:
    """One diagnosis of a file: the result and what the model writer needs of it."""

    diag: Diagnosis
    rec: Recording
    keep_for_model: Callable[[Recording], Recording]
    model_friction: object


def _diagnose_file(
    recording: Path | list[Path],
    model: Path,
    validate: Path | None,
    say: Callable[[str], None],
    columns: Mapping[str, str] | None = None,
) -> _Run:
    from gateway.diagnose import transient
    from gateway.diagnose.engine import diagnose, load_kernels, reference_mode

    recordings = list(recording) if isinstance(recording, list | tuple) else [recording]
    model_friction, cfg = load_model(model)
    load_kernels(model_friction)  # type: ignore[arg-type]  # LLVM's pages given back after
    if len(recordings) > 1:
        return _diagnose_joined(recordings, model_friction, cfg, validate, say, columns)
    recording = recordings[0]
    rec, nominal = _read(recording, model_friction, cfg, columns)  # type: ignore[arg-type]
    friction: object = nominal  # the nominal chain; the model's effects are in ``rec``
    say(
        f"{rec.source}: {rec.samples} samples x {rec.cables} cables"
        + (f", {rec.skipped_rows} rows skipped (missing values)" if rec.skipped_rows else "")
    )

    keep_for_model: Callable[[Recording], Recording] = _unchanged
    if reference_mode(rec) == "wrench":  # no platform tensions: the wrench balance
        from gateway.diagnose.wrench_select import diagnose_wrench

        wrec = None if validate is None else _read(validate, model_friction, cfg, columns)[0]  # type: ignore[arg-type]
        diag: Diagnosis = diagnose_wrench(rec, friction, cfg, wrec, progress=say)  # type: ignore[arg-type]
    else:
        rec, keep_for_model = _slim(rec)
        tp, dm = _tensions(rec, cfg, say)
        rec = _without_pose(rec)
        validation = None
        if validate is not None:
            vread = _read(validate, model_friction, cfg, columns)  # type: ignore[arg-type]
            vrec = dataclasses.replace(vread[0], length=None)
            vtp, vdm = _tensions(vrec, cfg, say)
            validation = (_without_pose(vrec), vtp, vdm if dm is not None else None)
        diag = diagnose(rec, friction, tp=tp, dtp_dm=dm, validation=validation, progress=say)  # type: ignore[arg-type]
    transient.annotate(diag.report, rec, nominal)  # the start-up transient, said as such
    return _Run(diag, rec, keep_for_model, model_friction)


def _diagnose_joined(
    recordings: list[Path],
    model_friction,
    cfg: Config | None,
    validate,
    say,
    columns: Mapping[str, str] | None = None,
) -> _Run:
    """Several recordings of one machine, joined (:mod:`gateway.diagnose.sessions`) and
    diagnosed as one against their platform tensions (or, none of them having any, the
    wrench balance: :func:`_diagnose_joined_wrench`)."""
    from gateway.diagnose import transient
    from gateway.diagnose.engine import diagnose, reference_mode
    from gateway.diagnose.sessions import join

    first, nominal = _read(recordings[0], model_friction, cfg, columns)
    if reference_mode(first) == "wrench":
        return _diagnose_joined_wrench(
            first, recordings, model_friction, nominal, cfg, validate, say, columns
        )
    parts = []
    keep_for_model: Callable[[Recording], Recording] = _unchanged
    for k, path in enumerate(recordings):
        if k == 0:
            rec, first = first, None  # type: ignore[assignment]  # read above, held once
        else:
            rec, nominal = _read(path, model_friction, cfg, columns)
        say(f"{rec.source}: {rec.samples} samples x {rec.cables} cables")
        if reference_mode(rec) == "wrench":
            raise GatewayError(
                f"{path}: no tension_platform_i columns, {recordings[0]} has them: the "
                "recordings diagnosed together must all have platform tensions or none"
            )
        if k == 0:
            rec, keep_for_model = _slim(rec)  # the model writer reads the first's lengths
        else:
            rec = dataclasses.replace(rec, length=None)
        tp, dm = _tensions(rec, cfg, say)
        parts.append((_without_pose(rec), tp, dm))
    joined, tp, dm, sessions = join(parts, [str(p) for p in recordings])
    del parts
    validation = None
    if validate is not None:
        vrec = dataclasses.replace(_read(validate, model_friction, cfg, columns)[0], length=None)
        vtp, vdm = _tensions(vrec, cfg, say)
        validation = (_without_pose(vrec), vtp, vdm if dm is not None else None)
    say(f"{sessions.count} recordings joined: {joined.samples} samples")
    diag = diagnose(
        joined,
        nominal,
        tp=tp,
        dtp_dm=dm,
        validation=validation,
        progress=say,
        sessions=sessions,
    )
    assert nominal is not None  # at least two recordings were read
    transient.annotate(diag.report, joined, nominal)
    return _Run(diag, joined, keep_for_model, model_friction)


def _diagnose_joined_wrench(
    first: Recording,
    recordings: list[Path],
    model_friction,
    nominal,
    cfg: Config | None,
    validate,
    say,
    columns: Mapping[str, str] | None = None,
) -> _Run:
    """Several recordings without platform tensions, joined and diagnosed as one against
    the wrench balance (:func:`gateway.diagnose.wrench_select.diagnose_joined_wrench`)."""
    from gateway.diagnose import transient
    from gateway.diagnose.engine import reference_mode
    from gateway.diagnose.wrench_select import diagnose_joined_wrench

    recs = [first]
    for path in recordings[1:]:
        rec = _read(path, model_friction, cfg, columns)[0]
        if reference_mode(rec) != "wrench":
            raise GatewayError(
                f"{path}: tension_platform_i columns, {recordings[0]} has none: the "
                "recordings diagnosed together must all have platform tensions or none"
            )
        recs.append(rec)
    for rec in recs:
        say(f"{rec.source}: {rec.samples} samples x {rec.cables} cables")
    wrec = None if validate is None else [_read(validate, model_friction, cfg, columns)[0]]
    diag, joined = diagnose_joined_wrench(
        recs, [str(p) for p in recordings], nominal, cfg, wrec, progress=say
    )
    transient.annotate(diag.report, joined, nominal)
    return _Run(diag, joined, _unchanged, model_friction)


def report_json(report: dict) -> str:
    """The text of ``--json REPORT.json``."""
    return json.dumps(report, indent=1)


def diagnose_report(
    recording: Path | list[Path],
    model: Path,
    validate: Path | None = None,
    progress: Callable[[str], None] | None = None,
    columns: Mapping[str, str] | None = None,
) -> dict:
    """The report ``diagnose RECORDING [RECORDING ...] --model MODEL [--validate OTHER]
    [--columns MAP]`` writes, as a dict (:func:`report_json` gives its text); bad input
    raises :class:`GatewayError`. The one entry point for a caller that diagnoses files
    (``cdpr-gateway fleet``); ``recording``: one path, or a list of one machine's;
    ``columns`` as :func:`gateway.recordings.columns.column_map` gives it."""
    paths = [Path(p) for p in recording] if isinstance(recording, list | tuple) else Path(recording)
    return _diagnose_file(paths, Path(model), validate, progress or _silent, columns).diag.report


def _silent(msg: str) -> None:
    pass


def run_command(command: str, args: argparse.Namespace) -> int:
    from gateway.diagnose.writemodel import write_model

    start = time.perf_counter()

    def say(msg: str) -> None:
        if not args.quiet:
            print(f"[{time.perf_counter() - start:6.1f} s] {msg}", file=sys.stderr, flush=True)

    columns = column_map(args.columns)  # before the work, as the paths below
    if args.json is not None:  # before the work; never creates directories
        output_path(args.json, "--json")
    if args.write_model is not None:
        output_path(args.write_model, "--write-model")
    if args.report is not None:  # a directory: one level is created, now, not after the work
        output_dir(args.report, "--report")
    run = _diagnose_file(args.recording, args.model, args.validate, say, columns)
    diag, rec = run.diag, run.rec
    if args.json is not None:
        try:
            args.json.write_text(report_json(diag.report), encoding="utf-8")
        except OSError as exc:
            raise GatewayError(f"{args.json}: cannot write the report: {exc}") from exc
        say(f"report in {args.json}")
    if args.report is not None:
        from gateway.diagnose.plots import write_report
        from gateway.diagnose.wrench_plots import write_report as write_wrench_report

        name = " + ".join(str(p) for p in args.recording)
        if diag.report["reference"] == "wrench":
            write_wrench_report(diag, args.report, name)  # type: ignore[arg-type]
        else:
            write_report(diag, args.report, name)
        say(f"pictures and summary.md in {args.report}")
    if args.write_model is not None:
        refused = heldout.refusal(diag.report, heldout.motion(rec.t, rec.velocity))
        if refused is not None:
            raise GatewayError(f"--write-model {args.write_model}: {refused}")
        fitted_from = run.keep_for_model(rec)
        write_model(args.write_model, args.model, run.model_friction, diag.report, fitted_from)  # type: ignore[arg-type]
        say(f"fitted model in {args.write_model}")
    rep = diag.report
    verdict = ", ".join(f["effect"] for f in rep["findings"]) or "none"
    print(
        f"verdict: {verdict}; RMSE {rep['baseline']['rmse_n']:.3f} N -> "
        f"{rep['final']['rmse_n']:.3f} N (held out {rep['final']['holdout_rmse_n']:.3f} N)"
    )
    return 0
