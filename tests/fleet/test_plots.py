"""The fleet's pictures read right: the time axis spans the recordings, every parameter
axis has its unit, counts have their plural (issue 31 item 10)."""

from __future__ import annotations

import datetime

from gateway.fleet.plots import axis_label, plural, time_span


def test_one_recording_spans_hours_not_years():
    start = datetime.datetime(2026, 11, 28, 10, 0, tzinfo=datetime.UTC)
    lo, hi = time_span([start])
    assert hi - lo == datetime.timedelta(hours=2) and lo < start < hi
    later = start + datetime.timedelta(days=10)
    lo, hi = time_span([start, later])
    assert lo < start and hi > later and hi - lo < datetime.timedelta(days=12)


def test_units_and_plurals():
    assert axis_label("offset", "c_n") == "offset\nc_n (N)"
    assert axis_label("viscous", "c_ns_m") == "viscous\nc_ns_m (N s/m)"
    assert axis_label("coulomb", "mu") == "coulomb\nmu"
    assert plural(1, "recording") == "1 recording" and plural(2, "recording") == "2 recordings"
    assert plural(0, "recording") == "0 recordings"
