"""The F3 flight pipeline for one nav frame, stage by stage, in two halves on one time axis.

    frame ─┬─ track:    C1 visual odometry ─────────────────────────────────────┐
           │                                                                    ├→ C5 time axis → state
           └─ localise: C2 VPR (prior-gated) → C2.5 rerank → C3 match → C4 pose ┘   (at the exposure time)

Every stage's failure has one meaning for the estimator:
- no attitude/altitude at exposure → no absolute fix from this frame (never reuse stale data);
- VPR/rerank/matcher error or too few inliers → no fix; C5 propagates on VO (``visual_propagated``);
- pose rejected (degenerate, implausible) → no fix;
- the autopilot's tilt shown off by the image-only tilts of the recent fixes, or by the ground tilt VO
  sees between frames (``c1_vio/ground_tilt.py``, at the camera rate; ``c4_pose/attitude_check.py``):
  a fix solved from points stands on its own image (``_stand_on_image_rad``: its attitude prior allows
  what its image shows, and it states what a slope as steep would make of it); a fix that leaned on the
  autopilot's tilt (no tilt of its own, an area alignment; or solved before any check spoke) is refused
  (``attitude_off``, ``vo_attitude_off``: wherever VO has shown it, however late the fix arrives), and
  so is a fix whose tilt jumped from the recent ones (``attitude_jump``); when a check first shows a
  tilt error (or a larger one) the estimate states what the fixes and VO fused before may carry from
  it, and while either shows one the IMU is left out;
- fix refused by the integrity rule (weak evidence, ambiguous candidates, disagrees with the prior; see
  ``c4_pose/integrity.py``) → no fix; a fix it passes states a covariance that reflects its evidence,
  scaled by how consistent the recent fixes were with each other through VO (``c4_pose/consistency.py``);
- fix outside the estimator's gate → rejected by C5 (a wrong tile cannot teleport the estimate);
- while no map fix has confirmed the start prior, failed attempts on frames that should match count
  against it: its sigma grows and the search sweeps outward, the prior's own place kept in each attempt,
  until the map answers (``c5_estimator/prior_doubt.py``);
- fix older than the time axis can rewind to → refused as too late (never fused at its arrival time).
Each half is synchronous and single-threaded by contract (INV-1); the daemon runs them off the loop.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import threading
import time
import uuid
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Final

import numpy as np
import structlog

from gps_denied_onboard.camera.types import CameraCalibration, CameraMount, FrameTiming, NavCameraFrame
from gps_denied_onboard.components.c1_vio.types import VoError, VoMotion
from gps_denied_onboard.components.c2_5_rerank.footprint import FootprintChips
from gps_denied_onboard.components.c2_5_rerank.protocol import RerankStrategy
from gps_denied_onboard.components.c2_5_rerank.types import RerankResult, SearchPrior
from gps_denied_onboard.components.c2_vpr.protocol import SearchRegion, VprStrategy
from gps_denied_onboard.components.c2_vpr.types import VprError, VprQuery, VprResult
from gps_denied_onboard.components.c3_matcher.errors import InsufficientInliersError, MatcherError
from gps_denied_onboard.components.c3_matcher.ladder import EffortLadder, Rung
from gps_denied_onboard.components.c3_matcher.protocol import CrossDomainMatcher
from gps_denied_onboard.components.c3_matcher.types import CandidateMatchSet, MatchResult
from gps_denied_onboard.components.c4_pose.area_pose import AreaPoseSolver
from gps_denied_onboard.components.c4_pose.attitude_check import AttitudeCheck, AttitudeVerdict
from gps_denied_onboard.components.c4_pose.consistency import ConsistencyVerdict, FixConsistency
from gps_denied_onboard.components.c4_pose.heading_height_check import (
    HeadingHeightCheck,
    HeadingHeightVerdict,
)
from gps_denied_onboard.components.c4_pose.integrity import (
    AreaEvidence,
    CandidateFix,
    FixIntegrity,
    IntegrityVerdict,
    evidence_of,
    with_regional_error,
    with_timing_error,
)
from gps_denied_onboard.components.c4_pose.types import PoseError, PoseFix
from gps_denied_onboard.components.c5_estimator.journal import UNIT_FIX, UNIT_FIX_PRIOR, UNIT_TRACK
from gps_denied_onboard.components.c5_estimator.prior import InitialPrior
from gps_denied_onboard.components.c5_estimator.prior_doubt import DoubtVerdict, PriorDoubt
from gps_denied_onboard.components.c5_estimator.time_axis import Refusal, TimeAxis
from gps_denied_onboard.components.c5_estimator.types import EstimatorState
from gps_denied_onboard.components.c13_fdr.protocol import FdrClient
from gps_denied_onboard.config import VprConfig
from gps_denied_onboard.constants import FdrKind, IntegrityReason, LogEvent, Provenance
from gps_denied_onboard.geo import LocalTangentPlane, haversine_m
from gps_denied_onboard.helpers.frame_rectifier import principal_ground_offset_m
from gps_denied_onboard.helpers.texture import edge_share

log = structlog.get_logger(__name__)

#: ``FixOutcome.no_fix_reason`` of a fix that passed every check but came later than the time axis can
#: still fuse it (``estimator.max_fix_delay_s``).
FIX_TOO_LATE_REASON: Final = f"gated:{Refusal.TOO_LATE.value}"
#: How long one tilt jump (a fix's tilt that left what the ones before it pin, not yet proof that the
#: attitude is off) leaves the IMU out when no verdict follows it, s: a check hears only frames whose
#: timing doubt cannot make the tilt by itself, and in a link-drop flight on the ArduPilot emulator the
#: jump seen at the cut's edge was the last such verdict: the IMU stayed out for the rest of the flight,
#: the speed sigma above 3D's bound, and the emulated EKF failed safe. Four jumps in a row prove it off.
TILT_JUMP_IMU_HOLD_S: Final[float] = 2.0
#: A bare matcher's one rung gets every candidate C2.5 hands on (``rerank.top_n`` is at most this).
MAX_CANDIDATES: Final = 10
#: Alignment-only fixes in a row that disagree with the VO-propagated prior before the next ones state
#: that disagreement (``NavigationPipeline._with_area_doubt``).
AREA_DISAGREEMENT_RUN: Final = 3
#: Integrity refusals of an area alignment whose peak does not stand out (``c4_pose/integrity.py``): the
#: map did not answer in the disc, so the sweep does not hold its ranks for them (``_absolute_fix``).
_NO_PEAK_REASONS: Final = frozenset(
    {f"integrity:{IntegrityReason.LOW_PSR}", f"integrity:{IntegrityReason.LOW_PEAK}"}
)


@dataclass(frozen=True)
class TrackOutcome:
    """What the camera-rate half (VO into the estimator) made of one frame."""

    frame_id: uuid.UUID
    seq: int
    exposure_time_unix_usec: int
    #: The estimate at the frame's exposure after fusing its VO (None before initialisation).
    state: EstimatorState | None
    vo_ok: bool
    #: Why the VO was not fused (None when it was): C1's reason, or the estimator's/time axis' refusal.
    vo_reason: str | None
    timings_ms: dict[str, float] = field(default_factory=dict)
    #: The VO ground-tilt check after this frame's tilt (None when the frame gave none).
    ground_tilt: AttitudeVerdict | None = None

    @property
    def provenance(self) -> Provenance:
        return self.state.provenance if self.state is not None else Provenance.NO_ESTIMATE


@dataclass(frozen=True)
class FixOutcome:
    """What the absolute-fix half (VPR -> rerank -> C3 -> C4 -> C5) made of one frame."""

    frame_id: uuid.UUID
    seq: int
    exposure_time_unix_usec: int
    fix: PoseFix | None
    fix_accepted: bool
    inliers: int
    residual_px: float | None
    #: Why there was no accepted absolute fix (None when there was one).
    no_fix_reason: str | None
    #: How far behind the newest fused input this fix was fused at its own exposure time, s (0: in order).
    fused_behind_s: float
    timings_ms: dict[str, float] = field(default_factory=dict)
    #: The integrity rule's verdict on the solved fix (None when no fix was solved).
    integrity: IntegrityVerdict | None = None
    #: The attitude check after the solved fix (None when no fix was solved).
    attitude: AttitudeVerdict | None = None
    #: The VO ground-tilt check when the fix was fused (None: off, or no tilt seen yet).
    ground_tilt: AttitudeVerdict | None = None
    #: The effort-ladder rung the attempt was made on (``c3_matcher/ladder.py``; None: no matcher ran).
    rung: str | None = None
    #: The autopilot's heading and height against an accepted area fix's (``c4_pose/heading_height_check``;
    #: None: no such fix, or its evidence too weak to count).
    heading_height: HeadingHeightVerdict | None = None
    #: What the attempt did to the doubt on an unconfirmed start prior (None: the prior is confirmed).
    prior_doubt: DoubtVerdict | None = None


@dataclass(frozen=True)
class FixAttempt:
    """What C2 -> C2.5 -> C3 -> C4 made of one frame, before the estimator has seen it."""

    fix: PoseFix | None
    inliers: int
    residual_px: float | None
    #: Why there is no fix (None when there is one).
    no_fix_reason: str | None
    timings_ms: dict[str, float] = field(default_factory=dict)
    #: The integrity rule's verdict on the solved fix (None when no fix was solved or it never got there).
    integrity: IntegrityVerdict | None = None
    #: The attitude check after the solved fix (None when no fix was solved).
    attitude: AttitudeVerdict | None = None
    #: Corpus-wide search only: the VPR rank this attempt's candidates started at (the sweep's position).
    vpr_first_rank: int | None = None
    #: The effort-ladder rung the attempt was made on (None: it never got to a matcher).
    rung: str | None = None
    #: An alignment-only fix's stated disagreement with the prior (``_with_area_doubt``), m; else None.
    area_doubt_m: float | None = None
    #: While the start prior is unconfirmed (``c5_estimator/prior_doubt.py``): the edge shares of the
    #: frame and of the map where the search started (None: not measured), and where the attempt searched
    #: from (lat_deg, lon_deg, the map-frame horizontal sigma m).
    frame_texture: float | None = None
    map_texture: float | None = None
    searched_from: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class _OffSpan:
    """Exposures (us, Unix) over which the ground-tilt check showed the autopilot's tilt off (its
    evidence since, its newest tilt)."""

    since_usec: int
    until_usec: int


@dataclass(frozen=True)
class FrameOutcome:
    """Both halves run one after the other on one frame (:meth:`NavigationPipeline.process`)."""

    track: TrackOutcome
    fix: FixOutcome | None

    @property
    def state(self) -> EstimatorState | None:
        return self.track.state

    @property
    def provenance(self) -> Provenance:
        return self.track.provenance

    @property
    def no_fix_reason(self) -> str | None:
        return "not_initialised" if self.fix is None else self.fix.no_fix_reason


class NavigationPipeline:
    """The F3 flow in two halves that share one time axis (C5):

    - :meth:`track` (camera rate): C1 VO on every frame, fused at the frame's exposure time;
    - :meth:`localise` (as fast as the matcher allows, on the newest frame): C2 -> C2.5 -> C3 -> C4, the
      fix fused at the frame's exposure time however late it arrives (or refused as too late).

    The daemon runs them on two worker threads so a slow matcher never starves VO or the output;
    :meth:`process` runs both in sequence (tests). Each half is single-threaded by contract (INV-1): one
    caller per half at a time. Every visit to the time axis is one journal unit
    (``c5_estimator.journal``), so ``gdnav replay`` can run :meth:`track`, :meth:`attempt_fix` and
    :meth:`fuse_attempt` on one thread in the order the daemon's two threads reached the axis.
    """

    def __init__(
        self,
        *,
        calibration: CameraCalibration,
        ltp: LocalTangentPlane,
        ground_alt_amsl_m: float,
        vo,  # HomographyVo  # type: ignore[no-untyped-def]
        vpr: VprStrategy | None,
        vpr_config: VprConfig,
        rerank: RerankStrategy | None,
        matcher: CrossDomainMatcher | None,
        pose_solver,  # PoseSolver
        time_axis: TimeAxis,
        fdr: FdrClient,
        integrity: FixIntegrity,
        consistency: FixConsistency,
        attitude_check: AttitudeCheck,
        ground_tilt_check: AttitudeCheck | None = None,
        mount: CameraMount | None = None,
        footprint_chips: FootprintChips | None = None,
        clock_ns: Callable[[], int] = time.perf_counter_ns,
        attitude_sigma_deg: float | None = None,
        ladder: EffortLadder | None = None,
        area_pose_solver: AreaPoseSolver | None = None,
        heading_height_check: HeadingHeightCheck | None = None,
        prior_doubt: PriorDoubt | None = None,
        map_extent: tuple[float, float, float] | None = None,
    ) -> None:
        """``matcher``: C3 alone (a one-rung ladder, every candidate); ``ladder``: the effort ladder,
        which then replaces it (``c3_matcher/ladder.py``). ``area_pose_solver``: the pose of an area
        matcher's alignments (``c4_pose/area_pose.py``; needed when a rung runs ``orientation_corr``).
        ``prior_doubt``: the rule that finds a wrong start prior out (None: never doubted);
        ``map_extent``: the map's centre (lat_deg, lon_deg) and radius, m, that a doubted prior's sigma
        grows to cover at most."""
        self._calib = calibration
        self._footprint_chips = footprint_chips
        self._mount = mount if mount is not None else CameraMount()
        self._ltp = ltp
        self._ground_alt_amsl_m = ground_alt_amsl_m
        self._vo = vo
        self._vpr = vpr
        self._vpr_cfg = vpr_config
        self._rerank = rerank
        #: The effort ladder (``c3_matcher/ladder.py``); a bare ``matcher`` is a one-rung ladder.
        self._ladder = ladder
        if ladder is None and matcher is not None:
            self._ladder = EffortLadder.single(type(matcher).__name__, matcher, MAX_CANDIDATES)
        self._pose = pose_solver
        self._area_pose = area_pose_solver
        #: The innovations (fix minus prior, north and east, m) of the latest alignment-only fixes, while
        #: each disagreed with the VO-propagated prior (``_with_area_doubt``).
        self._area_disagreements: deque[np.ndarray] = deque(maxlen=AREA_DISAGREEMENT_RUN)
        #: What alignment-only fixes state they may carry from the autopilot's tilt beyond their own
        #: sigma, m (``_with_area_doubt``; None: nothing).
        self._area_doubt_m: float | None = None
        #: How far accepted fixes found the autopilot's tilt from the camera's, with their exposure
        #: (``measured_ahrs_doubt_rad``): written by the fix thread, read by the track thread.
        self._tilt_off_seen: deque[TiltSeen] = deque(maxlen=TILT_OFF_HISTORY)
        self._tilt_off_lock = threading.Lock()
        self._prior_gate_chi2 = integrity.config.prior_gate_chi2
        self._heading_height = heading_height_check
        self._axis = time_axis
        self._fdr = fdr
        self._integrity = integrity
        self._consistency = consistency
        self._attitude = attitude_check
        self._ground_tilt = ground_tilt_check
        #: The ground-tilt check's newest verdict (written by the track half, read by the fix half, both
        #: inside units of the axis: a replay reads the same).
        self._ground_tilt_verdict: AttitudeVerdict | None = None
        #: Exposure spans (us, Unix) the ground-tilt check has shown the attitude off over (evidence
        #: since, newest tilt), merged, newest last: a fix exposed inside one is refused however late.
        self._vo_off_spans: deque[_OffSpan] = deque(maxlen=64)
        #: The fixes' attitude check's newest verdict (the fix half's own).
        self._fix_tilt_verdict: AttitudeVerdict | None = None
        #: The largest tilt error (deg) each check has shown in its current refusal, and answered by
        #: raising the position's sigma (``_answer_tilt``); 0 while it refuses nothing.
        self._tilt_answered_deg = {"fixes": 0.0, "vo": 0.0}
        #: Until when (us, Unix) each tilt check's last refusal leaves the IMU out (``_answer_tilt``):
        #: None while it refuses nothing, the next verdict for an attitude proven off,
        #: ``TILT_JUMP_IMU_HOLD_S`` after a jump. The IMU is trusted while neither holds.
        self._tilt_refused_until: dict[str, float | None] = {"fixes": None, "vo": None}
        #: What this pipeline last told the time axis about the IMU (``c4_pose/attitude_check.py``).
        self._imu_trusted = True
        self._clock_ns = clock_ns
        #: F6 re-localisation (corpus-wide VPR) currently active; logged on transitions only.
        self._corpus_wide = False
        #: The start prior's doubt (``c5_estimator/prior_doubt.py``) and the map it may grow to cover.
        self._doubt = prior_doubt
        self._map_extent = map_extent
        #: How the newest attempt searched: ``prior`` (the prior's region), ``doubt`` (a doubted prior's
        #: region, swept outward) or ``corpus`` (F6, corpus-wide, swept down the ranking).
        self._search_mode = "prior"
        #: The corpus-wide sweep: the VPR rank the next corpus-wide attempt starts at (``_sweep``).
        self._sweep_rank = 0
        #: The last corpus-wide attempt kept its ranks for the next one (at most once in a row).
        self._sweep_held = False
        #: A tilt is compared with the autopilot's only while the frame's own doubt of that tilt (timing,
        #: the autopilot's recent manoeuvres) is under half the attitude's sigma
        #: (``pose.attitude_sigma_deg``): like with like (None: always).
        self._timing_tilt_max_rad = (
            math.radians(attitude_sigma_deg) / 2.0 if attitude_sigma_deg is not None else None
        )
        #: The newest frames' timing, for VO's ground tilt (it is on the previous frame's axes).
        self._timing_of: OrderedDict[uuid.UUID, tuple[int, FrameTiming | None]] = OrderedDict()

    @property
    def time_axis(self) -> TimeAxis:
        return self._axis

    @property
    def ladder(self) -> EffortLadder | None:
        """The effort ladder (None without a map: no fix path)."""
        return self._ladder

    def _initialise(self, prior: InitialPrior, frame: NavCameraFrame) -> None:
        alt_agl_m = frame.alt_agl_m if frame.alt_agl_m is not None else 0.0
        pos = self._ltp.to_ned(prior.lat_deg, prior.lon_deg, self._ground_alt_amsl_m + alt_agl_m)
        t = frame.exposure_time_unix_usec
        if prior.handover is not None:
            self._axis.resume(prior.handover)  # the core's filter as it is: velocity and covariance kept
        else:
            self._axis.initialise(pos, prior.sigma_m, t, map_confirmed=prior.confirmed)
        if self._doubt is not None:
            self._doubt.start()
        log.info(
            LogEvent.ESTIMATOR_INITIALISED,
            source=prior.source,
            why=prior.why,
            lat_deg=prior.lat_deg,
            lon_deg=prior.lon_deg,
            sigma_m=prior.sigma_m,
        )

    def _search_region(
        self, state: EstimatorState, frame: NavCameraFrame
    ) -> tuple[SearchRegion | None, bool]:
        """(region, sweep): where this attempt searches, and whether attempts sweep it (``_sweep``).

        - ``prior``: the state's uncertainty region (``vpr.prior_sigma_scale`` sigmas and the frame's
          half-footprint, clamped to ``vpr.prior_radius_max_m``), the same tiles each attempt;
        - ``doubt``: a doubted start prior's region, not clamped: it grows until the map answers, swept;
        - past ``vpr.corpus_wide_sigma_m``, with an appearance strategy: ``reach``, the same region not
          clamped and swept, while it leaves part of the map out (the vehicle is where the state's
          sigma says, however long ago a fix last said so: over a mission area the whole map is hours
          of attempts, the region minutes); ``corpus`` (F6, ``None``: ranked by appearance over the
          whole map) once it covers the map, or when the map's extent is not known."""
        cfg = self._vpr_cfg
        # The tile centre can be up to the frame's half-footprint away from the camera and still overlap.
        half_footprint_m = (frame.alt_agl_m or 0.0) * math.tan(self._calib.hfov_rad / 2.0)
        radius = max(cfg.prior_sigma_scale * state.horiz_sigma_m + half_footprint_m, cfg.prior_radius_min_m)
        wide = (
            state.horiz_sigma_m > cfg.corpus_wide_sigma_m
            and self._vpr is not None
            and self._vpr.descriptor_dim() > 0
        )
        corpus_wide = wide and self._covers_map(state, radius)
        if corpus_wide != self._corpus_wide:
            self._corpus_wide = corpus_wide
            log.warning(
                LogEvent.VPR_CORPUS_WIDE if corpus_wide else LogEvent.VPR_PRIOR_GATED,
                horiz_sigma_m=round(state.horiz_sigma_m, 1),
                threshold_m=cfg.corpus_wide_sigma_m,
            )
        doubted = self._doubt is not None and self._doubt.doubted
        reach = wide and not corpus_wide
        mode = "corpus" if corpus_wide else "reach" if reach else "doubt" if doubted else "prior"
        if mode != self._search_mode:
            if mode == "reach":
                log.warning(
                    LogEvent.VPR_REACHABLE_SWEEP,
                    horiz_sigma_m=round(state.horiz_sigma_m, 1),
                    radius_m=round(radius, 1),
                    map_radius_m=None if self._map_extent is None else round(self._map_extent[2], 1),
                )
            self._search_mode = mode
            self._sweep_rank, self._sweep_held = 0, False
        if corpus_wide:
            return None, True
        if not (doubted or reach):
            radius = min(radius, cfg.prior_radius_max_m)
        return SearchRegion(state.lat_deg, state.lon_deg, radius), doubted or reach

    def _covers_map(self, state: EstimatorState, radius_m: float) -> bool:
        """Whether a disc of ``radius_m`` at the state holds the whole map (True when its extent is not
        known: corpus-wide is then the only whole search)."""
        if self._map_extent is None:
            return True
        c_lat, c_lon, map_radius_m = self._map_extent
        return float(haversine_m(state.lat_deg, state.lon_deg, c_lat, c_lon)) + map_radius_m <= radius_m

    def process(self, frame: NavCameraFrame, prior: InitialPrior | None) -> FrameOutcome:
        """Both halves on one frame, in sequence."""
        track = self.track(frame, prior)
        fix = self.localise(frame) if self._axis.is_initialised else None
        return FrameOutcome(track, fix)

    # -- camera-rate half ----------------------------------------------------------------------------

    def _comparable(self, timing: FrameTiming | None) -> bool:
        """Whether a tilt at this frame's timing says anything about the autopilot's attitude."""
        limit = self._timing_tilt_max_rad
        if limit is None or timing is None:
            return True
        # a gentle swing's AHRS doubt is no reason to stop comparing: a fault that steps the reported
        # attitude by a few degrees must not hide itself as a manoeuvre
        ahrs_rad = max(0.0, timing.ahrs_sigma_rad - AHRS_DOUBT_FREE_RAD)
        return math.hypot(timing.tilt_sigma_rad, ahrs_rad) <= limit

    def measured_ahrs_doubt_rad(self, time_unix_usec: int) -> tuple[float, float]:
        """What accepted fixes measured of the autopilot's tilt before ``time_unix_usec``, rad: its error
        (``measured_tilt_doubt_rad``) and how far it changed from one fix's frame to the next while they
        stood on their own images (``measured_tilt_change_rad``); one copy under the lock a frame."""
        with self._tilt_off_lock:
            seen = list(self._tilt_off_seen)
        return measured_tilt_doubt_rad(seen, time_unix_usec), measured_tilt_change_rad(seen, time_unix_usec)

    def _note_camera_tilt(
        self, tilt_off_cam_rad: tuple[float, float], exposure_unix_usec: int, timing: FrameTiming | None
    ) -> None:
        """One image-minus-autopilot tilt for the camera's stamp lateness (``clock.CameraStampOffset``)."""
        camera = self._axis.camera_offset
        if camera is not None and timing is not None:
            camera.note(tilt_off_cam_rad, exposure_unix_usec, timing.stamp_offset_s)

    def track(self, frame: NavCameraFrame, prior: InitialPrior | None) -> TrackOutcome:
        """VO on ``frame`` fused at its exposure time; initialises the estimator from ``prior`` on the
        first frame. The frame must already be admitted by the time axis (``admit_frame``)."""
        t = frame.exposure_time_unix_usec
        self._timing_of[frame.frame_id] = (t, frame.timing)
        while len(self._timing_of) > 8:
            self._timing_of.popitem(last=False)
        timings: dict[str, float] = {}
        t0 = self._clock_ns()
        motion: VoMotion | None = None
        reason: str | None = None
        try:
            motion = self._vo.process(self._on_camera(frame))
        except VoError as exc:
            reason = f"vo:{exc.reason}"
            log.debug("c1.vo.no_motion", frame=frame.seq, reason=exc.reason)
        t1 = self._clock_ns()
        timings["vo"] = (t1 - t0) / 1e6
        state: EstimatorState | None = None
        ground_tilt: AttitudeVerdict | None = None
        # One unit: no fix from the other thread lands between this frame's VO and its state.
        with self._axis.unit(UNIT_TRACK, t) as unit:
            if not self._axis.is_initialised and prior is not None:
                self._initialise(prior, frame)
                unit["initialised"] = True
            tilt = motion.ground_tilt_off_cam_rad if motion is not None else None
            if tilt is not None and motion is not None:
                prev_t, prev_timing = self._timing_of.get(motion.prev_frame_id, (t, None))
                self._note_camera_tilt(tilt, prev_t, prev_timing)
                if not self._comparable(prev_timing):
                    tilt = None  # the timing doubt alone could make this tilt: no evidence either way
            if self._ground_tilt is not None and tilt is not None and frame.alt_agl_m is not None:
                ground_tilt = self._ground_tilt.note_tilt(t, tilt)
                before = self._ground_tilt_verdict
                if ground_tilt.refused != (before.refused if before is not None else None):
                    log.warning(
                        LogEvent.VO_ATTITUDE,
                        frame=frame.seq,
                        refused=ground_tilt.refused,
                        **ground_tilt.fdr_fields(),
                    )
                self._ground_tilt_verdict = ground_tilt
                if ground_tilt.refused is not None:
                    self._note_vo_off(ground_tilt.since_unix_usec, t)
                elif before is not None and before.refused is not None and self._vo_off_spans:
                    self._note_vo_off(self._vo_off_spans[-1].until_usec, t - 1)  # never shown right before t
                self._answer_tilt("vo", ground_tilt, frame.alt_agl_m, t)
            elif not self._imu_trusted:
                self._refresh_imu_trust(t)  # a jump's hold may have lapsed with no verdict since
            if self._axis.is_initialised:
                fused: VoMotion | None = None
                if motion is not None:
                    motion = _with_attitude_doubt(motion, frame, *self.measured_ahrs_doubt_rad(t))
                    decision = self._axis.fuse_vo(motion, t)
                    if decision.accepted:
                        fused = motion
                    else:
                        reason = f"estimator:{decision.reason}"
                self._consistency.note_track(frame.frame_id, t, fused)
                state = self._axis.state_at(t)
            elif reason is None:
                reason = "no_prior"
        timings["estimator_vo"] = (self._clock_ns() - t1) / 1e6
        vo_ok = motion is not None and reason is None
        out = TrackOutcome(frame.frame_id, frame.seq, t, state, vo_ok, reason, timings, ground_tilt)
        self._fdr.record(
            FdrKind.FRAME,
            {
                "frame_id": str(frame.frame_id),
                "frame_seq": frame.seq,
                "exposure_time_unix_usec": t,
                "provenance": out.provenance.value,
                "vo_ok": vo_ok,
                "vo_reason": reason,
                "vo_inliers": motion.inlier_count if motion is not None else 0,
                "vo_delta_ne_m": [float(v) for v in motion.delta_ne_m] if motion is not None else None,
                "vo_dt_s": float(motion.dt_s) if motion is not None else None,
                "ground_tilt_check": ground_tilt.fdr_fields() if ground_tilt is not None else None,
                "lat_deg": state.lat_deg if state else None,
                "lon_deg": state.lon_deg if state else None,
                "horiz_sigma_m": state.horiz_sigma_m if state else None,
                "has_attitude": frame.attitude is not None,
                # What the frame was tracked with (a replay gives the pipeline the same again).
                "attitude_rad": (
                    [frame.attitude.roll_rad, frame.attitude.pitch_rad, frame.attitude.yaw_rad]
                    if frame.attitude is not None
                    else None
                ),
                "alt_agl_m": frame.alt_agl_m,
                "timing": dataclasses.asdict(frame.timing) if frame.timing is not None else None,
                "timings_ms": timings,
            },
        )
        return out

    # -- absolute-fix half ---------------------------------------------------------------------------

    def localise(self, frame: NavCameraFrame) -> FixOutcome:
        """The absolute fix for ``frame`` (already tracked), fused at its exposure time."""
        return self.fuse_attempt(frame, self.attempt_fix(frame))

    def attempt_fix(self, frame: NavCameraFrame) -> FixAttempt:
        """C2 -> C2.5 -> C3 -> C4 on ``frame``, searching around the estimate read when it starts."""
        timings: dict[str, float] = {}
        attempt = self._absolute_fix(self._on_camera(frame), timings)
        return replace(attempt, timings_ms=timings)

    def _on_camera(self, frame: NavCameraFrame) -> NavCameraFrame:
        """``frame`` with the camera's attitude (the autopilot's turned by ``camera.mount_*``): what VO,
        the fix path and both tilt checks use. The FDR keeps the autopilot's, as it came."""
        if frame.attitude is None or self._mount.is_nadir:
            return frame
        return replace(frame, attitude=self._mount.camera_attitude(frame.attitude))

    def fuse_attempt(self, frame: NavCameraFrame, attempt: FixAttempt) -> FixOutcome:
        """Fuse ``attempt`` (from :meth:`attempt_fix` on ``frame``) at the frame's exposure time, or note
        that the attempt gave no fix; records the ``pipeline.fix`` record."""
        t = frame.exposure_time_unix_usec
        timings = dict(attempt.timings_ms)
        fix, inliers, residual, reason, verdict = (
            attempt.fix,
            attempt.inliers,
            attempt.residual_px,
            attempt.no_fix_reason,
            attempt.integrity,
        )
        mark = self._clock_ns()
        accepted = False
        consistency: ConsistencyVerdict | None = None
        with self._axis.unit(UNIT_FIX, t) as unit:
            if attempt.attitude is not None and fix is not None:
                self._answer_tilt("fixes", attempt.attitude, self._agl_m(fix), t)
            ground_tilt = self._ground_tilt_verdict
            if fix is not None and reason is None and fix.attitude_doubt_rad <= 0.0 and self._vo_off_at(t):
                # VO's ground tilt has shown the autopilot's tilt off over this exposure, and the fix
                # leaned on it (it measured no tilt of its own, or was solved before any check showed
                # the error: a slow matcher's): refused however late it comes.
                reason = "vo_attitude_off"
                log.warning(LogEvent.FIX_ATTITUDE_REFUSED, frame=frame.seq, reason=reason)
            head = self._axis.head_unix_usec
            behind_s = max(0.0, ((head if head is not None else t) - t) / 1e6)
            if fix is not None and reason is None:
                full_evidence = verdict is None or verdict.sigma_scale <= 1.0
                consistency = self._consistency.assess(fix, full_evidence=full_evidence)
                # The regional error cancels between map fixes: added after both comparisons.
                fix = with_regional_error(consistency.fix, verdict.regional_sigma_m if verdict else 0.0)
                if frame.timing is not None:  # the exposure time's doubt, along the motion
                    fix = with_timing_error(fix, self._axis.state_at(t).vel_ned_m_s, frame.timing.sigma_s)
                if consistency.accepted:
                    decision = self._axis.fuse_fix(fix)
                    accepted = bool(decision.accepted)
                    if not accepted:
                        reason = f"gated:{decision.reason}"
                else:
                    reason = f"consistency:{consistency.reason}"
            if not accepted:
                self._axis.note_no_fix(t)
            else:
                self._sweep_rank, self._sweep_held = 0, False
                if fix is not None and fix.image_tilt_off_cam_rad is not None:
                    # a fix that measured its own tilt, and the tilt checks let through: the tilt is right
                    self._area_doubt_m = None
                    self._area_disagreements.clear()
                    with self._tilt_off_lock:
                        self._tilt_off_seen.append(
                            TiltSeen(t, fix.image_tilt_off_cam_rad, fix.attitude_doubt_rad > 0.0)
                        )
            heading_height = None
            evidence = verdict.evidence if verdict is not None else None
            if accepted and self._heading_height is not None and isinstance(evidence, AreaEvidence):
                heading_height = self._heading_height.note(evidence)
            if attempt.rung is not None and self._ladder is not None:
                self._ladder.note(attempt.rung, accepted)
            doubt = self._note_doubt(frame, attempt, fix if accepted else None, reason, t)
            unit["accepted"] = accepted
        timings["estimator_fix"] = (self._clock_ns() - mark) / 1e6
        out = FixOutcome(
            frame.frame_id,
            frame.seq,
            t,
            fix,
            accepted,
            inliers,
            residual,
            reason,
            behind_s,
            timings,
            verdict,
            attempt.attitude,
            ground_tilt,
            attempt.rung,
            heading_height,
            doubt,
        )
        self._fdr.record(
            FdrKind.FIX,
            {
                "frame_id": str(frame.frame_id),
                "frame_seq": frame.seq,
                "exposure_time_unix_usec": t,
                "fix_accepted": accepted,
                "inliers": inliers,
                "residual_px": residual,
                "no_fix_reason": reason,
                "vpr_first_rank": attempt.vpr_first_rank,
                "rung": attempt.rung,
                "area_doubt_m": None if attempt.area_doubt_m is None else round(attempt.area_doubt_m, 2),
                "fused_behind_s": round(behind_s, 4),
                "fix_lat_deg": fix.lat_deg if fix else None,
                "fix_lon_deg": fix.lon_deg if fix else None,
                "fix_sigma_m": fix.horiz_sigma_m if fix else None,
                "fix_shared_sigma_m": fix.shared_sigma_m if fix else None,
                "fix_image_tilt_off_deg": (
                    round(math.degrees(fix.attitude_disagreement_rad), 3)
                    if fix and fix.attitude_disagreement_rad is not None
                    else None
                ),
                "fix_image_tilt_off_cam_deg": (
                    [round(math.degrees(v), 4) for v in fix.image_tilt_off_cam_rad]
                    if fix and fix.image_tilt_off_cam_rad is not None
                    else None
                ),
                "fix_attitude_doubt_deg": round(math.degrees(fix.attitude_doubt_rad), 3) if fix else None,
                "fix_slope_sigma_m": round(fix.slope_sigma_m, 3) if fix else None,
                "fix_yaw_deg": round(math.degrees(fix.yaw_rad), 3) if fix else None,
                "fix_alt_amsl_m": round(fix.alt_amsl_m, 2) if fix else None,
                "timing": _timing_fields(frame.timing),
                "attitude_check": attempt.attitude.fdr_fields() if attempt.attitude is not None else None,
                "ground_tilt_check": ground_tilt.fdr_fields() if ground_tilt is not None else None,
                "integrity": verdict.fdr_fields() if verdict is not None else None,
                "consistency": consistency.fdr_fields() if consistency is not None else None,
                "heading_height_check": heading_height.fdr_fields() if heading_height is not None else None,
                "prior_doubt": (
                    {
                        **doubt.fdr_fields(),
                        "frame_texture": _rounded(attempt.frame_texture),
                        "map_texture": _rounded(attempt.map_texture),
                    }
                    if doubt is not None
                    else None
                ),
                "timings_ms": timings,
            },
        )
        return out

    def _note_doubt(
        self, frame: NavCameraFrame, attempt: FixAttempt, fused: PoseFix | None, reason: str | None, t: int
    ) -> DoubtVerdict | None:
        """The attempt's outcome for the doubt on an unconfirmed start prior, inside the fix's unit of the
        axis at ``t``: a counted failure may raise the position's sigma (from ``t`` on), and the first
        fix after the prior was doubted says how far off it was. None once the prior is confirmed."""
        doubt = self._doubt
        if doubt is None or not doubt.active or attempt.searched_from is None:
            return None
        lat, lon, sigma_m = attempt.searched_from
        cover_m = math.inf
        if self._map_extent is not None:
            c_lat, c_lon, radius_m = self._map_extent
            cover_m = float(haversine_m(lat, lon, c_lat, c_lon)) + radius_m
        moved_m = float(haversine_m(lat, lon, fused.lat_deg, fused.lon_deg)) if fused is not None else None
        verdict = doubt.note(
            accepted=fused is not None,
            reason=reason,
            frame_texture=attempt.frame_texture,
            map_texture=attempt.map_texture,
            searched_sigma_m=sigma_m,
            cover_sigma_m=cover_m,
            moved_m=moved_m,
        )
        raise_to = verdict.raise_to_sigma_m
        if raise_to is not None and self._axis.raise_position_sigma(raise_to, t):
            fields = {"frame": frame.seq, "searched_sigma_m": round(sigma_m, 1), **verdict.fdr_fields()}
            log.warning(LogEvent.PRIOR_DOUBTED, **fields)
            self._fdr.record(FdrKind.PRIOR_DOUBT, {"event": "doubted", **fields})
        if verdict.reanchored_m is not None:
            fields = {
                "frame": frame.seq,
                "reanchored_m": round(verdict.reanchored_m, 1),
                "widenings": doubt.widenings,
            }
            log.warning(LogEvent.PRIOR_REANCHORED, **fields)
            self._fdr.record(FdrKind.PRIOR_DOUBT, {"event": "reanchored", **fields})
        return verdict

    def _agl_m(self, fix: PoseFix) -> float:
        """Height of ``fix`` above the map's ground, m (flat ground; never below it)."""
        return max(0.0, fix.alt_amsl_m - self._ground_alt_amsl_m)

    def _with_slope_doubt(self, fix: PoseFix) -> PoseFix:
        """``fix``, where it was solved allowing the autopilot's tilt an error (``attitude_doubt_rad``),
        stating the ground distance the error shown makes at its height as error it shares with the
        fixes around it. The image's tilt to the ground and the autopilot's tilt to gravity differ by
        that much, and a wrong attitude and a ground sloping as much look the same: the pose is solved
        against flat ground, so on such a slope the fix that stands on the image is off by it, as one
        leaning on the autopilot is under a wrong attitude. Fusing more fixes over the same slope does
        not average it away; nor does it make any one of them noisier, so the estimator weighs the fix
        without it (``PoseFix.slope_sigma_m``) and states it in every output after."""
        if fix.attitude_doubt_rad <= 0.0:
            return fix
        shown_rad = fix.attitude_doubt_rad / TILT_DOUBT_MARGIN
        slope_m = self._agl_m(fix) * math.tan(shown_rad)
        return replace(with_regional_error(fix, slope_m), slope_sigma_m=slope_m)

    def _footprint_m(self, fix: PoseFix) -> float:
        """Ground the frame of ``fix`` covers across, m (nadir, flat ground)."""
        return 2.0 * self._agl_m(fix) * math.tan(self._calib.hfov_rad / 2.0)

    def _note_vo_off(self, since_usec: int, t: int) -> None:
        """The ground-tilt check shows the attitude off at ``t`` on evidence since ``since_usec``."""
        spans = self._vo_off_spans
        if spans and since_usec <= spans[-1].until_usec:
            spans[-1] = _OffSpan(min(spans[-1].since_usec, since_usec), max(spans[-1].until_usec, t))
        else:
            spans.append(_OffSpan(since_usec, t))

    def _vo_off_at(self, t: int) -> bool:
        """Whether the ground-tilt check has shown the attitude off over an exposure at ``t``: ``t`` lies
        in a span where it refused, or after its newest verdict while that verdict refuses (until a tilt
        says otherwise the attitude is still off). A span runs on to just before the first verdict that
        lets go, so a slow fix exposed between the last verdict that refused and that one is judged by it
        however late. A frame whose pair gave no tilt, or a fix fused before its own frame's VO, has no
        verdict of its own; measured without this rule on a GPU (3 deg of roll at 1200 m AGL across
        dates), one such fix in about 15 slipped through, 64 m off at a stated 4 m."""
        spans = self._vo_off_spans
        if any(span.since_usec <= t <= span.until_usec for span in spans):
            return True
        newest = self._ground_tilt_verdict
        return newest is not None and newest.refused is not None and bool(spans) and t > spans[-1].until_usec

    def _tilt_shown_at(self, t: int) -> bool:
        """Whether either check shows the autopilot's tilt off for an exposure at ``t``: VO over ``t``, or
        the fixes' check in its newest verdict."""
        fixes = self._fix_tilt_verdict
        return self._vo_off_at(t) or (fixes is not None and fixes.off)

    def _answer_tilt(self, source: str, verdict: AttitudeVerdict, agl_m: float, t: int) -> None:
        """What the estimate does with a tilt check's verdict (``source``: ``fixes`` or ``vo``), inside
        a unit of the axis at ``t``. When the check first shows a tilt error, or a larger one than it
        has shown since it last refused nothing, the fixes fused before it saw it, and VO, leaned on the
        same wrong tilt: the position's sigma is raised to twice the ground distance it makes from
        ``agl_m`` (m), in the filter's covariance, so a fix solved without leaning on it may pull the
        state back by that much. Raised once per error, not on every verdict: the fixes fused since are
        standing on their own images (``_stand_on_image_rad``), and VO states its own
        (``measured_ahrs_doubt_rad``). The IMU's accelerations are
        rotated with the same attitude (gravity leaks in): it is left out while either check refuses
        (after a lone jump, for ``TILT_JUMP_IMU_HOLD_S`` unless a verdict follows), and said again on
        the next frame when the axis could not take it (not yet initialised)."""
        if verdict.suspect_deg is not None and verdict.suspect_deg > self._tilt_answered_deg[source]:
            tilt_m = agl_m * math.tan(math.radians(min(verdict.suspect_deg, 45.0)))
            if self._axis.raise_position_sigma(2.0 * tilt_m, t):
                self._tilt_answered_deg[source] = verdict.suspect_deg
        elif verdict.refused is None:
            self._tilt_answered_deg[source] = 0.0
        if verdict.refused is None:
            self._tilt_refused_until[source] = None
        elif verdict.off:
            self._tilt_refused_until[source] = math.inf
        else:  # a jump: held back, not proof; the IMU comes back unless the next verdicts say so
            self._tilt_refused_until[source] = t + TILT_JUMP_IMU_HOLD_S * 1e6
        self._refresh_imu_trust(t)

    def _refresh_imu_trust(self, t: int) -> None:
        """Tell the time axis at ``t`` (inside one of its units) whether the IMU is trusted: while no tilt
        check's refusal holds (``_tilt_refused_until``)."""
        trusted = all(until is None or t >= until for until in self._tilt_refused_until.values())
        if trusted != self._imu_trusted and self._axis.set_imu_trusted(trusted, t):
            self._imu_trusted = trusted

    def _absolute_fix(self, frame: NavCameraFrame, timings: dict[str, float]) -> FixAttempt:
        if self._vpr is None or self._rerank is None or self._ladder is None:
            return FixAttempt(None, 0, None, "no_map")  # a replay without a map cache: VO only, never a fix
        if frame.attitude is None or frame.alt_agl_m is None:
            return FixAttempt(None, 0, None, "no_attitude_or_altitude")
        with self._axis.unit(UNIT_FIX_PRIOR, frame.exposure_time_unix_usec):
            prior_state = self._axis.state_at(frame.exposure_time_unix_usec)
            tilt_shown = self._tilt_shown_at(frame.exposure_time_unix_usec)
        search_prior = _search_prior(prior_state)
        doubting = self._doubt is not None and self._doubt.active
        frame_texture = edge_share(frame.image_bgr) if doubting else None
        # The effort ladder: this attempt's matcher and how many of the candidates it gets.
        rung = self._ladder.choose(prior_state.horiz_sigma_m)
        t0 = self._clock_ns()
        first_rank: int | None = None
        pinned = False
        try:
            query = self._vpr.embed_query(frame, self._calib)
            region, sweep = self._search_region(prior_state, frame)
            if sweep:
                # the prior's own place stays in every attempt of a doubted prior's sweep, while the rung
                # gets room for more (a right prior the matcher failed on is tried again each time)
                pinned = region is not None and rung.candidates >= 2
                first_rank, vpr_result = self._sweep(self._vpr, query, region, pinned)
            else:
                vpr_result = self._vpr.retrieve_topk(query, self._vpr_cfg.top_k, region=region)
        except VprError as exc:
            log.error(LogEvent.VPR_ERROR, frame=frame.seq, error=str(exc))
            return FixAttempt(None, 0, None, "vpr_error", frame_texture=frame_texture)
        t1 = self._clock_ns()
        timings["vpr"] = (t1 - t0) / 1e6
        searched_from = (prior_state.lat_deg, prior_state.lon_deg, search_prior.sigma_m) if doubting else None
        if not vpr_result.candidates:
            return FixAttempt(
                None, 0, None, "no_tiles_in_region", frame_texture=frame_texture, searched_from=searched_from
            )
        rerank_result = self._footprint_first(frame, prior_state, self._rerank.rerank(frame, vpr_result))
        # Corpus-wide, the prior says nothing of where to look: an area matcher searches a disc around
        # each candidate the sweep hands on (a disc at the prior would take the first one's place).
        rerank_result = replace(rerank_result, search=None if region is None else search_prior)
        rerank_result = replace(rerank_result, candidates=rerank_result.candidates[: rung.candidates])
        map_texture = None
        if doubting and rerank_result.candidates:
            map_texture = edge_share(np.asarray(rerank_result.candidates[0].tile_pixels_handle.pixels()))
        attempt = replace(
            self._matched(frame, prior_state, rung, rerank_result, timings, t1, tilt_shown),
            rung=rung.name,
            frame_texture=frame_texture,
            map_texture=map_texture,
            searched_from=searched_from,
        )
        if first_rank is None:
            return attempt
        # The next sweeping attempt goes on past the tiles this one matched (back to the top after a
        # fix), unless it solved a pose there: then once more on the same ranks, so that a fix the
        # integrity rule or the consistency monitor held back can be confirmed by the next frame's. An
        # area alignment is solved on every attempt: one whose peak does not stand out of its disc is
        # the map not answering there, not a fix to confirm (holding on it halved the sweep's pace).
        no_answer = attempt.no_fix_reason in _NO_PEAK_REASONS
        hold = attempt.fix is not None and not no_answer and not self._sweep_held
        self._sweep_held = hold
        if not hold:
            swept = len(rerank_result.candidates) - (1 if pinned else 0)
            self._sweep_rank = first_rank + max(1, swept)
        return replace(attempt, vpr_first_rank=first_rank)

    def _sweep(
        self, vpr: VprStrategy, query: VprQuery, region: SearchRegion | None, pinned: bool
    ) -> tuple[int, VprResult]:
        """Retrieval as a sweep: the tiles ranked from ``_sweep_rank`` on (``vpr.top_k`` of them, for the
        rerank to choose from), so that consecutive attempts that fail go down the ranking instead of
        matching the same top tiles again; past the last tile it starts again at the top. ``region``:
        None corpus-wide (F6, ranked by appearance), else a doubted prior's region (ranked by the VPR
        strategy within it: ``geo_prior`` by distance, so the sweep goes outward). ``pinned``: the
        region's first tile (the prior's own place) leads every window and the sweep goes on from rank 1.
        Returns (the first rank swept, the result). One pass over N tiles takes ceil(N / n) attempts
        with n tiles swept an attempt (``rerank.top_n``, one fewer when pinned), at most twice that when
        poses are solved and refused."""
        k = self._vpr_cfg.top_k
        lead = 1 if pinned else 0
        first = max(self._sweep_rank, lead)
        result = vpr.retrieve_topk(query, first + k - lead, region=region)
        ranked = result.candidates
        if first >= len(ranked):  # past the end: from the top again
            first = lead
        window = ranked[first : first + k - lead]
        if pinned and ranked:
            window = [ranked[0], *window]
        return first, replace(result, candidates=window)

    def _matched(
        self,
        frame: NavCameraFrame,
        prior_state: EstimatorState,
        rung: Rung,
        rerank_result: RerankResult,
        timings: dict[str, float],
        t1: int,
        tilt_shown: bool,
    ) -> FixAttempt:
        """C3 -> C4 on the reranked candidates (``t1``: when retrieval ended, for ``timings``;
        ``tilt_shown``: a check showed the autopilot's tilt off when the attempt began)."""
        t2 = self._clock_ns()
        timings["rerank"] = (t2 - t1) / 1e6
        try:
            match = rung.matcher.match(frame, rerank_result, self._calib)
        except InsufficientInliersError as exc:
            timings["match"] = (self._clock_ns() - t2) / 1e6
            return FixAttempt(None, exc.best_inlier_count, None, "insufficient_inliers")
        except MatcherError as exc:
            timings["match"] = (self._clock_ns() - t2) / 1e6
            log.error(LogEvent.PIPELINE_FRAME_ERROR, frame=frame.seq, stage="match", error=str(exc))
            return FixAttempt(None, 0, None, "matcher_error")
        t3 = self._clock_ns()
        timings["match"] = (t3 - t2) / 1e6
        best = match.best
        if best.area is not None and best.inlier_count == 0:
            return self._area_matched(frame, match, rerank_result, prior_state, timings, t3)
        handle = next(c.tile_pixels_handle for c in rerank_result.candidates if c.tile_id == best.tile_id)
        try:
            fix = self._pose.solve(frame, best, handle, self._calib)
        except PoseError as exc:
            timings["pose"] = (self._clock_ns() - t3) / 1e6
            return FixAttempt(
                None, best.inlier_count, match.reprojection_residual_px, f"pose_rejected:{exc.reason}"
            )
        t4 = self._clock_ns()
        timings["pose"] = (t4 - t3) / 1e6
        assert fix.image_tilt_off_cam_rad is not None  # a solve from points measures the tilt
        self._note_camera_tilt(fix.image_tilt_off_cam_rad, frame.exposure_time_unix_usec, frame.timing)
        attitude: AttitudeVerdict | None = None
        if self._comparable(frame.timing):
            attitude = self._attitude.note(fix, self._footprint_m(fix))
            self._fix_tilt_verdict = attitude
            if attitude.refused is not None and not attitude.off:  # a jump: held back until the next say
                log.warning(LogEvent.FIX_ATTITUDE_REFUSED, frame=frame.seq, **attitude.fdr_fields())
                return FixAttempt(
                    fix,
                    best.inlier_count,
                    match.reprojection_residual_px,
                    attitude.refused,
                    attitude=attitude,
                )
        # (Where the timing doubt at this attitude rate could make the tilt difference by itself, the check
        # learns nothing from it, and the solver has already widened the tilt prior by it.)
        stand_rad = self._stand_on_image_rad(fix, tilt_shown, attitude)
        if stand_rad != fix.attitude_doubt_rad:
            try:
                fix = self._pose.solve(frame, best, handle, self._calib, attitude_doubt_rad=stand_rad)
            except PoseError:
                reason = attitude.refused if attitude is not None and attitude.off else "vo_attitude_off"
                log.warning(LogEvent.FIX_ATTITUDE_REFUSED, frame=frame.seq, reason=reason)
                return FixAttempt(
                    fix, best.inlier_count, match.reprojection_residual_px, reason, attitude=attitude
                )
        fix = self._with_slope_doubt(fix)
        verdict = self._judge(frame, match, rerank_result, fix, prior_state)
        timings["integrity"] = (self._clock_ns() - t4) / 1e6
        return self._judged(frame, match, best, verdict, attitude)

    def _stand_on_image_rad(self, fix: PoseFix, tilt_shown: bool, attitude: AttitudeVerdict | None) -> float:
        """What the attitude prior of ``fix`` (solved from points) allows the autopilot's tilt beyond its
        sigma, rad: 0 while neither check shows the tilt off (``tilt_shown``: one did when the attempt
        began; ``attitude``: the fixes' check after this one, None where it could not judge).
        Else ``TILT_DOUBT_MARGIN`` x the larger of the tilt difference this fix's own image shows, the
        error the fixes' check has shown, and ``pose.attitude_sigma_deg``: the fix stands on its image.
        Not VO's error: a fix that measures its own tilt is the sharper witness of it (on a real PX4, VO's
        ground tilt at a slow corner called the autopilot 16-25 deg off while the fixes, each measuring
        1-2 deg, were refused for 24 s and the output withheld into a failsafe)."""
        fixes_off = attitude is not None and attitude.off
        if not tilt_shown and not fixes_off:
            return 0.0
        assert fix.image_tilt_off_cam_rad is not None
        shown_deg = max(
            math.degrees(math.hypot(*fix.image_tilt_off_cam_rad)),
            (attitude.suspect_deg or 0.0) if attitude is not None and attitude.off else 0.0,
            self._attitude.sigma_deg,
        )
        return math.radians(TILT_DOUBT_MARGIN * min(shown_deg, MAX_TILT_DOUBT_DEG))

    def _area_matched(
        self,
        frame: NavCameraFrame,
        match: MatchResult,
        rerank_result: RerankResult,
        prior_state: EstimatorState,
        timings: dict[str, float],
        t3: int,
    ) -> FixAttempt:
        """C4 on an area matcher's best alignment without correspondences (``c4_pose/area_pose.py``):
        its pose, then the integrity rule. The fix measured no tilt of its own, so neither the camera's
        stamp fit nor the fixes' attitude check hears from it (VO's ground tilt still judges its
        exposure). An alignment with correspondences is solved from them like any point match."""
        best = match.best
        if self._area_pose is None:
            raise RuntimeError("an area matcher ran but the pipeline has no area pose solver (composition)")
        try:
            fix = self._area_pose.solve(frame, best)
        except PoseError as exc:
            timings["pose"] = (self._clock_ns() - t3) / 1e6
            return FixAttempt(None, 0, None, f"pose_rejected:{exc.reason}")
        t4 = self._clock_ns()
        timings["pose"] = (t4 - t3) / 1e6
        stated, doubt_m = self._with_area_doubt(fix)
        verdict = self._judge(frame, match, rerank_result, stated, prior_state)
        self._note_area_agreement(fix, prior_state)
        timings["integrity"] = (self._clock_ns() - t4) / 1e6
        return replace(self._judged(frame, match, best, verdict, None), area_doubt_m=doubt_m)

    def _with_area_doubt(self, fix: PoseFix) -> tuple[PoseFix, float | None]:
        """``fix`` (alignment-only) stating the area doubt when there is one (``_note_area_agreement``), as
        error it shares with its neighbours; and the doubt, m (None: none).

        Such a fix leans wholly on the autopilot's tilt, which the image cannot check: after a tilt fault
        (3 deg of roll is 63 m at 1200 m AGL) every fix lands the same distance off, and VO's ground tilt,
        noisy from high up, may take seconds to prove it. A run of ``AREA_DISAGREEMENT_RUN`` fixes that
        disagree with the VO-propagated prior is that fault's trace, or a wrong prior's: from then on the
        fixes state the run's offset. It is not dropped when a later fix agrees with the estimate, which
        the doubted fixes themselves have moved: only what can check the tilt ends it (a fix that measured
        its own tilt, or VO's ground tilt ruling out a tilt that large at this height)."""
        doubt = self._area_doubt_m
        if doubt is None:
            return fix, None
        agl_m = self._agl_m(fix)
        verdict = self._ground_tilt_verdict
        if (
            verdict is not None
            and verdict.refused is None
            and agl_m * math.tan(math.radians(min(verdict.bias_upper_deg, 45.0))) < doubt
        ):
            self._area_doubt_m = None  # VO's ground tilt now rules out a tilt that would make the doubt
            self._area_disagreements.clear()
            return fix, None
        return with_regional_error(fix, doubt), doubt

    def _note_area_agreement(self, fix: PoseFix, prior: EstimatorState) -> None:
        """Whether this alignment-only fix, as solved, disagrees with the VO-propagated prior (NIS beyond
        ``integrity.prior_gate_chi2``): a disagreement joins the run, and a run of
        ``AREA_DISAGREEMENT_RUN`` sets the area doubt (``_with_area_doubt``) to its median offset, or raises
        it; an agreement ends the run (not the doubt)."""
        innov = (
            np.asarray(fix.pos_ned_m, dtype=np.float64)[:2]
            - np.asarray(prior.pos_ned_m, dtype=np.float64)[:2]
        )
        s_mat = prior.map_frame_cov_ne_m2 + np.asarray(fix.cov_ned_m2, dtype=np.float64)[:2, :2]
        try:
            nis = float(innov @ np.linalg.solve(s_mat, innov))
        except np.linalg.LinAlgError:
            return
        if not math.isfinite(nis):
            return
        if nis <= self._prior_gate_chi2:
            self._area_disagreements.clear()
            return
        self._area_disagreements.append(innov)
        if len(self._area_disagreements) == AREA_DISAGREEMENT_RUN:
            offset_m = float(np.hypot(*np.median(np.asarray(self._area_disagreements), axis=0)))
            self._area_doubt_m = max(offset_m, self._area_doubt_m or 0.0)

    def _judged(
        self,
        frame: NavCameraFrame,
        match: MatchResult,
        best: CandidateMatchSet,
        verdict: IntegrityVerdict,
        attitude: AttitudeVerdict | None,
    ) -> FixAttempt:
        """The attempt the integrity rule's ``verdict`` makes of a solved fix."""
        residual = None if best.inlier_count == 0 else match.reprojection_residual_px
        if not verdict.accepted:
            log.warning(
                LogEvent.FIX_INTEGRITY_REFUSED,
                frame=frame.seq,
                reason=verdict.reason,
                **{k: v for k, v in verdict.fdr_fields().items() if k not in ("accepted", "reason")},
            )
            return FixAttempt(
                verdict.fix,
                best.inlier_count,
                residual,
                f"integrity:{verdict.reason}",
                integrity=verdict,
                attitude=attitude,
            )
        return FixAttempt(
            verdict.fix,
            best.inlier_count,
            residual,
            None,
            integrity=verdict,
            attitude=attitude,
        )

    def _footprint_first(
        self, frame: NavCameraFrame, prior_state: EstimatorState, result: RerankResult
    ) -> RerankResult:
        """``result`` with the chip around the ground under the principal point first (``FootprintChips``)
        while the prior is tight: where the prior puts the camera, plus the ground offset of the
        principal ray from the camera's attitude and height (``frame`` carries the camera's attitude)."""
        chips = self._footprint_chips
        if chips is None or not chips.applies(prior_state.horiz_sigma_m):
            return result
        if frame.attitude is None or frame.alt_agl_m is None:
            return result
        offset_m = principal_ground_offset_m(self._calib, frame.attitude, frame.alt_agl_m)
        if offset_m is None:
            return result
        centre_ned_m = np.array(prior_state.pos_ned_m, dtype=np.float64)
        centre_ned_m[:2] += offset_m
        lat, lon, _ = self._ltp.to_geodetic(centre_ned_m)
        return chips.first(result, float(lat), float(lon))

    def _judge(
        self,
        frame: NavCameraFrame,
        match: MatchResult,
        rerank_result: RerankResult,
        fix: PoseFix,
        prior_state: EstimatorState,
    ) -> IntegrityVerdict:
        """The integrity rule on the best candidate's fix: its evidence, the poses of the rival
        candidates it asks for (solved here; one that cannot be solved is no rival), and the prior."""
        size = (self._calib.width_px, self._calib.height_px)
        best = match.best
        best_ev = evidence_of(best, size)
        handles = {c.tile_id: c.tile_pixels_handle for c in rerank_result.candidates}
        rivals = []
        for i, cand in enumerate(match.per_candidate):
            rival_ev = evidence_of(cand, size)
            if i == match.best_candidate_idx or not self._integrity.wants_rival(best_ev, rival_ev):
                continue
            try:
                if cand.area is not None and cand.inlier_count == 0 and self._area_pose is not None:
                    rival_fix = self._area_pose.solve(frame, cand)
                else:
                    rival_fix = self._pose.solve(
                        frame,
                        cand,
                        handles[cand.tile_id],
                        self._calib,
                        attitude_doubt_rad=fix.attitude_doubt_rad,
                    )
            except PoseError:
                continue
            rivals.append(CandidateFix(rival_fix, rival_ev))
        gsd = best.area.map_gsd_m_px if best.area is not None else float(handles[best.tile_id].gsd_m_px)
        return self._integrity.assess(
            CandidateFix(fix, best_ev),
            map_gsd_m_px=gsd,
            rivals=rivals,
            prior=prior_state,
        )


