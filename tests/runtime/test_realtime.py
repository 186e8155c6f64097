"""loop.realtime: the config (errors naming the key) and gateway.runtime.realtime.apply/undo."""

from __future__ import annotations

import errno
import gc
import os

import pytest

from gateway.core.config import LoopConfig, RealtimeConfig
from gateway.core.configtypes import convert
from gateway.errors import ConfigError
from gateway.runtime import realtime


def _refuse(err: int):
    def op(*args: object) -> None:
        raise OSError(err, os.strerror(err))

    return op


class FakeOps(realtime.Ops):
    def __init__(self, **over: object) -> None:
        super().__init__()
        self.calls: list[tuple] = []
        self.setscheduler = lambda pid, pol, param: self.calls.append(("sched", pol, param))
        self.getscheduler = lambda pid: os.SCHED_OTHER
        self.setaffinity = lambda pid, cpus: self.calls.append(("cpus", set(cpus)))
        self.getaffinity = lambda pid: {0, 1}
        self.mlockall = lambda: self.calls.append(("mlockall",))
        self.munlockall = lambda: self.calls.append(("munlockall",))
        self.open_latency = lambda us: self.calls.append(("latency", us)) or 99
        self.close = lambda fd: self.calls.append(("close", fd))
        for k, v in over.items():
            setattr(self, k, v)


@pytest.fixture(autouse=True)
def _gc_restored():
    was = gc.isenabled()
    yield
    gc.unfreeze()
    if was:
        gc.enable()


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"priority": 0}, r"f\.yaml: loop\.realtime\.priority: must be in 1\.\.99"),
        ({"priority": 100}, r"loop\.realtime\.priority"),
        ({"policy": "deadline"}, r"loop\.realtime\.policy: 'deadline' is not one of"),
        ({"cpus": [0, 0]}, r"loop\.realtime\.cpus: must not repeat"),
        ({"cpus": [-1]}, r"loop\.realtime\.cpus\[0\]: must be in 0\.\.4095"),
        ({"mlock": True}, r"loop\.realtime\.mlock: unknown key"),
        ({"enabled": "yes"}, r"loop\.realtime\.enabled: expected true or false"),
    ],
)
def test_bad_realtime_config_names_the_key(data: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        convert(LoopConfig, {"realtime": data}, "loop", "f.yaml")


def test_config_defaults_on_and_other_policy_takes_priority_zero() -> None:
    loop = convert(LoopConfig, {"realtime": {"policy": "other", "priority": 0}}, "loop")
    assert loop.realtime.policy == "other"
    assert LoopConfig().realtime.enabled is True  # a 1 kHz service tries it by default
    off = convert(LoopConfig, {"realtime": {"enabled": False}}, "loop")
    assert off.realtime.enabled is False


def test_disabled_applies_nothing() -> None:
    ops = FakeOps()
    report = realtime.apply(RealtimeConfig(enabled=False), ops)
    assert ops.calls == [] and not report.enabled
    assert "off" in report.line()


def test_everything_applied_is_reported_in_one_line() -> None:
    ops = FakeOps()
    cfg = RealtimeConfig(enabled=True, priority=70, cpus=(1,))
    report = realtime.apply(cfg, ops)
    assert ops.calls[0][:2] == ("sched", os.SCHED_FIFO)
    assert ops.calls[0][2].sched_priority == 70
    assert ("cpus", {1}) in ops.calls and ("mlockall",) in ops.calls
    assert not gc.isenabled()
    line = report.line()
    assert "\n" not in line
    assert "SCHED_FIFO priority 70" in line and "CPUs [1]" in line and "mlockall" in line
    assert ("latency", 0) in ops.calls and "cpu_dma_latency 0 us" in line
    assert line.endswith("refused nothing")
    realtime.undo(report, ops)
    assert ops.calls[-3:] == [("cpus", {0, 1}), ("munlockall",), ("close", 99)]
    assert ops.calls[-4][1] == os.SCHED_OTHER
    assert gc.isenabled()


def test_refusals_say_why_and_the_rest_is_still_applied() -> None:
    ops = FakeOps(
        setscheduler=_refuse(errno.EPERM),
        mlockall=_refuse(errno.ENOMEM),
        open_latency=_refuse(errno.EACCES),
    )
    cfg = RealtimeConfig(enabled=True, policy="rr", priority=20, cpus=(0, 5))
    report = realtime.apply(cfg, ops)
    line = report.line()
    assert "SCHED_RR priority 20: not permitted (needs root, CAP_SYS_NICE" in line
    assert "CPUs [0, 5]: [5] not available" in line
    assert "mlockall: over the locked-memory limit" in line
    assert "cpu_dma_latency 0 us: /dev/cpu_dma_latency: not permitted (needs root)" in line
    assert report.applied == ["gc frozen and off"]
    realtime.undo(report, ops)
    assert ops.calls == []  # nothing to put back but the GC


def test_real_apply_on_a_thread_other_policy_is_always_allowed() -> None:
    """The real system calls, with what any process may do (SCHED_OTHER, its own CPUs)."""
    cpus = tuple(sorted(os.sched_getaffinity(0)))
    cfg = RealtimeConfig(
        enabled=True,
        policy="other",
        priority=0,
        cpus=cpus[:1],
        lock_memory=False,
        gc_off=False,
        cpu_dma_latency_us=None,
    )
    report = realtime.apply(cfg)
    try:
        assert report.refused == []
        assert os.sched_getaffinity(0) == set(cpus[:1])
        assert os.sched_getscheduler(0) == os.SCHED_OTHER
    finally:
        realtime.undo(report)
    assert os.sched_getaffinity(0) == set(cpus)


def test_cpu_dma_latency_none_leaves_the_idle_states_alone_and_enoent_is_named() -> None:
    ops = FakeOps()
    report = realtime.apply(RealtimeConfig(enabled=True, cpu_dma_latency_us=None), ops)
    assert not any(c[0] == "latency" for c in ops.calls)
    assert "cpu_dma_latency" not in report.line()
    realtime.undo(report)
    ops = FakeOps(open_latency=_refuse(errno.ENOENT))
    report = realtime.apply(RealtimeConfig(enabled=True, cpu_dma_latency_us=5), ops)
    assert "cpu_dma_latency 5 us: /dev/cpu_dma_latency: no such device" in report.line()
    assert report.latency_fd is None
    realtime.undo(report, ops)
    assert not any(c[0] == "close" for c in ops.calls)


def _effective_latency() -> int:
    fd = os.open(realtime.CPU_DMA_LATENCY, os.O_RDONLY)
    try:
        return int.from_bytes(os.read(fd, 4), "little", signed=True)
    finally:
        os.close(fd)


@pytest.mark.skipif(
    not os.access(realtime.CPU_DMA_LATENCY, os.R_OK | os.W_OK),
    reason="needs root and /dev/cpu_dma_latency (CI runs as root)",
)
def test_real_cpu_dma_latency_is_held_while_applied_and_released_by_undo() -> None:
    """The kernel's effective PM QoS target reads back the request while it is held."""
    before = _effective_latency()
    want = 3 if before != 3 else 4
    cfg = RealtimeConfig(
        enabled=True,
        policy="other",
        priority=0,
        lock_memory=False,
        gc_off=False,
        cpu_dma_latency_us=want,
    )
    report = realtime.apply(cfg)
    try:
        assert report.refused == [] and report.latency_fd is not None
        assert _effective_latency() == min(want, before)
    finally:
        realtime.undo(report)
    assert report.latency_fd is None
    assert _effective_latency() == before
