"""Issue 10: `gdnav sitl run --autopilot` against the ArduPilot emulator (its own process, real UDP).

The emulator is a test double of measured ArduPilot behaviour (sitl/ap_emulator.py), not ArduPilot.
Its EKF start-up (measured 10 s / 28 s after the first fix) is shortened here to 2 s / 4 s to keep CI
short; nothing below judges the start-up timing.
"""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from conftest import REPO_ROOT, shared_path
from gps_denied_onboard.clock import CAMERA_OFFSET_MAX_SE_S, CAMERA_OFFSET_SE_FLOOR_S
from gps_denied_onboard.components.c13_fdr import read_records
from gps_denied_onboard.config import CameraConfig
from gps_denied_onboard.constants import CORE_FDR_SUBDIR, FdrKind
from gps_denied_onboard.sitl.render import MapRenderer
from gps_denied_onboard.sitl.scenario import load_scenario

pytestmark = [pytest.mark.sitl, pytest.mark.realdata, pytest.mark.slow]
SQUARE = REPO_ROOT / "sitl" / "scenarios" / "autopilot_square.yaml"


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _sitl_against_emulator(
    root: Path,
    scenario: Path,
    home: str,
    emulator_args: list[str],
    timeout_s: float,
    emulator_module: str = "ap_emulator",
) -> subprocess.CompletedProcess[str]:
    """The emulator ``sitl.<emulator_module>`` (its own process, home ``home`` as lat,lon,alt,yaw) and
    `gdnav sitl run --autopilot` against it over loopback UDP, over GeoVision; the emulator is stopped
    afterwards."""
    ortho = shared_path("data", "geovision_india", "geovision_india_z18.tif")
    port = _free_port()
    emulator = [sys.executable, "-m", f"gps_denied_onboard.sitl.{emulator_module}", "--home", home]
    emu = subprocess.Popen([*emulator, "--port", str(port), *emulator_args, "--quiet"])
    try:
        return subprocess.run(
            [
                sys.executable,
                "-m",
                "gps_denied_onboard.cli",
                "sitl",
                "run",
                "--autopilot",
                f"udpout:127.0.0.1:{port}",
                "--map",
                str(ortho),
                "--scenario",
                str(scenario),
                "--report",
                str(root / "report.json"),
                "--workdir",
                str(root / "work"),
                "--set",
                "matcher.strategy=classical",
                "--quiet",
            ],
            capture_output=True,
            text=True,
            timeout=timeout_s,
        )
    finally:
        emu.send_signal(signal.SIGTERM)
        emu.wait(10)


def _fly(
    root: Path, scenario: Path
) -> tuple[dict[str, Any], dict[str, Any], subprocess.CompletedProcess[str]]:
    ortho = shared_path("data", "geovision_india", "geovision_india_z18.tif")
    traj = load_scenario(scenario).resolve(MapRenderer(ortho).bbox_lonlat, 0.0)
    lat, lon = traj.waypoints_lat_lon_deg[0]
    events = root / "emulator_events.json"
    delays = ["--ekf-origin-delay-s", "2", "--ekf-using-gps-delay-s", "4", "--events", str(events)]
    cli = _sitl_against_emulator(root, scenario, f"{lat},{lon},400,0", delays, timeout_s=500)
    assert cli.returncode == 0, cli.stdout + cli.stderr
    return json.loads((root / "report.json").read_text()), json.loads(events.read_text()), cli


def _kinds(emu: dict[str, Any]) -> list[str]:
    return [e["kind"] for e in emu["events"]]


@pytest.fixture(scope="module")
def square(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], dict[str, Any], Any]:
    return _fly(tmp_path_factory.mktemp("square"), SQUARE)


def test_mission_arms_takes_off_flies_gnss_off_and_lands(square: Any) -> None:
    report, emu, _cli = square
    kinds = [e["kind"] for e in report["mission"]["log"]]
    for k in ("armed", "takeoff", "takeoff_done", "gnss_off", "gnss_on", "landed"):
        assert k in kinds, kinds
    assert kinds.index("gnss_off") < kinds.index("gnss_on") < kinds.index("landed")
    ek = _kinds(emu)
    assert "armed" in ek and "landed_disarmed" in ek, ek
    reached = [e["seq"] for e in emu["events"] if e["kind"] == "mission_item_reached"]
    assert reached[:5] == [1, 2, 3, 4, 5], reached  # the five corners of the square, in AUTO
    assert report["autopilot"]["truth_source"] == "SIMSTATE"
    assert report["daemon_exit_code"] == 0


