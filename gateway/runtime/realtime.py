"""Real-time settings of a process: scheduling policy and priority, CPU affinity, memory
locking, garbage collection (``loop.realtime``, :class:`gateway.core.config.RealtimeConfig`).

:func:`apply` tries each enabled setting on the calling thread (Linux applies the
scheduling policy and the affinity per thread; threads started afterwards inherit them)
and returns a :class:`RealtimeReport` of what was applied and what was refused and why.
It logs nothing and raises nothing for a refusal: the caller logs ``report.line()``, one
line. :func:`undo` puts back what a report says was applied (benchmarks compare both).

* ``policy``/``priority``: ``sched_setscheduler`` (SCHED_FIFO/SCHED_RR need root,
  CAP_SYS_NICE or an ``RLIMIT_RTPRIO`` of at least the priority: systemd's
  ``LimitRTPRIO``, ``CPUSchedulingPolicy``);
* ``cpus``: ``sched_setaffinity`` (only CPUs the process may use);
* ``lock_memory``: ``mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT)`` via libc (needs
  CAP_IPC_LOCK or an ``RLIMIT_MEMLOCK`` large enough: ``LimitMEMLOCK=infinity``), so no
  page the process has touched is paged out and no cycle takes a major page fault. On
  fault: pages are locked as they are touched, not every mapped page at once (without it
  the gateway's RSS grew from 194 to 502 MB: numpy, numba and LLVM are mapped whole);
  the cycle's pages are touched by the warm-up before the loop starts;
* ``cpu_dma_latency_us``: writes the value to ``/dev/cpu_dma_latency`` and holds the
  file open while the process runs (the kernel's PM QoS request, as ``cyclictest`` does;
  it ends when the file is closed: :func:`undo` or the process's exit). With 0, idle CPUs
  poll instead of entering a sleep state. On a virtual machine with the ``haltpoll``
  idle driver, a halted vCPU waits for the host to schedule it again: on the 2-core
  development VM that wake-up made RT-on runs overrun 0.69 % of cycles idle (more
  than under load, where no CPU halts); held at 0: 0.04 % (docs/realtime.md). Needs root
  (the device is mode 0600);
* ``gc_off``: ``gc.collect(); gc.freeze(); gc.disable()``: what exists at start is
  never scanned again and no collection runs in a cycle (the cycle allocates no cycles
  of references; memory stays bounded -- ``bench loop`` shows the RSS).

The operations are injectable (:class:`Ops`) so tests can refuse them.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import errno
import gc
import os
import resource
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # annotations only: the recorder's writer process imports this module
    from gateway.core.config import RealtimeConfig  # without the model and numba

MCL_CURRENT, MCL_FUTURE, MCL_ONFAULT = 1, 2, 4
_POLICIES = {"fifo": "SCHED_FIFO", "rr": "SCHED_RR", "other": "SCHED_OTHER"}


def _libc() -> Any:
    return ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)


def _mlockall() -> None:
    """Lock every page once it is touched (MCL_ONFAULT, Linux >= 4.4; older kernels
    refuse the flag with EINVAL and lock everything mapped at once)."""
    libc = _libc()
    if libc.mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT) == 0:
        return
    err = ctypes.get_errno()
    if err == errno.EINVAL and libc.mlockall(MCL_CURRENT | MCL_FUTURE) == 0:
        return
    err = ctypes.get_errno() if err == errno.EINVAL else err
    raise OSError(err, os.strerror(err))


def _munlockall() -> None:
    _libc().munlockall()


CPU_DMA_LATENCY = "/dev/cpu_dma_latency"


def _open_latency(us: int) -> int:
    """Open the PM QoS device and request ``us`` (a native int32); returns the fd to hold."""
    fd = os.open(CPU_DMA_LATENCY, os.O_WRONLY | os.O_CLOEXEC)
    try:
        os.write(fd, us.to_bytes(4, sys.byteorder, signed=True))
    except OSError:
        os.close(fd)
        raise
    return fd


@dataclass
class Ops:
    """The system calls :func:`apply` makes (replaced in tests)."""

    setscheduler: Callable[[int, int, Any], None] = os.sched_setscheduler
    getscheduler: Callable[[int], int] = os.sched_getscheduler
    setaffinity: Callable[[int, Any], None] = os.sched_setaffinity
    getaffinity: Callable[[int], set[int]] = os.sched_getaffinity
    mlockall: Callable[[], None] = _mlockall
    munlockall: Callable[[], None] = _munlockall
    open_latency: Callable[[int], int] = _open_latency
    close: Callable[[int], None] = os.close


@dataclass
class RealtimeReport:
    applied: list[str] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)
    enabled: bool = True
    # what undo() needs to put back
    old_policy: int | None = None
    old_cpus: set[int] | None = None
    locked: bool = False
    gc_was_enabled: bool | None = None
    latency_fd: int | None = None

    def line(self, who: str = "real-time") -> str:
        """One log line: what was applied and what was refused and why."""
        if not self.enabled:
            return f"{who}: off (loop.realtime.enabled is false)"
        applied = ", ".join(self.applied) or "nothing"
        refused = "; ".join(self.refused) or "nothing"
        return f"{who}: applied {applied}; refused {refused}"


def _why(exc: OSError, needs: str) -> str:
    if exc.errno in (errno.EPERM, errno.EACCES):
        return f"not permitted (needs {needs})"
    if exc.errno == errno.ENOMEM:
        return f"over the locked-memory limit (needs {needs})"
    return exc.strerror or str(exc)


def _rtprio_limit() -> str:
    try:
        soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
    except (AttributeError, OSError):
        return ""
    return "" if soft == resource.RLIM_INFINITY else f", RLIMIT_RTPRIO is {soft}"


def _schedule(cfg: RealtimeConfig, ops: Ops, report: RealtimeReport) -> None:
    name = _POLICIES[cfg.policy]
    prio = 0 if cfg.policy == "other" else cfg.priority
    try:
        report.old_policy = ops.getscheduler(0)
        ops.setscheduler(0, getattr(os, name), os.sched_param(prio))
    except OSError as exc:
        needs = f"root, CAP_SYS_NICE or LimitRTPRIO >= {prio}{_rtprio_limit()}"
        report.refused.append(f"{name} priority {prio}: {_why(exc, needs)}")
        report.old_policy = None
        return
    report.applied.append(f"{name} priority {prio}" if prio else name)


def _affinity(cfg: RealtimeConfig, ops: Ops, report: RealtimeReport) -> None:
    try:
        allowed = set(ops.getaffinity(0))
        missing = sorted(set(cfg.cpus) - allowed)
        if missing:
            report.refused.append(
                f"CPUs {list(cfg.cpus)}: {missing} not available to this process "
                f"(allowed: {sorted(allowed)})"
            )
            return
        ops.setaffinity(0, set(cfg.cpus))
    except OSError as exc:
        report.refused.append(f"CPUs {list(cfg.cpus)}: {_why(exc, 'CAP_SYS_NICE')}")
        return
    report.old_cpus = allowed
    report.applied.append(f"CPUs {list(cfg.cpus)}")


def _lock(ops: Ops, report: RealtimeReport) -> None:
    try:
        ops.mlockall()
    except (OSError, AttributeError) as exc:
        why = (
            _why(exc, "CAP_IPC_LOCK or LimitMEMLOCK=infinity")
            if isinstance(exc, OSError)
            else ("mlockall not available")
        )
        report.refused.append(f"mlockall: {why}")
        return
    report.locked = True
    report.applied.append("mlockall")


def _latency(us: int, ops: Ops, report: RealtimeReport) -> None:
    what = f"cpu_dma_latency {us} us"
    try:
        report.latency_fd = ops.open_latency(us)
    except OSError as exc:
        why = "no such device" if exc.errno == errno.ENOENT else _why(exc, "root")
        report.refused.append(f"{what}: {CPU_DMA_LATENCY}: {why}")
        return
    report.applied.append(what)


def apply(cfg: RealtimeConfig, ops: Ops | None = None, force: bool = False) -> RealtimeReport:
    """Apply ``cfg`` (if ``enabled`` or ``force``) to the calling thread and process."""
    if not (cfg.enabled or force):
        return RealtimeReport(enabled=False)
    ops = ops or Ops()
    report = RealtimeReport()
    _schedule(cfg, ops, report)
    if cfg.cpus:
        _affinity(cfg, ops, report)
    if cfg.lock_memory:
        _lock(ops, report)
    if cfg.cpu_dma_latency_us is not None:
        _latency(cfg.cpu_dma_latency_us, ops, report)
    if cfg.gc_off:
        report.gc_was_enabled = gc.isenabled()
        gc.collect()
        gc.freeze()
        gc.disable()
        report.applied.append("gc frozen and off")
    return report


def undo(report: RealtimeReport, ops: Ops | None = None) -> None:
    """Put back what ``report`` says :func:`apply` changed (best effort)."""
    ops = ops or Ops()
    if report.old_policy is not None:
        prio = os.sched_get_priority_min(report.old_policy)
        with contextlib.suppress(OSError):
            ops.setscheduler(0, report.old_policy, os.sched_param(prio))
        report.old_policy = None
    if report.old_cpus is not None:
        with contextlib.suppress(OSError):
            ops.setaffinity(0, report.old_cpus)
        report.old_cpus = None
    if report.locked:
        ops.munlockall()
        report.locked = False
    if report.latency_fd is not None:
        with contextlib.suppress(OSError):
            ops.close(report.latency_fd)
        report.latency_fd = None
    if report.gc_was_enabled is not None:
        gc.unfreeze()
        if report.gc_was_enabled:
            gc.enable()
        report.gc_was_enabled = None


def below_the_cycle() -> None:
    """Run the calling thread below the cycle (the exporter, the recorder's writer): back
    to SCHED_OTHER if it was started real-time (threads inherit the policy of the thread
    that starts them; the unit's CPUSchedulingPolicy=fifo), and nice 10. Linux applies both
    per thread; lowering needs no privilege. Elsewhere a no-op."""
    with contextlib.suppress(AttributeError, OSError):
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    with contextlib.suppress(AttributeError, OSError):
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, max(os.getpriority(os.PRIO_PROCESS, tid), 10))
