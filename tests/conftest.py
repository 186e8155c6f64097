"""Suite-wide test settings.

Hypothesis runs without a per-example deadline: the machines are shared and noisy, and
speed is measured in benchmarks (make bench), never asserted in tests.

Two profiles: ``cdpr`` (the default) draws new examples on every run, so a developer's runs
keep exploring; ``ci`` (``HYPOTHESIS_PROFILE=ci``, set by ``.ci/run``) draws the same
examples every time, so a submission is judged on one reproducible set and a new find
shows up on a developer's machine first, with its failing example printed.
"""

from __future__ import annotations

import gc
import os
import signal
from collections.abc import Iterator

import pytest
from hypothesis import HealthCheck, settings

settings.register_profile(
    "cdpr",
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
    print_blob=True,
)
settings.register_profile("ci", parent=settings.get_profile("cdpr"), derandomize=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "cdpr"))


# pytest started as a background job of a non-interactive shell (`cmd &` in a script)
# inherits SIGINT ignored, and so does every child a test starts: the gateway
# keeps an ignored SIGINT ignored (gateway/cli.py, as a background job should), so each test
# that interrupts a child with SIGINT failed with the child running on (exit 0 after its
# work, or 'still running 60 s after SIGINT'; 4 tests in one such run). The tests mean a
# SIGINT as a terminal's Ctrl-C sends it: the default handler back, once, for the children.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(autouse=True)
def _frozen_heap() -> Iterator[None]:
    """Each test starts on a frozen heap (unfrozen after it). The loop's start-up collects
    the whole heap (gateway/runtime/loop.py): in a test process, 0.2-1.8 s a test that runs
    a loop under load; frozen, only what the test itself allocated. Nothing a test checks
    depends on it: the loop still collects, freezes and unfreezes as it does in the daemon.
    Tests that run loops many times (hypothesis) freeze before each run:
    tests.loop_helpers.run_frozen."""
    gc.freeze()
    yield
    gc.unfreeze()
