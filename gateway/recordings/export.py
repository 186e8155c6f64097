"""``cdpr-gateway export RECORDING --to mcap OUT.mcap [--columns MAP]``: a recording (CSV,
CSV.gz or Parquet; another logger's with ``--columns``) as MCAP
(:mod:`gateway.recordings.mcap_export`). OUT must end in the format's extension."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from gateway.core.config import output_path
from gateway.errors import ConfigError
from gateway.recordings.columns import add_columns_option, column_map

EXTENSIONS = {"mcap": ".mcap"}  # --to FORMAT: the name OUT must end in


def configure_parser(command: str, parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", type=Path, help="recording (.csv, .csv.gz or .parquet)")
    parser.add_argument("--to", choices=("mcap",), required=True, help="the format to write")
    parser.add_argument("out", type=Path, help="the file to write (OUT.mcap)")
    add_columns_option(parser)


def run_command(command: str, args: argparse.Namespace) -> int:
    from gateway.recordings.mcap_export import export_mcap

    output_path(args.out, "OUT")
    regular = args.out.is_file() or not args.out.exists()  # else export_mcap says why
    if regular and args.out.suffix != EXTENSIONS[args.to]:
        raise ConfigError(
            f"OUT {args.out}: the name must end in {EXTENSIONS[args.to]} "
            f"(--to {args.to} writes {args.to.upper()})"
        )
    columns = column_map(args.columns)
    t0 = time.perf_counter()
    count = export_mcap(args.recording, args.out, columns=columns)
    if not args.quiet:
        print(
            f"export: {count} messages -> {args.out} ({time.perf_counter() - t0:.1f} s)",
            file=sys.stderr,
        )
    return 0
