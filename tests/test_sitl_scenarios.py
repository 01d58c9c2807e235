"""Issue-5 acceptance flights over a real orthophoto: map gap, wrong-tile trap, link drop.

Each runs the whole loop (daemon process, UDP MAVLink, TCP camera) for about two minutes and checks the
report and the analysis of the daemon's own flight data recorder against the issue's bounds.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest

from conftest import shared_path
from gps_denied_onboard.sitl.runner import ATTITUDE_BIAS_RAD, SitlOptions, run_sitl, summary_lines
from gps_denied_onboard.sitl.scenario import load_scenario

pytestmark = [pytest.mark.sitl, pytest.mark.realdata, pytest.mark.slow]


def _fly(tmp_path_factory: pytest.TempPathFactory, scenario: str) -> dict:
    ortho = shared_path("data", "geovision_india", "geovision_india_z18.tif")
    root = tmp_path_factory.mktemp(scenario)
    return run_sitl(
        SitlOptions(
            map_path=ortho,
            scenario=scenario,
            report_path=root / "report.json",
            workdir=root / "work",
            overrides=("matcher.strategy=classical",),
            quiet=True,
        )
    )


@pytest.fixture(scope="module")
def map_gap(tmp_path_factory: pytest.TempPathFactory) -> dict:
    return _fly(tmp_path_factory, "map_gap")


@pytest.fixture(scope="module")
def trap(tmp_path_factory: pytest.TempPathFactory) -> dict:
    return _fly(tmp_path_factory, "wrong_tile_trap")


@pytest.fixture(scope="module")
def link_drop(tmp_path_factory: pytest.TempPathFactory) -> dict:
    return _fly(tmp_path_factory, "link_drop")


def test_map_gap_switches_to_visual_propagated_within_one_frame(map_gap: dict) -> None:
    """The first insufficient-inliers frame is already visual_propagated (lag <= 1 frame), and the
    autopilot heard it: STATUSTEXT and NAMED_VALUE provenance, with the accuracy inflating."""
    a = map_gap["analysis"]
    assert a["no_fix_reasons"].get("insufficient_inliers", 0) > 20, a["no_fix_reasons"]
    assert a["provenance_switch_lag_frames"] is not None and a["provenance_switch_lag_frames"] <= 1
    assert any("visual_propagated" in (s["text"] or "") for s in map_gap["statustext"])
    rows = map_gap["per_frame"]
    # The gap's VIO stretch: after the first anchored frame (the frames tracked before the first fix
    # landed are visual_propagated too, at the start-up prior's sigma).
    first_anchored = next(i for i, r in enumerate(rows) if r.get("provenance") == "satellite_anchored")
    vio = [r for r in rows[first_anchored:] if r.get("provenance") == "visual_propagated"]
    assert vio and vio[-1]["horiz_accuracy_m"] > vio[0]["horiz_accuracy_m"]


def test_map_gap_drift_and_recovery_within_bounds(map_gap: dict) -> None:
    """While VIO-only the error grows by <= 3 % of the distance flown; after the gap the error is back
    under the nominal p95 within 5 fixes; availability stays >= 0.95."""
    segs = [s for s in map_gap["analysis"]["vio_segments"] if s["frames"] >= 10]
    assert segs, map_gap["analysis"]
    for s in segs:
        assert s["drift_pct_of_distance"] is not None and s["drift_pct_of_distance"] <= 3.0, s
        assert s["fixes_to_recover_nominal_p95"] is not None and s["fixes_to_recover_nominal_p95"] <= 5, s
    assert map_gap["availability"] >= 0.95, summary_lines(map_gap)


def test_wrong_tile_trap_accepts_no_fix_beyond_3_sigma(trap: dict) -> None:
    """The look-alike's fixes are offered (and gated); no accepted fix is more than 3 sigma from truth."""
    a = trap["analysis"]
    assert a["no_fix_reasons"].get("gated", 0) > 10, a["no_fix_reasons"]
    assert a["accepted_fixes"] > 50
    assert a["accepted_fixes_beyond_3sigma"] == 0, a
    assert trap["horizontal_error_m"]["max"] < 10.0, summary_lines(trap)


