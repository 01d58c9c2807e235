"""SITL world: scenarios and truth trajectories, the nav-camera renderer, photometry, the demo map."""

from __future__ import annotations

import copy
import hashlib
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import rasterio
from rasterio.transform import Affine
from rasterio.warp import transform as warp_transform

from gps_denied_onboard.camera.types import Attitude, CameraCalibration
from gps_denied_onboard.geo import LocalTangentPlane
from gps_denied_onboard.sitl.demo_map import generate_demo_map, render_demo_pixels
from gps_denied_onboard.sitl.photometric import GapKind, PhotometricModel, PhotometricParams, degrade_for_gap
from gps_denied_onboard.sitl.render import MapRenderer, RenderError
from gps_denied_onboard.sitl.scenario import (
    BUILTIN_SCENARIOS_DIR,
    FaultKind,
    Scenario,
    ScenarioError,
    SpoofedSource,
    load_scenario,
    scenario_from_mapping,
    spoofed_start_from_yaml,
)


def _from_origin(west: float, north: float, xsize: float, ysize: float) -> Affine:
    """North-up geotransform (rasterio's from_origin without its deprecation warning)."""
    return Affine(xsize, 0.0, west, 0.0, -ysize, north)


GEOVISION = Path("/work/shared/data/geovision_india/geovision_india_z18.tif")

# A map bbox (W, S, E, N) of roughly 2.3 km x 2.2 km around Zurich for resolving scenarios without a map.
BBOX = (8.53, 47.387, 8.561, 47.407)

BASE: dict[str, Any] = {
    "name": "t",
    "alt_agl_m": 100.0,
    "speed_m_s": 10.0,
    "start_delay_s": 2.0,
    "camera": {"width_px": 640, "height_px": 480, "hfov_deg": 70.0},
    "attitude_wobble": {"roll_amp_deg": 3.0, "pitch_amp_deg": 2.0, "period_s": 7.0},
    "waypoints": {
        "frame": "map_relative",
        "points": [[0.2, 0.2], [0.8, 0.2], [0.8, 0.8, {"alt_agl_m": 150}]],
    },
}


def _scenario(**changes: Any) -> Scenario:
    data = copy.deepcopy(BASE)
    data.update(changes)
    return scenario_from_mapping(data)


def _error_for(data: dict[str, Any]) -> ScenarioError:
    with pytest.raises(ScenarioError) as info:
        scenario_from_mapping(data)
    return info.value


def _ne(lat: float, lon: float, ltp: LocalTangentPlane) -> np.ndarray:
    return ltp.to_ned(lat, lon, ltp.origin_alt_m)[:2]


# ---------------------------------------------------------------------------------------------- scenarios


def test_scenario_timestamp_faults_shift_one_frame_stamp() -> None:
    """A timestamp fault shifts the stamp of the first frame at or after at_s only; 0 is refused."""
    faults = [{"at_s": 6.0, "ahead_s": 3600.0}, {"at_s": 9.0, "ahead_s": -0.5}]
    sc = _scenario(timestamp_faults=faults)
    assert sc.stamp_offset_s(6.0) == 3600.0 and sc.stamp_offset_s(9.1) == -0.5
    assert sc.stamp_offset_s(5.9) == 0.0 and sc.stamp_offset_s(6.0 + 1 / 3) == 0.0
    err = _error_for({**BASE, "timestamp_faults": [{"at_s": 1.0, "ahead_s": 0.0}]})
    assert "timestamp_faults[0].ahead_s" in str(err)


def test_scenario_faults_parse_windows_and_instants() -> None:
    """Window faults are active in [from_s, to_s); instants fire between two exposures; a bad kind or a
    non-boolean reconnect is refused with its key path."""
    sc = _scenario(
        faults=[
            {"kind": "camera_stall", "from_s": 5.0, "to_s": 7.0, "reconnect": True},
            {"kind": "bomb_frame", "at_s": 9.0},
        ]
    )
    stall = sc.fault_at(FaultKind.CAMERA_STALL, 6.0)
    assert stall is not None and stall.reconnect and sc.fault_at(FaultKind.CAMERA_STALL, 7.0) is None
    assert [f.kind for f in sc.instant_faults(8.9, 9.1)] == [FaultKind.BOMB_FRAME]
    assert sc.instant_faults(9.0, 9.3) == []
    err = _error_for({**BASE, "faults": [{"kind": "gremlins", "at_s": 1.0}]})
    assert "faults[0].kind" in str(err)
    err = _error_for(
        {**BASE, "faults": [{"kind": "camera_stall", "from_s": 1, "to_s": 2, "reconnect": "yes"}]}
    )
    assert "faults[0].reconnect" in str(err)


def test_scenario_spoofed_start_drags_the_start_points_it_names() -> None:
    """Issue 37: ``spoofed_start`` drags HOME, the autopilot's ground position and the configured start
    (all three by default; ``resume`` only when named) by ``offset_m`` stating ``sigma_m``; none by default;
    a bad source or offset is refused with its key path."""
    assert _scenario().spoofed_start is None
    sc = _scenario(spoofed_start={"offset_m": [300, -40.5]})
    assert sc.spoofed_start is not None
    assert (sc.spoofed_start.offset_ne_m, sc.spoofed_start.sigma_m) == ((300.0, -40.5), 5.0)
    assert sc.spoofed_start.sources == {SpoofedSource.HOME, SpoofedSource.AUTOPILOT, SpoofedSource.CONFIG}
    home = _scenario(spoofed_start={"offset_m": [0, 3000], "sigma_m": 50, "sources": ["home", "resume"]})
    assert home.spoofed_start is not None
    assert home.spoofed_start.sources == {SpoofedSource.HOME, SpoofedSource.RESUME}
    err = _error_for({**BASE, "spoofed_start": {"offset_m": [1, 2], "sources": ["gnss"]}})
    assert "spoofed_start.sources[0]" in str(err) and "home, autopilot, config, resume" in str(err)
    assert "spoofed_start.offset_m" in str(_error_for({**BASE, "spoofed_start": {"offset_m": 300}}))
    err = _error_for({**BASE, "spoofed_start": {"offset_m": [1, 2], "sigma": 5}})
    assert "spoofed_start.sigma" in str(err)
    for name in ("spoofed_start", "spoofed_home"):
        assert load_scenario(name).spoofed_start is not None
    given = spoofed_start_from_yaml("{offset_m: [3000, 0], sigma_m: 50}", "--spoofed-start")
    assert given is not None and (given.offset_ne_m, given.sigma_m) == ((3000.0, 0.0), 50.0)
    assert spoofed_start_from_yaml("null", "--spoofed-start") is None
    with pytest.raises(ScenarioError, match="--spoofed-start: spoofed_start: not valid YAML"):
        spoofed_start_from_yaml("{offset_m: [", "--spoofed-start")


