"""Prometheus metrics, read from the loop's statistics through shared memory (the README's
metrics table).

:class:`GatewayCollector` is a custom collector (prometheus_client). The loop publishes
:class:`gateway.runtime.loop.LoopStats`, the compensator's arrays and the driver's state
into a seqlock block (:mod:`gateway.service.metrics_shm`, at most every 50 ms, no lock, no
allocation); each collection, in the exporter's own process, turns one consistent snapshot
of it into exactly these families:

========================================  =========  ===============  ==========================
name                                      type       labels           source
========================================  =========  ===============  ==========================
cdpr_gateway_cycle_seconds                histogram                   read + compensate + write
cdpr_gateway_jitter_seconds               histogram                   start - deadline
cdpr_gateway_overruns_total               counter                     cycles past the deadline
cdpr_gateway_record_dropped_total         counter                     samples not recorded
cdpr_gateway_bus_roundtrip_seconds        histogram  bus              one transaction
cdpr_gateway_errors_total                 counter    kind             see ``ERROR_KINDS``
cdpr_gateway_gated_total                  counter    reason           values the gate wrote invalid
cdpr_gateway_reconnects_total             counter    bus
cdpr_gateway_connected                    gauge      bus              1 while the bus is up
cdpr_gateway_tension_raw_newtons          gauge      cable            scaled reading
cdpr_gateway_tension_corrected_newtons    gauge      cable            platform tension
cdpr_gateway_friction_newtons             gauge      cable            corrected - sensor
cdpr_gateway_channel_status               gauge      cable            0 good 1 subst. 2 invalid
cdpr_gateway_build_info                   gauge      version, bus     1
cdpr_gateway_state                        gauge                       lifecycle, as register 125
cdpr_gateway_plc_heartbeat_age_seconds    gauge                       since the PLC heartbeat moved
cdpr_gateway_sample_age_seconds           gauge                       since the last good read
========================================  =========  ===============  ==========================

``cdpr_gateway_state`` is the wire code the PLC reads: 0 stopped, 1 connected (not yet
writing), 2 active, 3 fault. The two ages are NaN until the first reading.

Serving (HTTP/TLS, basic auth, bounded connections) is :mod:`gateway.service.exporter`, in
the process :mod:`gateway.service.exporter_proc` starts; ``process_*`` are the gateway's
process (read from /proc/PID).

Cables are labelled 1..m. The tension and friction gauges of a channel whose status is 2
(invalid; every channel during a PLC heartbeat fault) are NaN, never its last good value:
the series stays (Prometheus' "avoid missing metrics": a series that comes and goes breaks
``rate``, ``for:`` and dashboards) but carries no number that could pass for a reading, as
the PLC's registers hold NaN. ``errors_total{kind="invalid_value"}`` counts channels going
from good to flagged (events, not flagged cycles). Every label value of ``kind`` is
always present (0 until it happens) so dashboards and alerts see a stable set.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

import numpy as np
from prometheus_client import CollectorRegistry, ProcessCollector
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
)
from prometheus_client.registry import Collector

from gateway import __version__
from gateway.runtime.loopstats import Histogram
from gateway.service.metrics_shm import MetricsBlock, Snapshot

if TYPE_CHECKING:
    from gateway.runtime.loop import CyclicService

__all__ = ["GatewayCollector", "exporter_registry", "make_registry"]

PREFIX = "cdpr_gateway"
# drivers.base.ChannelStatus.INVALID (a test holds them equal): drivers.base imports numba,
# which the exporter process has no use for (it would add ~1 s and ~60 MB to its start)
INVALID = 2


def _histogram(name: str, doc: str, hist: Histogram, labels: dict[str, str] | None = None):
    labels = labels or {}
    family = HistogramMetricFamily(f"{PREFIX}_{name}", doc, labels=list(labels))
    family.add_metric(list(labels.values()), hist.cumulative(), hist.sum)
    return family


class GatewayCollector(Collector):
    """Yields the metric families of the README's table from one :class:`Snapshot` per
    collection (``read``: the exporter process reads the shared block; nothing before the
    loop's first publication)."""

    def __init__(
        self, read: Callable[[], Snapshot | None], bus: str, gate_reasons: tuple[str, ...]
    ) -> None:
        self.read = read
        self.bus = bus
        self.gate_reasons = gate_reasons

    def collect(self) -> Iterator[Metric]:
        snap = self.read()
        if snap is None:
            return
        bus = self.bus
        yield _histogram("cycle_seconds", "Duration of read + compensate + write.", snap.cycle)
        yield _histogram(
            "jitter_seconds", "Lateness of each cycle start against its deadline.", snap.jitter
        )
        yield CounterMetricFamily(
            f"{PREFIX}_overruns_total", "Cycles that missed their deadline.", snap.overruns
        )
        yield CounterMetricFamily(
            f"{PREFIX}_record_dropped_total",
            "Samples the recorder dropped (its buffer was full or the disk failed).",
            snap.record_dropped,
        )
        yield _histogram(
            "bus_roundtrip_seconds", "One fieldbus transaction.", snap.roundtrip, {"bus": bus}
        )
        errors = CounterMetricFamily(f"{PREFIX}_errors_total", "Errors by kind.", labels=["kind"])
        for kind, count in snap.errors.items():
            errors.add_metric([kind], count)
        yield errors
        gated = CounterMetricFamily(
            f"{PREFIX}_gated_total",
            "Values the output gate wrote invalid instead of good, by reason.",
            labels=["reason"],
        )
        for reason, stopped in zip(self.gate_reasons, snap.gated, strict=True):
            gated.add_metric([reason], float(stopped))
        yield gated
        yield _labelled(
            CounterMetricFamily,
            "reconnects_total",
            "Bus reconnections.",
            "bus",
            {bus: snap.reconnects},
        )
        yield _labelled(
            GaugeMetricFamily,
            "connected",
            "1 while the bus is up.",
            "bus",
            {bus: 1.0 if snap.bus_up else 0.0},
        )
        status, invalid = channel_status(snap.status, snap.heartbeat_fault)
        per_cable = (
            (
                "tension_raw_newtons",
                "Scaled sensor reading (NaN while invalid).",
                np.where(invalid, np.nan, snap.raw_n),
            ),
            (
                "tension_corrected_newtons",
                "Compensated platform tension (NaN while invalid).",
                np.where(invalid, np.nan, snap.corrected_n),
            ),
            (
                "friction_newtons",
                "Estimated friction between sensor and platform (NaN while invalid).",
                np.where(invalid, np.nan, snap.friction_n),
            ),
            ("channel_status", "0 good, 1 substituted, 2 invalid.", status),
        )
        for name, doc, values in per_cable:
            yield _labelled(
                GaugeMetricFamily,
                name,
                doc,
                "cable",
                {str(i + 1): float(v) for i, v in enumerate(values)},
            )
        info = GaugeMetricFamily(
            f"{PREFIX}_build_info", "Version and bus.", labels=["version", "bus"]
        )
        info.add_metric([__version__, bus], 1.0)
        yield info
        yield GaugeMetricFamily(
            f"{PREFIX}_state",
            "Lifecycle as the PLC sees it: 0 stopped, 1 connected, 2 active, 3 fault.",
            float(snap.state),
        )
        yield GaugeMetricFamily(
            f"{PREFIX}_plc_heartbeat_age_seconds",
            "Seconds since the PLC heartbeat last changed (NaN before the first reading).",
            snap.plc_heartbeat_age_s,
        )
        yield GaugeMetricFamily(
            f"{PREFIX}_sample_age_seconds",
            "Seconds since the last successful read from the PLC (NaN before the first).",
            snap.sample_age_s,
        )


def channel_status(status: np.ndarray, heartbeat_fault: bool) -> tuple[np.ndarray, np.ndarray]:
    """(status per cable as the PLC was last told it, True where invalid). A heartbeat
    fault invalidates every channel (the fault frame), whatever the readings were."""
    status = np.asarray(status, dtype=float).copy()
    if heartbeat_fault:
        status[:] = INVALID
    return status, status == INVALID


def _labelled(kind: Any, name: str, doc: str, label: str, values: dict[str, float]) -> Metric:
    family = kind(f"{PREFIX}_{name}", doc, labels=[label])
    for value_label, value in values.items():
        family.add_metric([value_label], value)
    return family


def make_registry(service: CyclicService, bus: str | None = None) -> CollectorRegistry:
    """An in-process registry of ``service`` (tests, tools): each collection publishes the
    service into a private block and reads it back, the very path the exporter process
    reads; with prometheus_client's process collector (``process_resident_memory_bytes``,
    ``process_cpu_seconds_total``, ``process_open_fds``, ...: this process, from /proc)."""
    block = MetricsBlock(service.cfg.cables, len(service.driver.GATE_REASONS), fd=-1)
    block.attach(service)

    def read() -> Snapshot | None:
        block.publish()
        return block.snapshot()

    registry = CollectorRegistry()
    registry.register(
        GatewayCollector(read, bus or service.cfg.bus.driver, service.driver.GATE_REASONS)
    )
    ProcessCollector(registry=registry)
    return registry


def exporter_registry(
    block: MetricsBlock, bus: str, gate_reasons: tuple[str, ...], pid: int
) -> CollectorRegistry:
    """The exporter process's registry: the gateway collector over the shared block, and
    the process collector of the gateway's process ``pid`` (read from /proc/PID), so
    ``process_*`` keeps meaning the gateway, not the exporter."""
    registry = CollectorRegistry()
    registry.register(GatewayCollector(block.snapshot, bus, gate_reasons))
    ProcessCollector(pid=lambda: pid, registry=registry)
    return registry
