"""Every catchable terminating signal ends the daemon with the STOPPED frame.

A real ``cdpr-gateway run`` subprocess against the soft PLC's Modbus server (in this
process, loopback): once the gateway writes ACTIVE, the signal is sent; the process exits
0 and the PLC's image holds state 0 (stopped), every channel invalid and NaN tensions.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.base import ChannelStatus, Lifecycle
from gateway.runtime.loop import STOP_SIGNALS
from tests.config_helpers import edited_config
from tests.modbus_helpers import plc_server

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.loopback


def test_every_catchable_terminating_signal_is_handled() -> None:
    names = {s.name for s in STOP_SIGNALS}
    assert {"SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT", "SIGUSR1", "SIGUSR2", "SIGALRM"} <= names
    assert "SIGPIPE" not in names  # ignored by Python: a broken socket is a write error


@pytest.mark.parametrize("sig", [signal.SIGHUP, signal.SIGQUIT, signal.SIGUSR1])
def test_signal_writes_the_stopped_frame(tmp_path: Path, sig: signal.Signals) -> None:
    with plc_server() as (server, img, _cfg):

        def edit(data):
            data["bus"]["modbus_tcp"]["port"] = server.port
            data["loop"]["heartbeat_timeout_s"] = 60.0  # the test moves the heartbeat slowly
            data["metrics"]["enabled"] = False

        path = edited_config(tmp_path, edit)
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        env.pop("NOTIFY_SOCKET", None)
        proc = subprocess.Popen(
            [sys.executable, "-m", "gateway.cli", "run", "--config", str(path)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        try:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and proc.poll() is None:
                with img.lock:
                    img.plc_heartbeat = (img.plc_heartbeat + 1) & 0xFFFF  # a live PLC
                    good = np.all(np.isfinite(img.corrected_n))
                    if img.gateway_state == Lifecycle.ACTIVE and img.gateway_writes > 20 and good:
                        break
                time.sleep(0.05)
            with img.lock:
                assert img.gateway_state == Lifecycle.ACTIVE, proc.poll()
                assert np.all(np.isfinite(img.corrected_n))
            proc.send_signal(sig)
            assert proc.wait(timeout=30) == 0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(timeout=10)
            assert proc.stderr is not None
            err = proc.stderr.read()
            proc.stderr.close()
        with img.lock:
            assert img.gateway_state == Lifecycle.STOPPED == 0, err
            assert np.all(img.channel_status == ChannelStatus.INVALID)
            assert np.all(np.isnan(img.corrected_n))
        assert "stopped: cycles" in err
