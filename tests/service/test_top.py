"""``cdpr-gateway top`` (gateway/service/top.py): the rendering from a canned exposition
text, malformed replies and an unreachable endpoint, and one end-to-end run under a
pseudo-terminal against the soft PLC and the gateway daemon on loopback."""

from __future__ import annotations

import contextlib
import fcntl
import http.server
import math
import os
import re
import select
import signal
import struct
import subprocess
import sys
import termios
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from gateway.core.config import DEFAULT_CONFIG_PATH
from gateway.service import top
from tests.loop_helpers import free_port

ROOT = Path(__file__).resolve().parents[2]
CABLES = [str(i) for i in range(1, 9)]


def canned(corrected: list[float], status: list[int], rt_count: float, rt_sum: float) -> str:
    """An exposition text as the exporter writes it (docs/metrics.md), 8 cables."""
    lines = [
        "# HELP cdpr_gateway_cycle_seconds Duration of read + compensate + write.",
        "# TYPE cdpr_gateway_cycle_seconds histogram",
        'cdpr_gateway_cycle_seconds_bucket{le="0.001"} ' + f"{rt_count}",
        'cdpr_gateway_cycle_seconds_bucket{le="+Inf"} ' + f"{rt_count}",
        f"cdpr_gateway_cycle_seconds_count {rt_count}",
        f"cdpr_gateway_cycle_seconds_sum {rt_sum / 2}",
        "# TYPE cdpr_gateway_overruns_total counter",
        "cdpr_gateway_overruns_total 7.0",
        "# TYPE cdpr_gateway_bus_roundtrip_seconds histogram",
        'cdpr_gateway_bus_roundtrip_seconds_bucket{bus="modbus_tcp",le="0.0003"} '
        + f"{rt_count * 0.5}",
        'cdpr_gateway_bus_roundtrip_seconds_bucket{bus="modbus_tcp",le="0.0005"} ' + f"{rt_count}",
        'cdpr_gateway_bus_roundtrip_seconds_bucket{bus="modbus_tcp",le="+Inf"} ' + f"{rt_count}",
        f'cdpr_gateway_bus_roundtrip_seconds_count{{bus="modbus_tcp"}} {rt_count}',
        f'cdpr_gateway_bus_roundtrip_seconds_sum{{bus="modbus_tcp"}} {rt_sum}',
        "# TYPE cdpr_gateway_errors_total counter",
        'cdpr_gateway_errors_total{kind="timeout"} 3.0',
        'cdpr_gateway_errors_total{kind="io"} 0.0',
        "# TYPE cdpr_gateway_connected gauge",
        'cdpr_gateway_connected{bus="modbus_tcp"} 1.0',
    ]
    for metric, values in (
        ("tension_raw_newtons", [v + 10 for v in corrected]),
        ("tension_corrected_newtons", corrected),
        ("friction_newtons", [-10.0] * 8),
        ("channel_status", status),
    ):
        lines.append(f"# TYPE cdpr_gateway_{metric} gauge")
        lines += [
            f'cdpr_gateway_{metric}{{cable="{c}"}} {v}' for c, v in zip(CABLES, values, strict=True)
        ]
    lines += [
        "# TYPE cdpr_gateway_build_info gauge",
        'cdpr_gateway_build_info{bus="modbus_tcp",version="9.8.7"} 1.0',
        "# TYPE cdpr_gateway_state gauge",
        "cdpr_gateway_state 2.0",
        "# TYPE cdpr_gateway_plc_heartbeat_age_seconds gauge",
        "cdpr_gateway_plc_heartbeat_age_seconds 0.004",
    ]
    return "\n".join(lines) + "\n"


CORRECTED = [101.25, 202.5, 303.75, 404.0, 55.5, 66.25, 77.0, 88.125]


def rows(lines: list[str]) -> dict[str, list[str]]:
    """The cable table of a screen: cable -> [raw, corrected, friction, status]."""
    out = {}
    for line in lines:
        fields = line.split()
        if len(fields) == 5 and fields[0].isdigit():
            out[fields[0]] = fields[1:]
    return out


