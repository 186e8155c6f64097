"""Suite-wide test settings.

Hypothesis runs without a per-example deadline: the machines are shared and noisy, and
speed is measured in benchmarks (make bench), never asserted in tests.
"""

from __future__ import annotations

from hypothesis import HealthCheck, settings

settings.register_profile(
    "cdpr",
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
    print_blob=True,
)
settings.load_profile("cdpr")