def _search_prior(state: EstimatorState) -> SearchPrior:
    """Where the estimate puts the camera, for a matcher that searches around it: its position and its
    horizontal sigma relative to the map (the map's own error is common to the map and the fix)."""
    cov = state.map_frame_cov_ne_m2
    if not np.all(np.isfinite(cov)):
        return SearchPrior(state.lat_deg, state.lon_deg, math.inf)
    sigma = math.sqrt(max(float(np.max(np.linalg.eigvalsh(cov))), 0.0))
    return SearchPrior(state.lat_deg, state.lon_deg, sigma)


def _rounded(value: float | None) -> float | None:
    return None if value is None else round(value, 4)


def _timing_fields(timing: FrameTiming | None) -> dict[str, object] | None:
    """A frame's timing for the FDR (``FrameTiming``): rates in deg/s, times in s."""
    if timing is None:
        return None
    return {
        "down_rate_cam_deg_s": [round(math.degrees(v), 3) for v in timing.down_rate_cam_rad_s],
        "stamp_offset_s": round(timing.stamp_offset_s, 4),
        "sigma_s": round(timing.sigma_s, 4),
    }


#: The AHRS doubt (``FrameTiming.ahrs_sigma_rad``) a gentle manoeuvre gives, up to a 10 deg swing, which
#: still leaves a tilt comparable with the autopilot's: it states error, it does not stop the checks.
AHRS_DOUBT_FREE_RAD: Final[float] = math.radians(1.0)
#: Accepted fixes' tilt errors kept for ``measured_ahrs_doubt_rad`` (3 Hz over its window), and the
#: window, s (as the autopilot's swing window, ``vehicle_state.AHRS_SWING_WINDOW_S``).
TILT_OFF_HISTORY: Final[int] = 32
MEASURED_TILT_WINDOW_S: Final[float] = 8.0
#: The newest two fixes' tilt errors speak for themselves within this, s (a fix comes 0.3-1.2 s after
#: its exposure on a busy CPU, so the track half may see none younger than that).
RECENT_TILT_WINDOW_S: Final[float] = 3.0
#: Consecutive fixes further apart than this, s, say nothing of how the tilt error changes between two
#: of VO's frames; fewer pairs than ``MIN_CHANGE_PAIRS`` in the window say nothing either.
MAX_CHANGE_PAIR_GAP_S: Final[float] = 1.0
MIN_CHANGE_PAIRS: Final[int] = 3
#: A fix that stands on its own image while a tilt check shows the autopilot's tilt off allows that tilt
#: this times the difference its image shows (``NavigationPipeline._stand_on_image_rad``): one image's
#: measure of it scatters.
TILT_DOUBT_MARGIN: Final[float] = 1.5
#: The most tilt difference, deg, a fix's attitude prior is widened for (the solver's own gate on the
#: image's tilt against the autopilot's, ``pose.max_attitude_disagreement_deg``, refuses beyond).
MAX_TILT_DOUBT_DEG: Final[float] = 15.0
#: The camera's axis is taken at most this far from nadir for VO's lever (cos 60 deg).
MIN_COS_OFF_NADIR: Final[float] = 0.5
#: How fast the autopilot's attitude error changes, as a share of its size per second: it built up and
#: decayed over 2-10 s on ArduPilot SITL (``VehicleStateTracker.ahrs_doubt_rad``), so take 2 s.
AHRS_ERROR_CHANGE_TIME_S: Final[float] = 2.0


