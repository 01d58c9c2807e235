"""The autopilot's heading and height against what strong area fixes measured
(``c4_pose/heading_height_check.py``)."""

from __future__ import annotations

from gps_denied_onboard.components.c4_pose.heading_height_check import (
    HEADING_HEIGHT_MIN_SAMPLES,
    HeadingHeightCheck,
)
from gps_denied_onboard.components.c4_pose.integrity import AreaEvidence


def _ev(heading_deg: float, scale: float, psr: float = 20.0) -> AreaEvidence:
    return AreaEvidence(psr, 0.2, 0.3, 1.0, 0.2, 5.0, 0.04, 150.0, heading_deg, scale)


def test_a_steady_heading_error_is_found_once_the_window_holds_enough_strong_fixes() -> None:
    check = HeadingHeightCheck(full_evidence_psr=15.0)
    verdicts = [check.note(_ev(-3.0, 1.0)) for _ in range(HEADING_HEIGHT_MIN_SAMPLES)]
    assert all(v is not None and not v.heading_off for v in verdicts[:-1])
    last = verdicts[-1]
    assert last is not None and last.heading_off and not last.height_off
    assert last.heading_offset_deg == -3.0 and last.height_scale == 1.0


def test_weak_fixes_do_not_count_and_grid_quantisation_is_not_an_error() -> None:
    check = HeadingHeightCheck(full_evidence_psr=15.0)
    assert check.note(_ev(-4.0, 0.9, psr=10.0)) is None
    verdicts = [check.note(_ev(h, 1.02)) for h in (1.0, -1.0, 1.0, 0.0, 1.0, 1.0)]
    last = verdicts[-1]
    assert last is not None and not last.heading_off and not last.height_off


def test_a_height_off_by_five_percent_is_found_and_clears_when_it_agrees_again() -> None:
    check = HeadingHeightCheck(full_evidence_psr=15.0)
    for _ in range(HEADING_HEIGHT_MIN_SAMPLES):
        off = check.note(_ev(0.0, 0.95))
    assert off is not None and off.height_off
    for _ in range(15):
        back = check.note(_ev(0.0, 1.0))
    assert back is not None and not back.height_off
