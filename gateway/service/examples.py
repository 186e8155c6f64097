"""``cdpr-gateway examples [DIR]`` and ``cdpr-gateway examples deploy DIR``: the bundled
files, listed or copied.

Without DIR: one line per bundled file (its path relative to the bundle and the first
line of its header comment). With DIR: every bundled config copied into DIR, keeping the
folders (``DIR/default.yaml``, ``DIR/calibrate/viscous.yaml``, the EDS files), so that the
README's commands run as written from a wheel install: ``cdpr-gateway examples config``
in an empty directory gives the ``config/`` of a checkout.

``examples deploy DIR`` writes what installing the daemon as a service needs
(docs/service.md): the systemd unit with this installation's console script in
``ExecStart`` and its documents in ``Documentation=``, the config the unit reads
(``gateway.yaml``, the shipped ``default.yaml``), the Prometheus scrape config, alert
rules and their tests, the Alertmanager config, the Grafana dashboard and its
provisioning, and ``site/`` (many gateways in one Prometheus).

DIR is created (one level); an existing file is never overwritten (one line naming it,
exit status 2, nothing copied).
"""

from __future__ import annotations

import argparse
import re
import shutil
import sys
from pathlib import Path

from gateway.core.cliopts import output_dir
from gateway.core.resources import data_dir, deploy_dir, docs_dir
from gateway.errors import ConfigError

SUFFIXES = (".yaml", ".eds")
DEPLOY_SUFFIXES = (".yml", ".json", ".service")
UNIT = "cdpr-gateway.service"
CONFIG_IN_UNIT = "gateway.yaml"  # the unit's --config file, written beside it from default.yaml
SCRIPT = "cdpr-gateway"

EPILOG = """examples:
  cdpr-gateway examples                  list the bundled configs and service files
  cdpr-gateway examples config           copy the configs into ./config
  cdpr-gateway examples deploy service   write the unit, gateway.yaml, the Prometheus,
                                         Alertmanager and Grafana files into ./service
                                         (docs/service.md installs them)"""


def configure_parser(command: str, parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "target",
        nargs="*",
        metavar="[deploy] DIR",
        help="DIR: copy the bundled configs here; 'deploy DIR': write the service files "
        "(systemd unit for this installation, gateway.yaml, Prometheus rules, Alertmanager, "
        "Grafana) here. DIR is created; existing files are never overwritten. Without "
        "DIR: list them",
    )
    parser.epilog = EPILOG
    parser.formatter_class = argparse.RawDescriptionHelpFormatter


def bundled() -> list[Path]:
    """The bundled configs, relative to the bundle, sorted (top level first)."""
    return _listing(data_dir(), SUFFIXES)


def bundled_deploy() -> list[Path]:
    """The bundled service files, relative to their bundle, sorted (top level first)."""
    return _listing(deploy_dir(), DEPLOY_SUFFIXES)


def _listing(root: Path, suffixes: tuple[str, ...]) -> list[Path]:
    found = [p.relative_to(root) for p in root.rglob("*") if p.suffix in suffixes]
    return sorted(found, key=lambda p: (len(p.parts), str(p)))


def describe(path: Path) -> str:
    """The first comment line of a file's header; for EDS and JSON files, what they are."""
    if path.suffix == ".eds":
        return "CANopen device description (EDS)"
    if path.suffix == ".json":
        return "Grafana dashboard (JSON)"
    with path.open(encoding="utf-8") as f:
        first = f.readline().strip()
    return first.lstrip("# ")[:72] if first.startswith("#") else ""


def console_script() -> Path:
    """This installation's ``cdpr-gateway`` (the venv's ``bin/`` beside the interpreter, else
    the one on PATH); refused in one line when there is none."""
    beside = Path(sys.executable).with_name(SCRIPT)
    if beside.is_file():
        return beside.absolute()
    found = shutil.which(SCRIPT)
    if found is None:
        raise ConfigError(
            f"examples deploy: no {SCRIPT} console script beside {sys.executable} or on "
            "PATH (install the package with pip first)"
        )
    return Path(found).absolute()