@dataclass(frozen=True)
class TiltSeen:
    """What one accepted fix solved from points measured of the autopilot's tilt."""

    #: The fix's exposure, us (Unix).
    time_unix_usec: int
    #: World down by its image minus by the autopilot, on the camera's x and y axes, rad.
    off_cam_rad: tuple[float, float]
    #: Whether it stood on its own image (a tilt check showed the autopilot's tilt off).
    stood: bool


def _seen_in_window(seen: list[TiltSeen], time_unix_usec: int) -> list[TiltSeen]:
    lo = time_unix_usec - int(MEASURED_TILT_WINDOW_S * 1e6)
    return sorted(
        (x for x in seen if lo <= x.time_unix_usec <= time_unix_usec), key=lambda x: x.time_unix_usec
    )


def measured_tilt_doubt_rad(seen: list[TiltSeen], time_unix_usec: int) -> float:
    """The autopilot's tilt error, rad, that accepted fixes measured before ``time_unix_usec`` (a fix
    solved from points measures the camera's own tilt); 0 with none there (no fix measured it: area
    correlation, VO alone). The larger of their median over ``MEASURED_TILT_WINDOW_S`` and the smaller of
    the newest two within ``RECENT_TILT_WINDOW_S``: an error that appears is VO's doubt as soon as two
    fixes agree on it, not once it fills half the window (on a real PX4 beside two busy loops, a 4-8 deg
    error carried VO 20 m off in 2 s while the 8 s median still said little); one fix made with a stale
    attitude (6.3 deg at a link cut, in the emulator) holds up nothing alone."""
    kept = _seen_in_window(seen, time_unix_usec)
    if not kept:
        return 0.0
    sizes = [math.hypot(*x.off_cam_rad) for x in kept]
    recent_lo = time_unix_usec - int(RECENT_TILT_WINDOW_S * 1e6)
    newest = [size for x, size in zip(kept[-2:], sizes[-2:], strict=True) if x.time_unix_usec >= recent_lo]
    return max(float(np.median(sizes)), min(newest) if len(newest) == 2 else 0.0)