def test_emulator_health_and_failsafe_rules_never_trip(square: Any) -> None:
    """While the vehicle flies on GPS 2 alone (GNSS off .. GNSS back on) GPS 2's health never trips,
    and the EKF never loses its position source (no NO_FIX, no EKF failsafe) in the whole run.

    (In the last metres of the landing the daemon stops reporting a 3D fix, so GPS 2 times out there,
    after the GNSS is back on: that is reported by the emulator and is not a failure of this flight.)"""
    report, emu, _cli = square
    ev = emu["events"]
    lo, hi = report["gnss_off"]["window_unix_s"]
    unhealthy = [
        e for e in ev if e["kind"] == "gps_health" and not e["healthy"] and lo <= e["t_unix_s"] <= hi
    ]
    assert unhealthy == [], unhealthy
    lost = [e for e in ev if e["kind"] in ("gps_loss", "ekf_failsafe")]
    assert lost == [], lost
    assert not any("Failsafe" in e.get("text", "") for e in ev)
    primary = [e["instance"] for e in ev if e["kind"] == "gps_primary"]
    assert primary[:1] == [2], primary  # GPS 2 (GPS_INPUT) took over when the GNSS went off


def test_gnss_off_stretch_meets_issue_10_bounds(square: Any) -> None:
    report, _emu, _cli = square
    off = report["gnss_off"]
    iv = off["stream"]["interval_ms"]
    assert iv["mean_ms"] <= 120.0 and iv["p99_ms"] <= 200.0 and iv["max_ms"] <= 245.0, iv
    assert off["availability"] >= 0.95, off["availability"]
    assert off["horizontal_error_m"]["p95"] <= 5.0, off["horizontal_error_m"]
    assert off["consistency"]["beyond_3sigma"] == 0, off["consistency"]
    assert off["window_unix_s"][1] - off["window_unix_s"][0] > 30.0  # the square was flown GNSS-off


def _attitude_refused_right_fixes(report: dict[str, Any]) -> dict[str, int]:
    """Fixes the tilt checks refused although they were within their own sigma of the truth."""
    refused = report["analysis"]["refused_fix_errors"]
    return {
        reason: r["within_1sigma"]
        for reason, r in refused.items()
        if reason in ("attitude_off", "attitude_jump", "vo_attitude_off") and r["within_1sigma"]
    }


def _issue_26_bounds(report: dict[str, Any], emu: dict[str, Any]) -> None:
    """What a real ArduPilot flight must show (issue 26), judged on the emulator's rules: the mission
    done with no failsafe or LAND before its own, no GPS glitch while the vehicle flies on the daemon
    alone, GPS_INPUT p95 <= 5 m there, 0 beyond 3 sigma in the whole flight, the autopilot's own position
    p95 <= 6 m, no right fix refused by a tilt check, and the ground altitude read once the EKF had an
    origin.

    In the landing, with the GNSS back, the daemon's speed accuracy may rise past EKF3's glitch test: the
    matcher sees nothing below 20 m AGL, VO loses its texture in the flare, and the IMU alone carries
    the velocity with the attitude's doubt. That is the honest answer (stated lower, 17 messages went
    out beyond 3 sigma there once), and EKF3 then leans on the GNSS it has again."""
    kinds = [e["kind"] for e in report["mission"]["log"]]
    assert "landed" in kinds, kinds
    assert not [e for e in emu["events"] if e["kind"] in ("gps_loss", "ekf_failsafe")]
    off = report["gnss_off"]
    lo, hi = off["window_unix_s"]
    glitches = [e for e in emu["events"] if e["kind"] == "gps_glitch" and lo <= e["t_unix_s"] <= hi]
    assert not glitches, f"EKF3 would call the GPS glitching: {glitches}"
    assert off["horizontal_error_m"]["p95"] <= 5.0, off["horizontal_error_m"]
    assert off["consistency"]["beyond_3sigma"] == 0, off["consistency"]
    assert report["consistency"]["beyond_3sigma"] == 0, report["consistency"]
    assert off["glitch_spans_s"] == [], off["speed_accuracy_m_s"]
    ap = off["autopilot_position_error_m"]
    assert ap["n"] > 100 and ap["p95"] <= 6.0, ap
    assert _attitude_refused_right_fixes(report) == {}
    assert "terrain.ground_alt_amsl_m=400.0" in report["daemon_overrides"], report["daemon_overrides"]


