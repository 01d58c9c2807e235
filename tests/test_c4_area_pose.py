"""C4 for an area alignment (``c4_pose/area_pose.py``) and the integrity rule on its evidence
(``c4_pose/integrity.py``): the pose, the error budget it states, and when the correlation's evidence
refuses it."""

from __future__ import annotations

import dataclasses
import math
import time
import uuid

import numpy as np
import pytest

from gps_denied_onboard.camera.types import Attitude, FrameTiming, NavCameraFrame
from gps_denied_onboard.components.c3_matcher.types import AreaAlignment, CandidateMatchSet
from gps_denied_onboard.components.c4_pose.area_pose import ALIGNMENT_SIGMA_PX, AreaPoseSolver
from gps_denied_onboard.components.c4_pose.integrity import CandidateFix, FixIntegrity, evidence_of
from gps_denied_onboard.components.c4_pose.types import PoseError
from gps_denied_onboard.components.c6_tiles.types import TileId
from gps_denied_onboard.config import IntegrityConfig, PoseConfig
from gps_denied_onboard.constants import IntegrityReason
from gps_denied_onboard.geo import LocalTangentPlane, haversine_m

LAT, LON, GROUND = 47.02, -99.15, 400.0
LTP = LocalTangentPlane(LAT, LON, GROUND)
GSD = 3.26


def _area(**changes: float) -> AreaAlignment:
    base = AreaAlignment(
        nadir_lat_deg=LAT + 0.001,
        nadir_lon_deg=LON - 0.002,
        heading_offset_rad=math.radians(-2.0),
        heading_step_rad=math.radians(1.0),
        height_scale=0.98,
        height_scale_step=0.02,
        map_gsd_m_px=GSD,
        peak=0.16,
        psr=16.0,
        secondary_ratio=0.3,
        coverage=1.0,
        texture=0.2,
        radius_m=150.0,
        hypotheses_tried=15,
        null_psr=5.0,
        null_peak=0.045,
    )
    return dataclasses.replace(base, **changes)


def _candidate(area: AreaAlignment) -> CandidateMatchSet:
    return CandidateMatchSet(TileId.of(15, LAT, LON), 0, np.empty((0, 4), np.float32), 0, math.nan, area=area)


def _frame(alt: float = 1200.0, timing: FrameTiming | None = None) -> NavCameraFrame:
    return NavCameraFrame(
        uuid.uuid4(), 1, 1_800_000_000_000_000, np.zeros((480, 640, 3), np.uint8),
        Attitude(0.01, -0.02, math.radians(30.0)), alt, time.monotonic_ns(), timing=timing,
    )  # fmt: skip


def test_the_fix_is_the_aligned_nadir_at_the_measured_height_with_the_measured_heading() -> None:
    fix = AreaPoseSolver(PoseConfig(), LTP, GROUND).solve(_frame(), _candidate(_area()))
    assert (fix.lat_deg, fix.lon_deg) == (LAT + 0.001, LON - 0.002)
    assert fix.alt_amsl_m == pytest.approx(GROUND + 1200.0 * 0.98)
    assert math.degrees(fix.yaw_rad) == pytest.approx(28.0)
    lat, lon, _ = LTP.to_geodetic(fix.pos_ned_m)
    assert haversine_m(float(lat), float(lon), fix.lat_deg, fix.lon_deg) < 1e-3
    # It measured no tilt of its own: nothing for the tilt checks.
    assert fix.attitude_disagreement_rad is None and fix.image_tilt_off_cam_rad is None