def test_scenario_host_faults_parse_and_never_reach_the_camera() -> None:
    """clock_jump steps accumulate into the host's wall clock from their instant; ort_fault carries its
    count (3 by default); tile_corrupt and fdr_full are windows; none of them is sent as a bad frame; a
    zero step or a zero count is refused with its key path."""
    sc = _scenario(
        faults=[
            {"kind": "clock_jump", "at_s": 5.0, "step_s": -30.0},
            {"kind": "clock_jump", "at_s": 8.0, "step_s": 30.5},
            {"kind": "ort_fault", "at_s": 6.0},
            {"kind": "ort_fault", "at_s": 7.0, "count": 5},
            {"kind": "tile_corrupt", "from_s": 2.0, "to_s": 4.0},
            {"kind": "fdr_full", "from_s": 3.0, "to_s": 4.0},
        ]
    )
    assert [sc.wall_step_s(t) for t in (4.99, 5.0, 7.9, 8.0)] == [0.0, -30.0, -30.0, 0.5]
    assert [f.count for f in sc.faults_of(FaultKind.ORT_FAULT)] == [3, 5]
    assert (
        sc.fault_at(FaultKind.TILE_CORRUPT, 3.0) is not None and sc.fault_at(FaultKind.FDR_FULL, 4.0) is None
    )
    assert sc.instant_faults(0.0, 10.0) == []
    err = _error_for({**BASE, "faults": [{"kind": "clock_jump", "at_s": 1.0, "step_s": 0}]})
    assert "faults[0].step_s" in str(err)
    err = _error_for({**BASE, "faults": [{"kind": "clock_jump", "at_s": 1.5, "step_s": 30}]})
    assert "faults[0].at_s" in str(err) and "whole number of seconds" in str(err)
    err = _error_for({**BASE, "faults": [{"kind": "ort_fault", "at_s": 1.0, "count": 0}]})
    assert "faults[0].count" in str(err)
    err = _error_for({**BASE, "faults": [{"kind": "attitude_offset", "from_s": 1.0, "to_s": 2.0}]})
    assert "faults[0].roll_deg" in str(err) and "non-zero" in str(err)


def test_scenario_builtin_files_load() -> None:
    """The shipped scenarios load, by path and by bare name, with the documented shape."""
    names = sorted(p.stem for p in BUILTIN_SCENARIOS_DIR.glob("*.yaml"))
    assert names == [
        "attitude_offset",
        "autopilot_restart",
        "autopilot_square",
        "autopilot_worker_crash",
        "clock_faults",
        "demo",
        "faults",
        "link_drop",
        "map_gap",
        "naip_cross_date",
        "naip_cross_date_attitude",
        "nominal_real",
        "px4_restart",
        "px4_square",
        "px4_worker_crash",
        "restart",
        "smoke",
        "soak",
        "spoofed_home",
        "spoofed_start",
        "wrong_tile_trap",
    ]
    demo = load_scenario(BUILTIN_SCENARIOS_DIR / "demo.yaml")
    assert demo == load_scenario("demo")
    assert demo.frame_rate_hz == 3.0 and demo.alt_agl_m == 120.0 and demo.max_alt_agl_m == 150.0
    assert len(demo.waypoints.points) >= 3
    smoke = load_scenario("smoke")
    assert smoke.duration_s is not None and 8.0 <= smoke.duration_s <= 10.0


def test_scenario_unknown_key_names_path() -> None:
    """A misspelt key is an error naming its full path and the valid keys."""
    data = copy.deepcopy(BASE)
    data["photometric"] = {"noise_sigma": 3.0}
    err = _error_for(data)
    assert err.key_path == "photometric.noise_sigma"
    assert "noise_sigma_dn" in str(err)


@pytest.mark.parametrize(
    ("key", "value", "path", "expected"),
    [
        ("speed_m_s", "12", "speed_m_s", "expected a number"),
        ("speed_m_s", -1.0, "speed_m_s", "> 0"),
        ("duration_s", True, "duration_s", "expected a number"),
        ("camera", {"width_px": 640.0}, "camera.width_px", "expected an integer"),
        ("camera", {"hfov_deg": 200}, "camera.hfov_deg", "< 179"),
        ("photometric", {"gain_range": [1.2, 0.9]}, "photometric.gain_range", "lo <= hi"),
        ("photometric", {"blur_prob": 2}, "photometric.blur_prob", "<= 1"),
        ("attitude_wobble", [], "attitude_wobble", "expected a mapping"),
    ],
)
def test_scenario_wrong_value_names_path(key: str, value: object, path: str, expected: str) -> None:
    """Wrong types and out-of-range values name the key path and what was expected."""
    data = copy.deepcopy(BASE)
    data[key] = value
    err = _error_for(data)
    assert err.key_path == path
    assert expected in str(err)


