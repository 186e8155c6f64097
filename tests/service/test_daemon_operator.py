"""``cdpr-gateway run`` as an operator meets it: a real subprocess each time.

* under systemd (a fake ``NOTIFY_SOCKET``) it is ready once configured, with no PLC
  listening, and pings the watchdog while it retries;
* a metrics port another process holds is a condition a restart can fix: not exit 2
  (the unit's ``RestartPreventExitStatus=2``), but 75 (EX_TEMPFAIL);
* the start-up lines tell the truth about real time.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from gateway.core.config import DEFAULT_CONFIG_PATH
from tests.loop_helpers import free_port

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.loopback


def write_config(tmp_path: Path, **edits) -> Path:
    """The default config pointed at a port nobody listens on; ``edits`` by dotted key."""
    data = yaml.safe_load(DEFAULT_CONFIG_PATH.read_text())
    data["bus"]["modbus_tcp"]["port"] = free_port()
    data["metrics"]["port"] = 0
    for dotted, value in edits.items():
        *parents, last = dotted.split("__")
        node = data
        for key in parents:
            node = node.setdefault(key, {})
        node[last] = value
    path = tmp_path / "gw.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def start_run(config: Path, env_extra: dict[str, str] | None = None, *args: str):
    env = {**os.environ, "PYTHONPATH": str(ROOT), **(env_extra or {})}
    if not env_extra or "NOTIFY_SOCKET" not in env_extra:
        env.pop("NOTIFY_SOCKET", None)
    return subprocess.Popen(
        [sys.executable, "-m", "gateway", "run", "--config", str(config), *args],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


def finish(proc: subprocess.Popen, exits_by_itself: bool = False) -> tuple[int, str]:
    if exits_by_itself:
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=60)
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        rc = proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        rc = proc.wait(timeout=10)
    assert proc.stderr is not None
    err = proc.stderr.read()
    proc.stderr.close()
    return rc, err


def test_ready_without_a_plc_then_watchdog_pings_while_it_retries(tmp_path):
    """READY=1 is the daemon's first message, before the first connection attempt's
    outcome (a STATUS line), so systemd's start never waits for the PLC. An order, not a
    time: under load (both cores busy) the start-up alone took 16.6 s where it had been
    asserted to take at most 5 s; how long the start takes is the benchmarks' business."""
    path = str(tmp_path / "notify")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(0.2)
    env = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "200000"}  # a ping every 0.1 s
    t0 = time.monotonic()
    proc = start_run(write_config(tmp_path), env)
    msgs: list[tuple[float, str]] = []
    try:
        deadline = t0 + 60  # bounded; a loaded machine's start-up took 16.6 s
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                msgs.append((time.monotonic() - t0, sock.recv(4096).decode()))
            except TimeoutError:
                continue
            ready = [t for t, m in msgs if m == "READY=1"]
            if ready and sum(m == "WATCHDOG=1" and t > ready[0] for t, m in msgs) >= 5:
                break
    finally:
        rc, err = finish(proc)
        sock.close()
    ready = [t for t, m in msgs if m == "READY=1"]
    assert ready, (msgs, err)
    texts = [m for _, m in msgs]
    assert texts[0] == "READY=1", (texts[:3], err)
    assert "STATUS=active" not in texts  # no PLC ever answered: ready while unreachable
    assert any(m.startswith("STATUS=cannot reach the PLC yet") for m in texts), texts
    pings = [t for t, m in msgs if m == "WATCHDOG=1" and t > ready[0]]
    assert len(pings) >= 5, (msgs, err)
    assert "cannot reach the PLC yet" in err
    assert rc == 0, err


def test_metrics_port_in_use_is_a_temporary_failure_not_a_config_error(tmp_path):
    holder = socket.socket()
    holder.bind(("127.0.0.1", 0))
    holder.listen(1)
    port = holder.getsockname()[1]
    try:
        proc = start_run(write_config(tmp_path, metrics__port=port))
        rc, err = finish(proc, exits_by_itself=True)
    finally:
        holder.close()
    lines = err.strip().splitlines()
    assert rc == 75, err  # EX_TEMPFAIL: Restart=on-failure retries it
    assert f"metrics.port: cannot serve metrics on 127.0.0.1:{port}" in lines[-1]
    assert "Traceback" not in err


def test_the_unit_restarts_a_temporary_failure_but_not_a_config_error():
    unit = (ROOT / "deploy" / "cdpr-gateway.service").read_text().splitlines()
    settings = dict(line.split("=", 1) for line in unit if "=" in line and line[0] != "#")
    assert settings["Restart"] == "on-failure"  # restarts any non-zero exit ...
    assert settings["RestartPreventExitStatus"].split() == ["2"]  # ... but the config's


def test_the_banner_tells_the_truth_about_real_time(tmp_path):
    proc = start_run(write_config(tmp_path), None, "--seconds", "1")
    rc, err = finish(proc, exits_by_itself=True)
    assert rc == 0, err
    assert "not configured" not in err
    rt = [line for line in err.splitlines() if "cdpr_gateway: real-time: " in line]
    assert len(rt) == 1, err  # tried by default: one line, what was applied and refused
    assert "applied" in rt[0] and "refused" in rt[0]
    banner = [line for line in err.splitlines() if " loop: period " in line]
    assert len(banner) == 1 and "real-time: tried (loop.realtime" in banner[0], err


def test_real_time_off_when_the_config_says_so(tmp_path):
    proc = start_run(
        write_config(tmp_path, loop__realtime={"enabled": False}), None, "--seconds", "1"
    )
    rc, err = finish(proc, exits_by_itself=True)
    assert rc == 0, err
    assert "real-time: off (loop.realtime.enabled is false)" in err
    assert "real-time: applied" not in err