def test_the_error_budget_is_tilt_times_height_registration_and_alignment() -> None:
    cfg = PoseConfig(attitude_sigma_deg=0.5, min_sigma_m=1.0)
    fix = AreaPoseSolver(cfg, LTP, GROUND).solve(_frame(), _candidate(_area(height_scale=1.0)))
    tilt = 1200.0 * math.tan(math.radians(0.5))
    expected = math.sqrt(tilt**2 + 1.0 + (ALIGNMENT_SIGMA_PX * GSD) ** 2)
    assert math.sqrt(fix.cov_ned_m2[0, 0]) == pytest.approx(expected)
    assert fix.shared_sigma_m == pytest.approx(math.hypot(tilt, 1.0))
    # The frame's timing doubt of the attitude adds to the tilt; at 100 m it all shrinks with height.
    timing = FrameTiming((0.0, 0.0), 0.0, 0.05, ahrs_sigma_rad=math.radians(0.5))
    timed = AreaPoseSolver(cfg, LTP, GROUND).solve(_frame(timing=timing), _candidate(_area(height_scale=1.0)))
    tilt_timed = 1200.0 * math.tan(math.radians(math.hypot(0.5, 0.5)))
    assert timed.shared_sigma_m == pytest.approx(math.hypot(tilt_timed, 1.0))
    low = AreaPoseSolver(cfg, LTP, GROUND).solve(_frame(alt=100.0), _candidate(_area(height_scale=1.0)))
    assert low.horiz_sigma_m < fix.horiz_sigma_m / 5


def test_a_measured_height_far_from_the_autopilots_is_no_fix() -> None:
    with pytest.raises(PoseError) as excinfo:
        AreaPoseSolver(PoseConfig(max_alt_disagreement_frac=0.2), LTP, GROUND).solve(
            _frame(), _candidate(_area(height_scale=0.7))
        )
    assert excinfo.value.reason == "altitude_disagreement"


def _assess(area: AreaAlignment, cfg: IntegrityConfig = IntegrityConfig()) -> object:
    fix = AreaPoseSolver(PoseConfig(), LTP, GROUND).solve(_frame(), _candidate(area))
    evidence = evidence_of(_candidate(area), (640, 480))
    return FixIntegrity(cfg).assess(CandidateFix(fix, evidence), map_gsd_m_px=GSD)


@pytest.mark.parametrize(
    ("changes", "reason"),
    [
        ({"psr": 7.9}, IntegrityReason.LOW_PSR),  # below the floor (8)
        ({"psr": 9.0, "null_psr": 6.5}, IntegrityReason.LOW_PSR),  # below 1.5 x this map's wrong places
        ({"peak": 0.05}, IntegrityReason.LOW_PEAK),  # below the floor (0.06)
        ({"peak": 0.12, "null_peak": 0.07}, IntegrityReason.LOW_PEAK),  # below 2 x this map's wrong places
        ({"secondary_ratio": 0.85}, IntegrityReason.AMBIGUOUS_PEAK),
        # close enough to the map for its patches to be tried, but they do not fall into place (a tilt fault)
        ({"patches_tried": 43, "patches_agreeing": 23}, IntegrityReason.PATCHES_DISAGREE),
    ],
)
def test_weak_or_ambiguous_correlation_evidence_refuses_the_fix(changes: dict, reason: str) -> None:
    verdict = _assess(_area(**changes))
    assert not verdict.accepted and verdict.reason == reason  # type: ignore[attr-defined]


def test_a_weaker_peak_inflates_only_the_alignments_own_error() -> None:
    strong = _assess(_area(psr=20.0, peak=0.2))
    weak = _assess(_area(psr=10.0, peak=0.1))  # k = 1.5 x 1.5
    assert strong.accepted and weak.accepted  # type: ignore[attr-defined]
    assert weak.sigma_scale == pytest.approx(2.25)  # type: ignore[attr-defined]
    shared = strong.fix.shared_sigma_m  # type: ignore[attr-defined]
    assert weak.fix.shared_sigma_m == pytest.approx(shared)  # type: ignore[attr-defined]
    own = math.sqrt(strong.fix.cov_ned_m2[0, 0] - shared**2)  # type: ignore[attr-defined]
    weak_own = math.sqrt(weak.fix.cov_ned_m2[0, 0] - shared**2)  # type: ignore[attr-defined]
    assert weak_own == pytest.approx(2.25 * own)
    # The shared part is floored at the map's pixel: the map's georeference is common to every fix.
    assert shared >= GSD
