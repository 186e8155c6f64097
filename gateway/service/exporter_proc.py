"""The metrics exporter's own process: no HTTP is ever handled in the loop's process.

The 1 ms loop and an HTTP server in one process share one GIL: 32 clients scraping
``/metrics`` flat out raised the overruns from 0.17 % to 2.09 % of cycles and made 13
gaps over 10 ms between writes (issue 30). So the daemon serves nothing itself:

* the loop publishes its figures into a seqlock block in shared memory
  (:mod:`gateway.service.metrics_shm`, at most every 50 ms, no lock, no allocation);
* :class:`ExporterProcess` starts ``python -m gateway.service.exporter_proc`` (a fresh
  interpreter: fork+exec from a thread below the cycle, never a fork of the threaded
  gateway), passing the block's descriptor; the child maps it, builds the registry
  (:func:`gateway.service.metrics.exporter_registry`) and serves it with the bounded
  :class:`gateway.service.exporter.MetricsServer` (connection cap, per-exchange deadline,
  TLS and basic auth as configured, one render per 0.25 s at most,
  ``cdpr_gateway_exporter_events_total``), at SCHED_OTHER and nice 10;
* stdin: the first line is the job (JSON); the daemon keeps the pipe open. EOF -- the
  daemon's close, or its death, which closes its end too -- ends the exporter, as does a
  changed parent pid (checked every second): the exporter never outlives the daemon.
  SIGINT and SIGTERM are ignored (systemd's stop and a terminal's Ctrl-C reach the whole
  group; the daemon stops its loop and then closes the pipe);
* stdout: one event, ``{"ready": PORT}`` or ``{"error": LINE, "temporary": BOOL}`` (a
  config error: exit 2; a port in use: 75, as the daemon would);
* a watcher thread in the daemon (blocked on the child's stdout, below the cycle) restarts
  an exporter that died, with backoff (:data:`RESTART_MIN_S` doubling to
  :data:`RESTART_MAX_S`), and logs each death once.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

from gateway.errors import ConfigError, TemporaryError
from gateway.runtime import realtime
from gateway.service.metrics_shm import MetricsBlock

if TYPE_CHECKING:  # the exporter process never imports the config (and its model: numba)
    from gateway.core.config import MetricsConfig

log = logging.getLogger("cdpr_gateway.exporter")

PACKAGE_ROOT = str(Path(__file__).resolve().parents[2])  # where ``gateway`` is found
START_TIMEOUT_S = 60.0  # a fresh interpreter importing numpy and prometheus_client
RESTART_MIN_S = 0.5
RESTART_MAX_S = 30.0
STABLE_S = 60.0  # an exporter that lived this long resets the backoff
PARENT_CHECK_S = 1.0


class ExporterProcess:
    """Start, watch and restart the exporter process serving ``block``."""

    def __init__(
        self,
        cfg: MetricsConfig,
        block: MetricsBlock,
        *,
        bus: str,
        gate_reasons: tuple[str, ...],
        source: str = "",
        log_level: str = "INFO",
    ) -> None:
        self.cfg = cfg
        self.block = block
        self.job: dict[str, Any] = {
            "fd": block.fd,
            "cables": block.cables,
            "bus": bus,
            "gate_reasons": list(gate_reasons),
            "metrics": dataclasses.asdict(cfg),
            "source": source,
            "log_level": log_level,
            "pid": os.getpid(),
        }
        self.port = -1
        self.restarts = 0
        self._proc: subprocess.Popen[str] | None = None
        self._closing = threading.Event()
        self._lock = threading.Lock()
        self._watcher: threading.Thread | None = None

    @property
    def pid(self) -> int | None:
        """The exporter process's pid (tests and benchmarks)."""
        proc = self._proc
        return proc.pid if proc is not None else None

    def start(self) -> int:
        """Start the exporter and wait until it listens; returns the port. A config error
        raises :class:`ConfigError`, a port in use :class:`TemporaryError` (one line each)."""
        self.port = self._launch()
        self.job["metrics"]["port"] = self.port  # a restart takes the same port (port 0)
        self._watcher = threading.Thread(target=self._watch, name="metrics-watch", daemon=True)
        self._watcher.start()
        return self.port

    def _launch(self) -> int:
        proc = self._spawn()
        with self._lock:
            if self._closing.is_set():  # closed while it started: never left running
                _end(proc)
                _close_stdout(proc)
                raise TemporaryError("metrics: closing")
            self._proc = proc
        assert proc.stdin is not None and proc.stdout is not None
        try:
            proc.stdin.write(json.dumps(self.job) + "\n")
            proc.stdin.flush()
        except OSError:
            pass  # it died at start: its status is reported below
        event = _read_event(proc, START_TIMEOUT_S)
        if event is not None and "ready" in event:
            return int(event["ready"])
        _end(proc)
        _close_stdout(proc)
        if event is None:
            raise TemporaryError(
                f"metrics: the exporter process did not start (exit status {proc.returncode})"
            )
        raise (TemporaryError if event.get("temporary") else ConfigError)(event["error"])

    def _spawn(self) -> subprocess.Popen[str]:
        """Fork+exec from a thread lowered below the cycle (a child inherits the policy and
        nice of the thread that forks it)."""
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (PACKAGE_ROOT, env.get("PYTHONPATH")) if p)
        result: list[Any] = []

        def spawn() -> None:
            realtime.below_the_cycle()
            try:
                result.append(
                    subprocess.Popen(
                        [sys.executable, "-m", "gateway.service.exporter_proc"],
                        stdin=subprocess.PIPE,
                        stdout=subprocess.PIPE,
                        pass_fds=(self.block.fd,),
                        env=env,
                        text=True,
                    )
                )
            except OSError as exc:
                result.append(exc)

        starter = threading.Thread(target=spawn, name="metrics-start")
        starter.start()
        starter.join()
        if isinstance(result[0], OSError):
            raise TemporaryError(f"metrics: cannot start the exporter process: {result[0]}")
        proc: subprocess.Popen[str] = result[0]
        return proc

    def _watch(self) -> None:
        """Wait for the exporter's end; restart it (with backoff) unless closing."""
        realtime.below_the_cycle()
        delay = RESTART_MIN_S
        started = time.monotonic()
        while True:
            proc = self._proc
            assert proc is not None and proc.stdout is not None
            with contextlib.suppress(OSError, ValueError):
                while proc.stdout.readline():  # nothing more is sent: blocks until its end
                    pass
            code = proc.wait()
            _close_stdout(proc)
            if self._closing.is_set():
                return
            if time.monotonic() - started >= STABLE_S:
                delay = RESTART_MIN_S
            log.error(
                "metrics: the exporter process ended (exit status %s); restarting in %.1f s",
                code,
                delay,
            )
            _end(proc)
            while not self._closing.wait(delay):
                delay = min(2 * delay, RESTART_MAX_S)
                started = time.monotonic()
                try:
                    self._launch()
                    self.restarts += 1
                    log.warning("metrics: exporter restarted (%d restarts)", self.restarts)
                    break
                except (ConfigError, TemporaryError) as exc:
                    if self._closing.is_set():
                        return
                    log.error("metrics: %s; retrying in %.1f s", exc, delay)
            else:
                return

    def close(self, timeout_s: float = 5.0) -> None:
        """End the exporter (EOF on its stdin) and the watcher; safe to call twice."""
        with self._lock:
            self._closing.set()
            proc = self._proc
        if proc is not None:
            _end(proc, timeout_s)
        if self._watcher is not None:
            self._watcher.join(timeout_s)
            self._watcher = None