def test_scenario_missing_required_key_is_error() -> None:
    """A missing alt_agl_m is reported as required."""
    data = copy.deepcopy(BASE)
    del data["alt_agl_m"]
    err = _error_for(data)
    assert err.key_path == "alt_agl_m" and "required" in str(err)


@pytest.mark.parametrize(
    ("waypoints", "path"),
    [
        ({"frame": "map_relative", "points": [[0.2, 0.2], [1.2, 0.2]]}, "waypoints.points[1][0]"),
        (
            {"frame": "map_relative", "points": [[0.2, 0.2], [0.3, 0.2, {"alt": 150}]]},
            "waypoints.points[1][2].alt",
        ),
        ({"frame": "map_relative", "points": [[0.2, 0.2]]}, "waypoints.points"),
        ({"frame": "map_relative", "points": [[0.2, 0.2], [0.3]]}, "waypoints.points[1]"),
        ({"frame": "utm", "points": [[0.2, 0.2], [0.3, 0.2]]}, "waypoints.frame"),
        ({"frame": "wgs84", "margin_m": 10, "points": [[47.39, 8.54], [47.40, 8.54]]}, "waypoints.margin_m"),
        ({"frame": "wgs84", "points": [[47.39, 8.54], [95.0, 8.54]]}, "waypoints.points[1][0]"),
        ({"points": [[0.2, 0.2], [0.3, 0.2]]}, "waypoints.frame"),
    ],
)
def test_scenario_bad_waypoints_name_path(waypoints: dict[str, Any], path: str) -> None:
    """Waypoint errors point at the offending point or key."""
    data = copy.deepcopy(BASE)
    data["waypoints"] = waypoints
    assert _error_for(data).key_path == path


def test_scenario_map_gaps_parse_and_validate() -> None:
    """Map gaps select frames by time; a reversed window or an unknown kind is an error."""
    sc = _scenario(
        map_gaps=[
            {"from_s": 5, "to_s": 8.5, "kind": "blackout"},
            {"from_s": 10, "to_s": 12, "kind": "featureless"},
        ]
    )
    assert sc.gap_at(4.99) is None
    assert sc.gap_at(5.0) is GapKind.BLACKOUT
    assert sc.gap_at(8.5) is None
    assert sc.gap_at(11.0) is GapKind.FEATURELESS
    data = copy.deepcopy(BASE)
    data["map_gaps"] = [{"from_s": 5, "to_s": 4, "kind": "blackout"}]
    assert _error_for(data).key_path == "map_gaps[0].to_s"
    data["map_gaps"] = [{"from_s": 5, "to_s": 6, "kind": "fog"}]
    assert _error_for(data).key_path == "map_gaps[0].kind"


