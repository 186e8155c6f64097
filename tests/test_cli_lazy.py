"""``--help`` and a bad argument never import numba (issue 31 item 1): every command's
arguments are parsed before the modules that load numba and the compiled kernels are
imported (2-3.6 s for every ``--help`` before). An import-time check in a fresh
interpreter, not a timing: after ``main([cmd, ...])`` exits, ``numba`` is not in
``sys.modules``."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from gateway.cli import COMMANDS

ROOT = Path(__file__).resolve().parents[1]

PROBE = """
import contextlib, io, sys
from gateway.cli import main
out, err = io.StringIO(), io.StringIO()
try:
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(sys.argv[1:])
except SystemExit as exc:
    status = exc.code
print(status, 'numba' in sys.modules, len(out.getvalue()), len(err.getvalue()))
"""


def _run(*argv: str) -> tuple[int, bool, int, int]:
    """(exit status, numba imported, characters on stdout, on stderr) of ``main(argv)``."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run(
        [sys.executable, "-c", PROBE, *argv],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr
    status, numba, out, err = proc.stdout.split()
    return int(status), numba == "True", int(out), int(err)


def test_the_probe_sees_numba_when_a_command_loads_it() -> None:
    # `check` of the shipped config builds the driver (the output gate is compiled)
    status, numba, _, _ = _run("check", "--config", "config/default.yaml")
    assert status == 0 and numba


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_help_imports_no_numba(command: str) -> None:
    status, numba, out, _ = _run(command, "--help")
    assert status == 0 and out > 0  # the help was printed
    assert not numba, f"cdpr-gateway {command} --help imported numba"


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_bad_argument_imports_no_numba(command: str) -> None:
    status, numba, _, err = _run(command, "--no-such-option")
    assert status == 2 and err > 0
    assert not numba, f"cdpr-gateway {command} --no-such-option imported numba"


def test_the_top_level_help_imports_no_numba() -> None:
    status, numba, out, _ = _run("--help")
    assert status == 0 and out > 0 and not numba


FLOOR_PROBE = """
import importlib, pkgutil, sys
import drivers, gateway.core
names = []
for pkg in (gateway.core, drivers):
    for m in pkgutil.iter_modules(pkg.__path__, pkg.__name__ + "."):
        if m.name != "drivers.kernels":  # the drivers' compiled kernels themselves
            importlib.import_module(m.name)
            names.append(m.name)
print(len(names), 'numba' in sys.modules)
"""


def test_the_floor_and_the_drivers_import_without_numba() -> None:
    """Issue 28 item 4: every module of ``gateway.core`` and ``drivers`` (but
    ``drivers.kernels``, which the first gate or codec imports) imports without loading
    numba, so ``check`` and the configuration do not pay for the compiler."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run(
        [sys.executable, "-c", FLOOR_PROBE],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr
    count, numba = proc.stdout.split()
    assert int(count) >= 15 and numba == "False", proc.stdout
