"""The whole loop, end to end: SITL renderer + simulated autopilot over real UDP + TCP camera + the daemon
as its own process with config/sitl.yaml, scored against the truth."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import pytest

from daemon_harness import fly_small_map
from gps_denied_onboard.components.c13_fdr.reader import FdrReader
from gps_denied_onboard.constants import FdrKind
from gps_denied_onboard.sitl.runner import summary_lines

pytestmark = pytest.mark.sitl

REPORT_KEYS = {"frames", "availability", "horizontal_error_m", "latency_ms", "provenance_counts", "per_frame"}


@pytest.fixture(scope="module")
def smoke_report(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    root = tmp_path_factory.mktemp("sitl")
    # the loop, not the matcher, is under test: the same (weights-free) strategy on every machine
    report = fly_small_map(root, "smoke")
    report_path = root / "out" / "report.json"
    return report, report_path


def test_sitl_smoke_localises_within_issue_bounds(smoke_report: tuple[dict, Path]) -> None:
    """A short flight over a procedural map: availability >= 0.9 and horizontal p95 <= 10 m."""
    report, _ = smoke_report
    assert report["frames"] >= 20
    assert report["availability"] >= 0.9, summary_lines(report)
    assert report["horizontal_error_m"]["p95"] <= 10.0, summary_lines(report)
    assert report["provenance_counts"].get("satellite_anchored", 0) >= 0.8 * report["frames_answered"]


def test_sitl_report_has_required_fields_and_files(smoke_report: tuple[dict, Path]) -> None:
    """The JSON on disk has the issue's fields, per-frame rows, and the PNG plot exists."""
    report, path = smoke_report
    on_disk = json.loads(path.read_text())
    assert set(on_disk) >= REPORT_KEYS
    assert {"p50", "p95", "max"} <= set(on_disk["horizontal_error_m"])
    assert {"p50", "p95"} <= set(on_disk["latency_ms"])
    assert len(on_disk["per_frame"]) == on_disk["frames"] == report["frames"]
    answered = [r for r in on_disk["per_frame"] if r.get("latency_ms") is not None]
    assert answered and all(r["latency_ms"] > 0 for r in answered)
    png = path.with_suffix(".png")
    assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_sitl_daemon_accuracy_fields_are_honest(smoke_report: tuple[dict, Path]) -> None:
    """GPS_INPUT horiz_accuracy is a covariance-derived sigma: 95 % of the 3D fixes' errors lie within 3
    sigma. (Frames answered before the estimator started are fix_type 0 with no accuracy: no claim.)"""
    report, _ = smoke_report
    rows = [r for r in report["per_frame"] if r.get("horizontal_error_m") is not None and r["fix_type"] == 3]
    assert len(rows) >= 20, [r["fix_type"] for r in report["per_frame"]]
    within = [r["horizontal_error_m"] <= 3.0 * max(r["horiz_accuracy_m"], 0.1) for r in rows]
    assert sum(within) >= 0.95 * len(within)


def test_sitl_estimate_stream_is_steady_enough_for_ardupilot(smoke_report: tuple[dict, Path]) -> None:
    """GPS_INPUT goes out at the configured 10 Hz between frames: the daemon's own send times (its FDR
    ``mavlink.estimate`` records) never more than 245 ms apart; at the simulated autopilot, interval mean
    <= 120 ms and p99 <= 200 ms, and the ArduPilot health rule (test double) never trips.

    The receive side's single largest interval is not asserted: it is stamped when the simulator's own
    loop reads the socket, so a simulator stalled for a moment on this 2-core machine shows a gap the
    daemon did not make (seen once: 447 ms received while the daemon's sends were at most 102.5 ms apart).
    The health rule, which tolerates one late message but not two in a row, still judges what arrived."""
    report, report_path = smoke_report
    iv = report["stream"]["interval_ms"]
    assert report["gps_input_received"] >= 2.5 * report["frames"], report["gps_input_received"]
    assert iv["mean_ms"] <= 120.0 and iv["p99_ms"] <= 200.0, iv
    assert not report["stream"]["health"]["tripped"], report["stream"]
    assert report["stream"]["ekf_failsafe_land_s"] is None
    fdr = FdrReader(report_path.parent.parent / "work" / "fdr")
    sent_usec = [r["time_unix_usec"] for r in fdr.records(FdrKind.ESTIMATE_SENT) if r["sent"]]
    assert len(sent_usec) >= iv["n"], (len(sent_usec), iv["n"])
    assert max(b - a for a, b in itertools.pairwise(sent_usec)) <= 245_000


def test_sitl_daemon_stopped_cleanly(smoke_report: tuple[dict, Path]) -> None:
    """The daemon process exited 0 on SIGTERM within 2 s, and sent its HEARTBEAT throughout."""
    report, _ = smoke_report
    assert report["daemon_exit_code"] == 0
    assert report["daemon_stop_s"] is not None and report["daemon_stop_s"] < 2.0
    assert report["heartbeats_received"] >= 5