def unit_text(template: str, script: Path, docs: Path) -> str:
    """The shipped unit with ``ExecStart`` (and the warmup's ``ExecStartPre``) running
    ``script`` and ``Documentation=``
    pointing at the installed documents (file URIs: systemd opens them with
    ``systemctl help``)."""
    out, n = re.subn(
        r"(?m)^(ExecStart(?:Pre)?=)\S+/cdpr-gateway ",
        lambda m: f"{m.group(1)}{script} ",
        template,
    )
    if not re.search(rf"(?m)^ExecStart={re.escape(str(script))} ", out):
        raise ConfigError(f"{UNIT}: no 'ExecStart=.../cdpr-gateway ...' line to point at {script}")
    docs_line = "Documentation=" + " ".join(
        (docs / name).as_uri() for name in ("service.md", "security.md")
    )
    out, n = re.subn(r"(?m)^#? ?Documentation=.*$", lambda _m: docs_line, out, count=1)
    if n != 1:
        raise ConfigError(f"{UNIT}: no Documentation= line")
    return out


def _refuse_existing(out: Path, rels: list[Path]) -> None:
    taken = [rel for rel in rels if (out / rel).exists()]
    if taken:
        raise ConfigError(
            f"{out / taken[0]}: exists; nothing copied (remove it or choose another DIR)"
        )


def _copy_configs(dest: Path) -> int:
    root, files = data_dir(), bundled()
    _refuse_existing(dest, files)
    out = output_dir(dest, "DIR")
    for rel in files:
        (out / rel).parent.mkdir(exist_ok=True)
        shutil.copyfile(root / rel, out / rel)
    print(f"copied {len(files)} files into {out}")
    return 0


def _write_deploy(dest: Path) -> int:
    root, files = deploy_dir(), bundled_deploy()
    script = console_script()
    unit = unit_text((root / UNIT).read_text(encoding="utf-8"), script, docs_dir())
    _refuse_existing(dest, [*files, Path(CONFIG_IN_UNIT)])
    out = output_dir(dest, "DIR")
    for rel in files:
        (out / rel).parent.mkdir(exist_ok=True)
        if rel.as_posix() == UNIT:
            (out / rel).write_text(unit, encoding="utf-8")
        else:
            shutil.copyfile(root / rel, out / rel)
    shutil.copyfile(data_dir() / "default.yaml", out / CONFIG_IN_UNIT)
    print(
        f"wrote {len(files) + 1} files into {out}: {UNIT} (ExecStart {script}), "
        f"{CONFIG_IN_UNIT} (edit it for your PLC), the Prometheus, Alertmanager and "
        f"Grafana files; install them as {docs_dir() / 'service.md'} says"
    )
    return 0


def run_command(command: str, args: argparse.Namespace) -> int:
    target = [str(t) for t in args.target]
    if not target:
        root = data_dir()
        print(f"bundled configs ({root}); 'cdpr-gateway examples DIR' copies them:")
        for rel in bundled():
            print(f"  {rel.as_posix():27} {describe(root / rel)}")
        droot = deploy_dir()
        print(f"service files ({droot}); 'cdpr-gateway examples deploy DIR' writes them:")
        for rel in bundled_deploy():
            print(f"  {rel.as_posix():27} {describe(droot / rel)}")
        return 0
    if len(target) == 1 and target[0] != "deploy":
        return _copy_configs(Path(target[0]))
    if len(target) == 2 and target[0] == "deploy":
        return _write_deploy(Path(target[1]))
    if target == ["deploy"]:
        raise ConfigError(
            "examples deploy: needs DIR, the directory to write the service files into"
        )
    raise ConfigError(f"examples: takes DIR or 'deploy DIR', not {' '.join(target)!r}")
