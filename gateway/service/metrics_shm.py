"""The metrics hand-off between the loop's process and the exporter's: a seqlock block in
shared memory.

The loop publishes what the metrics table needs (:class:`Snapshot`'s fields) into a fixed
block of float64 slots at most every :data:`PUBLISH_S`, from the cycle thread, with no lock,
no system call and no array allocation (numpy views made once); the exporter process
(:mod:`gateway.service.exporter_proc`) reads a consistent copy whenever it renders. The
protocol (one writer, any number of readers):

* slot 0 of the header is the sequence ``seq`` (int64). The writer makes it odd, writes
  every value, then makes it even (``seq + 2`` in all). A reader copies ``seq``, the values,
  then ``seq`` again, and keeps the copy only when both were the same even number; otherwise
  it tries again (spinning :data:`READ_TRIES` times, then napping :data:`READ_NAP_S`
  between tries: a writer may be preempted mid-write), for :data:`READ_TIMEOUT_S` at
  most, then raises :class:`TornSnapshot` (the exporter answers 500).
* Memory ordering: as the recorder's ring (gateway/service/recorder_proc.py), this relies on
  x86-64's total store order and on aligned 8-byte loads and stores being atomic.
* The shared memory is a ``memfd`` (no name: nothing left in ``/dev/shm``), passed to the
  exporter as a descriptor.

Counters are carried as float64: exact up to 2**53 (285 000 years of 1 kHz cycles).
The two ages are published as measured on the loop's clock together with the
``time.monotonic()`` of the publication; the reader adds the time since, so an age keeps
growing while the loop does not publish (a stalled loop shows as a growing age).
"""

from __future__ import annotations

import mmap
import os
import tempfile
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gateway.runtime.loopstats import (
    CYCLE_BUCKETS_S,
    ERROR_KINDS,
    JITTER_BUCKETS_S,
    ROUNDTRIP_BUCKETS_S,
    Histogram,
)

PUBLISH_S = 0.05  # the loop publishes at most this often (the exporter renders every 0.25 s)
HEADER_BYTES = 64  # seq, on its own cache line
READ_TRIES = 100  # spins before the reader sleeps (the writer may be preempted mid-write)
READ_NAP_S = 0.001
READ_TIMEOUT_S = 1.0  # then the block is taken as torn (a writer that died mid-write)
SCALARS = (
    "published_at",  # time.monotonic() of the publication
    "state",
    "bus_up",
    "heartbeat_fault",
    "reconnects",
    "overruns",
    "record_dropped",
    "plc_heartbeat_age_s",
    "sample_age_s",
)
HISTOGRAMS = {
    "cycle": CYCLE_BUCKETS_S,
    "jitter": JITTER_BUCKETS_S,
    "roundtrip": ROUNDTRIP_BUCKETS_S,
}
PER_CABLE = ("raw_n", "corrected_n", "friction_n", "status")


class TornSnapshot(RuntimeError):
    """No consistent copy in :data:`READ_TRIES` tries (a writer that died mid-write)."""


def layout(cables: int, gate_reasons: int) -> dict[str, tuple[int, int]]:
    """Field name -> (first slot, slots) in the float64 values."""
    fields: list[tuple[str, int]] = [(name, 1) for name in SCALARS]
    for name, bounds in HISTOGRAMS.items():
        fields += [(f"{name}_counts", len(bounds) + 1), (f"{name}_sum", 1)]
    fields += [("errors", len(ERROR_KINDS)), ("gated", gate_reasons)]
    fields += [(name, cables) for name in PER_CABLE]
    out, at = {}, 0
    for name, size in fields:
        out[name] = (at, size)
        at += size
    return out


def block_bytes(cables: int, gate_reasons: int) -> int:
    slots = sum(size for _, size in layout(cables, gate_reasons).values())
    return HEADER_BYTES + 8 * slots


@dataclass
class Snapshot:
    """One consistent reading of everything the metrics table shows."""

    state: int
    bus_up: bool
    heartbeat_fault: bool
    reconnects: float
    overruns: float
    record_dropped: float
    plc_heartbeat_age_s: float
    sample_age_s: float
    cycle: Histogram
    jitter: Histogram
    roundtrip: Histogram
    errors: dict[str, float]
    gated: np.ndarray
    raw_n: np.ndarray
    corrected_n: np.ndarray
    friction_n: np.ndarray
    status: np.ndarray
    published_at: float = field(default=float("nan"))


def shared_fd(nbytes: int, name: str = "cdpr-gateway-metrics") -> int:
    """A descriptor of ``nbytes`` of shared memory without a name (nothing to leak)."""
    try:
        fd = os.memfd_create(name, os.MFD_CLOEXEC)
    except (AttributeError, OSError):  # not Linux, or a seccomp filter without memfd
        shm = "/dev/shm" if os.path.isdir("/dev/shm") else None
        with tempfile.TemporaryFile(dir=shm) as tmp:  # already unlinked
            fd = os.dup(tmp.fileno())
    os.ftruncate(fd, nbytes)
    return fd


