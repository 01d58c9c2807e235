"""The per-frame pipeline: search region choice (prior-gated vs F6 corpus-wide) and no-fix reasons.

Fakes stand in for C1/C2/C2.5/C3/C4 at their component boundaries; the estimator is the real one.
"""

from __future__ import annotations

import math
import uuid
from dataclasses import dataclass, field, replace

import numpy as np
import pytest

from gps_denied_onboard.camera.types import (
    Attitude,
    CameraCalibration,
    CameraMount,
    FrameTiming,
    NavCameraFrame,
)
from gps_denied_onboard.components.c1_vio.types import VoError, VoMotion
from gps_denied_onboard.components.c2_5_rerank.types import RerankResult
from gps_denied_onboard.components.c2_vpr.protocol import SearchRegion
from gps_denied_onboard.components.c2_vpr.types import VprCandidate, VprQuery, VprResult
from gps_denied_onboard.components.c3_matcher.errors import InsufficientInliersError
from gps_denied_onboard.components.c3_matcher.ladder import EffortLadder
from gps_denied_onboard.components.c3_matcher.types import CandidateMatchSet, MatchResult
from gps_denied_onboard.components.c4_pose.attitude_check import MIN_FIXES, AttitudeCheck, AttitudeVerdict
from gps_denied_onboard.components.c4_pose.consistency import FixConsistency
from gps_denied_onboard.components.c4_pose.integrity import FixIntegrity
from gps_denied_onboard.components.c4_pose.types import PoseError, PoseFix
from gps_denied_onboard.components.c5_estimator import NavEstimator, TimeAxis
from gps_denied_onboard.components.c6_tiles.types import TileId
from gps_denied_onboard.config import EstimatorConfig, IntegrityConfig, PoseConfig, VprConfig
from gps_denied_onboard.constants import Provenance
from gps_denied_onboard.geo import LocalTangentPlane, haversine_m
from gps_denied_onboard.pipeline import (
    MAX_CANDIDATES,
    TILT_JUMP_IMU_HOLD_S,
    InitialPrior,
    NavigationPipeline,
)

LTP = LocalTangentPlane(47.0, 8.0, 400.0)
T0 = 1_700_000_000_000_000


class _NoVo:
    def process(self, frame: NavCameraFrame) -> None:
        raise VoError("no motion in a unit test", reason="test")


@dataclass
class _Vpr:
    dim: int
    regions: list[SearchRegion | None] = field(default_factory=list)

    def descriptor_dim(self) -> int:
        return self.dim

    def embed_query(self, frame, calibration):  # type: ignore[no-untyped-def]
        return VprQuery(frame.frame_id, np.zeros(self.dim, np.float32), 0)

    def retrieve_topk(self, query, k, *, region=None):  # type: ignore[no-untyped-def]
        self.regions.append(region)
        return VprResult(query.frame_id, [], 0, "fake")


class _Unused:
    def rerank(self, frame, vpr_result):  # type: ignore[no-untyped-def]
        return RerankResult(frame.frame_id, [], 0)

    def match(self, frame, rerank_result, calibration):  # type: ignore[no-untyped-def]
        raise InsufficientInliersError(
            "none",
            frame_id=frame.frame_id,
            best_inlier_count=0,
            threshold=25,
            candidates_input=0,
            candidates_dropped=0,
        )


class _Fdr:
    def __init__(self) -> None:
        self.records: list[tuple[str, dict]] = []

    def record(self, kind, fields):  # type: ignore[no-untyped-def]
        self.records.append((kind, dict(fields)))


class _HoverVo:
    """VO of a hovering vehicle: no motion, 0.3 m sigma, every frame."""

    def process(self, frame: NavCameraFrame) -> VoMotion:
        return VoMotion(frame.frame_id, uuid.uuid4(), 1 / 3, np.zeros(2), np.eye(2) * 0.09, 200)


@dataclass
class _TiltedVo:
    """VO of a hovering vehicle whose ground tilt (``VoMotion.ground_tilt_off_cam_rad``) is
    ``tilt_off_rad`` on the camera's x axis from the autopilot's."""

    tilt_off_rad: float | None  # None: the pair gives no ground tilt (too short a baseline)
    #: What the wrong tilt makes VO measure: metres north a frame while the vehicle hovers.
    north_m_per_frame: float = 0.0

    def process(self, frame: NavCameraFrame) -> VoMotion:
        delta = np.array([self.north_m_per_frame, 0.0])
        tilt = None if self.tilt_off_rad is None else (self.tilt_off_rad, 0.0)
        return VoMotion(frame.frame_id, uuid.uuid4(), 1 / 3, delta, np.eye(2) * 0.09, 200, tilt)


def _pipeline(
    vpr: _Vpr,
    fdr: _Fdr,
    vo: object | None = None,
    mount: CameraMount | None = None,
    max_delay_s: float = 5.0,
    clock_unix_usec: object = None,
    map_extent: tuple[float, float, float] | None = None,
) -> NavigationPipeline:
    calib = CameraCalibration.from_hfov(640, 480, 70.0)
    return NavigationPipeline(
        calibration=calib,
        ltp=LTP,
        ground_alt_amsl_m=400.0,
        vo=vo or _NoVo(),
        vpr=vpr,
        vpr_config=VprConfig(corpus_wide_sigma_m=300.0),
        rerank=_Unused(),
        matcher=_Unused(),  # type: ignore[arg-type]
        pose_solver=None,
        time_axis=TimeAxis(
            NavEstimator(EstimatorConfig(), LTP),
            max_delay_s=max_delay_s,
            max_frame_age_s=1.0,
            clock_unix_usec=clock_unix_usec or (lambda: T0),  # type: ignore[arg-type]
        ),
        fdr=fdr,
        integrity=FixIntegrity(IntegrityConfig()),
        consistency=FixConsistency(IntegrityConfig()),
        attitude_check=AttitudeCheck(PoseConfig()),
        ground_tilt_check=AttitudeCheck(PoseConfig(), samples=24, max_age_s=10.0, ground_correlated=False),
        mount=mount,
        attitude_sigma_deg=PoseConfig().attitude_sigma_deg,
        map_extent=map_extent,
    )


def _frame(seq: int, t_us: int) -> NavCameraFrame:
    return NavCameraFrame(
        uuid.uuid4(), seq, t_us, np.zeros((480, 640, 3), np.uint8), Attitude(0, 0, 0), 120.0, 0
    )


def test_pipeline_searches_prior_region_when_uncertainty_is_small() -> None:
    """With a 30 m prior the VPR search is gated to a region around the estimate."""
    vpr, fdr = _Vpr(dim=256), _Fdr()
    p = _pipeline(vpr, fdr)
    out = p.process(_frame(0, T0), InitialPrior(47.0, 8.0, 30.0, "test"))
    assert isinstance(vpr.regions[0], SearchRegion)
    assert 60.0 <= vpr.regions[0].radius_m <= 2000.0
    assert out.no_fix_reason == "no_tiles_in_region"
    kinds = [(kind, fields["frame_seq"]) for kind, fields in fdr.records]
    assert kinds == [("pipeline.frame", 0), ("pipeline.fix", 0)]
    assert fdr.records[-1][1]["no_fix_reason"] == "no_tiles_in_region"


def test_pipeline_goes_corpus_wide_when_uncertainty_is_large() -> None:
    """F6: with a 500 m prior and an appearance strategy, the search is corpus-wide (region None)."""
    vpr = _Vpr(dim=256)
    p = _pipeline(vpr, _Fdr())
    p.process(_frame(0, T0), InitialPrior(47.0, 8.0, 500.0, "test"))
    assert vpr.regions == [None]


