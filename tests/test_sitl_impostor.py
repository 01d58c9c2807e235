"""An impostor with the autopilot's system and component ids, from another UDP source port, during a
flight (issue 36: in two hostile flights the daemon's output followed one, and the autopilot got no
GPS_INPUT for 19.9 s and 35.8 s and failed safe). Real daemon process, real pymavlink over loopback UDP."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from daemon_harness import fly_small_map
from gps_denied_onboard.components.c13_fdr import read_records
from gps_denied_onboard.constants import CORE_FDR_SUBDIR, LINK_EVENT_IMPOSTOR, FdrKind
from gps_denied_onboard.sitl.ardupilot_rules import HEALTH_DELAYED_INTERVAL_MS
from gps_denied_onboard.sitl.runner import summary_lines
from gps_denied_onboard.sitl.scenario import BUILTIN_SCENARIOS_DIR

pytestmark = pytest.mark.sitl


def test_an_impostor_with_the_autopilots_ids_never_pauses_its_gps_input(tmp_path: Path) -> None:
    """HEARTBEAT, NaN/huge/out-of-order ATTITUDE, SYSTEM_TIME going back and TIMESYNC requests with the
    autopilot's ids from another port, 500 a second over 6 s of flight: the autopilot's GPS_INPUT never
    pauses more than 245 ms (ArduPilot's delayed-interval rule), nothing reaches the impostor, nothing is
    sent beyond 3 sigma, and the daemon counts the impostor and reports it (FDR, status)."""
    smoke = yaml.safe_load((BUILTIN_SCENARIOS_DIR / "smoke.yaml").read_text())
    smoke.update(
        name="smoke_impostor",
        faults=[{"kind": "impostor", "from_s": 1.5, "to_s": 7.5, "rate_hz": 500}],
    )
    scenario = tmp_path / "smoke_impostor.yaml"
    scenario.write_text(yaml.safe_dump(smoke))
    report = fly_small_map(tmp_path, str(scenario))
    injected = [f for f in report["faults_injected"] if f["kind"] == "impostor"]
    assert injected and injected[0]["messages"] >= 2000, report["faults_injected"]
    assert injected[0]["received_datagrams"] == 0, injected
    iv = report["stream"]["interval_ms"]
    print(f"impostor: {injected[0]['messages']} msgs; GPS_INPUT p99 {iv['p99_ms']} ms, max {iv['max_ms']} ms")
    assert iv["max_ms"] <= HEALTH_DELAYED_INTERVAL_MS == 245, summary_lines(report)
    assert not report["stream"]["health"]["tripped"], report["stream"]
    assert report["consistency"]["beyond_3sigma"] == 0, summary_lines(report)
    # the navigator core holds the autopilot's link: its records say what it refused
    records = list(read_records(tmp_path / "work" / "fdr" / CORE_FDR_SUBDIR))
    events = [r.get("event") for r in records if r["kind"] == FdrKind.LINK_EVENT]
    assert LINK_EVENT_IMPOSTOR in events, "no impostor report in the FDR"
    status = [r for r in records if r["kind"] == FdrKind.CORE_STATUS]
    assert max(r["mavlink_impostor_messages"] for r in status) >= 1000
