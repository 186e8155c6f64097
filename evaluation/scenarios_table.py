"""The scenario suites' tables in docs/diagnose-suite.md (``make suite-table``), and the
sealed set's draw and seal: ``python -m evaluation.scenarios_table --table FILE``,
``--seal SEED`` (draw the sealed file anew), ``--twin NAME --seal SEED`` (append one
tuning scenario's twin drawn alone), ``--reseal REASON`` (record its hash).

Apart from :mod:`evaluation.scenarios` so that the suite does not import its own sealed
draw (:mod:`evaluation.sealed_draw` builds on the suite).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from evaluation import sealed_draw, sealing
from evaluation.scenarios import (
    SEALED_FILE,
    _row,
    evaluate,
    sealed,
    sealed_section,
    suite,
    tuning_section,
)
from evaluation.suitedoc import replace_section


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m evaluation.scenarios_table", description=__doc__
    )
    parser.add_argument("--table", type=Path, help="write the results into this file")
    parser.add_argument("--set", choices=("tuning", "sealed", "both"), default="both")
    parser.add_argument("--only", nargs="*", help="scenario names to run")
    parser.add_argument("--seal", type=int, metavar="SEED", help="draw SEALED_FILE anew")
    parser.add_argument("--reseal", metavar="REASON", help="record the sealed file's hash")
    parser.add_argument(
        "--twin",
        metavar="NAME",
        help="with --seal SEED: append the twin of tuning scenario NAME drawn alone from SEED",
    )
    args = parser.parse_args(argv)
    doc = args.table or Path("docs/diagnose-suite.md")
    if args.twin:
        if args.seal is None:
            parser.error("--twin needs --seal SEED")
        case = sealed_draw.append(SEALED_FILE, args.twin, args.seal)
        print(f"{SEALED_FILE}: appended {case['name']}; record it with --reseal REASON")
        return 0
    if args.seal is not None:
        sealed_draw.write(SEALED_FILE, args.seal)
        print(f"{SEALED_FILE}: drawn from seed {args.seal}; record it with --reseal REASON")
        return 0
    if args.reseal:
        sealing.add(doc, SEALED_FILE, args.reseal)
        return 0
    digest = sealing.check(doc, SEALED_FILE) if args.set != "tuning" else ""
    sets = {"tuning": suite(), "sealed": sealed()}
    for name in ("tuning", "sealed"):
        if args.set not in (name, "both"):
            continue
        results = []
        for sc in sets[name]:
            if args.only and sc.name not in args.only:
                continue
            res = evaluate(sc)
            print(_row(res), file=sys.stderr, flush=True)
            results.append(res)
        if args.table:
            text = tuning_section(results) if name == "tuning" else sealed_section(results, digest)
            replace_section(args.table, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