def measured_tilt_change_rad(seen: list[TiltSeen], time_unix_usec: int) -> float:
    """How far the autopilot's tilt error changed between consecutive fixes' frames, rad (the root mean
    square over ``MEASURED_TILT_WINDOW_S`` of the change of the error vector, from pairs at most
    ``MAX_CHANGE_PAIR_GAP_S`` apart; at least ``MIN_CHANGE_PAIRS``), while the newest fix stood on its own
    image (a check shows the autopilot's tilt off); else 0. VO de-rotates each frame with the autopilot's
    tilt, so that change is what moves it, whatever makes it: a drifting AHRS, or attitudes taken from the
    wrong moment in a turn (on a real PX4 under load, fixes right to 0.07 m found the error swinging 1-2
    deg from frame to frame, and VO was 3-4 m wrong a frame at 79 m AGL, stating 0.9 m). Only while the
    tilt is shown off: otherwise the changes are the image's own noise, which from high up across dates
    would bury VO for nothing."""
    kept = _seen_in_window(seen, time_unix_usec)
    if not kept or not kept[-1].stood:
        return 0.0
    gap_usec = int(MAX_CHANGE_PAIR_GAP_S * 1e6)
    changes = [
        math.hypot(b.off_cam_rad[0] - a.off_cam_rad[0], b.off_cam_rad[1] - a.off_cam_rad[1])
        for a, b in itertools.pairwise(kept)
        if b.time_unix_usec - a.time_unix_usec <= gap_usec
    ]
    if len(changes) < MIN_CHANGE_PAIRS:
        return 0.0
    return math.sqrt(float(np.mean(np.square(changes))))