def test_scenario_file_errors_name_the_file(tmp_path: Path) -> None:
    """A missing file lists the built-ins; broken YAML is a ScenarioError naming the file."""
    listed = (
        r"built-in scenarios: attitude_offset, autopilot_restart, autopilot_square, autopilot_worker_crash, "
        r"clock_faults, demo, "
        r"faults, link_drop, "
        r".*, smoke"
    )
    with pytest.raises(ScenarioError, match=listed):
        load_scenario(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [unclosed\n", encoding="utf-8")
    with pytest.raises(ScenarioError, match="not valid YAML") as info:
        load_scenario(bad)
    assert info.value.source == str(bad)


# --------------------------------------------------------------------------------------------- trajectory


def test_trajectory_speed_profile_trapezoidal_and_velocity_consistent() -> None:
    """Speed ramps at accel_m_s2 to the cruise speed and back to rest; vel_ned matches the position
    derivative through legs, turns and ramps."""
    traj = _scenario().resolve(BBOX, 400.0)
    ltp = traj.origin
    dt = 0.05
    accel = traj.accel_m_s2
    for t in np.arange(traj.start_delay_s + 0.1, traj.flight_end_s - 0.1, 0.37):
        a, b = traj.truth_at(t), traj.truth_at(t + dt)
        d = _ne(b.lat_deg, b.lon_deg, ltp) - _ne(a.lat_deg, a.lon_deg, ltp)
        expected = min(10.0, accel * (t - traj.start_delay_s), accel * (traj.flight_end_s - t))
        assert np.hypot(*a.vel_ned_m_s[:2]) == pytest.approx(expected, abs=1e-6)
        np.testing.assert_allclose(d / dt, 0.5 * (a.vel_ned_m_s[:2] + b.vel_ned_m_s[:2]), atol=0.3)
    cruise = traj.truth_at(traj.start_delay_s + 10.0 / accel + 1.0)
    assert np.hypot(*cruise.vel_ned_m_s[:2]) == pytest.approx(10.0, abs=1e-9)


def test_trajectory_heading_follows_track_and_is_continuous() -> None:
    """Yaw equals the track direction and never changes faster than the turn rate."""
    sc = _scenario(turn_rate_deg_s=20.0)
    traj = sc.resolve(BBOX, 400.0)
    times = np.arange(traj.start_delay_s + 0.05, traj.flight_end_s - 0.05, 0.1)
    states = [traj.truth_at(t) for t in times]
    yaws = np.unwrap([s.yaw_rad for s in states])
    assert np.max(np.abs(np.diff(yaws))) <= math.radians(20.0) * 0.1 + 1e-6
    # The path has a left turn of 90 deg (east, then north).
    assert yaws[0] == pytest.approx(math.pi / 2, abs=0.02)
    assert yaws[-1] == pytest.approx(0.0, abs=0.02)
    for s in states[::10]:
        assert math.atan2(s.vel_ned_m_s[1], s.vel_ned_m_s[0]) == pytest.approx(s.yaw_rad, abs=1e-9)


def test_trajectory_climb_is_rate_limited_ramp() -> None:
    """An altitude change ramps at the climb rate, starting after the previous waypoint, to the target."""
    sc = _scenario(climb_rate_m_s=2.5)
    traj = sc.resolve(BBOX, 400.0)
    times = np.arange(0.0, traj.duration_s + 30.0, 0.1)
    alts = np.array([traj.truth_at(t).alt_agl_m for t in times])
    rates = np.diff(alts) / 0.1
    assert alts[0] == 100.0 and alts[-1] == pytest.approx(150.0)
    assert rates.min() >= -1e-9 and rates.max() <= 2.5 + 1e-6
    climbing = times[1:][rates > 1.0]
    assert climbing.size > 0
    # The climb starts in the middle of the second corner, about half-way through the flight.
    assert climbing[0] > traj.start_delay_s + 0.4 * traj.path_length_m / traj.speed_m_s
    mid = traj.truth_at(float(climbing[len(climbing) // 2]))
    assert mid.vel_ned_m_s[2] == pytest.approx(-2.5)
    assert mid.alt_amsl_m == pytest.approx(400.0 + mid.alt_agl_m)


def test_trajectory_holds_before_start_and_after_end() -> None:
    """The aircraft holds still at the first waypoint during the start delay and at the last one after."""
    traj = _scenario(duration_s=500.0).resolve(BBOX, 0.0)
    first, last = traj.waypoints_lat_lon_deg[0], traj.waypoints_lat_lon_deg[-1]
    for t in (0.0, 1.0, traj.start_delay_s):
        s = traj.truth_at(t)
        assert (s.lat_deg, s.lon_deg) == pytest.approx(tuple(first), abs=1e-9)
        assert not np.any(s.vel_ned_m_s[:2])
    s = traj.truth_at(traj.flight_end_s + 10.0)
    assert (s.lat_deg, s.lon_deg) == pytest.approx(tuple(last), abs=1e-9)
    assert not np.any(s.vel_ned_m_s[:2])
    assert traj.duration_s == 500.0
    assert len(traj.frame_times_s()) == 1500


def test_trajectory_default_duration_flies_path_once() -> None:
    """Without duration_s the run ends when the path ends; frames are k / rate."""
    traj = _scenario().resolve(BBOX, 0.0)
    assert traj.duration_s == pytest.approx(traj.flight_end_s)
    times = traj.frame_times_s()
    assert times[1] == pytest.approx(1 / 3.0) and times[-1] < traj.duration_s


def test_trajectory_map_relative_layout_lands_in_margin_box() -> None:
    """(u, v) = (0, 0), (1, 1), (0.5, 0.5) land on the SW/NE corners of the box shrunk by margin_m."""
    wps = {"frame": "map_relative", "margin_m": 200, "points": [[0.0, 0.0], [1.0, 1.0], [0.5, 0.5]]}
    traj = _scenario(waypoints=wps).resolve(BBOX, 0.0)
    ltp = LocalTangentPlane((BBOX[1] + BBOX[3]) / 2, (BBOX[0] + BBOX[2]) / 2, 0.0)
    corners = {
        "sw": _ne(BBOX[1], BBOX[0], ltp),
        "ne": _ne(BBOX[3], BBOX[2], ltp),
    }
    got = [_ne(lat, lon, ltp) for lat, lon in traj.waypoints_lat_lon_deg]
    # Within 1 m of the margin box: the box uses the narrower (northern) edge, a few dm narrower.
    np.testing.assert_allclose(got[0], corners["sw"] + 200.0, atol=1.0)
    np.testing.assert_allclose(got[1], corners["ne"] - 200.0, atol=1.0)
    np.testing.assert_allclose(got[2], [0.0, 0.0], atol=1e-6)


def test_trajectory_auto_margin_is_footprint() -> None:
    """The automatic margin keeps the footprint at the highest altitude on the map."""
    sc = _scenario(
        waypoints={"frame": "map_relative", "points": [[0.0, 0.0], [1.0, 0.0, {"alt_agl_m": 150}]]}
    )
    traj = sc.resolve(BBOX, 0.0)
    ltp = LocalTangentPlane((BBOX[1] + BBOX[3]) / 2, (BBOX[0] + BBOX[2]) / 2, 0.0)
    sw = _ne(BBOX[1], BBOX[0], ltp)
    got = _ne(*traj.waypoints_lat_lon_deg[0], ltp)
    radius = sc.footprint_radius_m()
    # 150 m AGL, 70 x 55 deg FOV, 5 deg wobble: corner ray 46.2 deg off nadir.
    assert radius == pytest.approx(
        150.0 * math.tan(math.atan(400.0 / (320.0 / math.tan(math.radians(35)))) + math.radians(5))
    )
    np.testing.assert_allclose(got, sw + radius + 5.0, atol=1.0)


def test_trajectory_map_too_small_is_error() -> None:
    """A map smaller than twice the margin is refused with the sizes in the message."""
    tiny = (8.54, 47.39, 8.5415, 47.391)
    with pytest.raises(ScenarioError, match="too small for a margin") as info:
        _scenario().resolve(tiny, 0.0)
    assert info.value.key_path == "waypoints.margin_m"


def test_trajectory_wgs84_layout_is_exact_and_checked() -> None:
    """wgs84 waypoints are used as given; one off the map is an error naming it."""
    pts = [[47.390, 8.535], [47.390, 8.545], [47.398, 8.545]]
    traj = _scenario(waypoints={"frame": "wgs84", "points": pts}).resolve(BBOX, 0.0)
    np.testing.assert_allclose(traj.waypoints_lat_lon_deg, pts, atol=1e-9)
    s = traj.truth_at(0.0)
    assert (s.lat_deg, s.lon_deg) == pytest.approx((47.390, 8.535), abs=1e-9)
    with pytest.raises(ScenarioError) as info:
        _scenario(waypoints={"frame": "wgs84", "points": [*pts, [47.5, 8.54]]}).resolve(BBOX, 0.0)
    assert info.value.key_path == "waypoints.points[3]"


def test_trajectory_ground_alt_from_scenario_or_runner() -> None:
    """A null ground height takes the runner's; a set one wins; neither is an error."""
    assert _scenario().resolve(BBOX, 321.0).truth_at(0).alt_amsl_m == pytest.approx(421.0)
    assert _scenario(ground_alt_amsl_m=50).resolve(BBOX, 321.0).truth_at(0).alt_amsl_m == pytest.approx(150.0)
    with pytest.raises(ScenarioError, match="ground_alt_amsl_m"):
        _scenario().resolve(BBOX)


def test_trajectory_wobble_is_deterministic_and_bounded() -> None:
    """Roll and pitch stay within their amplitudes and are the same for the same time."""
    traj = _scenario().resolve(BBOX, 0.0)
    states = [traj.truth_at(t) for t in np.arange(0, 40, 0.25)]
    rolls = np.array([s.roll_rad for s in states])
    pitches = np.array([s.pitch_rad for s in states])
    assert np.abs(rolls).max() <= math.radians(3.0) + 1e-12 and np.abs(rolls).max() > math.radians(2.5)
    assert np.abs(pitches).max() <= math.radians(2.0) + 1e-12 and np.abs(pitches).max() > math.radians(1.5)
    assert traj.truth_at(12.3) == traj.truth_at(12.3)


# ----------------------------------------------------------------------------------------------- renderer


def _blob_map(path: Path, crs: str, gsd_m: float, lat0: float, lon0: float) -> list[tuple[float, float]]:
    """Write a dark textured map with bright 1.5 m square blobs on a grid; return the blobs' (lat, lon)."""
    size_m = 300.0
    n = round(size_m / gsd_m)
    if crs == "EPSG:4326":
        dlat = gsd_m / 111_320.0
        dlon = gsd_m / (111_320.0 * math.cos(math.radians(lat0)))
        transform = _from_origin(lon0 - n / 2 * dlon, lat0 + n / 2 * dlat, dlon, dlat)
    else:
        (x0,), (y0,) = warp_transform("EPSG:4326", crs, [lon0], [lat0])
        transform = _from_origin(x0 - size_m / 2, y0 + size_m / 2, gsd_m, gsd_m)
    rng = np.random.default_rng(1)
    img = rng.integers(20, 60, size=(n, n), dtype=np.uint8)
    half = round(1.5 / gsd_m) // 2
    rows_cols = []
    for i in np.linspace(0.25, 0.75, 6):
        for j in np.linspace(0.25, 0.75, 6):
            r, c = int(i * n) + 3 * int(j * 7), int(j * n) + 2 * int(i * 5)
            img[r - half : r + half + 1, c - half : c + half + 1] = 255
            rows_cols.append((r, c))
    with rasterio.open(
        path, "w", driver="GTiff", width=n, height=n, count=1, dtype="uint8", crs=crs, transform=transform
    ) as dst:
        dst.write(img, 1)
    xs, ys = transform @ (
        np.array([c + 0.5 for _r, c in rows_cols]),
        np.array([r + 0.5 for r, _c in rows_cols]),
    )
    lons, lats = warp_transform(crs, "EPSG:4326", list(xs), list(ys))
    return list(zip(lats, lons, strict=True))


def _project(
    calib: CameraCalibration, lat: float, lon: float, alt_agl_m: float, att: Attitude, blobs
) -> np.ndarray:
    """Pinhole projection of ground points (lat, lon) into the camera: (n, 2) pixels."""
    ltp = LocalTangentPlane(lat, lon, 0.0)
    pts = ltp.to_ned(np.array([b[0] for b in blobs]), np.array([b[1] for b in blobs]), np.zeros(len(blobs)))
    cam = (pts - np.array([0.0, 0.0, -alt_agl_m])) @ att.R_ned_cam()
    uvw = cam @ calib.K.T
    return uvw[:, :2] / uvw[:, 2:3]


def _blob_centroids(img: np.ndarray) -> np.ndarray:
    """Intensity-weighted centroids of the bright blobs in a rendered frame, (n, 2) pixels."""
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float64)
    count, labels, _stats, _c = cv2.connectedComponentsWithStats((grey > 120).astype(np.uint8))
    weights = np.clip(grey - 60.0, 0.0, None)
    out = []
    for k in range(1, count):
        # Grow the component by a pixel so the blob's soft interpolated rim is weighed too.
        mask = cv2.dilate((labels == k).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        v, u = np.nonzero(mask)
        w = weights[v, u]
        out.append((np.sum(u * w) / w.sum(), np.sum(v * w) / w.sum()))
    return np.array(out)


def _check_blobs(renderer: MapRenderer, calib, lat, lon, alt, att, blobs, min_visible: int) -> float:
    img = renderer.render(calib, lat, lon, alt, att)
    predicted = _project(calib, lat, lon, alt, att, blobs)
    inside = (
        (predicted[:, 0] > 8)
        & (predicted[:, 0] < calib.width_px - 9)
        & (predicted[:, 1] > 8)
        & (predicted[:, 1] < calib.height_px - 9)
    )
    found = _blob_centroids(img)
    assert inside.sum() >= min_visible
    errors = [np.min(np.hypot(*(found - p).T)) for p in predicted[inside]]
    return float(max(errors))


@pytest.mark.parametrize(
    ("crs", "gsd_m", "lat0", "lon0"),
    [("EPSG:4326", 0.5, 47.39, 8.54), ("EPSG:32633", 0.5, 47.39, 14.2), ("EPSG:3857", 0.12, -33.9, 151.2)],
)
def test_render_features_at_predicted_pixels(
    tmp_path: Path, crs: str, gsd_m: float, lat0: float, lon0: float
) -> None:
    """Known map features appear within 1 px of their pinhole projection for a tilted, yawed camera."""
    path = tmp_path / "blobs.tif"
    blobs = _blob_map(path, crs, gsd_m, lat0, lon0)
    renderer = MapRenderer(path)
    calib = CameraCalibration.from_hfov(640, 480, 70.0)
    att = Attitude(math.radians(4.0), math.radians(-3.0), math.radians(37.0))
    # 0.12 m map at 120 m AGL: the frame samples the half-resolution pyramid level.
    err = _check_blobs(renderer, calib, lat0 + 2e-5, lon0 - 3e-5, 120.0, att, blobs, min_visible=12)
    assert err < 1.0


def test_render_north_up_east_right_at_zero_yaw(tmp_path: Path) -> None:
    """Level at yaw 0, a feature north of the camera is above the centre, one east is right of it."""
    path = tmp_path / "blobs.tif"
    blobs = _blob_map(path, "EPSG:4326", 0.5, 47.39, 8.54)
    renderer = MapRenderer(path)
    calib = CameraCalibration.from_hfov(640, 480, 70.0)
    lat, lon = blobs[0]
    img = renderer.render(
        calib, lat - 20.0 / 111_320.0, lon - 30.0 / 75_300.0, 100.0, Attitude(0.0, 0.0, 0.0)
    )
    found = _blob_centroids(img)
    near = found[np.argmin(np.hypot(found[:, 0] - (319.5 + 137), found[:, 1] - (239.5 - 91)))]
    # 30 m east and 20 m north at 100 m AGL with fx = 457 px: (+137, -91) px from the centre.
    assert near == pytest.approx((319.5 + 30 * calib.fx_px / 100, 239.5 - 20 * calib.fx_px / 100), abs=1.5)


def test_render_yaw_90_rotates_image(tmp_path: Path) -> None:
    """Yawing to the east turns the north-up view a quarter turn counter-clockwise."""
    path = tmp_path / "tex.tif"
    rng = np.random.default_rng(3)
    tex = cv2.GaussianBlur(rng.integers(0, 256, size=(800, 800), dtype=np.uint8), (0, 0), 3.0)
    tex = cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX)
    with rasterio.open(
        path, "w", driver="GTiff", width=800, height=800, count=1, dtype="uint8", crs="EPSG:32633",
        transform=_from_origin(500_000.0, 5_250_000.0, 0.5, 0.5),
    ) as dst:  # fmt: skip
        dst.write(tex, 1)
    renderer = MapRenderer(path)
    (lon,), (lat,) = warp_transform("EPSG:32633", "EPSG:4326", [500_200.0], [5_249_800.0])
    calib = CameraCalibration.from_hfov(400, 400, 60.0)
    north = renderer.render(calib, lat, lon, 100.0, Attitude(0.0, 0.0, 0.0)).astype(np.int16)
    east = renderer.render(calib, lat, lon, 100.0, Attitude(0.0, 0.0, math.pi / 2)).astype(np.int16)
    ccw = cv2.rotate(north, cv2.ROTATE_90_COUNTERCLOCKWISE)
    cw = cv2.rotate(north, cv2.ROTATE_90_CLOCKWISE)
    assert np.abs(east - ccw)[20:-20, 20:-20].mean() < 2.0
    assert np.abs(east - cw)[20:-20, 20:-20].mean() > 10.0


def test_render_higher_altitude_smaller_scale(tmp_path: Path) -> None:
    """Doubling the height halves the pixel distance between two ground features."""
    path = tmp_path / "blobs.tif"
    blobs = _blob_map(path, "EPSG:4326", 0.5, 47.39, 8.54)
    renderer = MapRenderer(path)
    calib = CameraCalibration.from_hfov(640, 480, 70.0)
    lat, lon = 47.39, 8.54
    spans = []
    for alt in (80.0, 160.0):
        found = _blob_centroids(renderer.render(calib, lat, lon, alt, Attitude(0.0, 0.0, 0.3)))
        predicted = _project(calib, lat, lon, alt, Attitude(0.0, 0.0, 0.3), blobs)
        idx = [int(np.argmin(np.hypot(*(found - p).T))) for p in predicted[[14, 21]]]
        spans.append(float(np.hypot(*(found[idx[0]] - found[idx[1]]))))
    assert spans[0] / spans[1] == pytest.approx(2.0, rel=0.01)


def test_render_off_map_pixels_are_black(tmp_path: Path) -> None:
    """Over the map's west edge, the part of the frame beyond it is 0 and the rest is not."""
    path = tmp_path / "blobs.tif"
    _blob_map(path, "EPSG:4326", 0.5, 47.39, 8.54)
    renderer = MapRenderer(path)
    west, south, _east, north = renderer.bbox_lonlat
    calib = CameraCalibration.from_hfov(640, 480, 70.0)
    img = renderer.render(calib, (south + north) / 2, west, 100.0, Attitude(0.0, 0.0, 0.0))
    assert not img[:, :310].any()
    assert (img[:, 330:] > 0).all()


def test_render_sky_is_black_when_pitched_up(tmp_path: Path) -> None:
    """Pitched 80 deg nose-up the top of the frame sees the sky (0) and the bottom still sees the map."""
    path = tmp_path / "blobs.tif"
    _blob_map(path, "EPSG:4326", 0.5, 47.39, 8.54)
    r = MapRenderer(path)
    calib = CameraCalibration.from_hfov(640, 480, 70.0)
    img = r.render(calib, 47.39, 8.54, 50.0, Attitude(0.0, math.radians(80), 0.0))
    assert not img[:100].any()
    assert (img[-20:] > 0).all()


def test_render_bbox_and_gsd_match_the_raster(tmp_path: Path) -> None:
    """bbox_lonlat is the raster's bounds for EPSG:4326 and lies inside a UTM raster's footprint."""
    path = tmp_path / "blobs.tif"
    _blob_map(path, "EPSG:4326", 0.5, 47.39, 8.54)
    r = MapRenderer(path)
    with rasterio.open(path) as ds:
        b = ds.bounds
    assert r.bbox_lonlat == pytest.approx((b.left, b.bottom, b.right, b.top), abs=1e-12)
    assert r.ground_gsd_m == pytest.approx(0.5, rel=0.01)
    utm = tmp_path / "utm.tif"
    _blob_map(utm, "EPSG:32633", 0.5, 47.39, 14.2)
    ru = MapRenderer(utm)
    w, s, e, n = ru.bbox_lonlat
    xs, ys = warp_transform("EPSG:4326", "EPSG:32633", [w, e, w, e], [s, s, n, n])
    with rasterio.open(utm) as ds:
        ub = ds.bounds
    assert all(ub.left <= x <= ub.right for x in xs) and all(ub.bottom <= y <= ub.top for y in ys)
    assert ru.ground_gsd_m == pytest.approx(0.5, rel=0.01)


def test_render_band_layouts_and_nodata(tmp_path: Path) -> None:
    """One band becomes grey BGR; RGBA is reordered to BGR with alpha-masked pixels at 0."""
    rgba = np.zeros((4, 64, 64), np.uint8)
    rgba[0], rgba[1], rgba[2], rgba[3] = 200, 100, 50, 255
    rgba[3, :, :8] = 0
    path = tmp_path / "rgba.tif"
    with rasterio.open(
        path, "w", driver="GTiff", width=64, height=64, count=4, dtype="uint8", crs="EPSG:3857",
        transform=_from_origin(950_000.0, 6_000_000.0, 1.0, 1.0), photometric="RGB", alpha="YES",
    ) as dst:  # fmt: skip
        dst.write(rgba)
    r = MapRenderer(path)
    assert r.pixels_bgr.shape == (64, 64, 3)
    assert tuple(r.pixels_bgr[10, 20]) == (50, 100, 200)
    assert not r.pixels_bgr[:, :8].any()
    grey = tmp_path / "grey.tif"
    with rasterio.open(
        grey, "w", driver="GTiff", width=64, height=64, count=1, dtype="uint8", crs="EPSG:3857",
        transform=_from_origin(950_000.0, 6_000_000.0, 1.0, 1.0), nodata=0,
    ) as dst:  # fmt: skip
        dst.write(np.full((64, 64), 77, np.uint8), 1)
    assert tuple(MapRenderer(grey).pixels_bgr[5, 5]) == (77, 77, 77)


@pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")
def test_render_refuses_bad_input(tmp_path: Path) -> None:
    """Missing files, non-georeferenced rasters, distorted calibrations and bad heights are RenderErrors."""
    with pytest.raises(RenderError, match="not found"):
        MapRenderer(tmp_path / "none.tif")
    plain = tmp_path / "plain.tif"
    with rasterio.open(plain, "w", driver="GTiff", width=8, height=8, count=1, dtype="uint8") as dst:
        dst.write(np.zeros((8, 8), np.uint8), 1)
    with pytest.raises(RenderError, match="no CRS"):
        MapRenderer(plain)
    path = tmp_path / "blobs.tif"
    _blob_map(path, "EPSG:4326", 0.5, 47.39, 8.54)
    r = MapRenderer(path)
    distorted = CameraCalibration(640, 480, 457.0, 457.0, 319.5, 239.5, (0.1, 0.0, 0.0, 0.0))
    with pytest.raises(RenderError, match="distort"):
        r.render(distorted, 47.39, 8.54, 100.0, Attitude(0, 0, 0))
    with pytest.raises(RenderError, match="alt_agl_m"):
        r.render(CameraCalibration.from_hfov(640, 480, 70), 47.39, 8.54, -5.0, Attitude(0, 0, 0))


@pytest.mark.realdata
def test_render_real_map_frame_is_textured() -> None:
    """A frame over the real geovision orthophoto (EPSG:3857) is full and textured."""
    if not GEOVISION.is_file():
        pytest.skip(f"real map not available: {GEOVISION}")
    r = MapRenderer(GEOVISION)
    assert r.ground_gsd_m == pytest.approx(0.284, abs=0.01)
    w, s, e, n = r.bbox_lonlat
    img = r.render(
        CameraCalibration.from_hfov(640, 480, 70), (s + n) / 2, (w + e) / 2, 120.0, Attitude(0.02, -0.03, 1.0)
    )
    assert img.shape == (480, 640, 3)
    assert not (img == 0).all(axis=2).any()
    assert cv2.Laplacian(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), cv2.CV_64F).var() > 50.0


@pytest.mark.realdata
def test_nominal_real_scenario_keeps_footprint_on_real_map() -> None:
    """Flying nominal_real over geovision, no frame sees off the map, and it climbs to 150 m."""
    if not GEOVISION.is_file():
        pytest.skip(f"real map not available: {GEOVISION}")
    r = MapRenderer(GEOVISION)
    sc = load_scenario("nominal_real")
    traj = sc.resolve(r.bbox_lonlat, 500.0)
    calib = sc.calibration()
    states = [traj.truth_at(float(t)) for t in traj.frame_times_s()]
    alts = [s.alt_agl_m for s in states]
    for s in states[::4]:
        img = r.render(calib, s.lat_deg, s.lon_deg, s.alt_agl_m, s.attitude)
        assert not (img == 0).all(axis=2).any(), f"frame at t={s.t_s:.2f}s sees off the map"
    assert 100.0 <= min(alts) < 102.0 and max(alts) == pytest.approx(150.0, abs=0.5)
    assert 40.0 < traj.duration_s < 120.0


# -------------------------------------------------------------------------------------------- photometric


def _texture() -> np.ndarray:
    rng = np.random.default_rng(5)
    return cv2.GaussianBlur(rng.integers(0, 256, size=(120, 160, 3), dtype=np.uint8), (0, 0), 1.5)


def test_photometric_is_deterministic_per_frame() -> None:
    """Frame k gets the same change whatever the order; different frames differ."""
    params = PhotometricParams((0.8, 1.2), (0.9, 1.1), 5.0, 3.0, 0.5, 1.0, seed=7)
    img = _texture()
    a = PhotometricModel(params)
    b = PhotometricModel(params)
    first = [a.apply(img, k) for k in range(4)]
    second = [b.apply(img, k) for k in reversed(range(4))][::-1]
    for x, y in zip(first, second, strict=True):
        assert np.array_equal(x, y)
    assert not np.array_equal(first[0], first[1])
    assert not np.array_equal(PhotometricModel(params, seed=8).apply(img, 0), first[0])


def test_photometric_identity_and_gain() -> None:
    """Identity parameters leave the frame unchanged; a gain above 1 brightens it."""
    img = _texture()
    same = PhotometricModel(PhotometricParams()).apply(img, 3)
    assert np.array_equal(same, img) and same is not img
    bright = PhotometricModel(PhotometricParams(gain_range=(1.3, 1.3))).apply(img, 0)
    assert bright.mean() > img.mean() * 1.2
    with pytest.raises(ValueError, match="gain_range"):
        PhotometricParams(gain_range=(1.2, 1.0))


def test_photometric_noise_has_requested_sigma() -> None:
    """Sensor noise is zero-mean with the configured standard deviation."""
    grey = np.full((240, 320, 3), 128, np.uint8)
    noisy = PhotometricModel(PhotometricParams(noise_sigma_dn=3.0)).apply(grey, 0).astype(np.float64)
    assert noisy.mean() == pytest.approx(128.0, abs=0.05)
    assert noisy.std() == pytest.approx(3.0, rel=0.05)


def test_degrade_featureless_and_blackout() -> None:
    """Featureless keeps the mean colour but no corners; blackout is near-black."""
    rng = np.random.default_rng(2)
    img = cv2.resize(
        rng.integers(0, 256, size=(60, 80, 3), dtype=np.uint8), (640, 480), interpolation=cv2.INTER_NEAREST
    )
    orb = cv2.ORB_create(500)
    assert len(orb.detect(img, None)) > 200
    flat = degrade_for_gap(img, GapKind.FEATURELESS)
    assert flat.shape == img.shape
    assert len(orb.detect(flat, None)) < 5
    assert abs(float(flat.mean()) - float(img.mean())) < 10.0
    dark = degrade_for_gap(img, "blackout")
    assert dark.max() <= 7 and dark.any()
    with pytest.raises(ValueError, match="featureless, blackout"):
        degrade_for_gap(img, "fog")


# ---------------------------------------------------------------------------------------------- demo map


def test_demo_map_same_seed_same_pixels(tmp_path: Path) -> None:
    """The demo map is byte-identical for a seed, different for another, georeferenced in EPSG:3857."""

    def sha(path: Path) -> str:
        with rasterio.open(path) as ds:
            return hashlib.sha256(ds.read().tobytes()).hexdigest()

    a = generate_demo_map(tmp_path / "a.tif", seed=11, size_m=400.0)
    b = generate_demo_map(tmp_path / "b.tif", seed=11, size_m=400.0)
    c = generate_demo_map(tmp_path / "c.tif", seed=12, size_m=400.0)
    assert sha(a) == sha(b) != sha(c)
    with rasterio.open(a) as ds:
        assert ds.crs.to_epsg() == 3857 and ds.count == 3 and ds.width == 800
        assert ds.compression is not None
    r = MapRenderer(a)
    assert r.ground_gsd_m == pytest.approx(0.5, rel=0.005)
    w, s, e, n = r.bbox_lonlat
    assert (s + n) / 2 == pytest.approx(47.3977, abs=1e-6) and (w + e) / 2 == pytest.approx(8.5456, abs=1e-6)


def test_demo_map_frame_localises_with_sift(tmp_path: Path) -> None:
    """A rendered demo-map frame matches the map with SIFT, and the homography finds the true spot."""
    path = generate_demo_map(tmp_path / "demo.tif", seed=2026, size_m=700.0)
    r = MapRenderer(path)
    w, s, e, n = r.bbox_lonlat
    lat, lon = s + 0.45 * (n - s), w + 0.55 * (e - w)
    calib = CameraCalibration.from_hfov(640, 480, 70.0)
    frame = r.render(calib, lat, lon, 120.0, Attitude(0.0, 0.0, math.radians(25.0)))
    with rasterio.open(path) as ds:
        row, col = ds.index(*[v[0] for v in warp_transform("EPSG:4326", ds.crs, [lon], [lat])])
    sift = cv2.SIFT_create(2000)
    kf, df = sift.detectAndCompute(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY), None)
    km, dm = sift.detectAndCompute(cv2.cvtColor(np.ascontiguousarray(r.pixels_bgr), cv2.COLOR_BGR2GRAY), None)
    pairs = [m for m, m2 in cv2.BFMatcher().knnMatch(df, dm, k=2) if m.distance < 0.8 * m2.distance]
    src = np.array([kf[m.queryIdx].pt for m in pairs], dtype=np.float32)
    dst = np.array([km[m.trainIdx].pt for m in pairs], dtype=np.float32)
    h, inliers = cv2.findHomography(src, dst, cv2.RANSAC, 3.0)
    assert h is not None and int(inliers.sum()) >= 50
    centre = cv2.perspectiveTransform(np.array([[[319.5, 239.5]]], dtype=np.float32), h)[0, 0]
    assert centre == pytest.approx((col, row), abs=2.0)


def test_demo_map_rejects_bad_size(tmp_path: Path) -> None:
    """A non-positive size or an absurd pixel count is refused before any work."""
    from gps_denied_onboard.sitl.demo_map import DemoMapError

    with pytest.raises(DemoMapError, match="positive"):
        generate_demo_map(tmp_path / "x.tif", size_m=-1.0)
    with pytest.raises(DemoMapError, match=r"64\.\.20000"):
        generate_demo_map(tmp_path / "x.tif", size_m=100_000.0, gsd_m=0.1)
    assert render_demo_pixels(seed=1, size_px=64).shape == (64, 64, 3)
