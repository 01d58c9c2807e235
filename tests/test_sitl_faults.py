"""The short soak: every fault the simulator can inject, in one minute of flight through the whole loop
(daemon process, UDP MAVLink, TCP camera). The daemon keeps flying, records every fault, and never sends
a fix_type 3 it cannot back (issue 9). The 20-minute form is the `soak` scenario (docs/benchmarks.md)."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import pytest

from daemon_harness import fly_small_map
from gps_denied_onboard.components.c13_fdr import read_records
from gps_denied_onboard.sitl.runner import summary_lines

pytestmark = [pytest.mark.sitl, pytest.mark.slow]


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> dict:
    return fly_small_map(tmp_path_factory.mktemp("faults"), "faults")


def _records(flight: dict) -> list[dict]:
    return list(read_records(Path(flight["fdr_dir"])))


def _log_events(flight: dict) -> list[dict]:
    lines = Path(flight["daemon_log"]).read_text(errors="replace").splitlines()
    return [json.loads(line) for line in lines if line.startswith("{")]


def test_faults_never_crash_the_daemon_or_make_it_lie(flight: dict) -> None:
    """Exit 0 after SIGTERM; no GPS_INPUT with fix_type 3 beyond 3x its stated accuracy; no EKF failsafe."""
    assert flight["daemon_exit_code"] == 0
    assert flight["consistency"]["beyond_3sigma"] == 0, flight["consistency"]
    assert flight["stream"]["ekf_failsafe_land_s"] is None, flight["stream"]
    assert flight["availability"] >= 0.8, summary_lines(flight)


def test_every_fault_is_in_the_flight_data_recorder(flight: dict) -> None:
    """Bad frames by stage, the future stamp, the link drop and the attitude outages are all recorded;
    one FDR frame record per tracked frame."""
    records = _records(flight)
    errors = Counter(r["stage"] for r in records if r["kind"] == "pipeline.frame_error")
    assert errors["decode"] >= 2 and errors["size"] >= 1, errors  # corrupt + bomb; wrong size
    refused = Counter(r["reason"] for r in records if r["kind"] == "pipeline.frame_refused")
    assert refused["future"] == 1, refused
    link = [r["event"] for r in records if r["kind"] == "mavlink.link_event"]
    assert "link_lost" in link and "link_restored" in link, link
    no_attitude = [
        r for r in records if r["kind"] == "pipeline.fix" and r["no_fix_reason"] == "no_attitude_or_altitude"
    ]
    assert len(no_attitude) >= 3, "NaN/absent attitude windows left no trace"
    stopped = next(e for e in _log_events(flight) if e.get("event") == "daemon.stopped")
    frames = [r for r in records if r["kind"] == "pipeline.frame"]
    assert len(frames) == stopped["frames_processed"], (len(frames), stopped)


def test_camera_reconnect_and_flood_are_survived_and_recorded(flight: dict) -> None:
    """The dropped camera connection is logged and re-established, and the MAVLink flood's bad packets are
    counted, both in the FDR's status records; the flood does not stop the estimate stream (no unhealthy
    span inside its window)."""
    events = Counter(e.get("event") for e in _log_events(flight))
    assert events["camera.disconnected"] >= 1 and events["camera.connected"] >= 2, events
    status = [r for r in _records(flight) if r["kind"] == "daemon.status"]
    assert status and status[-1]["camera_connections"] >= 2, status[-1:]
    assert status[-1]["mavlink_bad_packets"] > 100, status[-1]
    flood = next(f for f in flight["faults_injected"] if f["kind"] == "mavlink_flood")
    assert flood["datagrams"] > 1000, flood
    t_ref = flight["t0_unix_s"] - flight["stream_t0_unix_s"]
    spans = flight["stream"]["health"]["unhealthy_spans_s"]
    assert not any(a - t_ref < 35.0 and b - t_ref > 30.0 for a, b in spans), spans