def test_link_drop_keeps_daemon_running_and_recovers(link_drop: dict) -> None:
    """Through a 6 s link cut the daemon refuses fixes on stale attitude, keeps running, and is anchored
    again afterwards; it exits cleanly."""
    a = link_drop["analysis"]
    assert a["no_fix_reasons"].get("no_attitude_or_altitude", 0) >= 5, a["no_fix_reasons"]
    assert a["transitions"] and a["transitions"][-1]["to"] == "satellite_anchored"
    assert link_drop["daemon_exit_code"] == 0
    assert link_drop["horizontal_error_m"]["p95"] <= 8.0, summary_lines(link_drop)


def test_link_drop_trips_no_fix_but_never_the_ekf_failsafe(link_drop: dict) -> None:
    """Judged by the ArduPilot rules (test double): the 5.5 s cut trips NO_FIX once, as measured on a
    real ArduPilot, but the stream is back before the EKF loses its position (7 s) or fails safe (7.8 s):
    the daemon's way back takes at most four camera frames from the link's return."""
    stream = link_drop["stream"]
    assert len(stream["no_fix"]) == 1 and stream["no_fix"][0]["end_s"] is not None, stream["no_fix"]
    cut_end_s = load_scenario("link_drop").link_drops[0].to_s
    t_ref = link_drop["t0_unix_s"] - link_drop["stream_t0_unix_s"]  # the flight's 0 s on the stream's clock
    back_s = stream["no_fix"][0]["end_s"] - (t_ref + cut_end_s)
    assert 0.0 < back_s <= 4 / 3.0, (back_s, stream["no_fix"])
    assert stream["ekf_position_lost"] == [] and stream["ekf_failsafe_land_s"] is None, stream
    assert stream["health"]["healthy_at_end"]
    assert link_drop["consistency"]["beyond_3sigma"] == 0, link_drop["consistency"]


@pytest.fixture(scope="module")
def nominal(tmp_path_factory: pytest.TempPathFactory) -> dict:
    return _fly(tmp_path_factory, "nominal_real")


def test_nominal_real_meets_issue_5_bounds(nominal: dict) -> None:
    """Nominal flight at 100-150 m AGL over the real ortho: p50 <= 3 m, p95 <= 8 m, availability >= 0.95."""
    report = nominal
    assert report["availability"] >= 0.95, summary_lines(report)
    assert report["horizontal_error_m"]["p50"] <= 3.0 and report["horizontal_error_m"]["p95"] <= 8.0
    assert report["analysis"]["accepted_fixes_beyond_3sigma"] == 0
    # issue 10: the stated accuracy stays honest through turns and climbs (IMU-driven prediction)
    assert report["consistency"]["within_2sigma"] >= 0.95 and report["consistency"]["beyond_3sigma"] == 0
    assert not report["stream"]["health"]["tripped"], report["stream"]


def test_gdnav_fdr_boresight_finds_the_autopilots_tilt_offset(nominal: dict) -> None:
    """The SITL autopilot reports roll and pitch with a fixed bias (and a slow wander) while the camera
    sees the truth: ``gdnav fdr boresight``, run as its own process on the flight's recorder, finds the
    mount that cancels the bias (its negative) within its 99 % interval plus 0.1 deg: three times what
    the autopilot's wander (0.1 deg, 5 s) leaves in an 80 s mean, which the pairs share."""
    out = subprocess.run(
        [sys.executable, "-m", "gps_denied_onboard.cli", "fdr", "boresight", nominal["fdr_dir"], "--json"],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    b = json.loads(out.stdout)
    vo = b["vo_ground_tilt"]
    assert vo["samples"] >= 0.8 * nominal["frames"], vo
    expected = [-math.degrees(ATTITUDE_BIAS_RAD[0]), -math.degrees(ATTITUDE_BIAS_RAD[1])]
    for got, want, half in zip(b["mount_deg"], expected, vo["half_width_99_deg"], strict=True):
        assert abs(got - want) <= half + 0.1, (b["mount_deg"], expected, vo)
    assert max(vo["half_width_99_deg"]) < 0.15, vo  # VO at 120 m AGL: about 0.6 deg per pair
