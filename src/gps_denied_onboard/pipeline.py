"""The F3 flight pipeline for one nav frame, stage by stage.

    frame ─┬─ C1 visual odometry ───────────────────────────────┐
           └─ C2 VPR (prior-gated) → C2.5 rerank → C3 match → C4 pose ─┴→ C5 estimator → state

Every stage's failure has one meaning for the estimator:
- no attitude/altitude at exposure → no absolute fix from this frame (never reuse stale data);
- VPR/rerank/matcher error or too few inliers → no fix; C5 propagates on VO (``visual_propagated``);
- pose rejected (degenerate, implausible) → no fix;
- fix outside the estimator's gate → rejected by C5 (a wrong tile cannot teleport the estimate).
The pipeline is synchronous and single-threaded by contract (INV-1); the daemon runs it off the loop.
"""

from __future__ import annotations

import math
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field

import structlog

from gps_denied_onboard.camera.types import CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c1_vio.types import VoError, VoMotion
from gps_denied_onboard.components.c2_5_rerank.protocol import RerankStrategy
from gps_denied_onboard.components.c2_vpr.protocol import SearchRegion, VprStrategy
from gps_denied_onboard.components.c2_vpr.types import VprError
from gps_denied_onboard.components.c3_matcher.errors import InsufficientInliersError, MatcherError
from gps_denied_onboard.components.c3_matcher.protocol import CrossDomainMatcher
from gps_denied_onboard.components.c4_pose.types import PoseError, PoseFix
from gps_denied_onboard.components.c5_estimator.types import EstimatorState
from gps_denied_onboard.components.c13_fdr.protocol import FdrClient
from gps_denied_onboard.config import VprConfig
from gps_denied_onboard.constants import FdrKind, LogEvent, Provenance
from gps_denied_onboard.geo import LocalTangentPlane

log = structlog.get_logger(__name__)


@dataclass(frozen=True)
class InitialPrior:
    """Where the flight starts: from the autopilot's HOME_POSITION or the config."""

    lat_deg: float
    lon_deg: float
    sigma_m: float
    source: str


@dataclass(frozen=True)
class FrameOutcome:
    """What one frame produced; the daemon turns it into MAVLink output and FDR records."""

    frame_id: uuid.UUID
    seq: int
    exposure_time_unix_usec: int
    state: EstimatorState | None
    fix: PoseFix | None
    fix_accepted: bool
    inliers: int
    residual_px: float | None
    #: Why there was no accepted absolute fix (None when there was one).
    no_fix_reason: str | None
    vo_ok: bool
    timings_ms: dict[str, float] = field(default_factory=dict)

    @property
    def provenance(self) -> Provenance:
        return self.state.provenance if self.state is not None else Provenance.NO_ESTIMATE


