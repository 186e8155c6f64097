"""The gateway against a hostile Modbus PLC (tests/hostile_modbus.py), loopback only.

Two probes (a hostile PLC), each bounded in time:

* ``storm``: the real cycle (:class:`gateway.runtime.loop.CyclicService` with the Modbus driver)
  runs ``seconds`` against a PLC that answers exceptions (6, busy), malformed frames,
  accepts then drops, resets mid-frame, or refuses the client certificate (TLS); prints
  the TCP connections the gateway opened per second (goal: a growing interval up to
  ``reconnect_max_s``, not a storm);
* ``ratchet``: back-to-back reads for ``seconds`` against replies 46.5 ms late (timeout
  50 ms), whole and split in three; prints the timeouts of each.

``python -m bench hostile`` runs both with the defaults; ``python -m bench.bench_hostile
storm|ratchet [SECONDS]`` runs one (the same script measured the code before the fix).
"""

from __future__ import annotations

import sys
import tempfile
import threading
import time

from drivers.base import Inputs, make_driver
from gateway.core.config import Config, TlsConfig
from gateway.errors import DriverError, DriverTimeoutError
from gateway.runtime.loop import CyclicService
from tests.hostile_modbus import HostileServer, make_tls_pair
from tests.hostile_modbus import gateway_config as _config

STORM_MODES = ("exception", "malformed", "accept_drop", "reset_mid_frame", "tls_refuse")
LATENCY_S = 0.0465


def storm_one(mode: str, seconds: float) -> tuple[float, int]:
    """(connections per second, cycles) of the real loop against one hostile mode."""
    if mode == "tls_refuse":
        return _storm_tls(seconds)
    with HostileServer(mode, max_seconds=seconds + 10) as server:
        return _storm(server, _config(server.port), seconds)


def _storm_tls(seconds: float) -> tuple[float, int]:
    with tempfile.TemporaryDirectory() as tmp:
        pki = make_tls_pair(tmp)
        opts = {"tls_cert": pki["server_cert"], "tls_key": pki["server_key"]}
        with HostileServer("tls_refuse", max_seconds=seconds + 10, **opts) as server:
            tls = TlsConfig(pki["client_cert"], pki["client_key"], pki["server_cert"])
            return _storm(server, _config(server.port, tls=tls), seconds)


def _storm(server: HostileServer, cfg: Config, seconds: float) -> tuple[float, int]:
    service = CyclicService(cfg, make_driver(cfg))
    worker = threading.Thread(target=service.run, daemon=True)
    worker.start()
    time.sleep(seconds)
    service.stop()
    worker.join(timeout=10)
    return server.connections / seconds, service.stats.cycles


def storm(seconds: float = 3.0) -> None:
    print(f"   connections/s opened by the gateway, {seconds:g} s per mode")
    for mode in STORM_MODES:
        rate, cycles = storm_one(mode, seconds)
        print(f"   {mode:16s} {rate:8.2f} /s   ({cycles} cycles)", flush=True)


def ratchet_one(pieces: int, seconds: float) -> tuple[int, int]:
    """(timeouts, good replies) of back-to-back reads of 46.5-ms-late replies."""
    mode = "split" if pieces > 1 else "latency"
    with HostileServer(mode, latency_s=LATENCY_S, pieces=pieces, max_seconds=seconds + 10) as s:
        drv = make_driver(_config(s.port, timeout_s=0.05))
        inputs = Inputs.allocate(drv.cables)
        drv.open()
        timeouts = good = 0
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                drv.read_into(inputs)
                good += 1
            except DriverTimeoutError:
                timeouts += 1
            except DriverError:  # three timeouts in a row dropped the link: reopen
                drv.close()
                drv.open()
        drv.close()
        return timeouts, good


def ratchet(seconds: float = 3.0) -> None:
    print(f"   timeouts per {seconds:g} s, replies {LATENCY_S * 1e3:.1f} ms late, timeout 50 ms")
    for pieces in (1, 3):
        timeouts, good = ratchet_one(pieces, seconds)
        what = "whole" if pieces == 1 else f"split in {pieces}"
        print(f"   {what:12s} timeouts {timeouts:4d}   good {good:4d}", flush=True)


def run() -> None:
    storm()
    ratchet()


if __name__ == "__main__":
    which = sys.argv[1] if len(sys.argv) > 1 else "both"
    secs = float(sys.argv[2]) if len(sys.argv) > 2 else 3.0
    if which in ("storm", "both"):
        storm(secs)
    if which in ("ratchet", "both"):
        ratchet(secs)
