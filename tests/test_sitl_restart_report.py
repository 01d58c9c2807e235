"""The SITL report's per-restart figures: when the restarted daemon was back on the air, and when it
re-anchored on the map (its first accepted absolute fix) after how many attempts."""

from __future__ import annotations

from typing import Any

from gps_denied_onboard.constants import FdrKind
from gps_denied_onboard.sitl.autopilot import ReceivedMessage
from gps_denied_onboard.sitl.report import restart_recovery

KILL_1, START_1 = 1000.0, 1000.1
KILL_2, START_2 = 1100.0, 1100.2


def _gps(t: float, fix_type: int) -> ReceivedMessage:
    return ReceivedMessage(t, "GPS_INPUT", {"fix_type": fix_type})


def _attempt(t: float, accepted: bool, match_ms: float = 900.0) -> dict[str, Any]:
    return {
        "t_unix_s": t,
        "kind": FdrKind.FIX,
        "fix_accepted": accepted,
        "timings_ms": {"vpr": 100.0, "rerank": 5.0, "match": match_ms, "estimator_fix": 50.0},
    }


RESTARTS = [
    {"killed_unix_s": KILL_1, "restarted_unix_s": START_1},
    {"killed_unix_s": KILL_2, "restarted_unix_s": START_2},
]


def test_restart_recovery_times_re_anchoring_from_the_new_process_start() -> None:
    """The first restart re-anchors on its third attempt; a fix fused before the kill, or after the next
    kill, is not its."""
    received = [_gps(999.9, 3), _gps(1002.0, 0), _gps(1010.0, 1), _gps(1021.0, 3), _gps(1101.0, 3)]
    records = [
        _attempt(999.0, True),  # the killed run's
        {"t_unix_s": 1003.0, "kind": FdrKind.PRIOR, "source": "map_extent", "sigma_m": 2955.8},
        _attempt(1008.1, False, match_ms=1895.0),
        _attempt(1014.1, False),
        _attempt(1020.1, True),
        _attempt(1024.0, True),
        _attempt(1105.0, True),  # the second restart's
    ]
    first, second = restart_recovery(RESTARTS, received, records)
    assert first["first_after_s"] == 2.0 and first["first_3d_after_s"] == 21.0
    assert first["first_after_start_s"] == 1.9 and first["first_3d_after_start_s"] == 20.9
    assert (first["prior_source"], first["prior_sigma_m"]) == ("map_extent", 2955.8)
    assert first["first_anchored_after_start_s"] == 20.0
    assert first["fix_attempts_to_anchor"] == 3 and first["fix_attempts"] == 4
    assert first["fix_attempt_ms"] == {"p50": 1005.0, "max": 2000.0}  # up to the anchoring one
    assert first["last_before_kill_s"] == -0.1
    assert second["fix_attempts_to_anchor"] == 1 and second["first_anchored_after_start_s"] == 4.8
    assert second["prior_source"] is None


def test_restart_recovery_without_records_or_anchor_says_none() -> None:
    """Nothing recorded (the FDR's disk full) or never re-anchored: None, not zero."""
    received = [_gps(1001.0, 0)]
    (blind,) = restart_recovery(RESTARTS[:1], received, [])
    assert blind["fix_attempts"] is None and blind["first_anchored_after_start_s"] is None
    assert blind["first_3d_after_start_s"] is None and blind["first_after_start_s"] == 0.9
    (lost,) = restart_recovery(RESTARTS[:1], received, [_attempt(1005.0, False), _attempt(1009.0, False)])
    assert lost["fix_attempts"] == 2 and lost["fix_attempts_to_anchor"] is None
    assert lost["fix_attempt_ms"]["max"] == 1005.0
