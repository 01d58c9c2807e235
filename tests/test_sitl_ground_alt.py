"""The daemon checks its ground altitude against the autopilot's (issue 26: a driver that read it before
the EKF had an origin configured the daemon 520 m low, and nothing noticed)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from daemon_harness import fly_small_map
from gps_denied_onboard.components.c13_fdr import read_records
from gps_denied_onboard.constants import FdrKind
from gps_denied_onboard.sitl.scenario import BUILTIN_SCENARIOS_DIR

pytestmark = pytest.mark.sitl


def test_a_ground_altitude_off_the_autopilots_is_flagged_and_not_sent(tmp_path: Path) -> None:
    """The truth's ground (which the simulated autopilot reports as home) is at 60 m AMSL, far from the
    daemon's ``terrain.ground_alt_amsl_m``: the daemon records and says the disagreement, and GPS_INPUT
    flags its altitude as ignored rather than state one that far off."""
    smoke = yaml.safe_load((BUILTIN_SCENARIOS_DIR / "smoke.yaml").read_text())
    scenario = tmp_path / "smoke_ground_off.yaml"
    scenario.write_text(yaml.safe_dump({**smoke, "name": "smoke_ground_off", "ground_alt_amsl_m": 60.0}))
    report = fly_small_map(tmp_path, str(scenario))
    records = list(read_records(tmp_path / "work" / "fdr"))
    checks = [r for r in records if r.get("kind") == FdrKind.GROUND_ALT_CHECK]
    assert checks and checks[0]["disagrees"] is True, checks
    assert checks[0]["autopilot_ground_alt_amsl_m"] == pytest.approx(60.0, abs=1.0)
    assert checks[0]["difference_m"] == pytest.approx(checks[0]["daemon_ground_alt_amsl_m"] - 60.0, abs=1.0)
    texts = [s["text"] for s in report["statustext"]]
    assert any("ground alt" in t and "alt not sent" in t for t in texts), texts
    assert report["gps_input_received"] > 0
