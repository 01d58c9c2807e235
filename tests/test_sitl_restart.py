"""F8 restart recovery through the whole loop: the daemon is killed with SIGKILL mid-flight and started
again with the same command. Its FDR opens cleanly, it resumes from its last 3D estimate with a sigma
that covers the time it was down, GPS_INPUT flows again quickly, and no fix_type 3 is ever beyond 3
sigma of the truth (issue 9, defect 2)."""

from __future__ import annotations

import json
from datetime import datetime
from pathlib import Path

import pytest

from daemon_harness import fly_small_map
from gps_denied_onboard.components.c13_fdr import read_records
from gps_denied_onboard.sitl.runner import summary_lines

pytestmark = [pytest.mark.sitl, pytest.mark.slow]


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> dict:
    root = tmp_path_factory.mktemp("restart")
    return fly_small_map(root, "restart")


def test_restarted_daemon_resumes_from_its_fdr_with_an_honest_sigma(flight: dict) -> None:
    """The second run starts from the first run's last 3D estimate, its sigma grown by the time since;
    nothing the first run recorded is lost (the kill may tear at most the line being written)."""
    records = list(read_records(Path(flight["fdr_dir"])))
    priors = [r for r in records if r["kind"] == "estimator.prior"]
    assert [p["source"] for p in priors] == ["home_position", "fdr_resume"], priors
    assert priors[1]["sigma_m"] > 10.0, priors[1]  # >= 25 m/s x the seconds it was down
    restart = flight["daemon_restarts"][0]
    kill_s = restart["killed_unix_s"]
    before = [r for r in records if r["kind"] == "pipeline.frame" and r["t_unix_s"] < kill_s]
    assert len(before) >= 3 * 14 - 2, len(before)  # ~3 Hz for the 15 s before the kill


def test_gps_input_flows_again_soon_after_the_restart(flight: dict) -> None:
    """GPS_INPUT is back within the daemon's start-up time, and a 3D fix within 2 s of the new run's
    first frame."""
    restart = flight["daemon_restarts"][0]
    records = list(read_records(Path(flight["fdr_dir"])))
    first_frame = min(
        r["t_unix_s"]
        for r in records
        if r["kind"] == "pipeline.frame" and r["t_unix_s"] > restart["restarted_unix_s"]
    )
    assert restart["first_after_s"] is not None and restart["first_3d_after_s"] is not None, restart
    assert restart["killed_unix_s"] + restart["first_3d_after_s"] <= first_frame + 2.0, restart


def test_no_confident_lie_across_the_restart(flight: dict) -> None:
    """No GPS_INPUT with fix_type 3 beyond 3 sigma of the truth, before, across or after the restart."""
    assert flight["consistency"]["beyond_3sigma"] == 0, flight["consistency"]
    assert flight["horizontal_error_m"]["p95"] <= 2.0, summary_lines(flight)
    assert flight["daemon_exit_code"] == 0


#: Issue 27, item 5: after a kill -9, GPS_INPUT again within this long of the new process's start (the
#: start-up beacon's, fix_type 0, before the fix path has loaded), and an honest 3D fix within this long,
#: s. Bounds for a loaded 2-core CI machine; measured figures are in docs/benchmarks.md ("Restart in
#: flight"). The unit's RestartSec= (0.2 s) comes before them.
FIRST_GPS_INPUT_AFTER_START_MAX_S = 2.0
FIRST_3D_AFTER_START_MAX_S = 4.5
#: ArduPilot declares NO_FIX this long after the last GPS_INPUT, s.
ARDUPILOT_NO_FIX_S = 4.0
#: The daemon's start-up milestones in its log, in order.
_MILESTONES = (
    "daemon.config",
    "daemon.beacon_started",
    "daemon.ready",
    "c8.mavlink.autopilot_address",
    "c5.estimator.prior",
)


def _restart_sec_s() -> float:
    unit = (Path(__file__).resolve().parents[1] / "systemd" / "gdnav.service").read_text()
    (value,) = [line.split("=", 1)[1] for line in unit.splitlines() if line.startswith("RestartSec=")]
    return float(value.rstrip("s"))


def _milestones_after(log_path: Path, start_unix_s: float) -> dict[str, float]:
    """Seconds from ``start_unix_s`` to the first of each ``_MILESTONES`` event logged after it."""
    out: dict[str, float] = {}
    for line in log_path.read_text(errors="replace").splitlines():
        try:
            rec = json.loads(line)
            t = datetime.fromisoformat(rec["timestamp"].replace("Z", "+00:00")).timestamp()
        except (ValueError, KeyError, TypeError, AttributeError):
            continue
        if rec.get("event") in _MILESTONES and t >= start_unix_s and rec["event"] not in out:
            out[rec["event"]] = round(t - start_unix_s, 3)
    return out


def test_back_on_the_air_within_the_no_fix_limit(flight: dict) -> None:
    """Issue 27, item 5: GPS_INPUT and a 3D fix soon after the restarted process's start (the bounds
    above); with the unit's RestartSec= before it, GPS_INPUT is back before ArduPilot's 4 s NO_FIX."""
    restart = flight["daemon_restarts"][0]
    spawn_s = restart["restarted_unix_s"] - restart["killed_unix_s"]
    first_s = restart["first_after_s"] - spawn_s
    first_3d_s = restart["first_3d_after_s"] - spawn_s
    steps = _milestones_after(Path(flight["daemon_log"]), restart["restarted_unix_s"])
    print(
        f"\nrestart: process start {spawn_s:.3f} s after the kill; after the start: {steps}, "
        f"first GPS_INPUT {first_s:.3f} s, first 3D {first_3d_s:.3f} s; under the unit (RestartSec="
        f"{_restart_sec_s():g}): GPS_INPUT {_restart_sec_s() + first_s:.3f} s and 3D "
        f"{_restart_sec_s() + first_3d_s:.3f} s after the kill"
    )
    assert first_s <= FIRST_GPS_INPUT_AFTER_START_MAX_S, (restart, steps)
    # The beacon speaks before the fix path has loaded, not after.
    assert first_s < steps["daemon.ready"], (restart, steps)
    assert first_3d_s <= FIRST_3D_AFTER_START_MAX_S, (restart, steps)
    assert _restart_sec_s() + first_s < ARDUPILOT_NO_FIX_S, (restart, steps)