def test_the_screen_shows_every_cable_and_the_gateway_from_a_canned_text():
    before = top.parse(canned(CORRECTED, [0] * 8, 1000, 0.4), at=10.0)
    now = top.parse(canned(CORRECTED, [0, 0, 1, 0, 0, 0, 2, 0], 1250, 0.4 + 250 * 0.0004), 10.25)
    assert before.error is None and now.error is None
    view = top.View("http://h/metrics", 0.25, now, top.window(now, before), scrapes=2)
    lines = top.screen(view)
    table = rows(lines)
    assert list(table) == CABLES
    for c, v in zip(CABLES, CORRECTED, strict=True):
        assert table[c][:3] == [f"{v + 10:.2f}", f"{v:.2f}", "-10.00"]
    assert [table[c][3] for c in ("1", "3", "7")] == ["good", "substituted", "invalid"]
    text = "\n".join(lines)
    assert "state active" in text and "PLC heartbeat age 4.0 ms" in text
    assert "version 9.8.7" in text
    assert "overruns 7 of 1,250 cycles" in text
    # the mean over the window: 250 round trips adding 0.1 s, 0.4 ms each; p99 in <= 0.5 ms
    assert "round trip 0.400 ms mean, p99 <= 0.5 ms" in text
    assert "errors: timeout 3" in text and "io 0" not in text
    one = top.one_line(view)
    assert "\n" not in one and "state=active" in one
    assert "corrected=" + ",".join(f"{v:.2f}" for v in CORRECTED) in one
    assert "status=0,0,1,0,0,0,2,0" in one


def test_an_invalid_channel_shows_nan_not_a_number():
    text = canned(CORRECTED, [0] * 8, 10, 0.1).replace(
        'cdpr_gateway_tension_corrected_newtons{cable="4"} 404.0',
        'cdpr_gateway_tension_corrected_newtons{cable="4"} NaN',
    )
    view = top.View("u", 0.25, top.parse(text))
    assert rows(top.screen(view))["4"][1] == "NaN"


def test_values_older_than_a_few_refreshes_are_marked_with_their_age():
    reading = top.parse(canned(CORRECTED, [0] * 8, 10, 0.1))
    fresh = top.View("u", 0.25, reading, last_good_at=time.monotonic())
    stale = top.View("u", 0.25, reading, last_good_at=time.monotonic() - 12.0)
    assert not any(line.startswith("!!") for line in top.screen(fresh))
    assert re.search(
        r"^!! the values below are 1[23]\.\d s old$", "\n".join(top.screen(stale)), re.M
    )


class FakeFetcher:
    """Replies from a list: a string is a reply, an exception is raised."""

    url = "http://fake/metrics"

    def __init__(self, replies: list[str | Exception]) -> None:
        self.replies = list(replies)

    def fetch(self) -> str:
        reply = self.replies.pop(0)
        if isinstance(reply, Exception):
            raise reply
        return reply


def test_a_malformed_reply_is_counted_and_shown_and_the_next_good_one_read():
    good = canned(CORRECTED, [0] * 8, 10, 0.1)
    cut = good.replace("cdpr_gateway_state 2.0", "cdpr_gateway_state two")
    fetcher = FakeFetcher([good, cut, "\x00garbage{{{\n", good.replace("101.25", "111.0")])
    seen = []
    for view, _ in top.refreshes(fetcher, 0.25, 4):  # type: ignore[arg-type]
        seen.append((view.malformed, top.screen(view)))
    assert [m for m, _ in seen] == [0, 1, 2, 2]
    # the families before the bad line are still shown; the state after it is not
    assert rows(seen[1][1])["1"][1] == "101.25" and "state NaN" in "\n".join(seen[1][1])
    assert "malformed 2 (last: " in seen[2][1][-1]
    assert rows(seen[3][1])["1"][1] == "111.00"


def test_an_unreachable_endpoint_is_retried_at_a_growing_interval_then_read():
    refused = top.FetchError("connection refused")
    good = canned(CORRECTED, [0] * 8, 10, 0.1)
    fetcher = FakeFetcher([refused] * 8 + [good])
    waits, texts = [], []
    for view, wait_s in top.refreshes(fetcher, 0.25, 9):  # type: ignore[arg-type]
        waits.append(wait_s)
        texts.append(top.screen(view)[1])
    assert waits == [0.25, 0.5, 1.0, 2.0, 4.0] + [top.MAX_RETRY_S] * 3 + [0.0]  # 0: the last
    assert texts[0].startswith("!! cannot reach http://fake/metrics: connection refused;")
    assert "retrying in 0.5 s (attempt 2)" in texts[1]
    assert rows(top.screen(view))["8"][1] == "88.12"


