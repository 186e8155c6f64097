"""The diagnosis on real recordings, blind, and the least-squares baseline
(:mod:`evaluation.realsuite`): EMPS against the published identification, the da Vinci
transmission against the baseline on two validation sets.

``python -m bench real`` (~6 min) reads the datasets from ``$REAL_DATA``: a folder
holding ``emps/`` and ``davinci/`` as their publishers ship them (the datasets and the
files read: ``evaluation/realdata.py``, which converts them; never copied into the
project; without ``$REAL_DATA``, a ``data/real`` folder beside the checkout's parent is
tried), and prints the section; with ``REAL_TABLE=docs/diagnose-suite.md`` it also writes
it there (the file's other sections are kept). ``REAL_REFITS=0`` skips the two refits on
the validation sets.
"""

from __future__ import annotations

import os
from pathlib import Path

from evaluation import realsuite
from evaluation.suitedoc import replace_section

DEFAULT_DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"


def data_dir() -> Path:
    return Path(os.environ.get("REAL_DATA", str(DEFAULT_DATA)))


def run() -> None:
    root = data_dir()
    if not (root / "emps").is_dir() or not (root / "davinci").is_dir():
        print(f"  no real recordings under {root} (set REAL_DATA): nothing measured")
        return
    emps = realsuite.run_emps(root)
    print(f"  EMPS: {emps['found']} in {emps['seconds']:.0f} s", flush=True)
    dv = realsuite.run_davinci(root, refits=os.environ.get("REAL_REFITS", "1") != "0")
    text = realsuite.table(emps, dv)
    print(text)
    table = os.environ.get("REAL_TABLE")
    if table:
        replace_section(Path(table), text)
        print(f"  written into {table}")