def test_square_meets_the_real_autopilot_bounds_with_its_clock_2_s_behind(square: Any) -> None:
    """The emulator's SYSTEM_TIME runs 2.0 s behind the host, as SITL's did (every frame was refused as
    stale before TIMESYNC): the daemon maps the autopilot's clock by TIMESYNC and meets issue 26's bounds."""
    report, emu, _cli = square
    _issue_26_bounds(report, emu)


def test_square_with_a_camera_stamping_0_2_s_late(tmp_path: Path) -> None:
    """The camera stamps every frame 0.2 s after its exposure: the daemon measures the lateness from the
    tilts and meets the same bounds. The correction is honest rather than exact: applied, it is within 3
    of its own stated sigmas of the truth (the fit ended at 0.185-0.285 s in six flights, stating
    0.04 s) and takes more than half the lateness off. It is applied only once the fit is sure
    (``CAMERA_OFFSET_MAX_SE_S``); the emulator's attitude error, which follows the swings as ArduPilot
    SITL's does, leans on the fit, and on an Intel Xeon the fit of 0.28-0.33 s kept stating
    0.035-0.05 s for a whole flight (CI's failure of 2026-12-02). Then nothing is taken off and the
    frames carry the camera's prior doubt instead, with the fit within 3 of its sigmas of the truth."""
    data = yaml.safe_load(SQUARE.read_text())
    data["name"] = "autopilot_square_camera_late"
    data["camera_stamp_offset_s"] = 0.2
    scenario = tmp_path / "square_camera_late.yaml"
    scenario.write_text(yaml.safe_dump(data))
    report, emu, _cli = _fly(tmp_path, scenario)
    _issue_26_bounds(report, emu)
    status = [r for r in read_records(tmp_path / "work" / "fdr") if r.get("kind") == FdrKind.STATUS]
    assert status, "no daemon.status record"
    last = status[-1]
    assert last["camera_stamp_sigma_s"] >= CAMERA_OFFSET_SE_FLOOR_S, last
    assert abs(last["camera_stamp_offset_s"] - 0.2) <= 3 * last["camera_stamp_sigma_s"], last
    if last["camera_stamp_offset_s"] == 0.0:  # never sure: carried as the prior's doubt
        assert last["camera_stamp_sigma_s"] >= CameraConfig().stamp_sigma_s, last
        fit_sigma_s = max(last["camera_stamp_fit_se_s"], CAMERA_OFFSET_SE_FLOOR_S)
        assert last["camera_stamp_fit_se_s"] > CAMERA_OFFSET_MAX_SE_S, last
        assert abs(last["camera_stamp_fit_s"] - 0.2) <= 3 * fit_sigma_s, last
    else:
        assert last["camera_stamp_offset_s"] >= 0.1, last


def test_link_drop_trips_no_fix_and_recovers_without_failsafe(tmp_path: Path) -> None:
    """A 6 s cut of the daemon's link while the vehicle flies on GPS_INPUT alone: the emulator reports
    NO_FIX (4 s, measured), never the EKF failsafe (7.8 s), and the flight completes."""
    data = yaml.safe_load(SQUARE.read_text())
    data["name"] = "autopilot_square_link_drop"
    data["link_drops"] = [{"from_s": 28.0, "to_s": 34.0}]
    scenario = tmp_path / "square_link_drop.yaml"
    scenario.write_text(yaml.safe_dump(data))
    report, emu, _cli = _fly(tmp_path, scenario)
    losses = [e for e in emu["events"] if e["kind"] == "gps_loss"]
    assert [e["stage"] for e in losses] == ["NO_FIX"], losses
    assert "ekf_failsafe" not in _kinds(emu)
    assert "gps_recovered" in _kinds(emu)
    assert "landed" in [e["kind"] for e in report["mission"]["log"]]