@given(st.text(max_size=300))
def test_any_reply_parses_and_draws_without_raising(text):
    view = top.View("u", 0.25, top.parse(text))
    top.screen(view)
    top.one_line(view)


@given(st.lists(st.sampled_from(canned(CORRECTED, [0] * 8, 10, 0.1).splitlines(True))))
def test_any_subset_of_the_lines_draws_without_raising(lines):
    reading = top.parse("".join(lines))
    view = top.View("u", 0.25, reading, top.window(reading, reading))
    top.screen(view)
    top.one_line(view)


def test_the_default_url_is_the_bundled_configs_metrics_address(tmp_path):
    assert top.url_from_config(str(DEFAULT_CONFIG_PATH)) == "http://127.0.0.1:9109/metrics"
    fetcher = top.Fetcher("http://op:s%3Acret@127.0.0.1:1/metrics")
    assert fetcher.url == "http://127.0.0.1:1/metrics"  # no password on screen
    assert fetcher.headers["Authorization"] == "Basic b3A6czpjcmV0"  # op:s:cret


# --- under a pseudo-terminal ------------------------------------------------------------


def _env() -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "TERM": "xterm"}
    env.pop("NOTIFY_SOCKET", None)
    return env


class Pty:
    """``cdpr-gateway top ARGS`` on a pseudo-terminal of 50 x 160 that is its controlling
    terminal (so Ctrl-C typed there is a SIGINT); everything it writes is kept."""

    def __init__(self, *args: str) -> None:
        self.master, slave = os.openpty()
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 50, 160, 0, 0))
        self.before = termios.tcgetattr(slave)
        self.slave = slave

        def controlling_tty() -> None:
            os.setsid()
            fcntl.ioctl(0, termios.TIOCSCTTY, 0)

        self.proc = subprocess.Popen(
            [sys.executable, "-m", "gateway", "top", *args],
            stdin=slave,
            stdout=slave,
            stderr=slave,
            env=_env(),
            cwd=ROOT,
            preexec_fn=controlling_tty,
        )
        self.out = b""

    def read(self, timeout_s: float) -> None:
        ready, _, _ = select.select([self.master], [], [], timeout_s)
        if ready:
            with contextlib.suppress(OSError):  # EIO: the child closed its side
                self.out += os.read(self.master, 1 << 16)

    def frames(self) -> list[list[str]]:
        """Every complete frame drawn so far, as plain lines."""
        text = self.out.decode(errors="replace")
        out = []
        for chunk in text.split(top.HOME)[1:]:
            if top.CLEAR_EOS in chunk:
                body = chunk.split(top.CLEAR_EOS)[0].replace(top.CLEAR_EOL, "")
                out.append(body.replace("\r", "").split("\n"))
        return out

    def wait_for(self, predicate, timeout_s: float) -> list[str]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.read(0.1)
            for frame in reversed(self.frames()):
                if predicate(frame):
                    return frame
        pytest.fail(f"no such frame within {timeout_s} s; last: {self.frames()[-1:]}")

    def finish(self, typed: bytes, timeout_s: float = 30.0) -> int:
        os.write(self.master, typed)
        deadline = time.monotonic() + timeout_s
        while self.proc.poll() is None and time.monotonic() < deadline:
            self.read(0.1)
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)
            pytest.fail(f"top did not end within {timeout_s} s of {typed!r}")
        self.read(0.2)
        return self.proc.returncode

    def restored(self) -> bool:
        return termios.tcgetattr(self.slave) == self.before

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)
        os.close(self.master)
        os.close(self.slave)


@contextlib.contextmanager
def pty_top(*args: str) -> Iterator[Pty]:
    term = Pty(*args)
    try:
        yield term
    finally:
        term.close()


def ended_cleanly(term: Pty) -> None:
    text = term.out.decode(errors="replace")
    assert "Traceback" not in text, text[-2000:]
    assert text.rstrip("\r\n").endswith(top.LEAVE), repr(text[-200:])
    assert term.restored()  # cbreak and echo as they were


def test_unreachable_under_a_terminal_says_so_and_q_quits():
    port = free_port()  # nobody listens
    with pty_top("--metrics", f"http://127.0.0.1:{port}/metrics", "--interval", "0.1") as term:
        frame = term.wait_for(lambda f: "attempt 3" in "\n".join(f), 60)
        assert f"!! cannot reach http://127.0.0.1:{port}/metrics: connection refused" in frame[1]
        assert "retrying in 0.4 s (attempt 3)" in frame[1]
        assert not term.restored()  # top changed it (cbreak) while running: the check can fail
        assert term.finish(b"q") == 0
        ended_cleanly(term)