class MetricsBlock:
    """The block over a shared descriptor: ``fd`` None makes a new one (the daemon's side),
    an ``fd`` maps the one passed (the exporter's side), ``fd=-1`` private memory (an
    in-process registry: tests, tools)."""

    def __init__(self, cables: int, gate_reasons: int, fd: int | None = None) -> None:
        self.cables, self.gate_reasons = cables, gate_reasons
        self.nbytes = block_bytes(cables, gate_reasons)
        self.fd = shared_fd(self.nbytes) if fd is None else fd
        if self.fd >= 0 and os.fstat(self.fd).st_size < self.nbytes:
            size = os.fstat(self.fd).st_size
            raise ValueError(f"metrics block: {size} bytes shared, {self.nbytes} needed")
        self._mm: mmap.mmap | None = mmap.mmap(self.fd, self.nbytes)
        self._seq = np.ndarray((1,), np.int64, self._mm, 0)
        slots = (self.nbytes - HEADER_BYTES) // 8
        self.values = np.ndarray((slots,), np.float64, self._mm, HEADER_BYTES)
        if fd is None or fd < 0:
            self.values.fill(np.nan)
            self._seq[0] = 0
        self.fields = layout(cables, gate_reasons)
        self.views = {name: self.values[a : a + n] for name, (a, n) in self.fields.items()}
        self._copy = np.empty_like(self.values)  # the reader's buffer
        self._service: Any = None
        self._next = -float("inf")

    # --- the writer (the cycle thread) ---------------------------------------------------
    def attach(self, service: Any) -> MetricsBlock:
        """Publish ``service`` (a :class:`gateway.runtime.loop.CyclicService`) from now on."""
        self._service = service
        return self

    def publish_due(self, now: float) -> None:
        """The loop's hook: :meth:`publish` when :data:`PUBLISH_S` has passed on its clock."""
        if now >= self._next:
            self._next = now + PUBLISH_S
            self.publish()

    def publish(self) -> None:
        """Write the attached service's figures (seqlock; no lock, no array allocation)."""
        svc, v, seq = self._service, self.views, self._seq
        stats = svc.stats
        n = int(seq[0]) + 1
        seq[0] = n  # odd: being written
        v["state"][0] = int(svc.state)
        v["bus_up"][0] = svc.bus_up
        v["heartbeat_fault"][0] = svc.heartbeat_fault
        v["reconnects"][0] = svc.reconnects
        v["overruns"][0] = stats.overruns
        recorder = getattr(svc, "recorder", None)
        v["record_dropped"][0] = recorder.dropped if recorder is not None else 0
        v["plc_heartbeat_age_s"][0] = svc.plc_heartbeat_age_s()
        v["sample_age_s"][0] = svc.sample_age_s()
        for name in HISTOGRAMS:
            hist = getattr(stats, name)
            counts = v[f"{name}_counts"]
            for i, c in enumerate(hist.counts):
                counts[i] = c
            v[f"{name}_sum"][0] = hist.sum
        errors, kinds = v["errors"], stats.errors
        for i, kind in enumerate(ERROR_KINDS):
            errors[i] = kinds[kind]
        np.copyto(v["gated"], svc.driver.gated, casting="unsafe")
        comp = svc.comp
        np.copyto(v["raw_n"], comp.raw_n)
        np.copyto(v["corrected_n"], comp.corrected_n)
        np.copyto(v["friction_n"], comp.friction_n)
        np.copyto(v["status"], comp.status, casting="unsafe")
        v["published_at"][0] = time.monotonic()
        seq[0] = n + 1  # even: complete

    # --- the reader (the exporter) -------------------------------------------------------
    def snapshot(self) -> Snapshot | None:
        """A consistent copy (None before the first publication)."""
        seq, copy = self._seq, self._copy
        tries, deadline = 0, 0.0
        while True:
            before = int(seq[0])
            if not before & 1:
                np.copyto(copy, self.values)
                if int(seq[0]) == before:
                    break
            tries += 1
            if tries >= READ_TRIES:
                now = time.monotonic()
                deadline = deadline or now + READ_TIMEOUT_S
                if now >= deadline:
                    raise TornSnapshot(f"the metrics block stayed mid-write for {READ_TIMEOUT_S} s")
                time.sleep(READ_NAP_S)
        if before == 0:
            return None
        return self._decode(copy)

    def _decode(self, values: np.ndarray) -> Snapshot:
        def get(name: str) -> np.ndarray:
            a, n = self.fields[name]
            return values[a : a + n].copy()

        def scalar(name: str) -> float:
            return float(values[self.fields[name][0]])

        hists = {}
        for name, bounds in HISTOGRAMS.items():
            hist = Histogram(bounds)
            hist.counts = [int(c) for c in get(f"{name}_counts")]
            hist.count = sum(hist.counts)
            hist.sum = scalar(f"{name}_sum")
            hists[name] = hist
        since = time.monotonic() - scalar("published_at")
        errors = get("errors")
        return Snapshot(
            state=int(scalar("state")),
            bus_up=bool(scalar("bus_up")),
            heartbeat_fault=bool(scalar("heartbeat_fault")),
            reconnects=scalar("reconnects"),
            overruns=scalar("overruns"),
            record_dropped=scalar("record_dropped"),
            plc_heartbeat_age_s=scalar("plc_heartbeat_age_s") + since,
            sample_age_s=scalar("sample_age_s") + since,
            cycle=hists["cycle"],
            jitter=hists["jitter"],
            roundtrip=hists["roundtrip"],
            errors={k: float(errors[i]) for i, k in enumerate(ERROR_KINDS)},
            gated=get("gated"),
            raw_n=get("raw_n"),
            corrected_n=get("corrected_n"),
            friction_n=get("friction_n"),
            status=get("status"),
            published_at=scalar("published_at"),
        )

    def close(self) -> None:
        """Unmap and close the descriptor; safe to call twice."""
        if self._mm is None:
            return
        del self._seq, self.values, self.views, self._copy
        self._mm.close()
        self._mm = None
        if self.fd >= 0:
            os.close(self.fd)
        self.fd = -1