def _read_event(proc: subprocess.Popen[str], timeout_s: float) -> dict[str, Any] | None:
    """The child's first event, or None if it ended (or said nothing in time)."""
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], timeout_s)
    line = proc.stdout.readline() if ready else ""
    try:
        return json.loads(line) if line else None
    except ValueError:
        return None


def _end(proc: subprocess.Popen[str], timeout_s: float = 5.0) -> None:
    """Close the child's stdin (its signal to end), wait, kill if it does not."""
    with contextlib.suppress(OSError, ValueError):
        assert proc.stdin is not None
        proc.stdin.close()
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    # stdout is left to the watcher thread, which may be reading it


def _close_stdout(proc: subprocess.Popen[str]) -> None:
    with contextlib.suppress(OSError, ValueError):
        assert proc.stdout is not None
        proc.stdout.close()


# --- the child ---------------------------------------------------------------------------


def _emit(event: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(event) + "\n")
    sys.stdout.flush()


def main() -> int:
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    realtime.below_the_cycle()
    line = sys.stdin.readline()
    if not line:
        return 0  # the daemon went away before it sent the job
    job = json.loads(line)
    from gateway.core.cliopts import setup_logging  # light: argparse and logging
    from gateway.service.exporter import MetricsServer
    from gateway.service.metrics import exporter_registry

    setup_logging(job["log_level"])
    parent = job["pid"]
    block = MetricsBlock(job["cables"], len(job["gate_reasons"]), fd=job["fd"])
    registry = exporter_registry(block, job["bus"], tuple(job["gate_reasons"]), parent)
    try:
        cfg: Any = SimpleNamespace(**job["metrics"])  # the daemon's MetricsConfig, as JSON
        server = MetricsServer(cfg, registry, job["source"])
    except TemporaryError as exc:
        _emit({"error": str(exc), "temporary": True})
        return 75
    except ConfigError as exc:
        _emit({"error": str(exc), "temporary": False})
        return 2
    _emit({"ready": server.port})
    try:
        while os.getppid() == parent:
            ready, _, _ = select.select([sys.stdin], [], [], PARENT_CHECK_S)
            if ready and not sys.stdin.readline():
                break  # EOF: the daemon closed the pipe, or died
    finally:
        server.close()
        block.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