class NavigationPipeline:
    def __init__(
        self,
        *,
        calibration: CameraCalibration,
        ltp: LocalTangentPlane,
        ground_alt_amsl_m: float,
        vo,  # HomographyVo  # type: ignore[no-untyped-def]
        vpr: VprStrategy,
        vpr_config: VprConfig,
        rerank: RerankStrategy,
        matcher: CrossDomainMatcher,
        pose_solver,  # PoseSolver
        estimator,  # NavEstimator
        fdr: FdrClient,
        clock_ns: Callable[[], int] = time.perf_counter_ns,
    ) -> None:
        self._calib = calibration
        self._ltp = ltp
        self._ground_alt_amsl_m = ground_alt_amsl_m
        self._vo = vo
        self._vpr = vpr
        self._vpr_cfg = vpr_config
        self._rerank = rerank
        self._matcher = matcher
        self._pose = pose_solver
        self._est = estimator
        self._fdr = fdr
        self._clock_ns = clock_ns
        #: F6 re-localisation (corpus-wide VPR) currently active; logged on transitions only.
        self._corpus_wide = False

    @property
    def estimator(self):  # type: ignore[no-untyped-def]
        return self._est

    def _initialise(self, prior: InitialPrior, frame: NavCameraFrame) -> None:
        alt_agl_m = frame.alt_agl_m if frame.alt_agl_m is not None else 0.0
        pos = self._ltp.to_ned(prior.lat_deg, prior.lon_deg, self._ground_alt_amsl_m + alt_agl_m)
        self._est.initialise(pos, prior.sigma_m, frame.exposure_time_unix_usec)
        log.info(
            LogEvent.ESTIMATOR_INITIALISED,
            source=prior.source,
            lat_deg=prior.lat_deg,
            lon_deg=prior.lon_deg,
            sigma_m=prior.sigma_m,
        )

    def _search_region(self, state: EstimatorState, frame: NavCameraFrame) -> SearchRegion | None:
        """The prior's uncertainty region, or None (corpus-wide, F6) once the uncertainty is so large
        that the region says little and the VPR strategy can search by appearance."""
        cfg = self._vpr_cfg
        corpus_wide = state.horiz_sigma_m > cfg.corpus_wide_sigma_m and self._vpr.descriptor_dim() > 0
        if corpus_wide != self._corpus_wide:
            self._corpus_wide = corpus_wide
            log.warning(
                LogEvent.VPR_CORPUS_WIDE if corpus_wide else LogEvent.VPR_PRIOR_GATED,
                horiz_sigma_m=round(state.horiz_sigma_m, 1),
                threshold_m=cfg.corpus_wide_sigma_m,
            )
        if corpus_wide:
            return None
        # The tile centre can be up to the frame's half-footprint away from the camera and still overlap.
        half_footprint_m = (frame.alt_agl_m or 0.0) * math.tan(self._calib.hfov_rad / 2.0)
        radius = cfg.prior_sigma_scale * state.horiz_sigma_m + half_footprint_m
        radius = min(max(radius, cfg.prior_radius_min_m), cfg.prior_radius_max_m)
        return SearchRegion(state.lat_deg, state.lon_deg, radius)

    def process(self, frame: NavCameraFrame, prior: InitialPrior | None) -> FrameOutcome:
        t = frame.exposure_time_unix_usec
        timings: dict[str, float] = {}
        mark = self._clock_ns()

        def lap(name: str) -> None:
            nonlocal mark
            now = self._clock_ns()
            timings[name] = (now - mark) / 1e6
            mark = now

        motion: VoMotion | None = None
        try:
            motion = self._vo.process(frame)
        except VoError as exc:
            log.debug("c1.vo.no_motion", frame=frame.seq, reason=exc.reason)
        lap("vo")

        if not self._est.is_initialised:
            if prior is None:
                return self._outcome(frame, None, None, False, 0, None, "no_prior", motion, timings)
            self._initialise(prior, frame)
        self._est.predict_to(t)
        if motion is not None:
            self._est.update_vo(motion, time_unix_usec=t)
        lap("estimator_predict")

        fix, accepted, inliers, residual, reason = self._absolute_fix(frame, timings)
        mark = self._clock_ns()
        if fix is not None:
            decision = self._est.update_fix(fix)
            accepted = bool(decision.accepted)
            if not accepted:
                reason = f"gated:{decision.reason}"
        state = self._est.state(t)
        lap("estimator_update")
        return self._outcome(
            frame, state, fix, accepted, inliers, residual, None if accepted else reason, motion, timings
        )

    def _absolute_fix(
        self, frame: NavCameraFrame, timings: dict[str, float]
    ) -> tuple[PoseFix | None, bool, int, float | None, str | None]:
        if frame.attitude is None or frame.alt_agl_m is None:
            return None, False, 0, None, "no_attitude_or_altitude"
        prior_state = self._est.state(frame.exposure_time_unix_usec)
        t0 = self._clock_ns()
        try:
            query = self._vpr.embed_query(frame, self._calib)
            vpr_result = self._vpr.retrieve_topk(
                query, self._vpr_cfg.top_k, region=self._search_region(prior_state, frame)
            )
        except VprError as exc:
            log.error(LogEvent.VPR_ERROR, frame=frame.seq, error=str(exc))
            return None, False, 0, None, "vpr_error"
        t1 = self._clock_ns()
        timings["vpr"] = (t1 - t0) / 1e6
        if not vpr_result.candidates:
            return None, False, 0, None, "no_tiles_in_region"
        rerank_result = self._rerank.rerank(frame, vpr_result)
        t2 = self._clock_ns()
        timings["rerank"] = (t2 - t1) / 1e6
        try:
            match = self._matcher.match(frame, rerank_result, self._calib)
        except InsufficientInliersError as exc:
            timings["match"] = (self._clock_ns() - t2) / 1e6
            return None, False, exc.best_inlier_count, None, "insufficient_inliers"
        except MatcherError as exc:
            timings["match"] = (self._clock_ns() - t2) / 1e6
            log.error(LogEvent.PIPELINE_FRAME_ERROR, frame=frame.seq, stage="match", error=str(exc))
            return None, False, 0, None, "matcher_error"
        t3 = self._clock_ns()
        timings["match"] = (t3 - t2) / 1e6
        best = match.best
        handle = next(c.tile_pixels_handle for c in rerank_result.candidates if c.tile_id == best.tile_id)
        try:
            fix = self._pose.solve(frame, best, handle, self._calib)
        except PoseError as exc:
            timings["pose"] = (self._clock_ns() - t3) / 1e6
            return (
                None,
                False,
                best.inlier_count,
                match.reprojection_residual_px,
                f"pose_rejected:{exc.reason}",
            )
        timings["pose"] = (self._clock_ns() - t3) / 1e6
        return fix, True, best.inlier_count, match.reprojection_residual_px, None

    def _outcome(
        self,
        frame: NavCameraFrame,
        state: EstimatorState | None,
        fix: PoseFix | None,
        accepted: bool,
        inliers: int,
        residual: float | None,
        reason: str | None,
        motion: VoMotion | None,
        timings: dict[str, float],
    ) -> FrameOutcome:
        outcome = FrameOutcome(
            frame.frame_id,
            frame.seq,
            frame.exposure_time_unix_usec,
            state,
            fix,
            accepted,
            inliers,
            residual,
            reason,
            motion is not None,
            timings,
        )
        self._fdr.record(
            FdrKind.FRAME,
            {
                "frame_id": str(frame.frame_id),
                "frame_seq": frame.seq,
                "exposure_time_unix_usec": frame.exposure_time_unix_usec,
                "provenance": outcome.provenance.value,
                "fix_accepted": accepted,
                "inliers": inliers,
                "residual_px": residual,
                "no_fix_reason": reason,
                "vo_ok": motion is not None,
                "lat_deg": state.lat_deg if state else None,
                "lon_deg": state.lon_deg if state else None,
                "horiz_sigma_m": state.horiz_sigma_m if state else None,
                "fix_lat_deg": fix.lat_deg if fix else None,
                "fix_lon_deg": fix.lon_deg if fix else None,
                "fix_sigma_m": fix.horiz_sigma_m if fix else None,
                "timings_ms": timings,
            },
        )
        return outcome
