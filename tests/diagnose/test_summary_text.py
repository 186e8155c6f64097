"""summary.md's region lines: the wrench reference's regions are the
platform's, listed as cable 0 in the report; the summary says so."""

from __future__ import annotations


def test_summary_names_the_platform_not_cable_0() -> None:
    from gateway.diagnose.plots import region_line

    region = {"cable": 0, "start_s": 0.0, "end_s": 1.0, "regime": "accelerating", "share": 0.4}
    assert "cable 0" not in region_line(region) and "the platform" in region_line(region)
    assert region_line({**region, "cable": 3}).startswith("- cable 3, 0.00-1.00 s")
