"""Frames whose stamps lie, through the whole loop (daemon process, UDP MAVLink, TCP camera): refused by
the time axis, counted and recorded, and never a confident lie afterwards (issue 9, defect 1)."""

from __future__ import annotations

from pathlib import Path

import pytest

from daemon_harness import fly_small_map
from gps_denied_onboard.components.c13_fdr import read_records
from gps_denied_onboard.sitl.runner import summary_lines

pytestmark = [pytest.mark.sitl, pytest.mark.slow]


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> dict:
    root = tmp_path_factory.mktemp("clock_faults")
    return fly_small_map(root, "clock_faults")


def test_lying_stamps_are_refused_by_reason(flight: dict) -> None:
    """An hour ahead and 5 s ahead: future; 0.5 s back: out of order; 2 s back: stale. Each once."""
    assert flight["analysis"]["frames_refused"] == {"future": 2, "out_of_order": 1, "stale": 1}, flight[
        "analysis"
    ]


def test_fixes_keep_being_accepted_after_a_future_frame(flight: dict) -> None:
    """The +5 s frame of the defect used to bias the filter and gate every correct fix after it."""
    fixes = [r for r in read_records(Path(flight["fdr_dir"])) if r["kind"] == "pipeline.fix"]
    t_fault_us = min(r["exposure_time_unix_usec"] for r in fixes) + 11 * 1_000_000
    after = [r for r in fixes if r["exposure_time_unix_usec"] > t_fault_us]
    assert after and sum(r["fix_accepted"] for r in after) >= 0.9 * len(after), summary_lines(flight)


def test_no_confident_lie_after_clock_faults(flight: dict) -> None:
    """No GPS_INPUT with fix_type 3 is farther from the truth than 3x its stated accuracy; accuracy and
    availability stay nominal; the stream stays healthy for ArduPilot; the daemon exits 0."""
    assert flight["consistency"]["beyond_3sigma"] == 0, flight["consistency"]
    assert flight["horizontal_error_m"]["p95"] <= 2.0, summary_lines(flight)
    assert flight["availability"] >= 0.95, summary_lines(flight)
    assert not flight["stream"]["health"]["tripped"], flight["stream"]
    assert flight["daemon_exit_code"] == 0
