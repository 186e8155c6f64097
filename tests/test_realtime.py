"""loop.realtime: the config (errors naming the key) and gateway.realtime.apply/undo."""

from __future__ import annotations

import errno
import gc
import os

import pytest

from gateway import realtime
from gateway.config import LoopConfig, RealtimeConfig
from gateway.configtypes import convert
from gateway.errors import ConfigError


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
        ({"cpus": [-1]}, r"loop\.realtime\.cpus: must be CPU numbers"),
        ({"mlock": True}, r"loop\.realtime\.mlock: unknown key"),
        ({"enabled": "yes"}, r"loop\.realtime\.enabled: expected true or false"),
    ],
)
def test_bad_realtime_config_names_the_key(data: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        convert(LoopConfig, {"realtime": data}, "loop", "f.yaml")


def test_config_defaults_off_and_other_policy_takes_priority_zero() -> None:
    loop = convert(LoopConfig, {"realtime": {"policy": "other", "priority": 0}}, "loop")
    assert loop.realtime.policy == "other"
    assert LoopConfig().realtime.enabled is False


def test_disabled_applies_nothing() -> None:
    ops = FakeOps()
    report = realtime.apply(RealtimeConfig(), ops)
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
    assert line.endswith("refused nothing")
    realtime.undo(report, ops)
    assert ops.calls[-2:] == [("cpus", {0, 1}), ("munlockall",)]
    assert ops.calls[-3][1] == os.SCHED_OTHER
    assert gc.isenabled()


def test_refusals_say_why_and_the_rest_is_still_applied() -> None:
    ops = FakeOps(setscheduler=_refuse(errno.EPERM), mlockall=_refuse(errno.ENOMEM))
    cfg = RealtimeConfig(enabled=True, policy="rr", priority=20, cpus=(0, 5))
    report = realtime.apply(cfg, ops)
    line = report.line()
    assert "SCHED_RR priority 20: not permitted (needs root, CAP_SYS_NICE" in line
    assert "CPUs [0, 5]: [5] not available" in line
    assert "mlockall: over the locked-memory limit" in line
    assert report.applied == ["gc frozen and off"]
    realtime.undo(report, ops)
    assert ops.calls == []  # nothing to put back but the GC


def test_real_apply_on_a_thread_other_policy_is_always_allowed() -> None:
    """The real system calls, with what any process may do (SCHED_OTHER, its own CPUs)."""
    cpus = tuple(sorted(os.sched_getaffinity(0)))
    cfg = RealtimeConfig(enabled=True, policy="other", priority=0, cpus=cpus[:1],
                         lock_memory=False, gc_off=False)  # fmt: skip
    report = realtime.apply(cfg)
    try:
        assert report.refused == []
        assert os.sched_getaffinity(0) == set(cpus[:1])
        assert os.sched_getscheduler(0) == os.SCHED_OTHER
    finally:
        realtime.undo(report)
    assert os.sched_getaffinity(0) == set(cpus)