@pytest.mark.parametrize("sigma_m", [500.0, 3000.0])
def test_over_a_mission_area_a_wide_state_sweeps_the_region_it_can_be_in(sigma_m: float) -> None:
    """Past the corpus-wide sigma over a map much larger than the state's region (a 50 km mission area),
    the attempts sweep that region (3 sigma and the half-footprint, not clamped), ranked by the
    strategy, rather than the whole map: the map is hours of attempts, the region minutes."""
    vpr = _Vpr(dim=256)
    p = _pipeline(vpr, _Fdr(), map_extent=(47.0, 8.0, 35_000.0))
    for k in range(3):
        p.process(_frame(k, T0 + k * 333_333), InitialPrior(47.0, 8.0, sigma_m, "test") if k == 0 else None)
    assert all(isinstance(r, SearchRegion) for r in vpr.regions), vpr.regions
    radius = vpr.regions[0].radius_m
    assert radius == pytest.approx(3 * sigma_m + 120.0 * np.tan(np.radians(35.0)), rel=0.05)
    assert p._search_mode == "reach"


def test_a_wide_state_whose_region_holds_the_whole_map_searches_it_corpus_wide() -> None:
    """The same state over a map its region covers (2 km across): corpus-wide (F6), as before."""
    vpr = _Vpr(dim=256)
    p = _pipeline(vpr, _Fdr(), map_extent=(47.0, 8.0, 1000.0))
    p.process(_frame(0, T0), InitialPrior(47.0, 8.0, 500.0, "test"))
    assert vpr.regions == [None]


def test_pipeline_geo_prior_never_searches_corpus_wide() -> None:
    """A strategy with no appearance index keeps a region (3 sigma + half footprint) with a 500 m prior."""
    vpr = _Vpr(dim=0)
    p = _pipeline(vpr, _Fdr())
    p.process(_frame(0, T0), InitialPrior(47.0, 8.0, 500.0, "test"))
    region = vpr.regions[0]
    assert isinstance(region, SearchRegion)
    assert region.radius_m == pytest.approx(3 * 500.0 + 120.0 * np.tan(np.radians(35.0)), rel=1e-3)


def test_pipeline_without_attitude_makes_no_fix_and_says_why() -> None:
    """A frame without attitude/altitude produces no absolute fix; the reason is recorded."""
    vpr, fdr = _Vpr(dim=256), _Fdr()
    p = _pipeline(vpr, fdr)
    frame = NavCameraFrame(uuid.uuid4(), 3, T0, np.zeros((480, 640, 3), np.uint8), None, None, 0)
    out = p.process(frame, InitialPrior(47.0, 8.0, 30.0, "test"))
    assert vpr.regions == [] and out.no_fix_reason == "no_attitude_or_altitude"
    assert out.provenance in (Provenance.DEAD_RECKONING, Provenance.NO_ESTIMATE)


def test_pipeline_localises_an_older_frame_at_its_exposure_time() -> None:
    """The fix half runs behind the track half: localising frame 0 after frames 1..3 were tracked is
    recorded with how far behind the newest input it was fused, and does not move the clock back."""
    vpr, fdr = _Vpr(dim=256), _Fdr()
    p = _pipeline(vpr, fdr, _HoverVo())
    frames = [_frame(k, T0 - 1_000_000 + k * 333_333) for k in range(4)]
    for f in frames:
        p.track(f, InitialPrior(47.0, 8.0, 30.0, "test"))
    out = p.localise(frames[0])
    assert out.fused_behind_s == pytest.approx(1.0, abs=1e-3)
    fix_record = fdr.records[-1]
    assert fix_record[0] == "pipeline.fix" and fix_record[1]["fused_behind_s"] == pytest.approx(1.0, abs=1e-3)
    assert p.time_axis.head_unix_usec == frames[-1].exposure_time_unix_usec
    assert p.time_axis.stats().rewinds == 1


class _Handle:
    gsd_m_px = 0.3


@dataclass
class _Cand:
    tile_id: TileId
    tile_pixels_handle: _Handle = field(default_factory=_Handle)


class _OneTileVpr(_Vpr):
    def retrieve_topk(self, query, k, *, region=None):  # type: ignore[no-untyped-def]
        return VprResult(query.frame_id, [object()], 0, "fake")  # type: ignore[list-item]


