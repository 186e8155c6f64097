"""Prometheus metrics, read from the loop's statistics at scrape time (design.md table).

:class:`GatewayCollector` is a custom collector (prometheus_client): it allocates nothing
in the loop; each scrape turns :class:`gateway.loop.LoopStats`, the compensator's arrays
and the driver's state into exactly these families:

========================================  =========  ===============  ==========================
name                                      type       labels           source
========================================  =========  ===============  ==========================
cdpr_gateway_cycle_seconds                histogram                   read + compensate + write
cdpr_gateway_jitter_seconds               histogram                   start - deadline
cdpr_gateway_overruns_total               counter                     cycles past the deadline
cdpr_gateway_record_dropped_total         counter                     samples not recorded
cdpr_gateway_bus_roundtrip_seconds        histogram  bus              one transaction
cdpr_gateway_errors_total                 counter    kind             see ``ERROR_KINDS``
cdpr_gateway_reconnects_total             counter    bus
cdpr_gateway_connected                    gauge      bus              1 while the bus is up
cdpr_gateway_tension_raw_newtons          gauge      cable            scaled reading
cdpr_gateway_tension_corrected_newtons    gauge      cable            platform tension
cdpr_gateway_friction_newtons             gauge      cable            corrected - sensor
cdpr_gateway_channel_status               gauge      cable            0 good 1 subst. 2 invalid
cdpr_gateway_build_info                   gauge      version, bus     1
========================================  =========  ===============  ==========================

Cables are labelled 1..m. ``errors_total{kind="invalid_value"}`` counts channels going
from good to flagged (events, not flagged cycles). Every label value of ``kind`` is
always present (0 until it happens) so dashboards and alerts see a stable set.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import ssl
import threading
from collections.abc import Iterator
from socketserver import ThreadingMixIn
from typing import Any
from wsgiref.simple_server import WSGIRequestHandler, WSGIServer, make_server

from prometheus_client import CollectorRegistry, make_wsgi_app
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
)
from prometheus_client.registry import Collector

from gateway import __version__
from gateway.config import MetricsConfig
from gateway.errors import ConfigError
from gateway.loop import CyclicService, Histogram

PREFIX = "cdpr_gateway"


def _histogram(name: str, doc: str, hist: Histogram, labels: dict[str, str] | None = None):
    labels = labels or {}
    family = HistogramMetricFamily(f"{PREFIX}_{name}", doc, labels=list(labels))
    family.add_metric(list(labels.values()), hist.cumulative(), hist.sum)
    return family


class GatewayCollector(Collector):
    """Yields the design.md metric families from a running :class:`CyclicService`."""

    def __init__(self, service: CyclicService, bus: str | None = None) -> None:
        self.service = service
        self.bus = bus or service.cfg.bus.driver

    def collect(self) -> Iterator[Metric]:
        svc, stats, bus = self.service, self.service.stats, self.bus
        yield _histogram("cycle_seconds", "Duration of read + compensate + write.", stats.cycle)
        yield _histogram(
            "jitter_seconds", "Lateness of each cycle start against its deadline.", stats.jitter
        )
        yield CounterMetricFamily(
            f"{PREFIX}_overruns_total", "Cycles that missed their deadline.", stats.overruns
        )
        recorder = getattr(svc, "recorder", None)  # gateway.recorder: samples not recorded
        yield CounterMetricFamily(
            f"{PREFIX}_record_dropped_total",
            "Samples the recorder dropped (its buffer was full or the disk failed).",
            recorder.dropped if recorder is not None else 0,
        )
        yield _histogram(
            "bus_roundtrip_seconds", "One fieldbus transaction.", stats.roundtrip, {"bus": bus}
        )
        errors = CounterMetricFamily(f"{PREFIX}_errors_total", "Errors by kind.", labels=["kind"])
        for kind, count in stats.errors.items():
            errors.add_metric([kind], count)
        yield errors
        yield _labelled(CounterMetricFamily, "reconnects_total", "Bus reconnections.",
                        "bus", {bus: svc.reconnects})  # fmt: skip
        yield _labelled(GaugeMetricFamily, "connected", "1 while the bus is up.",
                        "bus", {bus: 1.0 if svc.bus_up else 0.0})  # fmt: skip
        comp = svc.comp
        per_cable = (
            ("tension_raw_newtons", "Scaled sensor reading.", comp.raw_n),
            ("tension_corrected_newtons", "Compensated platform tension.", comp.corrected_n),
            ("friction_newtons", "Estimated friction between sensor and platform.",
             comp.friction_n),
            ("channel_status", "0 good, 1 substituted, 2 invalid.", comp.status),
        )  # fmt: skip
        for name, doc, values in per_cable:
            yield _labelled(GaugeMetricFamily, name, doc, "cable",
                            {str(i + 1): float(v) for i, v in enumerate(values)})  # fmt: skip
        info = GaugeMetricFamily(
            f"{PREFIX}_build_info", "Version and bus.", labels=["version", "bus"]
        )
        info.add_metric([__version__, bus], 1.0)
        yield info


def _labelled(kind: Any, name: str, doc: str, label: str, values: dict[str, float]) -> Metric:
    family = kind(f"{PREFIX}_{name}", doc, labels=[label])
    for value_label, value in values.items():
        family.add_metric([value_label], value)
    return family


def make_registry(service: CyclicService, bus: str | None = None) -> CollectorRegistry:
    """A fresh registry holding only the gateway collector."""
    registry = CollectorRegistry()
    registry.register(GatewayCollector(service, bus))
    return registry


class _QuietHandler(WSGIRequestHandler):
    def log_message(self, format: str, *args: Any) -> None:  # no access log on stderr
        pass


class _ThreadingServer(ThreadingMixIn, WSGIServer):
    """One thread per scrape. With TLS the handshake runs in that thread, bounded by
    ``HANDSHAKE_TIMEOUT_S``, not in the accept loop: an idle or slow client cannot stall
    the other scrapes."""

    daemon_threads = True
    handshake_timeout_s = 5.0

    def finish_request(self, request: Any, client_address: Any) -> None:
        if isinstance(request, ssl.SSLSocket):
            request.settimeout(self.handshake_timeout_s)
            request.do_handshake()  # an error ends this thread only (handle_error)
        super().finish_request(request, client_address)

    def handle_error(self, request: Any, client_address: Any) -> None:
        """A failed handshake or a dropped client is not worth a traceback."""


def _basic_auth(app: Any, user: str, password_sha256: str) -> Any:
    """WSGI middleware: HTTP basic auth against a SHA-256 hex digest of the password."""
    expected = password_sha256.lower()

    def guarded(environ: dict[str, Any], start_response: Any) -> Any:
        header = environ.get("HTTP_AUTHORIZATION", "")
        ok = False
        if header.startswith("Basic "):
            try:
                name, _, password = base64.b64decode(header[6:]).decode().partition(":")
            except (ValueError, UnicodeDecodeError):
                name, password = "", ""
            digest = hashlib.sha256(password.encode()).hexdigest()
            ok = hmac.compare_digest(name, user) & hmac.compare_digest(digest, expected)
        if not ok:
            start_response("401 Unauthorized", [("WWW-Authenticate", 'Basic realm="cdpr-gateway"')])
            return [b"unauthorized\n"]
        return app(environ, start_response)

    return guarded


class MetricsServer:
    """The HTTP exporter on ``cfg.host:cfg.port`` (port 0: any free port, see ``.port``).

    Optional TLS (``certfile``/``keyfile``) and HTTP basic auth (``basic_auth_user`` and
    ``basic_auth_password_sha256``, the hex SHA-256 of the password). Serves every path
    (``/metrics`` by convention) from its own daemon threads.
    """

    def __init__(self, cfg: MetricsConfig, registry: CollectorRegistry, source: str = "") -> None:
        where = f"{source}: " if source else ""
        app = make_wsgi_app(registry)
        if (cfg.basic_auth_user is None) != (cfg.basic_auth_password_sha256 is None):
            raise ConfigError(
                f"{where}metrics.basic_auth_user and metrics.basic_auth_password_sha256 go together"
            )
        if cfg.basic_auth_user is not None and cfg.basic_auth_password_sha256 is not None:
            app = _basic_auth(app, cfg.basic_auth_user, cfg.basic_auth_password_sha256)
        try:
            server = make_server(cfg.host, cfg.port, app, _ThreadingServer, _QuietHandler)
        except OSError as exc:
            raise ConfigError(
                f"{where}metrics.port: cannot serve metrics on {cfg.host}:{cfg.port}: {exc}"
            ) from exc
        if cfg.certfile is not None:
            try:
                context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
                context.load_cert_chain(cfg.certfile, cfg.keyfile)
            except (OSError, ssl.SSLError) as exc:
                server.server_close()
                raise ConfigError(f"{where}metrics.certfile: {exc}") from exc
            server.socket = context.wrap_socket(
                server.socket, server_side=True, do_handshake_on_connect=False
            )
        self._server: _ThreadingServer | None = server
        self._thread = threading.Thread(
            target=server.serve_forever, name="metrics-http", daemon=True
        )
        self._thread.start()
        self.host = cfg.host
        self.port = int(server.server_port)

    def close(self) -> None:
        """Stop serving; safe to call twice."""
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
            self._thread.join(timeout=5)
            self._server = None
