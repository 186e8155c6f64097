"""The bounded metrics exporter (gateway/service/exporter.py) under hostile clients, on loopback.

Regression tests: idle clients no longer cost a thread and an fd each,
slow clients (TLS too) are dropped at a deadline, a burst of scrapes is served from one
rendering, and the fd reserve stops accepting without spinning. Every load is bounded in
count and time; speed itself is measured in bench/bench_exporter.py.
"""

from __future__ import annotations

import http.client
import shutil
import socket
import ssl
import subprocess
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest

from gateway.core.config import MetricsConfig
from gateway.service.exporter import MetricsServer, open_fds
from gateway.service.metrics import make_registry
from tests.service.test_metrics import ran_service
from tests.tls_helpers import self_signed

pytestmark = pytest.mark.loopback


def wait_until(predicate, seconds: float = 10.0) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.05)
    return predicate()


def scrape(port: int, timeout: float = 10.0) -> bytes:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=timeout) as reply:
        assert reply.status == 200
        return reply.read()


@pytest.fixture(scope="module")
def registry():
    return make_registry(ran_service(5))


@pytest.fixture
def server(registry) -> Iterator[MetricsServer]:
    srv = MetricsServer(
        MetricsConfig(host="127.0.0.1", port=0), registry, max_connections=8, timeout_s=1.0
    )
    yield srv
    srv.close()


def connect_idle(port: int, count: int) -> list[socket.socket]:
    clients = []
    for _ in range(count):
        s = socket.create_connection(("127.0.0.1", port), timeout=5)
        clients.append(s)
    return clients


def closed_by_peer(sock: socket.socket, seconds: float) -> bool:
    """True when the server closes (EOF or reset) within ``seconds``."""
    sock.settimeout(seconds)
    try:
        return sock.recv(1) == b""
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False


@pytest.mark.long
def test_300_idle_clients_cost_one_thread_and_at_most_the_cap_in_fds(server):
    threads_before = threading.active_count()
    fds_before = open_fds()
    clients = connect_idle(server.port, 300)  # 300 client-side fds live in this process
    try:
        time.sleep(0.5)
        assert server.connections <= server.max_connections == 8
        assert threading.active_count() == threads_before
        assert open_fds() - fds_before <= 300 + server.max_connections
        # an ordinary scrape gets through: the oldest idle connection is evicted for it
        assert b"cdpr_gateway_cycle_seconds_count 5.0" in scrape(server.port)
        assert server.counters.evicted >= 1
        assert server.counters.peak_connections <= 8
    finally:
        for c in clients:
            c.close()
    assert wait_until(lambda: server.connections == 0, 5.0)


def test_an_idle_client_is_dropped_at_the_deadline(server):
    (idle,) = connect_idle(server.port, 1)
    try:
        assert closed_by_peer(idle, 5.0)
        assert server.counters.timed_out >= 1
    finally:
        idle.close()


def test_a_byte_by_byte_client_is_dropped_whatever_its_progress(server):
    (slow,) = connect_idle(server.port, 1)
    try:
        start = time.monotonic()
        for byte in b"GET /metrics HTTP/1.1\r\nHost: x\r\n":  # never ends its headers
            try:
                slow.send(bytes([byte]))
            except OSError:
                break
            time.sleep(0.1)
            if time.monotonic() - start > 4.0:
                break
        assert closed_by_peer(slow, 5.0)
        assert server.counters.timed_out >= 1
    finally:
        slow.close()


def test_keep_alive_pipelining_and_bad_requests(server):
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=5)
    try:
        for _ in range(3):  # one connection, three scrapes
            conn.request("GET", "/metrics")
            reply = conn.getresponse()
            assert reply.status == 200
            assert reply.getheader("Content-Type", "").startswith("text/plain")
            assert b"cdpr_gateway_build_info" in reply.read()
        conn.request("HEAD", "/metrics")
        head = conn.getresponse()
        assert head.status == 200 and head.read() == b""
        conn.request("POST", "/metrics", body=b"x")
        assert conn.getresponse().status == 400
    finally:
        conn.close()
    (raw,) = connect_idle(server.port, 1)
    try:
        raw.sendall(b"GET / HTTP/1.1\r\n\r\nGET / HTTP/1.1\r\nConnection: close\r\n\r\n")
        data = b""
        while chunk := raw.recv(65536):
            data += chunk
        assert data.count(b"HTTP/1.1 200 OK") == 2
        raw.close()
        (raw,) = connect_idle(server.port, 1)
        raw.sendall(b"X" * 9000)
        assert raw.recv(100).startswith(b"HTTP/1.1 431")
    finally:
        raw.close()