# --- end to end: the soft PLC, the daemon, top ------------------------------------------


class RecordingProxy:
    """A loopback HTTP proxy in front of the exporter that keeps every reply it passed on,
    so a screen can be matched against the very text top read."""

    def __init__(self, upstream: str) -> None:
        self.replies: list[str] = []
        proxy = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                with urllib.request.urlopen(upstream, timeout=5) as reply:
                    body = reply.read()
                proxy.replies.append(body.decode())
                self.send_response(200)
                self.send_header("Content-Type", "text/plain; version=0.0.4")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args: object) -> None:
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/metrics"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def _start_gateway(tmp_path: Path, plc_port: int, metrics_port: int) -> subprocess.Popen:
    data = yaml.safe_load(DEFAULT_CONFIG_PATH.read_text())
    data["bus"]["modbus_tcp"]["port"] = plc_port
    data["metrics"]["port"] = metrics_port
    data.setdefault("loop", {})["realtime"] = {"enabled": False}  # shares 2 cores with us
    path = tmp_path / "gw.yaml"
    path.write_text(yaml.safe_dump(data))
    return subprocess.Popen(
        [sys.executable, "-m", "gateway", "run", "--config", str(path), "--seconds", "240"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=_env(),
        cwd=ROOT,
    )


def _active_and_good(frame: list[str]) -> bool:
    table = rows(frame)
    return (
        any(line.startswith("state active") for line in frame)
        and list(table) == CABLES
        and all(r[3] == "good" for r in table.values())
    )


def _matches(frame: list[str], reply: str) -> bool:
    """The frame's cable table is the one ``reply`` gives, to the digits shown."""
    reading = top.parse(reply)
    table = rows(frame)
    for c in CABLES:
        want = [
            reading.get("tension_raw_newtons", cable=c),
            reading.get("tension_corrected_newtons", cable=c),
            reading.get("friction_newtons", cable=c),
        ]
        if any(math.isnan(v) for v in want):
            return False
        if table[c][:3] != [f"{v:.2f}" for v in want]:
            return False
    return True


@pytest.mark.loopback
@pytest.mark.long  # ~20 s: the soft PLC and the daemon start, three runs of top
def test_top_against_the_soft_plc_and_the_daemon(tmp_path):
    from sim_plc.demo import SoftPlc

    plc = SoftPlc(str(DEFAULT_CONFIG_PATH), "modbus_tcp")
    metrics_port = free_port()
    gateway = _start_gateway(tmp_path, plc.port, metrics_port)
    proxy = RecordingProxy(f"http://127.0.0.1:{metrics_port}/metrics")
    try:
        # the view, then q: 8 cables' values as the endpoint served them
        with pty_top("--metrics", proxy.url) as term:
            frame = term.wait_for(_active_and_good, 240)
            assert any(_matches(frame, reply) for reply in proxy.replies[-4:]), frame
            later = term.wait_for(lambda f: _active_and_good(f) and f != frame, 30)
            assert rows(later) != rows(frame)  # it refreshes: the tensions moved
            assert term.finish(b"q") == 0
            ended_cleanly(term)
        # Ctrl-C: status 0, no traceback, the terminal restored
        with pty_top("--metrics", proxy.url) as term:
            term.wait_for(_active_and_good, 60)
            assert term.finish(b"\x03") == 0
            ended_cleanly(term)
        # not a terminal: one line per refresh
        done = subprocess.run(
            [sys.executable, "-m", "gateway", "top", "--metrics", proxy.url, "--count", "3"],
            capture_output=True,
            text=True,
            env=_env(),
            cwd=ROOT,
            timeout=60,
        )
        assert done.returncode == 0, done.stderr
        lines = done.stdout.splitlines()
        assert len(lines) == 3, done.stdout
        assert "\x1b" not in done.stdout
        for line in lines:
            assert "state=active" in line
            corrected = re.search(r"corrected=(\S+)", line)
            assert corrected is not None and len(corrected.group(1).split(",")) == 8
    finally:
        proxy.close()
        if gateway.poll() is None:
            gateway.send_signal(signal.SIGTERM)
        try:
            gateway.wait(timeout=30)
        except subprocess.TimeoutExpired:
            gateway.kill()
            gateway.wait(timeout=10)
        plc.close()