class _TwoTiles:
    """Rerank + matcher double: two candidate tiles, matched with ``inliers`` each."""

    def __init__(self, inliers: tuple[int, int]) -> None:
        self.inliers = inliers

    def rerank(self, frame, vpr_result):  # type: ignore[no-untyped-def]
        return RerankResult(frame.frame_id, [_Cand(TILE_A), _Cand(TILE_B)], 0)  # type: ignore[list-item]

    def match(self, frame, rerank_result, calibration):  # type: ignore[no-untyped-def]
        rng = np.random.default_rng(0)
        sets = []
        for tile, n in zip((TILE_A, TILE_B), self.inliers, strict=True):
            q = rng.uniform((0, 0), (640, 480), size=(n, 2))
            sets.append(CandidateMatchSet(tile, n, np.hstack([q, q]).astype(np.float32), n // 4, 0.8))
        return MatchResult(frame.frame_id, sets, 0, 0.8, 0, "fake")


class _PosePerTile:
    """C4 double: tile A solves to the prior's position, tile B 80 m north of it (1 m sigma); the
    image-only tilt is ``tilt_off_rad`` (camera x) from the autopilot's. A solve that allows the
    autopilot's tilt an error (``attitude_doubt_rad`` > 0) stands on the image's own tilt, which pins
    it here: tile A then solves to the truth (0 m north) however wrong the autopilot's tilt is."""

    def __init__(self, tilt_off_rad: float = 0.02) -> None:
        self.tilt_off_rad = tilt_off_rad
        self.north_m = 0.0  # where tile A solves to leaning on the autopilot's tilt (off by a wrong one)
        self.solvable = True  # False: every solve fails (no pose from this frame)
        self.doubts_rad: list[float] = []  # what each solve was asked to allow the autopilot's tilt

    def solve(self, frame, candidate, handle, calibration, *, attitude_doubt_rad=0.0):  # type: ignore[no-untyped-def]
        self.doubts_rad.append(attitude_doubt_rad)
        if not self.solvable:
            raise PoseError("no pose", reason="degenerate_geometry", frame_id=frame.frame_id)
        north = (0.0 if attitude_doubt_rad > 0.0 else self.north_m) if candidate.tile_id == TILE_A else 80.0
        return PoseFix(
            frame.frame_id,
            frame.exposure_time_unix_usec,
            np.array([north, 0.0, -120.0]),
            np.eye(3),
            47.0,
            8.0,
            520.0,
            0.0,
            0.01,
            abs(self.tilt_off_rad),
            (self.tilt_off_rad, 0.0),
            candidate.inlier_count,
            0.8,
            candidate.tile_id,
            1.0,
            attitude_doubt_rad,
        )


TILE_A, TILE_B = TileId(18, 1, 1), TileId(18, 1, 2)


def _two_tile_pipeline(
    fdr: _Fdr, vo: object, pose: _PosePerTile, inliers: tuple[int, int] = (200, 40), max_delay_s: float = 5.0
) -> NavigationPipeline:
    """A pipeline whose fix path always solves: one VPR candidate, tiles A and B matched with
    ``inliers`` (``_TwoTiles``), posed by ``pose``."""
    fakes = _TwoTiles(inliers)
    p = _pipeline(_OneTileVpr(dim=256), fdr, vo, max_delay_s=max_delay_s)
    p._rerank = fakes  # type: ignore[assignment]
    p._ladder = EffortLadder.single("fake", fakes, MAX_CANDIDATES)  # type: ignore[arg-type]
    p._pose = pose  # type: ignore[assignment]
    return p


@pytest.mark.parametrize(("inliers", "accepted"), [((200, 180), False), ((200, 40), True)])
def test_pipeline_refuses_an_ambiguous_fix_and_records_the_evidence(
    inliers: tuple[int, int], accepted: bool
) -> None:
    """Two well-supported tiles 80 m apart: the integrity rule refuses the fix, C5 never sees it, the FDR
    says why with the evidence. With a weak second tile the same fix is fused."""
    fdr = _Fdr()
    p = _two_tile_pipeline(fdr, _HoverVo(), _PosePerTile(), inliers=inliers)
    frame = _frame(0, T0)
    p.track(frame, InitialPrior(47.0, 8.0, 30.0, "test"))
    out = p.localise(frame)
    record = fdr.records[-1][1]
    assert out.fix_accepted is accepted and record["fix_accepted"] is accepted
    assert record["fix_image_tilt_off_deg"] == pytest.approx(1.146)  # the image-only axis vs the autopilot's
    if accepted:  # a tile with 40 of the best's 200 inliers is no rival: its pose is not even solved
        assert record["integrity"]["rival_inliers"] is None
        assert out.no_fix_reason is None and record["integrity"]["reason"] is None
        assert np.isfinite(p.time_axis.state_at(T0).last_fix_age_s)
    else:
        assert record["integrity"]["rival_inliers"] == inliers[1]
        assert record["integrity"]["rival_distance_m"] == pytest.approx(80.0, abs=0.5)
        assert out.no_fix_reason == "integrity:ambiguous_candidates"
        assert record["integrity"]["reason"] == "ambiguous_candidates" and out.integrity is not None
        assert p.time_axis.state_at(T0).last_fix_age_s == float("inf")


@pytest.mark.parametrize(
    ("timing", "proven"),
    [
        (FrameTiming((0.0, 0.0), 0.0, 0.01, math.radians(3.0)), False),  # just after a manoeuvre
        (FrameTiming((math.radians(40.0), 0.0), 0.0, 0.1, 0.0), False),  # pitching over, timing unsure
        (FrameTiming((0.0, 0.0), 0.0, 0.01, 0.0), True),  # steady: the check judges
    ],
)
def test_pipeline_compares_tilts_only_when_the_frame_can_tell(timing: FrameTiming, proven: bool) -> None:
    """Every fix's image-only tilt is 3 deg from the autopilot's. While the frame's own doubt of the
    autopilot's tilt (its AHRS after a manoeuvre, timing at a fast pitch-over) is beyond half the
    attitude's sigma, the tilt is no evidence: the fixes are solved and fused as usual (issue 26: a real
    copter's AHRS strayed 2.5-3.4 deg at the legs' ends and right fixes were refused until the EKF
    failed safe). In steady flight the same 3 deg is proven off, and each fix from then on is solved
    again allowing the autopilot's tilt that error (1.5 x the bound shown): it stands on the image."""
    fdr = _Fdr()
    pose = _PosePerTile(tilt_off_rad=math.radians(3.0))
    p = _two_tile_pipeline(fdr, _HoverVo(), pose)
    outs = []
    for k in range(6):
        frame = replace(_frame(k, T0 - (5 - k) * 333_333), timing=timing)
        p.track(frame, InitialPrior(47.0, 8.0, 30.0, "test") if k == 0 else None)
        outs.append(p.localise(frame))
    assert [o.no_fix_reason for o in outs] == [None] * 6
    shown = [o.attitude is not None and o.attitude.off for o in outs[MIN_FIXES - 1 :]]
    assert shown == [proven] * len(shown)
    doubts = [o.fix.attitude_doubt_rad for o in outs[MIN_FIXES - 1 :] if o.fix is not None]
    if proven:
        assert len(doubts) == len(shown) and min(doubts) >= math.radians(1.5 * 3.0)
    else:
        assert doubts == [0.0] * len(shown) and max(pose.doubts_rad) == 0.0
    records = [r for kind, r in fdr.records if kind == "pipeline.fix"]
    assert records[-1]["timing"]["sigma_s"] == pytest.approx(timing.sigma_s)


def test_while_the_autopilot_tilt_is_off_fixes_stand_on_the_image_and_what_was_fused_is_widened() -> None:
    """Every solved fix's image-only tilt is 3 deg from the autopilot's, and leaning on it puts tile A's
    fix 6.3 m north of the truth (120 m AGL). The first MIN_FIXES - 1 fixes are fused (the check cannot
    tell yet); then the check proves it off, with its numbers in the FDR: the estimate states the error
    what it fused may carry (the fixes and VO both turned the camera's rays with that attitude:
    2 x 120 m x tan 3 deg = 12.6 m), and each fix is solved again allowing the autopilot's tilt 1.5 x the
    error shown. Standing on the image, it lands at the truth, 6.3 m from the state: the raised sigma
    lets it through the gate, and the fixes after it pull the state back, each stating what a ground
    sloping by the error shown would make of it (6.3 m, shared with the fixes around it)."""
    fdr = _Fdr()
    pose = _PosePerTile(tilt_off_rad=math.radians(3.0))
    pose.north_m = 120.0 * math.tan(math.radians(3.0))
    p = _two_tile_pipeline(fdr, _HoverVo(), pose)
    outs = []
    for k in range(8):
        frame = _frame(k, T0 - (7 - k) * 333_333)  # the test clock stands at T0
        p.track(frame, InitialPrior(47.0, 8.0, 30.0, "test") if k == 0 else None)
        outs.append(p.localise(frame))
    assert [o.fix_accepted for o in outs] == [True] * 8, [o.no_fix_reason for o in outs]
    assert [o.fix.attitude_doubt_rad if o.fix else None for o in outs[: MIN_FIXES - 1]] == [0.0] * (
        MIN_FIXES - 1
    )
    stood = [o for o in outs[MIN_FIXES - 1 :] if o.attitude is not None and o.attitude.off]
    assert len(stood) == 9 - MIN_FIXES
    assert all(o.fix is not None and o.fix.attitude_doubt_rad >= math.radians(4.5) for o in stood)
    records = [r for kind, r in fdr.records if "attitude_check" in r]
    check = records[-1]["attitude_check"]
    assert check["off"] is True and check["bias_lower_deg"] > check["allowed_deg"] == pytest.approx(1.5)
    assert check["bias_deg"][0] == pytest.approx(3.0, abs=1e-3)
    assert records[-1]["fix_attitude_doubt_deg"] >= 4.5
    state = p.time_axis.state_at(T0)
    # Standing on the image, the fixes state what a ground sloping by the error shown would make of
    # them (a wrong attitude and a slope look the same): 120 m x tan 3 deg, shared, not averaged away.
    slope_m = 120.0 * math.tan(math.radians(3.0))
    assert abs(float(state.pos_ned_m[0])) < 0.5 * slope_m <= 0.5 * state.horiz_sigma_m
    assert records[-1]["fix_shared_sigma_m"] >= slope_m


def test_while_vo_ground_tilt_shows_the_autopilot_tilt_off_fixes_stand_on_their_own_tilt() -> None:
    """VO's ground tilt is 3 deg from the autopilot's on every frame, while every fix's own image finds
    the autopilot's tilt right (the fixes' check passes them). Once VO's check has proven it off (4
    tilts with no scatter), the IMU is left out and the estimate states once what VO and the fixes fused
    may carry (2 x 120 m x tan 3 deg); each fix is solved standing on its own image, which measures the
    tilt sharper than VO: it allows the autopilot's tilt what that image shows (here nothing, so 1.5 x
    the attitude's sigma) and is fused, and the fixes bring the stated sigma back. (On a real PX4, VO's
    ground tilt at a slow corner called the autopilot 16-25 deg off while the fixes measured 1-2 deg;
    refused for that, the fixes left the autopilot without a position for 24 s.) When VO's tilt agrees
    again, its check clears, the IMU comes back and the fixes lean on the autopilot's tilt as before."""
    fdr = _Fdr()
    vo = _TiltedVo(math.radians(3.0))
    pose = _PosePerTile(tilt_off_rad=0.0)
    p = _two_tile_pipeline(fdr, vo, pose)
    t0 = T0 - 44 * 333_333
    tracks, fixes = [], []
    for k in range(12):
        frame = _frame(k, t0 + k * 333_333)
        tracks.append(p.track(frame, InitialPrior(47.0, 8.0, 30.0, "test") if k == 0 else None))
        fixes.append(p.localise(frame))
    assert [t.ground_tilt.off for t in tracks if t.ground_tilt] == [False] * (MIN_FIXES - 1) + [True] * 9
    assert all(f.fix_accepted for f in fixes), [f.no_fix_reason for f in fixes]
    stood = [f.fix.attitude_doubt_rad for f in fixes[MIN_FIXES:] if f.fix is not None]
    assert stood == pytest.approx([math.radians(1.5 * PoseConfig().attitude_sigma_deg)] * (12 - MIN_FIXES))
    assert all(f.attitude is not None and not f.attitude.off for f in fixes)  # the fixes' check passed them
    frame_records = [r for kind, r in fdr.records if kind == "pipeline.frame"]
    fix_records = [r for kind, r in fdr.records if kind == "pipeline.fix"]
    assert frame_records[-1]["ground_tilt_check"]["bias_deg"][0] == pytest.approx(3.0, abs=1e-3)
    assert fix_records[-1]["ground_tilt_check"]["off"] is True
    state = p.time_axis.state_at(t0 + 11 * 333_333)
    assert abs(float(state.pos_ned_m[0])) < 1.0 and state.horiz_sigma_m < 5.0
    assert p._imu_trusted is False

    vo.tilt_off_rad = 0.0  # the attitude is right again
    for k in range(12, 44):
        frame = _frame(k, t0 + k * 333_333)
        tracks.append(p.track(frame, None))
        fixes.append(p.localise(frame))
    cleared = next(k for k, t in enumerate(tracks) if k >= 12 and t.ground_tilt and not t.ground_tilt.off)
    assert 12 < cleared < 44 and all(t.ground_tilt and not t.ground_tilt.off for t in tracks[cleared:])
    assert p._imu_trusted is True
    assert fixes[-1].no_fix_reason is None and fixes[-1].fix_accepted
    assert fixes[-1].fix is not None and fixes[-1].fix.attitude_doubt_rad == 0.0


@pytest.mark.parametrize("off", [False, True])
def test_a_lone_tilt_jump_leaves_the_imu_out_for_a_while_a_proven_offset_until_a_verdict(off: bool) -> None:
    """A fix whose tilt jumped (not yet proof that the attitude is off) leaves the IMU out; when no
    verdict follows (the frames after it cannot tell a tilt from their timing doubt), the IMU is back
    after ``TILT_JUMP_IMU_HOLD_S``, not left out for the rest of the flight (a link-drop flight on the
    ArduPilot emulator: the speed sigma stayed above 3D's bound and the emulated EKF failed safe). An
    attitude proven off keeps it out until a verdict says otherwise."""
    now = [T0]
    p = _pipeline(_Vpr(0), _Fdr(), vo=_HoverVo(), clock_unix_usec=lambda: now[0])
    p.track(_frame(0, T0), InitialPrior(47.0, 8.0, 30.0, "test"))
    jump = AttitudeVerdict((0.0, 2.1), 0.0, 11.0, 1.5, 16, off, not off, 2.1, (0.0, 2.1), T0)
    t_jump = now[0] = T0 + 333_333
    with p.time_axis.unit("fix", t_jump):
        p._answer_tilt("fixes", jump, 120.0, t_jump)
    assert p._imu_trusted is False
    trusted = []
    for k in range(2, 12):
        now[0] = T0 + k * 333_333
        p.track(_frame(k, now[0]), None)
        trusted.append(p._imu_trusted)
    if off:
        assert not any(trusted), trusted
    else:
        back = (T0 + (2 + trusted.index(True)) * 333_333 - t_jump) / 1e6
        assert TILT_JUMP_IMU_HOLD_S <= back < TILT_JUMP_IMU_HOLD_S + 0.34, back
        assert all(trusted[trusted.index(True) :]), trusted


def test_fixes_pull_back_the_state_vo_carried_off_while_the_autopilot_tilt_was_wrong() -> None:
    """The vehicle hovers over tile A. For 40 frames the autopilot's roll is 3 deg off and no pose can be
    solved: VO's ground tilt shows it, and the same wrong tilt makes VO measure 0.5 m of northward motion
    a frame, 20 m in all. What leaves stays within its stated sigma, and once the attitude is right the
    first fixes (at the true position, 20 m from the state) are fused and pull the state back. Measured
    before: the error was raised as the map's shared error, which the gates leave out, so every right fix
    after the offset was refused as too far from the state (a cross-date GPU flight at 1200 m AGL, to
    its end)."""
    fdr = _Fdr()
    vo = _TiltedVo(0.0)
    # Tile A solves to the true position, whatever the autopilot says; while the tilt is wrong no pose
    # can be solved (a featureless stretch), so VO alone carries the state.
    pose = _PosePerTile(tilt_off_rad=0.0)
    p = _two_tile_pipeline(fdr, vo, pose)
    t0 = T0 - 80 * 333_333
    outs: list[tuple[int, object, object]] = []
    for k in range(80):
        vo.tilt_off_rad, vo.north_m_per_frame = (math.radians(3.0), 0.5) if 5 <= k < 45 else (0.0, 0.0)
        pose.solvable = not 5 <= k < 45
        frame = _frame(k, t0 + k * 333_333)
        track = p.track(frame, InitialPrior(47.0, 8.0, 30.0, "test") if k == 0 else None)
        outs.append((k, track, p.localise(frame)))
    for k, track, _ in outs:
        north_m = float(track.state.pos_ned_m[0])  # the truth is 0 m north
        assert abs(north_m) <= 3.0 * np.sqrt(track.state.cov_pos_ned_m2[0, 0]), (k, north_m)
    carried = max(abs(float(track.state.pos_ned_m[0])) for k, track, _ in outs if k < 45)
    assert carried > 10.0  # VO did carry the state off while its tilt was wrong
    back = [k for k, _, fix in outs if k >= 45 and fix.fix_accepted]
    assert back and back[0] < 70, [(k, fix.no_fix_reason) for k, _, fix in outs[45:]]
    assert all(fix.fix_accepted for k, _, fix in outs if k > back[0])
    final = p.time_axis.state_at(t0 + 79 * 333_333)
    assert abs(float(final.pos_ned_m[0])) < 1.0 and final.horiz_sigma_m < 5.0


def test_while_vo_shows_the_attitude_off_a_frame_without_a_tilt_of_its_own_allows_it_too() -> None:
    """The autopilot's roll is 3 deg off from frame 5 to 30 and a fix leaning on it is 6.3 m off at
    120 m AGL; every third frame's pair gives no ground tilt, so it has no verdict of its own. Once VO's
    check has shown the attitude off, no fix is fused leaning on the autopilot's tilt until its tilt
    agrees again, those frames' included: each is solved standing on its own image (the estimate's
    raised sigma would let a leaning one through every gate: measured on a GPU across dates at 1200 m
    AGL, one in about 15, 64 m off at a stated 4 m). What leaves stays within 3 sigma of the truth
    throughout."""
    fdr = _Fdr()
    vo = _TiltedVo(0.0)
    pose = _PosePerTile(tilt_off_rad=0.0)
    p = _two_tile_pipeline(fdr, vo, pose)
    t0 = T0 - 60 * 333_333
    tracks, fixes = [], []
    for k in range(60):
        wrong = 5 <= k < 30
        vo.tilt_off_rad = None if k % 3 == 0 else (math.radians(3.0) if wrong else 0.0)
        pose.north_m = 120.0 * math.tan(math.radians(3.0)) if wrong else 0.0
        frame = _frame(k, t0 + k * 333_333)
        tracks.append(p.track(frame, InitialPrior(47.0, 8.0, 30.0, "test") if k == 0 else None))
        fixes.append(p.localise(frame))
    shown = next(k for k, t in enumerate(tracks) if t.ground_tilt and t.ground_tilt.off)
    cleared = next(k for k, t in enumerate(tracks) if k > shown and t.ground_tilt and not t.ground_tilt.off)
    assert 5 < shown < 12 and 30 < cleared < 60, (shown, cleared)
    fused = [k for k in range(shown, cleared) if fixes[k].fix_accepted]
    assert fused == list(range(shown, cleared)), [fixes[k].no_fix_reason for k in range(shown, cleared)]
    assert all((fixes[k].fix.attitude_doubt_rad if fixes[k].fix else 0.0) > 0.0 for k in fused)
    for k, track in enumerate(tracks):
        north_m = float(track.state.pos_ned_m[0])  # the truth is 0 m north
        assert abs(north_m) <= 3.0 * np.sqrt(track.state.cov_pos_ned_m2[0, 0]), (k, north_m)
    assert all(f.fix_accepted for f in fixes[cleared + 1 :]), [f.no_fix_reason for f in fixes[cleared:]]


def test_a_slow_fix_exposed_before_vo_lets_go_of_a_wrong_attitude_is_judged_by_what_it_allowed() -> None:
    """VO's check shows the roll off (frames 5-29), then its pairs give no tilt for 12 s (frames 30-65)
    while the attitude comes right at frame 33; tilts come back right and the check lets go. A slow
    matcher's fix of frame 31 arrives after that: its exposure lies between the last verdict that
    refused and the first that did not, where the attitude was never shown right. Started while VO
    showed the roll off, it was solved allowing that error, stands on the image and is fused however
    late; the same fix leaning on the autopilot's tilt (a matcher started before any check said
    anything) is refused however late (the estimate's raised sigma would let it through)."""
    fdr = _Fdr()
    vo = _TiltedVo(0.0)
    pose = _PosePerTile(tilt_off_rad=0.0)
    p = _two_tile_pipeline(fdr, vo, pose, max_delay_s=20.0)
    t0 = T0 - 90 * 333_333
    frames = [_frame(k, t0 + k * 333_333) for k in range(90)]
    tracks = []
    for k in range(90):
        wrong = 5 <= k < 33
        vo.tilt_off_rad = None if 30 <= k < 66 else (math.radians(3.0) if wrong else 0.0)
        tracks.append(p.track(frames[k], InitialPrior(47.0, 8.0, 30.0, "test") if k == 0 else None))
        if k == 31:
            pose.north_m = 120.0 * math.tan(math.radians(3.0))
            slow = p.attempt_fix(frames[31])  # solved now, fused once VO has let go
            pose.north_m = 0.0
        elif k < 30 or k >= 66:
            p.localise(frames[k])
    assert tracks[29].ground_tilt is not None and tracks[29].ground_tilt.off
    cleared = next(k for k in range(66, 90) if tracks[k].ground_tilt and not tracks[k].ground_tilt.off)
    assert slow.fix is not None and slow.fix.attitude_doubt_rad > 0.0
    assert abs(float(slow.fix.pos_ned_m[0])) < 1e-9  # it stood on the image
    leaning = replace(
        slow, fix=replace(slow.fix, attitude_doubt_rad=0.0, pos_ned_m=np.array([6.3, 0.0, -120.0]))
    )
    refused = p.fuse_attempt(frames[31], leaning)
    assert not refused.fix_accepted and refused.no_fix_reason == "vo_attitude_off", (
        cleared,
        refused.no_fix_reason,
    )
    late = p.fuse_attempt(frames[31], slow)
    assert late.fix_accepted, late.no_fix_reason


def test_a_slow_fix_exposed_where_vo_later_shows_the_attitude_off_is_refused() -> None:
    """A slow matcher starts on a frame exposed just after the attitude went wrong, before VO's ground
    tilt has seen that frame: it leans on the autopilot's tilt (nothing told it otherwise). By the time
    the fix is fused VO has proven it off: the fix leans on the wrong tilt and is refused as
    ``vo_attitude_off`` however late it comes. A fix exposed and fused before the attitude went wrong is
    not touched; one started once VO showed the tilt jump allows the error and is fused."""
    fdr = _Fdr()
    vo = _TiltedVo(0.0)
    pose = _PosePerTile(tilt_off_rad=0.0)  # the fixes' own check: nothing wrong
    p = _two_tile_pipeline(fdr, vo, pose)
    t0 = T0 - 20 * 333_333
    frames = [_frame(k, t0 + k * 333_333) for k in range(12)]
    for k in range(5):
        p.track(frames[k], InitialPrior(47.0, 8.0, 30.0, "test") if k == 0 else None)
    assert p.localise(frames[4]).fix_accepted
    vo.tilt_off_rad = math.radians(3.0)  # from frame 5 on
    slow = p.attempt_fix(frames[5])  # started before VO has seen frame 5
    assert slow.no_fix_reason is None and slow.fix is not None and slow.fix.attitude_doubt_rad == 0.0
    p.track(frames[5], None)
    p.track(frames[6], None)
    told = p.attempt_fix(frames[6])  # VO's tilt jumped at frame 5: the error is allowed
    assert told.fix is not None and told.fix.attitude_doubt_rad > 0.0
    outcomes = [p.track(frames[k], None) for k in range(7, 12)]
    assert outcomes[-1].ground_tilt is not None and outcomes[-1].ground_tilt.off
    late = p.fuse_attempt(frames[5], slow)
    assert not late.fix_accepted and late.no_fix_reason == "vo_attitude_off"
    assert late.ground_tilt is not None and late.ground_tilt.off
    assert [r for kind, r in fdr.records if kind == "pipeline.fix"][-1]["no_fix_reason"] == "vo_attitude_off"
    assert p.fuse_attempt(frames[6], told).fix_accepted


@dataclass
class _AttitudeSeen:
    """VO and VPR fakes that keep the attitude of each frame they were given."""

    seen: list[tuple[str, Attitude | None]] = field(default_factory=list)

    def process(self, frame: NavCameraFrame) -> VoMotion:
        self.seen.append(("vo", frame.attitude))
        return _HoverVo().process(frame)


def test_the_camera_mount_turns_the_attitude_vo_and_the_fix_path_see_not_the_one_recorded() -> None:
    """``camera.mount_*`` reaches VO and the fix path (every stage after them reads the frame they are
    given) as the autopilot's attitude turned by the mount; the FDR records the autopilot's, as it came,
    so a replay applies the recorded mount once."""
    seen = _AttitudeSeen()

    @dataclass
    class _SeeingVpr(_Vpr):
        def embed_query(self, frame, calibration):  # type: ignore[no-untyped-def]
            seen.seen.append(("fix", frame.attitude))
            return super().embed_query(frame, calibration)

    autopilot = Attitude(math.radians(2.0), math.radians(-1.0), math.radians(40.0))
    mount = CameraMount(math.radians(0.5), math.radians(-0.3))
    fdr = _Fdr()
    p = _pipeline(_SeeingVpr(dim=256), fdr, vo=seen, mount=mount)
    frame = NavCameraFrame(uuid.uuid4(), 0, T0, np.zeros((480, 640, 3), np.uint8), autopilot, 120.0, 0)
    p.process(frame, InitialPrior(47.0, 8.0, 30.0, "test"))
    assert [who for who, _ in seen.seen] == ["vo", "fix"]
    expected = mount.camera_attitude(autopilot)
    assert expected != autopilot
    assert all(att == expected for _, att in seen.seen)
    recorded = next(f for k, f in fdr.records if k == "pipeline.frame")
    assert recorded["attitude_rad"] == pytest.approx(
        [autopilot.roll_rad, autopilot.pitch_rad, autopilot.yaw_rad]
    )


class _Link:
    """The MAVLink link at its boundary: keeps the STATUSTEXTs the daemon sends."""

    def __init__(self) -> None:
        self.texts: list[str] = []

    def send_statustext(self, severity: int, text: str) -> None:
        self.texts.append(text)


def _slow_matcher_pipeline(
    n_frames: int, *, max_delay_s: float
) -> tuple[NavigationPipeline, list[NavCameraFrame]]:
    """A hovering pipeline whose fix path finds the true tile, and ``n_frames`` frames at 3 Hz ending at
    T0, the first already tracked: a test then holds a fix back while it tracks the others."""
    fakes = _TwoTiles((200, 40))
    p = _pipeline(_OneTileVpr(dim=256), _Fdr(), _HoverVo(), max_delay_s=max_delay_s)
    p._rerank = fakes  # type: ignore[assignment]
    p._ladder = EffortLadder.single("fake", fakes, MAX_CANDIDATES)  # type: ignore[arg-type]
    p._pose = _PosePerTile(tilt_off_rad=0.0)
    t0 = T0 - n_frames * 333_333
    frames = [_frame(k, t0 + k * 333_333) for k in range(n_frames)]
    p.track(frames[0], InitialPrior(47.0, 8.0, 30.0, "test"))
    return p, frames


def test_a_fix_as_late_as_disk_on_a_cpu_is_fused_at_its_exposure_with_the_default_delay() -> None:
    """DISK + LightGlue on a 2-core CPU answers 7-17 s after the exposure (docs/benchmarks.md). With the
    default ``estimator.max_fix_delay_s`` such a fix is fused at its own frame's time, behind the frames
    VO tracked meanwhile, not dropped as too late (the old 5 s default dropped every one)."""
    from gps_denied_onboard.config import load_config

    default_delay_s = load_config(None, []).estimator.max_fix_delay_s
    p, frames = _slow_matcher_pipeline(60, max_delay_s=default_delay_s)
    slow = p.attempt_fix(frames[0])
    for k in range(1, 52):  # 17 s of frames tracked while the matcher works
        p.track(frames[k], None)
    outcome = p.fuse_attempt(frames[0], slow)
    assert outcome.fix_accepted, outcome.no_fix_reason
    assert outcome.fused_behind_s == pytest.approx(17.0, abs=0.01)
    assert p.time_axis.stats().rewinds == 1


def test_fixes_later_than_the_axis_can_fuse_are_dropped_and_the_operator_is_told() -> None:
    """A matcher slower than ``estimator.max_fix_delay_s`` (5 s here): its right fix is dropped by the
    time axis (``gated:too_late``), counted, and the ground station hears it once per run of such fixes,
    with how late it was; a fix fused in time ends the run."""
    import asyncio
    from types import SimpleNamespace

    from gps_denied_onboard.clock import DaemonClock
    from gps_denied_onboard.config import load_config
    from gps_denied_onboard.daemon.service import NavDaemon
    from gps_denied_onboard.pipeline import FIX_TOO_LATE_REASON

    p, frames = _slow_matcher_pipeline(30, max_delay_s=5.0)
    slow = [p.attempt_fix(frames[k]) for k in (0, 1)]
    for k in range(1, 25):  # 8 s of frames tracked while the matcher works
        p.track(frames[k], None)
    late = [p.fuse_attempt(frames[k], a) for k, a in zip((0, 1), slow, strict=True)]
    assert [o.no_fix_reason for o in late] == [FIX_TOO_LATE_REASON] * 2
    assert all(o.fused_behind_s > 5.0 for o in late)
    in_time = p.localise(frames[24])
    assert in_time.fix_accepted

    link = _Link()
    config = load_config(None, ["estimator.max_fix_delay_s=5.0"])
    root = SimpleNamespace(config=config, time_axis=p.time_axis, clock=DaemonClock(), link=link)
    daemon = NavDaemon(root)  # type: ignore[arg-type]
    try:
        for outcome in (*late, in_time, late[0]):
            daemon._note_fix(outcome)
    finally:

        async def stop_workers() -> None:
            await asyncio.gather(daemon._track_thread.stop(1.0), daemon._fix_thread.stop(1.0))

        asyncio.run(stop_workers())
    assert daemon.counters.fixes_too_late == 3
    assert link.texts == [f"GDN: fix {late[0].fused_behind_s:.1f} s late > 5 s, dropped"] * 2
    assert all(len(t) <= 50 for t in link.texts)  # STATUSTEXT's text field


class _FootprintSpy:
    """C2.5 footprint-chip double: says whether a sigma is tight (``max_sigma_m``), records where it was
    asked to cut, and leaves the candidates as they are."""

    def __init__(self, max_sigma_m: float) -> None:
        self.max_sigma_m = max_sigma_m
        self.asked: list[tuple[float, float]] = []

    def applies(self, horiz_sigma_m: float) -> bool:
        return horiz_sigma_m <= self.max_sigma_m

    def first(self, result: RerankResult, lat_deg: float, lon_deg: float) -> RerankResult:
        self.asked.append((lat_deg, lon_deg))
        return result


@pytest.mark.parametrize(("max_sigma_m", "cut"), [(50.0, True), (10.0, False)])
def test_pipeline_cuts_the_first_chip_around_the_ground_under_the_camera(
    max_sigma_m: float, cut: bool
) -> None:
    """With a prior tight enough the chip is asked for around the ground the principal ray meets: the
    prior's position moved by the attitude's lean (5 deg of roll at 120 m AGL: 10.5 m across the
    heading, here east or west); with a looser prior it is not asked for at all."""
    fdr = _Fdr()
    p = _two_tile_pipeline(fdr, _HoverVo(), _PosePerTile())
    spy = _FootprintSpy(max_sigma_m)
    p._footprint_chips = spy  # type: ignore[assignment]
    frame = replace(_frame(0, T0), attitude=Attitude(math.radians(5.0), 0.0, 0.0))
    p.track(frame, InitialPrior(47.0, 8.0, 30.0, "test"))
    p.localise(frame)
    if not cut:
        assert spy.asked == []
        return
    ((lat, lon),) = spy.asked
    assert haversine_m(47.0, 8.0, lat, lon) == pytest.approx(120.0 * math.tan(math.radians(5.0)), abs=0.05)
    assert abs(lat - 47.0) * 111_320.0 < 0.05  # no north component: the lean is across a north heading


@dataclass
class _RankedVpr(_Vpr):
    """C2 double: ``tiles`` in the order of their descriptor distance, the same for every frame."""

    tiles: list[TileId] = field(default_factory=list)

    def retrieve_topk(self, query, k, *, region=None):  # type: ignore[no-untyped-def]
        self.regions.append(region)
        ranked = [VprCandidate(t, 0.1 * i, self.dim) for i, t in enumerate(self.tiles)]
        return VprResult(query.frame_id, ranked[:k], 0, "fake")


class _OnlyTrueTile:
    """Rerank (the first ``top_n``, as passthrough) and matcher double: only ``true`` is matched (200
    inliers), and ``rival`` as well when it is given too; the tiles each attempt was given are kept."""

    def __init__(self, true: TileId | None, rival: TileId | None = None, top_n: int = 3) -> None:
        self.true, self.rival, self.top_n = true, rival, top_n
        self.given: list[list[TileId]] = []

    def rerank(self, frame, vpr_result):  # type: ignore[no-untyped-def]
        cands = [_Cand(c.tile_id) for c in vpr_result.candidates[: self.top_n]]
        return RerankResult(frame.frame_id, cands, 0)  # type: ignore[arg-type]

    def match(self, frame, rerank_result, calibration):  # type: ignore[no-untyped-def]
        tiles = [c.tile_id for c in rerank_result.candidates]
        self.given.append(tiles)
        if self.true not in tiles:
            raise InsufficientInliersError(
                "none", frame_id=frame.frame_id, best_inlier_count=8, threshold=25,
                candidates_input=len(tiles), candidates_dropped=0,
            )  # fmt: skip
        q = np.random.default_rng(0).uniform((0, 0), (640, 480), size=(200, 2))
        pts = np.hstack([q, q]).astype(np.float32)
        sets = [CandidateMatchSet(t, 200, pts, 50, 0.8) for t in (self.true, self.rival) if t in tiles]
        return MatchResult(frame.frame_id, sets, 0, 0.8, 0, "fake")


def _sweeping_pipeline(fdr: _Fdr, tiles: list[TileId], fakes: _OnlyTrueTile) -> NavigationPipeline:
    """A pipeline over ``tiles`` (ranked in that order for every frame), matched by ``fakes``."""
    p = _pipeline(_RankedVpr(dim=256, tiles=tiles), fdr, _HoverVo())
    p._rerank = fakes  # type: ignore[assignment]
    p._ladder = EffortLadder.single("fake", fakes, MAX_CANDIDATES)  # type: ignore[arg-type]
    p._pose = _PosePerTile(tilt_off_rad=0.0)
    return p


def _fly(p: NavigationPipeline, n_frames: int) -> list[bool]:
    """``n_frames`` frames 1 s apart from the whole map as the prior; whether each fix was accepted."""
    accepted = []
    for k in range(n_frames):
        frame = _frame(k, T0 - n_frames * 1_000_000 + k * 1_000_000)
        p.track(frame, InitialPrior(47.0, 8.0, 3000.0, "map_extent"))
        accepted.append(p.localise(frame).fix_accepted)
    return accepted


def _ranks(fdr: _Fdr) -> list[int | None]:
    return [f["vpr_first_rank"] for kind, f in fdr.records if kind == "pipeline.fix"]


def test_corpus_wide_attempts_sweep_down_the_ranking_until_one_anchors() -> None:
    """With the whole map as the prior (a restart with nothing to resume), each failed attempt goes on
    to the next ``rerank.top_n`` tiles of the ranking: the true tile at rank 20 of 28 anchors on the 7th
    attempt, where matching the top 3 again and again never would; then the search is gated again."""
    fdr = _Fdr()
    tiles = [TileId(15, 1, i) for i in range(28)]
    fakes = _OnlyTrueTile(tiles[20])
    p = _sweeping_pipeline(fdr, tiles, fakes)
    assert _fly(p, 8)[:7] == [False] * 6 + [True]
    assert _ranks(fdr) == [0, 3, 6, 9, 12, 15, 18, None]
    assert fakes.given[6] == tiles[18:21]
    assert p._vpr.regions[-1] is not None  # type: ignore[union-attr]


def test_the_corpus_wide_sweep_starts_again_at_the_top_past_the_last_tile() -> None:
    """Eight tiles, none of them matched: the attempts start at ranks 0, 3, 6, then 0 again."""
    fdr = _Fdr()
    fakes = _OnlyTrueTile(None)
    p = _sweeping_pipeline(fdr, [TileId(15, 1, i) for i in range(8)], fakes)
    assert _fly(p, 5) == [False] * 5
    assert _ranks(fdr) == [0, 3, 6, 0, 3]
    assert [len(g) for g in fakes.given] == [3, 3, 2, 3, 3]


def test_the_sweep_tries_the_same_ranks_once_more_after_a_solved_pose_that_was_refused() -> None:
    """Two tiles of the first three both match (200 inliers each, 80 m apart): each pose is solved and
    refused as ambiguous. The next attempt tries the same ranks again (a held-back fix may be confirmed
    there), but only once: then the sweep goes on, so a wrong pair cannot hold it."""
    fdr = _Fdr()
    tiles = [TileId(15, 1, 0), TILE_A, TILE_B] + [TileId(15, 1, i) for i in range(3, 8)]
    p = _sweeping_pipeline(fdr, tiles, _OnlyTrueTile(TILE_A, rival=TILE_B))
    assert _fly(p, 6) == [False] * 6
    assert _ranks(fdr) == [0, 0, 3, 6, 0, 0]
    reasons = [f["no_fix_reason"] for kind, f in fdr.records if kind == "pipeline.fix"]
    assert reasons[:3] == ["integrity:ambiguous_candidates"] * 2 + ["insufficient_inliers"]


@dataclass
class _AreaMatcher:
    """An area matcher stand-in: the nadir it reports is the truth plus ``offset_north_m``, with strong
    correlation evidence and no correspondences (an alignment-only fix)."""

    lat_deg: float
    lon_deg: float
    offset_north_m: float = 0.0

    def match(self, frame, rerank_result, calibration):  # type: ignore[no-untyped-def]
        from gps_denied_onboard.components.c3_matcher.types import AreaAlignment

        area = AreaAlignment(
            nadir_lat_deg=self.lat_deg + self.offset_north_m / 111_320.0,
            nadir_lon_deg=self.lon_deg,
            heading_offset_rad=0.0,
            heading_step_rad=math.radians(1.0),
            height_scale=1.0,
            height_scale_step=0.02,
            map_gsd_m_px=0.5,
            peak=0.3,
            psr=30.0,
            secondary_ratio=0.2,
            coverage=1.0,
            texture=0.2,
            radius_m=30.0,
            hypotheses_tried=5,
            null_psr=5.0,
            null_peak=0.04,
        )
        tile = TileId.of(18, 47.0, 8.0)
        cand = CandidateMatchSet(tile, 0, np.empty((0, 4), np.float32), 0, math.nan, area=area)
        return MatchResult(frame.frame_id, [cand], 0, math.nan, 0, "orientation_corr", 1, 0)


class _OneTile:
    def rerank(self, frame, vpr_result):  # type: ignore[no-untyped-def]
        from gps_denied_onboard.components.c2_5_rerank.types import RerankCandidate

        return RerankResult(frame.frame_id, [RerankCandidate(TileId.of(18, 47.0, 8.0), None, -1, 0.0)], 0)  # type: ignore[arg-type]


@dataclass
class _AnyTile(_Vpr):
    def retrieve_topk(self, query, k, *, region=None):  # type: ignore[no-untyped-def]
        return VprResult(query.frame_id, [VprCandidate(TileId.of(18, 47.0, 8.0), 0.0, 0)], 0, "fake")


def test_alignment_only_fixes_that_keep_disagreeing_with_the_prior_state_the_disagreement() -> None:
    """A tilt fault puts every alignment-only fix the same distance off, and nothing in the frame can tell:
    after three that disagree with the VO-propagated prior, the next state that offset as shared error
    (honest whichever was wrong), and keep stating it after the estimate has moved towards them."""
    from gps_denied_onboard.components.c4_pose.area_pose import AreaPoseSolver

    fdr = _Fdr()
    matcher = _AreaMatcher(47.0, 8.0)
    now = [T0]
    p = replace_matcher(_pipeline(_AnyTile(0), fdr, vo=_HoverVo(), clock_unix_usec=lambda: now[0]), matcher)
    prior = InitialPrior(47.0, 8.0, 2.0, "config", "test")
    for i in range(20):
        if i == 6:
            matcher.offset_north_m = 30.0  # the fault: 30 m north, whatever the prior says
        now[0] = T0 + i * 333_333 + 50_000
        p.process(_frame(i, T0 + i * 333_333), prior)
    fixes = [f for k, f in fdr.records if k == "pipeline.fix"]
    doubted = [f for f in fixes[6:] if f["area_doubt_m"] is not None]
    assert doubted and all(f["area_doubt_m"] == pytest.approx(30.0, abs=1.0) for f in doubted), fixes
    assert all(f["area_doubt_m"] is None for f in fixes[:9])  # three to disagree first
    for f in fixes:
        if f["fix_accepted"]:
            err = haversine_m(f["fix_lat_deg"], f["fix_lon_deg"], 47.0, 8.0)
            assert err <= 3.0 * f["fix_sigma_m"], f
    assert any(f["fix_accepted"] for f in doubted), "stated honestly, the doubted fixes are fused"
    assert isinstance(p._area_pose, AreaPoseSolver)


def replace_matcher(p: NavigationPipeline, matcher: object) -> NavigationPipeline:
    """``p`` with ``matcher`` as its one rung, the one-tile rerank and the real area pose solver."""
    from gps_denied_onboard.components.c4_pose.area_pose import AreaPoseSolver

    p._ladder = EffortLadder.single("orientation_corr", matcher, MAX_CANDIDATES)  # type: ignore[arg-type]
    p._rerank = _OneTile()  # type: ignore[assignment]
    p._area_pose = AreaPoseSolver(PoseConfig(), LTP, 400.0)
    return p


@pytest.mark.parametrize(
    ("reason", "ranks"),
    [
        ("integrity:low_psr", [0, 3, 6, 0]),
        ("integrity:low_peak", [0, 3, 6, 0]),
        ("gated:gated", [0, 0, 3, 3]),
    ],
)
def test_an_area_alignment_without_a_peak_does_not_hold_the_sweep(reason: str, ranks: list[int]) -> None:
    """Issue 37: the area correlation solves a pose on every attempt; refused because its peak does not
    stand out of the disc (low PSR or peak), the map did not answer there and the sweep goes on at once.
    Holding on it (as on a fix to confirm) halved the sweep's pace over an 8 km map."""
    fdr = _Fdr()
    p = _sweeping_pipeline(fdr, [TileId(15, 1, i) for i in range(8)], _OnlyTrueTile(None))
    matched = p._matched

    def solved_and_refused(*args, **kwargs):  # type: ignore[no-untyped-def]
        attempt = matched(*args, **kwargs)
        cand = CandidateMatchSet(TILE_A, 0, np.empty((0, 4), np.float32), 0, float("nan"))
        fix = _PosePerTile(0.0).solve(args[0], cand, None, None)
        return replace(attempt, fix=fix, no_fix_reason=reason)

    p._matched = solved_and_refused  # type: ignore[method-assign]
    assert _fly(p, 4) == [False] * 4
    assert _ranks(fdr) == ranks


def test_vo_states_the_tilt_error_the_fixes_measured_through_the_off_nadir_lever() -> None:
    """PX4 SIH held a 38 deg roll with its attitude 2-5 deg off the truth and no swing to show it: VO,
    de-rotating with that attitude, was 1 m a frame wrong at 80 m. VO's covariance takes the larger of the
    autopilot's AHRS doubt and the tilt error accepted fixes measured, through height / cos(off-nadir)^2."""
    from gps_denied_onboard.pipeline import AHRS_ERROR_CHANGE_TIME_S, _with_attitude_doubt

    motion = VoMotion(uuid.uuid4(), uuid.uuid4(), 0.34, np.array([0.0, 2.4]), np.eye(2) * 0.01, 300, None)
    level = Attitude(0.0, 0.0, 0.0)
    rolled = Attitude(math.radians(38.0), 0.0, 0.0)
    timing = FrameTiming((0.0, 0.0), 0.0, 0.05, ahrs_sigma_rad=math.radians(0.3))

    def frame(att: Attitude) -> NavCameraFrame:
        image = np.zeros((480, 640, 3), np.uint8)
        return NavCameraFrame(uuid.uuid4(), 0, T0, image, att, 80.0, 0, timing=timing)

    def sigma(att: Attitude, measured_rad: float) -> float:
        cov = _with_attitude_doubt(motion, frame(att), measured_rad).cov_ne_m2
        return math.sqrt(float(cov[0, 0]))

    change = math.radians(4.0) * 0.34 / AHRS_ERROR_CHANGE_TIME_S
    assert sigma(level, math.radians(4.0)) == pytest.approx(math.hypot(0.1, 80.0 * change), rel=1e-6)
    assert sigma(rolled, math.radians(4.0)) == pytest.approx(
        math.hypot(0.1, 80.0 / math.cos(math.radians(38.0)) ** 2 * change), rel=1e-6
    )
    assert sigma(rolled, math.radians(4.0)) > 1.05  # the measured error per frame, 1 sigma
    without = math.hypot(0.1, 80.0 / math.cos(math.radians(38.0)) ** 2 * math.radians(0.3) * 0.17)
    assert sigma(rolled, 0.0) == pytest.approx(without, rel=1e-6)  # the autopilot's own doubt alone


def test_vo_doubts_a_tilt_error_as_soon_as_two_fixes_agree_on_it_not_one() -> None:
    """Fixes at 3 Hz found the autopilot's tilt 0.5 deg off for 6 s; then it drifts to 6 deg (a real
    PX4 beside two busy loops). Two fixes saying so are VO's doubt at once, where the 8 s median still
    said 0.5 deg; one fix alone (a stale attitude) moves nothing; and a window with none says 0."""
    from gps_denied_onboard.pipeline import TiltSeen, measured_tilt_doubt_rad

    small, large = math.radians(0.5), math.radians(6.0)
    seen = [TiltSeen(T0 - 6_000_000 + k * 333_333, (small, 0.0), False) for k in range(18)]
    now = T0 + 500_000
    assert measured_tilt_doubt_rad(seen, now) == pytest.approx(small)
    one = [*seen, TiltSeen(T0, (0.0, large), True)]
    assert measured_tilt_doubt_rad(one, now) == pytest.approx(small)
    two = [*one, TiltSeen(T0 + 333_333, (0.0, large), True)]
    assert measured_tilt_doubt_rad(two, now) == pytest.approx(large)
    assert measured_tilt_doubt_rad(two, T0 + 4_000_000) == pytest.approx(small)  # no longer the newest
    assert measured_tilt_doubt_rad(two, T0 - 7_000_000) == 0.0


def test_vo_states_how_far_the_tilt_error_swings_between_frames_while_fixes_stand_on_their_images() -> None:
    """On a real PX4 under load the fixes, right to 0.07 m, found the autopilot's tilt error swinging
    1-2 deg from one frame to the next, and VO, de-rotating with it, was 3-4 m wrong a frame at 79 m AGL
    while stating 0.9 m from the error's size alone. The swing the fixes measured is VO's change of
    attitude error at once, through the same lever; not while the fixes lean on the autopilot (their
    tilts' scatter is then the image's own noise), nor from fixes too far apart to say."""
    from gps_denied_onboard.pipeline import TiltSeen, _with_attitude_doubt, measured_tilt_change_rad

    swing = math.radians(1.5)
    zigzag = [
        TiltSeen(T0 - 3_000_000 + k * 333_333, (math.radians(3.0) + (swing if k % 2 else 0.0), 0.0), True)
        for k in range(9)
    ]
    now = T0
    assert measured_tilt_change_rad(zigzag, now) == pytest.approx(swing)
    leaning = [replace(x, stood=False) for x in zigzag]
    assert measured_tilt_change_rad(leaning, now) == 0.0
    sparse = [replace(x, time_unix_usec=T0 - 6_000_000 + k * 1_500_000) for k, x in enumerate(zigzag[:5])]
    assert measured_tilt_change_rad(sparse, now) == 0.0

    motion = VoMotion(uuid.uuid4(), uuid.uuid4(), 0.33, np.array([0.0, 2.4]), np.eye(2) * 0.01, 300, None)
    image = np.zeros((480, 640, 3), np.uint8)
    frame = NavCameraFrame(uuid.uuid4(), 0, T0, image, Attitude(0.0, 0.0, 0.0), 79.0, 0)
    stated = _with_attitude_doubt(motion, frame, math.radians(3.0), measured_tilt_change_rad(zigzag, now))
    assert math.sqrt(float(stated.cov_ne_m2[0, 0])) == pytest.approx(math.hypot(0.1, 79.0 * swing), rel=1e-6)
    assert 79.0 * swing > 2.0  # against 79 m x 3 deg x 0.33 s / 2 s = 0.7 m from the error's size