def test_200_concurrent_scrapes_all_served_from_few_renderings(registry):
    srv = MetricsServer(MetricsConfig(host="127.0.0.1", port=0), registry, cache_s=0.25)
    results: list[bytes] = []
    errors: list[BaseException] = []
    barrier = threading.Barrier(200)

    def one() -> None:
        barrier.wait(timeout=30)
        try:
            results.append(scrape(srv.port, timeout=20.0))
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads_before = threading.active_count()
    workers = [threading.Thread(target=one) for _ in range(200)]
    start = time.monotonic()
    try:
        for w in workers:
            w.start()
        for w in workers:
            w.join(timeout=60)
        elapsed = time.monotonic() - start
        assert not errors, errors[:3]
        assert len(results) == 200
        assert all(b"cdpr_gateway_cycle_seconds_count 5.0" in r for r in results)
        assert srv.counters.served == 200
        # rendering is cached: at most one collection per cache interval, not one per scrape
        assert srv.counters.renders <= elapsed / 0.25 + 2
        assert srv.counters.peak_connections <= srv.max_connections
        assert wait_until(lambda: threading.active_count() == threads_before, 10.0)
    finally:
        srv.close()


def test_the_fd_reserve_pauses_accepting_without_spinning(registry):
    import resource

    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    srv = MetricsServer(
        MetricsConfig(host="127.0.0.1", port=0), registry, fd_reserve=soft - open_fds() + 4
    )
    try:
        (client,) = connect_idle(srv.port, 1)  # the kernel completes it; the server waits
        time.sleep(1.0)
        assert srv.connections == 0
        paused = srv.counters.accept_paused
        assert 1 <= paused <= 1.0 / 0.25 + 3  # one pause per 0.25 s, not a busy loop
        srv.fd_reserve = 16  # fds freed: accepting resumes and serves the waiting client
        client.sendall(b"GET /metrics HTTP/1.1\r\nConnection: close\r\n\r\n")
        client.settimeout(5)
        assert client.recv(15) == b"HTTP/1.1 200 OK"
        client.close()
    finally:
        srv.close()


@pytest.fixture(scope="module")
def tls_files(tmp_path_factory) -> tuple[Path, Path]:
    openssl = shutil.which("openssl")
    if openssl is None:
        pytest.skip("openssl not installed")
    return self_signed(tmp_path_factory.mktemp("tls"), "server")


def test_a_slow_tls_client_is_dropped_during_the_handshake(registry, tls_files):
    cert, key = tls_files
    cfg = MetricsConfig(host="127.0.0.1", port=0, certfile=str(cert), keyfile=str(key))
    srv = MetricsServer(cfg, registry, timeout_s=1.0)
    try:
        (slow,) = connect_idle(srv.port, 1)
        hello = b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03" + b"\x00" * 40
        start, dropped = time.monotonic(), False
        for byte in hello:  # a ClientHello, one byte every 0.3 s
            try:
                slow.send(bytes([byte]))
            except OSError:
                dropped = True
                break
            if closed_by_peer(slow, 0.3):
                dropped = True
                break
            if time.monotonic() - start > 6.0:
                break
        assert dropped, "the slow TLS client was still connected after 6 s"
        assert srv.counters.timed_out >= 1
        slow.close()
        # a good client meanwhile and after: served over TLS
        context = ssl.create_default_context(cafile=str(cert))
        url = f"https://127.0.0.1:{srv.port}/metrics"
        with urllib.request.urlopen(url, timeout=5, context=context) as reply:
            assert b"cdpr_gateway_cycle_seconds_count 5.0" in reply.read()
    finally:
        srv.close()


def test_close_releases_the_port_and_every_connection(registry):
    srv = MetricsServer(MetricsConfig(host="127.0.0.1", port=0), registry)
    clients = connect_idle(srv.port, 3)
    try:
        assert wait_until(lambda: srv.connections == 3, 5.0)
        fds = open_fds()
        srv.close()
        srv.close()
        assert open_fds() <= fds - 3 - 1  # the 3 server-side ends and the listener
        assert not any(t.name == "metrics-http" for t in threading.enumerate())
        again = MetricsServer(MetricsConfig(host="127.0.0.1", port=srv.port), registry)
        again.close()
    finally:
        for c in clients:
            c.close()


def test_the_exporter_thread_runs_below_the_cycle(server):
    """nice 10 and SCHED_OTHER, per thread (Linux): the scrape path yields to the loop."""
    import os

    (thread,) = [t for t in threading.enumerate() if t.name == "metrics-http"]
    tid = thread.native_id
    assert tid is not None
    stat = Path(f"/proc/self/task/{tid}/stat")
    if not stat.exists():
        pytest.skip("no /proc task stats")
    assert wait_until(lambda: int(stat.read_text().rsplit(")", 1)[1].split()[16]) >= 10, 5.0)
    assert os.sched_getscheduler(tid) == os.SCHED_OTHER


def test_a_port_out_of_range_is_a_config_error_not_a_wrapped_port():
    import yaml

    from gateway.core.config import DEFAULT_CONFIG_PATH, config_from_mapping
    from gateway.errors import ConfigError

    data = yaml.safe_load(DEFAULT_CONFIG_PATH.read_text())
    data["metrics"] = {"port": 99999}  # getaddrinfo would silently wrap it to 34463
    with pytest.raises(ConfigError, match=r"x\.yaml: metrics\.port: must be in 0\.\.65535"):
        config_from_mapping(data, "x.yaml")