def _with_attitude_doubt(
    motion: VoMotion, frame: NavCameraFrame, measured_rad: float = 0.0, measured_change_rad: float = 0.0
) -> VoMotion:
    """``motion`` stating the displacement error a drifting autopilot attitude makes: VO de-rotates the
    frames with it, so a tilt error that changed by ``d`` between them moves the ground under the camera's
    axis by ``height / cos(off-nadir)^2 x d``. The error is the larger of the autopilot's AHRS doubt after
    its manoeuvres (``FrameTiming.ahrs_sigma_rad``) and ``measured_rad``, the tilt error the fixes found
    (``NavigationPipeline.measured_ahrs_doubt_rad``): on PX4 SIH, 2-5 deg through a sustained 38 deg roll
    with no swing to show it, which made VO 1 m a frame wrong at 80 m. The change over the interval is
    that error's share of ``AHRS_ERROR_CHANGE_TIME_S``, or ``measured_change_rad`` when more: how far the
    fixes found it change from one frame to the next (``NavigationPipeline.measured_ahrs_doubt_rad``)."""
    timing = frame.timing
    doubt_rad = max(timing.ahrs_sigma_rad if timing is not None else 0.0, measured_rad)
    change_rad = max(doubt_rad * min(1.0, motion.dt_s / AHRS_ERROR_CHANGE_TIME_S), measured_change_rad)
    if change_rad <= 0.0 or frame.alt_agl_m is None or frame.attitude is None:
        return motion
    cos_off_nadir = max(float(frame.attitude.R_ned_cam()[2, 2]), MIN_COS_OFF_NADIR)
    extra_m = frame.alt_agl_m / cos_off_nadir**2 * change_rad
    return replace(motion, cov_ne_m2=np.asarray(motion.cov_ne_m2) + np.eye(2) * extra_m**2)
