"""``cdpr-gateway examples [DIR]``: the bundled configs, listed or copied.

Without DIR: one line per bundled file (its path relative to the bundle and the first
line of its header comment). With DIR: every bundled file copied into DIR, keeping the
folders (``DIR/default.yaml``, ``DIR/calibrate/viscous.yaml``, the EDS files), so that the
README's commands run as written from a wheel install: ``cdpr-gateway examples config``
in an empty directory gives the ``config/`` of a checkout. DIR is created (one level);
an existing file is never overwritten (one line naming it, exit status 2, nothing copied).
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from gateway.core.cliopts import output_dir
from gateway.core.resources import data_dir
from gateway.errors import ConfigError

SUFFIXES = (".yaml", ".eds")


def configure_parser(command: str, parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "dir",
        nargs="?",
        type=Path,
        metavar="DIR",
        help="copy the bundled configs here (created; existing files are "
        "never overwritten); without it, list them",
    )


def bundled() -> list[Path]:
    """The bundled files, relative to the bundle, sorted (top level first)."""
    root = data_dir()
    found = [p.relative_to(root) for p in root.rglob("*") if p.suffix in SUFFIXES]
    return sorted(found, key=lambda p: (len(p.parts), str(p)))


def describe(path: Path) -> str:
    """The first comment line of a YAML file's header; for EDS files, what they are."""
    if path.suffix == ".eds":
        return "CANopen device description (EDS)"
    with path.open(encoding="utf-8") as f:
        first = f.readline().strip()
    return first.lstrip("# ")[:72] if first.startswith("#") else ""


def run_command(command: str, args: argparse.Namespace) -> int:
    root, files = data_dir(), bundled()
    if args.dir is None:
        print(f"bundled configs ({root}); 'cdpr-gateway examples DIR' copies them:")
        for rel in files:
            print(f"  {rel.as_posix():27} {describe(root / rel)}")
        return 0
    taken = [rel for rel in files if (args.dir / rel).exists()]
    if taken:
        raise ConfigError(
            f"{args.dir / taken[0]}: exists; nothing copied (remove it or choose another DIR)"
        )
    out = output_dir(args.dir, "DIR")
    for rel in files:
        (out / rel).parent.mkdir(exist_ok=True)
        shutil.copyfile(root / rel, out / rel)
    print(f"copied {len(files)} files into {out}")
    return 0