def test_a_failing_collector_answers_500_and_the_exporter_keeps_serving(caplog):
    from prometheus_client import CollectorRegistry

    class Broken:
        def collect(self):
            raise RuntimeError("collector bug")

    reg = CollectorRegistry()
    reg.register(Broken())
    srv = MetricsServer(MetricsConfig(host="127.0.0.1", port=0), reg, cache_s=0.0)
    try:
        for _ in range(2):
            with pytest.raises(urllib.error.HTTPError) as err:
                scrape(srv.port)
            assert err.value.code == 500
            err.value.close()
        assert any("rendering the registry failed" in r.message for r in caplog.records)
        assert any(t.name == "metrics-http" for t in threading.enumerate())
    finally:
        srv.close()


def _raw_get(port: int, headers: bytes = b"") -> bytes:
    """One request over a raw socket (any bytes in the headers); the reply's first bytes."""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(b"GET /metrics HTTP/1.1\r\n" + headers + b"Connection: close\r\n\r\n")
        return s.recv(64)


@pytest.mark.parametrize(
    "credentials",
    [
        "é:s3cret".encode(),  # TypeError in compare_digest killed the thread
        b"prom:\xff\xfe",  # not UTF-8
        "prom:sécret".encode("latin-1"),
        b"\x00:\x00",
        "ü" * 200 + ":x",
    ],
)
def test_any_credentials_get_an_answer_and_the_exporter_lives_on(registry, credentials):
    import base64
    import hashlib

    raw = credentials if isinstance(credentials, bytes) else credentials.encode()
    digest = hashlib.sha256("sécret".encode()).hexdigest()
    cfg = MetricsConfig(
        host="127.0.0.1", port=0, basic_auth_user="prömetheus", basic_auth_password_sha256=digest
    )
    srv = MetricsServer(cfg, registry, timeout_s=2.0)
    try:
        token = base64.b64encode(raw)
        assert _raw_get(srv.port, b"Authorization: Basic " + token + b"\r\n").startswith(
            b"HTTP/1.1 401"
        )
        good = base64.b64encode("prömetheus:sécret".encode())
        reply = _raw_get(srv.port, b"Authorization: Basic " + good + b"\r\n")
        assert reply.startswith(b"HTTP/1.1 200"), reply  # non-ASCII credentials work too
    finally:
        srv.close()


def test_an_unexpected_error_in_one_request_costs_only_that_connection(registry, caplog):
    srv = MetricsServer(MetricsConfig(host="127.0.0.1", port=0), registry, timeout_s=2.0)
    calls = {"n": 0}
    real = srv._respond

    def sometimes_broken(conn, request):
        calls["n"] += 1
        if calls["n"] == 1:
            raise TypeError("a bug in one request's handling")
        return real(conn, request)

    srv._respond = sometimes_broken  # type: ignore[method-assign]
    try:
        with socket.create_connection(("127.0.0.1", srv.port), timeout=5) as s:
            s.sendall(b"GET /metrics HTTP/1.1\r\nConnection: close\r\n\r\n")
            assert s.recv(64) == b""  # that connection is closed
        assert scrape(srv.port).startswith(b"# HELP")  # the thread lives on
        assert srv.counters.failed == 1
        assert "TypeError" in caplog.text
    finally:
        srv.close()


def test_running_out_of_descriptors_is_logged_once(registry, caplog):
    import resource

    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    srv = MetricsServer(
        MetricsConfig(host="127.0.0.1", port=0), registry, fd_reserve=soft - open_fds() + 4
    )
    try:
        clients = connect_idle(srv.port, 1)
        assert wait_until(lambda: srv.counters.accept_paused >= 3, 5.0)
        lines = [r for r in caplog.records if "descriptors" in r.getMessage()]
        assert len(lines) == 1, [r.getMessage() for r in lines]
        assert "RLIMIT_NOFILE" in lines[0].getMessage() or "LimitNOFILE" in lines[0].getMessage()
        for c in clients:
            c.close()
    finally:
        srv.close()


def test_check_warns_when_the_descriptor_limit_is_too_low():
    """under ``prlimit --nofile=48`` the metrics port never answered and
    nothing said why; ``check`` now warns before the gateway runs."""
    import os
    import resource
    import sys

    root = Path(__file__).resolve().parents[2]

    def low_limit() -> None:
        _, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        resource.setrlimit(resource.RLIMIT_NOFILE, (48, hard))

    env = {**os.environ, "PYTHONPATH": str(root)}
    done = subprocess.run(
        [sys.executable, "-m", "gateway.cli", "check", "--config", "config/default.yaml"],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
        preexec_fn=low_limit,
        cwd=root,
    )
    assert done.returncode == 0, done.stderr
    warnings = [ln for ln in done.stderr.splitlines() if "RLIMIT_NOFILE" in ln]
    assert len(warnings) == 1 and "48" in warnings[0], done.stderr
