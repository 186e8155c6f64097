"""``cdpr-gateway export RECORDING --to mcap OUT.mcap``: a recording (CSV, CSV.gz or
Parquet) as MCAP (:mod:`gateway.recordings.mcap_export`)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from gateway.core.config import output_path


def configure_parser(command: str, parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", type=Path, help="recording (.csv, .csv.gz or .parquet)")
    parser.add_argument("--to", choices=("mcap",), required=True, help="the format to write")
    parser.add_argument("out", type=Path, help="the file to write (OUT.mcap)")


def run_command(command: str, args: argparse.Namespace) -> int:
    from gateway.recordings.mcap_export import export_mcap

    output_path(args.out, "OUT")
    t0 = time.perf_counter()
    count = export_mcap(args.recording, args.out)
    if not args.quiet:
        print(
            f"export: {count} messages -> {args.out} ({time.perf_counter() - t0:.1f} s)",
            file=sys.stderr,
        )
    return 0
