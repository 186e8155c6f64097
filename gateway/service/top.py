"""``cdpr-gateway top [--metrics URL]``: a live view of a running gateway, read from its
metrics endpoint (never from the bus: it works beside a running service and writes nothing).

Every ``--interval`` (0.25 s, the exporter's render period: ``cache_s``) it fetches the
Prometheus exposition text, parses it with prometheus_client's own parser, and shows per
cable the raw and corrected tension, the friction and the channel status; the gateway's
state, the PLC heartbeat's age, the overruns, the cycle time and the bus round trip (means
over the last refresh), errors, gated values and reconnects (docs/metrics.md names them).

On a terminal it redraws in place (plain ANSI on the alternate screen, no curses) and
``q`` or Ctrl-C ends it with status 0 and the terminal as it was; when stdout is not a
terminal it prints one line per refresh. An unreachable endpoint is a status line that says
so, retried at a growing interval (doubling up to ``MAX_RETRY_S``); a reply that does not
parse is counted and shown, never a crash. Documented in docs/operation.md ("A live view").
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import math
import os
import select
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from gateway.core.cliopts import add_config_option
from gateway.core.config import DEFAULT_CONFIG_PATH, load_config
from gateway.errors import ConfigError

if TYPE_CHECKING:
    import ssl

INTERVAL_S = 0.25  # the exporter renders its payload at most every 0.25 s (docs/metrics.md)
MAX_RETRY_S = 5.0  # an unreachable endpoint is retried at a doubling interval up to this
FETCH_TIMEOUT_S = 2.0
MAX_REPLY_BYTES = 4 << 20
PREFIX = "cdpr_gateway_"
STATES = {0: "stopped", 1: "connected", 2: "active", 3: "fault"}
STATUSES = {0: "good", 1: "substituted", 2: "invalid"}

# The alternate screen and the cursor: entered once, left on every exit.
ENTER = "\x1b[?1049h\x1b[?25l"
LEAVE = "\x1b[?25h\x1b[?1049l"
HOME, CLEAR_EOL, CLEAR_EOS = "\x1b[H", "\x1b[K", "\x1b[J"


def configure_parser(command: str, parser: argparse.ArgumentParser) -> None:
    add_config_option(parser, default=DEFAULT_CONFIG_PATH)
    parser.add_argument(
        "--metrics",
        metavar="URL",
        default=None,
        help="the gateway's metrics endpoint, user:password@ in it for basic auth (default: "
        "from the config's metrics: section, http://127.0.0.1:9109/metrics for the bundled "
        "one)",
    )
    parser.add_argument(
        "--interval",
        metavar="SECONDS",
        type=float,
        default=INTERVAL_S,
        help="time between refreshes",
    )
    parser.add_argument(
        "--count",
        metavar="N",
        type=int,
        default=0,
        help="stop after N refreshes, 0 for never (default: 0)",
    )
    parser.add_argument(
        "--tls-ca", help="CA (PEM) the endpoint's certificate must chain to, for https"
    )


def url_from_config(path: str) -> str:
    """The metrics URL of the config at ``path`` (its ``metrics:`` host, port and TLS)."""
    cfg = load_config(Path(path))
    m = cfg.metrics
    if not m.enabled:
        raise ConfigError(f"{path}: metrics.enabled is false: no endpoint to read")
    if m.port == 0:
        raise ConfigError(f"{path}: metrics.port is 0 (any free port): give --metrics URL")
    host = {"0.0.0.0": "127.0.0.1", "::": "::1", "": "127.0.0.1"}.get(m.host, m.host)
    if ":" in host:
        host = f"[{host}]"
    scheme = "https" if m.certfile else "http"
    return f"{scheme}://{host}:{m.port}/metrics"


# --- reading the endpoint ---------------------------------------------------------------


class FetchError(Exception):
    """The endpoint could not be read; the message says why, in a few words."""


class Fetcher:
    """GET the exposition text from ``url`` (basic auth from the URL's user:password@)."""

    def __init__(self, url: str, cafile: str | None = None) -> None:
        parts = urllib.parse.urlsplit(url)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ConfigError(f"--metrics {url}: not an http:// or https:// URL")
        self.headers = {"Accept": "text/plain"}
        if parts.username is not None:
            user = urllib.parse.unquote(parts.username)
            password = urllib.parse.unquote(parts.password or "")
            token = base64.b64encode(f"{user}:{password}".encode()).decode()
            self.headers["Authorization"] = f"Basic {token}"
            netloc = parts.hostname if ":" not in parts.hostname else f"[{parts.hostname}]"
            if parts.port is not None:
                netloc += f":{parts.port}"
            parts = parts._replace(netloc=netloc)
        self.url = urllib.parse.urlunsplit(parts)  # shown on screen: no password in it
        self.context: ssl.SSLContext | None = None
        if parts.scheme == "https":
            import ssl

            try:
                self.context = ssl.create_default_context(cafile=cafile)
            except (OSError, ssl.SSLError) as exc:
                raise ConfigError(f"--tls-ca {cafile}: {exc}") from exc

    def fetch(self) -> str:
        request = urllib.request.Request(self.url, headers=self.headers)
        try:
            with urllib.request.urlopen(
                request, timeout=FETCH_TIMEOUT_S, context=self.context
            ) as reply:
                body = reply.read(MAX_REPLY_BYTES + 1)
        except urllib.error.HTTPError as exc:
            hint = ": give user:password@ in the URL" if exc.code == 401 else ""
            raise FetchError(f"HTTP {exc.code} {exc.reason}{hint}") from None
        except urllib.error.URLError as exc:
            reason = exc.reason
            text = reason.strerror if isinstance(reason, OSError) and reason.strerror else reason
            raise FetchError(str(text).lower()) from None
        except (OSError, ValueError) as exc:  # a reset, a timeout while reading, a bad reply
            raise FetchError(str(getattr(exc, "strerror", None) or exc).lower()) from None
        if len(body) > MAX_REPLY_BYTES:
            raise FetchError(f"reply larger than {MAX_REPLY_BYTES >> 20} MiB")
        return body.decode("utf-8", errors="replace")


# --- what a reply says ------------------------------------------------------------------

Labels = frozenset[tuple[str, str]]


@dataclass
class Reading:
    """One reply's samples by (sample name, labels); ``error`` when the text was malformed
    (the families before the bad line are kept: the parser yields a family when complete)."""

    samples: dict[tuple[str, Labels], float]
    error: str | None = None
    at: float = 0.0  # time.monotonic() of the fetch

    def get(self, name: str, **labels: str) -> float:
        return self.samples.get((PREFIX + name, frozenset(labels.items())), math.nan)

    def labelled(self, name: str, label: str) -> dict[str, float]:
        """``{label value: sample}`` of every sample of ``name`` carrying ``label``."""
        out = {}
        for (sample, labels), value in self.samples.items():
            if sample == PREFIX + name:
                found = dict(labels).get(label)
                if found is not None:
                    out[found] = value
        return out

    def buckets(self, name: str, **labels: str) -> list[tuple[float, float]]:
        """A histogram's cumulative buckets, ``(le, count)`` by ``le``."""
        out = []
        for (sample, lbls), value in self.samples.items():
            d = dict(lbls)
            le = d.pop("le", None)
            if sample == PREFIX + name + "_bucket" and le is not None and d == labels:
                out.append((float(le), value))
        return sorted(out)


def parse(text: str, at: float = 0.0) -> Reading:
    """The exposition ``text`` through prometheus_client's parser; never raises."""
    from prometheus_client.parser import text_string_to_metric_families

    samples: dict[tuple[str, Labels], float] = {}
    error = None
    try:
        for family in text_string_to_metric_families(text):
            for s in family.samples:
                samples[(s.name, frozenset(s.labels.items()))] = float(s.value)
    except Exception as exc:  # the parser raises ValueError, and others on odd input
        error = f"{type(exc).__name__}: {exc}"[:200]
    if error is None and not any(name.startswith(PREFIX) for name, _ in samples):
        error = "no cdpr_gateway_ metrics in the reply"
    return Reading(samples, error, at)


@dataclass
class Window:
    """Means over the time between two readings: a histogram's sum and count deltas."""

    seconds: float
    cycle_ms: float
    roundtrip_ms: dict[str, float]
    roundtrip_p99_ms: dict[str, float]
    overruns: float
    cycles: float


def _delta_mean_ms(now: Reading, before: Reading, name: str, **labels: str) -> float:
    n = now.get(f"{name}_count", **labels) - before.get(f"{name}_count", **labels)
    s = now.get(f"{name}_sum", **labels) - before.get(f"{name}_sum", **labels)
    return 1e3 * s / n if n > 0 else math.nan


def bucket_quantile(
    now: list[tuple[float, float]], before: list[tuple[float, float]], q: float
) -> float:
    """The upper bound (ms) of the bucket holding the ``q`` quantile of the observations
    between two readings; NaN without any."""
    old = dict(before)
    deltas = [(le, count - old.get(le, 0.0)) for le, count in now]
    if not deltas or deltas[-1][1] <= 0:
        return math.nan
    target = q * deltas[-1][1]
    for le, cumulative in deltas:
        if cumulative >= target:
            return 1e3 * le
    return math.nan


def window(now: Reading, before: Reading | None) -> Window | None:
    """What happened between ``before`` and ``now``; None without a usable ``before``
    (none yet, or a restarted gateway whose counters went back)."""
    if before is None:
        return None
    cycles = now.get("cycle_seconds_count") - before.get("cycle_seconds_count")
    if not cycles >= 0:
        return None
    buses = now.labelled("bus_roundtrip_seconds_count", "bus")
    return Window(
        seconds=now.at - before.at,
        cycle_ms=_delta_mean_ms(now, before, "cycle_seconds"),
        roundtrip_ms={
            b: _delta_mean_ms(now, before, "bus_roundtrip_seconds", bus=b) for b in buses
        },
        roundtrip_p99_ms={
            b: bucket_quantile(
                now.buckets("bus_roundtrip_seconds", bus=b),
                before.buckets("bus_roundtrip_seconds", bus=b),
                0.99,
            )
            for b in buses
        },
        overruns=now.get("overruns_total") - before.get("overruns_total"),
        cycles=cycles,
    )


@dataclass
class View:
    """What the screen shows: the last good reading and what went wrong since."""

    url: str
    interval_s: float
    reading: Reading | None = None
    window: Window | None = None
    scrapes: int = 0
    malformed: int = 0
    last_malformed: str = ""
    unreachable: str = ""  # why the last attempt failed, and when it is retried; "" if fine
    last_good_at: float = math.nan
    clock: str = ""  # the wall-clock time of the last refresh
    notes: list[str] = field(default_factory=list)


# --- drawing ----------------------------------------------------------------------------


def _num(value: float, fmt: str = "{:.2f}") -> str:
    return "NaN" if math.isnan(value) else fmt.format(value)


def _ms(seconds: float) -> str:
    if math.isnan(seconds):
        return "NaN"
    return f"{1e3 * seconds:.1f} ms" if seconds < 1 else f"{seconds:.1f} s"


def _state(r: Reading) -> str:
    code = r.get("state")
    return "NaN" if math.isnan(code) else STATES.get(int(code), f"code {code:g}")


def _status(code: float) -> str:
    return "NaN" if math.isnan(code) else STATUSES.get(int(code), f"code {code:g}")


def cables(r: Reading) -> list[str]:
    """The cable labels the reading has, in numeric order."""
    names = set(r.labelled("tension_corrected_newtons", "cable"))
    names |= set(r.labelled("tension_raw_newtons", "cable"))
    return sorted(names, key=lambda c: (len(c), c))


def _counts(values: dict[str, float]) -> str:
    nonzero = [f"{k} {v:g}" for k, v in sorted(values.items()) if v]
    return ", ".join(nonzero) if nonzero else "none"


def _overruns(r: Reading, w: Window | None) -> str:
    total, cycles = r.get("overruns_total"), r.get("cycle_seconds_count")
    text = f"overruns {_num(total, '{:g}')}"
    if cycles > 0:
        text += f" of {cycles:,.0f} cycles ({100 * total / cycles:.3f} %)"
    if w is not None:
        text += f", +{w.overruns:g} in the last {w.seconds:.2f} s"
    return text


def _buses(r: Reading, w: Window | None) -> list[str]:
    lines = []
    connected = r.labelled("connected", "bus")
    reconnects = r.labelled("reconnects_total", "bus")
    for bus in sorted(set(connected) | set(r.labelled("bus_roundtrip_seconds_count", "bus"))):
        up = {1.0: "connected", 0.0: "disconnected"}.get(connected.get(bus, math.nan), "?")
        text = f"bus {bus} {up}, reconnects {_num(reconnects.get(bus, math.nan), '{:g}')}"
        if w is not None:
            mean = w.roundtrip_ms.get(bus, math.nan)
            p99 = w.roundtrip_p99_ms.get(bus, math.nan)
            text += f", round trip {_num(mean, '{:.3f}')} ms mean, p99 <= {_num(p99, '{:g}')} ms"
        lines.append(text)
    return lines


def screen(view: View) -> list[str]:
    """The full-screen view, one string per line (no escape sequences)."""
    head = f"cdpr-gateway top  {view.url}  every {view.interval_s:g} s  (q quits)  {view.clock}"
    lines = [head]
    r, w = view.reading, view.window
    if view.unreachable:
        lines.append(f"!! {view.unreachable}")
    if r is None:
        if not view.unreachable:
            lines.append("waiting for the first reply ...")
        lines += _problems(view)
        return lines
    age = time.monotonic() - view.last_good_at
    if view.unreachable or age > max(1.0, 3 * view.interval_s):  # or malformed since
        lines.append(f"!! the values below are {age:.1f} s old")
    build = r.labelled("build_info", "version")
    version = next(iter(build), "?")
    lines.append(
        f"state {_state(r)}   PLC heartbeat age {_ms(r.get('plc_heartbeat_age_seconds'))}"
        f"   sample age {_ms(r.get('sample_age_seconds'))}   version {version}"
    )
    cycle = f"cycle {_num(w.cycle_ms, '{:.3f}')} ms mean   " if w is not None else ""
    lines.append(cycle + _overruns(r, w))
    lines += _buses(r, w)
    lines.append(
        f"errors: {_counts(r.labelled('errors_total', 'kind'))}   "
        f"gated: {_counts(r.labelled('gated_total', 'reason'))}"
    )
    lines.append("")
    lines.append(f"{'cable':>5} {'raw N':>10} {'corrected N':>12} {'friction N':>11}  status")
    for c in cables(r):
        lines.append(
            f"{c:>5} {_num(r.get('tension_raw_newtons', cable=c)):>10} "
            f"{_num(r.get('tension_corrected_newtons', cable=c)):>12} "
            f"{_num(r.get('friction_newtons', cable=c)):>11}  "
            f"{_status(r.get('channel_status', cable=c))}"
        )
    lines.append("")
    lines += _problems(view)
    return lines


def _problems(view: View) -> list[str]:
    text = f"replies {view.scrapes}, malformed {view.malformed}"
    if view.malformed:
        text += f" (last: {view.last_malformed})"
    return [text]


def one_line(view: View) -> str:
    """The view as one line, for a log or a pipe."""
    parts = [view.clock]
    r, w = view.reading, view.window
    if view.unreachable:
        parts.append(view.unreachable)
    elif r is not None:
        parts.append(f"state={_state(r)}")
        parts.append(f"heartbeat_age_ms={_num(1e3 * r.get('plc_heartbeat_age_seconds'))}")
        parts.append(f"overruns={_num(r.get('overruns_total'), '{:g}')}")
        for bus, mean in (w.roundtrip_ms if w is not None else {}).items():
            parts.append(f"roundtrip_ms[{bus}]={_num(mean, '{:.3f}')}")
        names = cables(r)
        for key, metric in (
            ("raw", "tension_raw_newtons"),
            ("corrected", "tension_corrected_newtons"),
            ("friction", "friction_newtons"),
        ):
            parts.append(f"{key}=" + ",".join(_num(r.get(metric, cable=c)) for c in names))
        status = (r.get("channel_status", cable=c) for c in names)
        parts.append("status=" + ",".join(_num(s, "{:g}") for s in status))
    if view.malformed:
        parts.append(f"malformed={view.malformed} ({view.last_malformed})")
    return " ".join(parts)


# --- the terminal -----------------------------------------------------------------------


class Screen:
    """Full-screen output on a terminal: the alternate screen, keys read without echo
    (cbreak: Ctrl-C still signals), everything put back on exit."""

    def __init__(self, out: TextIO, keys: TextIO | None) -> None:
        self.out = out
        self.key_fd = keys.fileno() if keys is not None and keys.isatty() else None
        self.saved: tuple[int, list] | None = None  # the keys' descriptor and its modes

    def __enter__(self) -> Screen:
        if self.key_fd is not None:
            import termios
            import tty

            self.saved = (self.key_fd, termios.tcgetattr(self.key_fd))
            tty.setcbreak(self.key_fd)
        self.out.write(ENTER)
        self.out.flush()
        return self

    def __exit__(self, *exc: object) -> None:
        with contextlib.suppress(OSError, ValueError):
            self.out.write(LEAVE)
            self.out.flush()
        if self.saved is not None:
            import termios

            fd, modes = self.saved
            termios.tcsetattr(fd, termios.TCSADRAIN, modes)

    def draw(self, lines: list[str]) -> None:
        size = os.get_terminal_size(self.out.fileno())
        shown = [line[: size.columns] for line in lines[: max(1, size.lines - 1)]]
        self.out.write(HOME + "".join(line + CLEAR_EOL + "\n" for line in shown) + CLEAR_EOS)
        self.out.flush()

    def wait(self, seconds: float) -> bool:
        """Wait ``seconds``; True if ``q`` was pressed meanwhile."""
        if self.key_fd is None:
            time.sleep(max(0.0, seconds))
            return False
        deadline = time.monotonic() + max(0.0, seconds)
        while True:
            left = deadline - time.monotonic()
            ready, _, _ = select.select([self.key_fd], [], [], max(0.0, left))
            if ready:
                typed = os.read(self.key_fd, 64)
                if not typed:  # end of input: nobody can press q any more
                    self.key_fd = None
                    time.sleep(max(0.0, deadline - time.monotonic()))
                    return False
                if b"q" in typed.lower():
                    return True
            if time.monotonic() >= deadline:
                return False


# --- the loop ---------------------------------------------------------------------------


def refreshes(fetcher: Fetcher, interval_s: float, count: int) -> Iterator[tuple[View, float]]:
    """Each refresh's view and how long to wait before the next one (``count`` of them,
    forever when 0; 0 s after the last): the interval after a reply, a doubling one after
    a failure."""
    view = View(fetcher.url, interval_s)
    last: Reading | None = None  # the last reply that differed from the one before it
    last_text = None
    failures = 0
    done = 0
    while count <= 0 or done < count:
        started = time.monotonic()
        view.clock = time.strftime("%H:%M:%S")
        done += 1
        final = 0 < count <= done
        try:
            text = fetcher.fetch()
        except FetchError as exc:
            failures += 1
            retry_s = min(MAX_RETRY_S, interval_s * 2 ** (failures - 1))
            view.unreachable = f"cannot reach {fetcher.url}: {exc}; " + (
                f"retrying in {retry_s:.1f} s (attempt {failures})" if not final else "stopped"
            )
            yield view, 0.0 if final else retry_s
            continue
        failures = 0
        view.unreachable = ""
        view.scrapes += 1
        reading = parse(text, time.monotonic())
        if reading.error is not None:
            view.malformed += 1
            view.last_malformed = reading.error
        if reading.samples:
            view.reading = reading
            view.last_good_at = reading.at
            if text != last_text:  # the exporter serves one payload for 0.25 s: a new one
                view.window = window(reading, last)
                last, last_text = reading, text
        yield view, 0.0 if final else interval_s - (time.monotonic() - started)


def run(fetcher: Fetcher, interval_s: float, count: int, out: TextIO, keys: TextIO | None) -> int:
    """Draw every refresh on ``out`` until ``q``, Ctrl-C or ``count``; status 0."""
    try:
        if out.isatty():
            with Screen(out, keys) as term:
                for view, wait_s in refreshes(fetcher, interval_s, count):
                    term.draw(screen(view))
                    if term.wait(wait_s):
                        break
        else:
            for view, wait_s in refreshes(fetcher, interval_s, count):
                out.write(one_line(view) + "\n")
                out.flush()
                time.sleep(max(0.0, wait_s))
    except KeyboardInterrupt:  # Ctrl-C (or SIGTERM, as gateway.cli raises it): how top ends
        pass
    return 0


def run_command(command: str, args: argparse.Namespace) -> int:
    if not args.interval > 0:
        raise ConfigError(f"--interval {args.interval}: must be above 0 seconds")
    if args.count < 0:
        raise ConfigError(f"--count {args.count}: must be 0 (never stop) or more")
    url = args.metrics or url_from_config(args.config)
    fetcher = Fetcher(url, args.tls_ca)
    return run(fetcher, args.interval, args.count, sys.stdout, sys.stdin)
