"""F8 restart recovery through the whole loop: the daemon is killed with SIGKILL mid-flight and started
again with the same command. Its FDR opens cleanly, it resumes from its last 3D estimate with a sigma
that covers the time it was down, GPS_INPUT flows again quickly, and no fix_type 3 is ever beyond 3
sigma of the truth (issue 9, defect 2)."""

from __future__ import annotations

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
