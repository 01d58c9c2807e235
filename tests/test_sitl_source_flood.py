"""A flood of fresh UDP source addresses during a flight (issue 27: pymavlink's udpin kept every sender
forever and wrote every message to each; 20,000 of them took the daemon from 2 % to 32 % CPU and the
autopilot's GPS_INPUT from ~620 to 458 a minute)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from daemon_harness import fly_small_map
from gps_denied_onboard.sitl.runner import summary_lines
from gps_denied_onboard.sitl.scenario import BUILTIN_SCENARIOS_DIR

pytestmark = pytest.mark.sitl


def test_a_flood_of_source_addresses_leaves_the_stream_to_the_autopilot_steady(tmp_path: Path) -> None:
    """10,000 ground-station HEARTBEATs, each from a new source port, over 5 s of flight: the autopilot
    still gets its 10 Hz GPS_INPUT with the health rule's margins, and nothing is sent beyond 3 sigma."""
    smoke = yaml.safe_load((BUILTIN_SCENARIOS_DIR / "smoke.yaml").read_text())
    smoke.update(
        name="smoke_source_flood",
        faults=[{"kind": "source_flood", "from_s": 2.0, "to_s": 7.0, "rate_hz": 2000}],
    )
    scenario = tmp_path / "smoke_source_flood.yaml"
    scenario.write_text(yaml.safe_dump(smoke))
    report = fly_small_map(tmp_path, str(scenario))
    sent = [f["datagrams"] for f in report["faults_injected"] if f["kind"] == "source_flood"]
    assert sent and sent[0] >= 5000, report["faults_injected"]
    iv = report["stream"]["interval_ms"]
    assert iv["p99_ms"] <= 200.0, summary_lines(report)
    assert not report["stream"]["health"]["tripped"], report["stream"]
    assert report["consistency"]["beyond_3sigma"] == 0, summary_lines(report)
