"""``cdpr-gateway diagnose RECORDING [RECORDING ...] --model MODEL.yaml [--json REPORT.json]
[--report DIR] [--validate OTHER] [--write-model FITTED.yaml] [--columns MAP]``: see
docs/recording-format.md, :mod:`gateway.diagnose.fromfiles` (the files' diagnosis),
:mod:`gateway.diagnose.engine`, (several recordings of one machine)
:mod:`gateway.diagnose.sessions` and (the model file's fitted effects)
:mod:`gateway.diagnose.writemodel`."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from gateway.core.cliopts import output_dir
from gateway.core.config import output_path
from gateway.errors import GatewayError
from gateway.recordings.columns import add_columns_option, column_map

# The diagnosis proper (:mod:`.fromfiles`: engine, statics, warm-up, model writer) loads
# numba and the compiled kernels: imported where a file is diagnosed, never for --help
# (tests/test_cli_lazy.py).


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


def report_json(report: dict) -> str:
    """The text of ``--json REPORT.json``."""
    return json.dumps(report, indent=1)


def run_command(command: str, args: argparse.Namespace) -> int:
    from gateway.diagnose.fromfiles import diagnose_file

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
    run = diagnose_file(args.recording, args.model, args.validate, columns=columns, progress=say)
    diag = run.diag
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
        run.write_model(args.write_model, f"--write-model {args.write_model}")
        say(f"fitted model in {args.write_model}")
    rep = diag.report
    verdict = ", ".join(f["effect"] for f in rep["findings"]) or "none"
    print(
        f"verdict: {verdict}; RMSE {rep['baseline']['rmse_n']:.3f} N -> "
        f"{rep['final']['rmse_n']:.3f} N (held out {rep['final']['holdout_rmse_n']:.3f} N)"
    )
    return 0