def test_vision_worker_killed_twice_the_stream_never_pauses(tmp_path: Path) -> None:
    """Issue 36: the navigator core and its vision worker, the worker killed (SIGKILL) twice while the
    vehicle flies on the daemon alone. The core keeps GPS_INPUT on its deadlines on the IMU (no interval
    over ArduPilot's 245 ms, no drop below 3D), restarts the worker, which starts from the core's filter;
    the flight meets issue 26's bounds with 0 beyond 3 sigma."""
    report, emu, _cli = _fly(tmp_path, REPO_ROOT / "sitl" / "scenarios" / "autopilot_worker_crash.yaml")
    kills = report["worker_kills"]
    assert len(kills) == 2, kills
    for kill in kills:
        assert kill["back_after_s"] is not None and kill["back_after_s"] <= 20.0, kill
        assert kill["prior_source"] == "core_handover", kill
        assert kill["max_interval_ms"] <= 245.0, kill
        assert kill["min_fix_type"] == 3, kill
    _issue_26_bounds(report, emu)
    iv = report["gnss_off"]["stream"]["interval_ms"]
    assert iv["max_ms"] <= 245.0, iv
    core_fdr = tmp_path / "work" / "fdr" / CORE_FDR_SUBDIR
    lost = [r for r in read_records(core_fdr) if r.get("kind") == FdrKind.CORE_WORKER]
    assert [r["event"] for r in lost].count("lost") == 2, lost
    assert all(r["exit"] == "SIGKILL" for r in lost if r["event"] == "lost"), lost
    texts = [t["text"] for t in report["statustext"]]
    assert sum(t.startswith("GDN: vision lost") for t in texts) == 2, texts
    assert sum(t.startswith("GDN: vision back") for t in texts) == 2, texts


#: After a kill -9 of the navigator core in flight, with two busy loops at nice 0 on the two cores,
#: GPS_INPUT back and a 3D fix within these of the kill, s. Issue 36 asks 2.0 s and 3.0 s of the real
#: ArduPilot, which logged 1.28-1.84 s and 2.28-2.74 s (docs/benchmarks.md, "A core crash"); this
#: emulator flight gave 1.69-1.70 s and 2.58-2.89 s on an Intel Xeon, so CI's machines get a quarter
#: more before a slower one fails it.
CORE_KILL_GPS_INPUT_BACK_MAX_S = 2.5
CORE_KILL_3D_BACK_MAX_S = 3.75


def test_a_core_killed_beside_two_busy_loops_is_back_within_the_bounds_and_adopts_its_worker(
    tmp_path: Path,
) -> None:
    """Issue 36: autopilot_restart, two busy processes at nice 0 for the whole flight (``cpu_hogs``), the
    navigator core killed (SIGKILL) in the GNSS-off stretch and started again after the unit's
    RestartSec=. The next core adopts the vision worker that ran on: GPS_INPUT is back and 3D soon after
    the kill (the bounds above), the mission is completed with no failsafe and nothing beyond 3 sigma."""
    report, emu, _cli = _fly(tmp_path, REPO_ROOT / "sitl" / "scenarios" / "autopilot_restart.yaml")
    (restart,) = report["daemon_restarts"]
    assert restart["worker_adopted"] is True, restart
    assert restart["first_after_s"] is not None and restart["first_3d_after_s"] is not None, restart
    assert restart["first_after_s"] <= CORE_KILL_GPS_INPUT_BACK_MAX_S, restart
    assert restart["first_3d_after_s"] <= CORE_KILL_3D_BACK_MAX_S, restart
    hogs = [f for f in report["faults_injected"] if f["kind"] == "cpu_hogs" and f["phase"] == "start"]
    assert hogs and len(hogs[0]["pids"]) == 2, report["faults_injected"]
    _issue_26_bounds(report, emu)


@pytest.mark.sitl
def test_home_off_the_map_is_refused_with_the_home_to_use(tmp_path: Path) -> None:
    """An autopilot whose home is off the map: exit 2, one line naming the map's extent and a --home."""
    cli = _sitl_against_emulator(tmp_path, SQUARE, "47.3977,8.5456,400,0", [], timeout_s=120)
    assert cli.returncode == 2, cli.stdout + cli.stderr
    err = cli.stderr.strip().splitlines()
    assert len(err) == 1 and "off the map" in err[0] and "--home 17." in err[0], cli.stderr
    assert "Traceback" not in cli.stderr
