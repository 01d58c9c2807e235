"""Area correlation, label ``orientation_corr``: the whole nav frame matched against the map as one image.

Across dates a matcher of points must find the same points in two images that differ in season, crops,
water and light; a frame correlated as a whole needs only the pattern of edges to survive (field
boundaries, roads, shores), and the map's side of the work is done once, at ``cache build``. Fielded scene
matchers have done this on small computers for decades (DSMAC-style area correlation); OrienterNet (CVPR
2023) does it with exhaustive FFT matching over position and heading.

Per attempt (``match``):
1. the frame is warped north-up with the autopilot's attitude and height (``helpers/frame_rectifier.py``)
   at the GSD of a working level of the map's fields (level 1: the map's pixels; level 2: half that):
   one that keeps the footprint within ``MIN_WORKING_SIDE_PX``..``MAX_WORKING_SIDE_PX``, so the work per
   fix does not grow with the map's resolution and the footprint stays near the size the map was
   calibrated with, and of those the one where the map's calibration tells places apart best (a 0.5 m map
   of striped fields repeats itself at 0.5 m and far less at 1 m). What is left is a 2-D shift plus the
   heading and height errors;
2. where to search: with a prior (``RerankResult.search``) one disc around it, of radius 3 sigma
   (``MIN_RADIUS_PX`` .. ``MAX_RADIUS_PX``); a prior too wide for that, or none, gives one disc of
   ``MAX_RADIUS_PX`` around each candidate tile (at most the rung's candidates), the prior's first;
3. each disc is searched over the heading and height hypotheses ``matcher.correlation`` allows
   (``c3_matcher/area_search.py``: gradient-orientation fields by FFT, coarse to fine, sub-pixel),
   climbing from the last frame's hypothesis while its peak stood out (the autopilot's heading and height
   errors change slowly), with the whole grid every ``FULL_SEARCH_EVERY`` attempts and after any weak
   one;
4. each disc found gives a candidate with an ``AreaAlignment``: where the ground under the camera lies,
   the heading and height errors measured, and the correlation's evidence with the map's own calibration
   of what a wrong place scores (``null_psr``, ``null_peak``). Candidates come best first by PSR;
5. the aligned footprint's patches are placed each by its own peak; where they agree with one another
   (the shared RANSAC keeps at least ``PATCH_MIN_INLIERS``, and ``PATCH_MIN_AGREEMENT`` of the patches
   tried), they are point correspondences and the candidate carries them.

C4 solves a candidate with correspondences like any point match (PnP with the attitude prior: the camera's
tilt is measured, and the tilt checks hear from it), and one without from the alignment alone
(``c4_pose/area_pose.py``: the tilt is the autopilot's). Same-source imagery gives patches that agree
(every one of 53 on GeoVision), imagery from another date mostly does not (a quarter to two thirds on
NAIP): there the alignment is the fix. Either way the integrity rule judges the correlation's evidence.

The map side is the cache's orientation fields and their calibration (``c6_tiles/map_fields.py``): the
strategy refuses to start without calibrated fields.

Failure phases: ``rectify`` (the frame cannot be warped to the ground: a ray above the horizon) fails the
frame; no disc with the footprint on the map raises ``InsufficientInliersError``.
"""

from __future__ import annotations

import dataclasses
import math
import time
import uuid
from dataclasses import dataclass
from typing import Final, NoReturn

import numpy as np
import structlog

from gps_denied_onboard.camera.types import CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c2_5_rerank.types import RerankCandidate, RerankResult
from gps_denied_onboard.components.c3_matcher.area_search import (
    AreaSearch,
    Hypothesis,
    LevelView,
    Template,
    search,
    to_level,
)
from gps_denied_onboard.components.c3_matcher.errors import InsufficientInliersError, MatcherBackboneError
from gps_denied_onboard.components.c3_matcher.health import RollingHealthWindow
from gps_denied_onboard.components.c3_matcher.types import (
    AreaAlignment,
    CandidateMatchSet,
    MatcherHealth,
    MatchResult,
)
from gps_denied_onboard.components.c6_tiles.map_fields import MapFields
from gps_denied_onboard.components.c6_tiles.types import TileId
from gps_denied_onboard.components.c13_fdr.protocol import FdrClient
from gps_denied_onboard.config import CorrelationConfig, MatcherConfig
from gps_denied_onboard.constants import FdrKind, LogEvent
from gps_denied_onboard.helpers.frame_rectifier import (
    RectificationError,
    RectifiedQuery,
    rectify_to_map_frame,
)
from gps_denied_onboard.helpers.orientation_field import grey_of
from gps_denied_onboard.helpers.ransac_filter import RansacFilter

LABEL: Final[str] = "orientation_corr"
#: The search disc's radius, working-level px: at least enough sidelobes beyond the peak's exclusion for
#: a peak-to-sidelobe ratio, at most the radius the map's calibration was made at
#: (``c10_cache_build.map_fields.CALIBRATION_RADIUS_PX``): a wider disc offers more places to look right.
MIN_RADIUS_PX: Final = 48.0
MAX_RADIUS_PX: Final = 192.0
#: The footprint's long side, px, a working level must keep it within (module docstring, step 1).
MIN_WORKING_SIDE_PX: Final = 160.0
MAX_WORKING_SIDE_PX: Final = 640.0
#: How much better a coarser working level must separate places to be chosen over a finer one.
COARSER_GAIN: Final = 1.5
#: The prior's sigmas the disc covers.
PRIOR_SIGMAS: Final = 3.0
#: Every this many attempts the whole hypothesis grid is searched, whatever the last frame found.
FULL_SEARCH_EVERY: Final = 8
#: The last frame's hypothesis is a starting point only when its peak stood this many times out of what
#: a wrong place scores on the map (``null_psr``).
START_PSR_FACTOR: Final = 1.5
#: Patches handed on as point correspondences only when this many agree (the shared RANSAC's inliers),
#: and at least this share of those tried (module docstring, step 5).
PATCH_MIN_INLIERS: Final = 12
PATCH_MIN_AGREEMENT: Final = 0.8

_LOG = structlog.get_logger(__name__)


@dataclass(frozen=True)
class _Disc:
    """One place to search: the candidate it is reported as, and the predicted nadir with its radius."""

    candidate: RerankCandidate
    lat_deg: float
    lon_deg: float
    #: In px of the level the search runs at.
    radius_px: float


def hypothesis_grid(config: CorrelationConfig) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(rotations, deg; scales) tried: out to 3 sigma of the heading and the height, in the config's
    steps, at most ``max_steps`` each way, always including (0, 1)."""
    n_rot = min(config.max_steps, math.ceil(3.0 * config.heading_sigma_deg / config.heading_step_deg))
    n_scale = min(config.max_steps, math.ceil(3.0 * config.height_sigma_frac / config.height_step_frac))
    rotations = tuple(round(i * config.heading_step_deg, 6) for i in range(-n_rot, n_rot + 1))
    scales = tuple(round(1.0 + i * config.height_step_frac, 6) for i in range(-n_scale, n_scale + 1))
    return rotations, scales


class OrientationCorrMatcher:
    """``CrossDomainMatcher`` by area correlation (module docstring)."""

    label = LABEL

    def __init__(
        self,
        *,
        config: MatcherConfig,
        fields: MapFields,
        health_window: RollingHealthWindow,
        ransac_filter: RansacFilter,
        fdr_client: FdrClient | None = None,
    ) -> None:
        if not fields.calibrated_levels:
            raise ValueError(
                f"{LABEL} needs the cache's calibrated map fields: run gdnav cache fields --cache "
                f"{fields.store.cache_dir}"
            )
        self._config = config
        self._fields = fields
        self._store = fields.store
        self._health = health_window
        self._ransac = ransac_filter
        self._fdr = fdr_client
        self._rotations, self._scales = hypothesis_grid(config.correlation)
        #: Where the next search climbs from (step 3 of the module docstring), and attempts since the
        #: whole grid was searched. The one fix worker is the only caller, so a replay climbs alike.
        self._start: Hypothesis | None = None
        self._since_full = 0

    def health_snapshot(self) -> MatcherHealth:
        return self._health.snapshot()

    @property
    def hypotheses(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """(rotations deg, scales) the search may try."""
        return self._rotations, self._scales

    def match(
        self, frame: NavCameraFrame, rerank_result: RerankResult, calibration: CameraCalibration
    ) -> MatchResult:
        """See ``CrossDomainMatcher.match`` and the module docstring."""
        t0 = time.perf_counter()
        frame_id = rerank_result.frame_id
        candidates = list(rerank_result.candidates)
        try:
            if frame.frame_id != frame_id:
                raise ValueError(f"rerank result is for frame {frame_id}, not for frame {frame.frame_id}")
            result = self._match(frame, rerank_result, candidates, calibration)
        except InsufficientInliersError:
            self._health.update(time.monotonic_ns(), best_inlier_count=0, had_backbone_error=False)
            raise
        except MatcherBackboneError:
            self._health.update(time.monotonic_ns(), best_inlier_count=0, had_backbone_error=True)
            raise
        best = result.best.area
        assert best is not None
        # The health window counts frames by their best "inliers": an area match has none, so a frame
        # counts as good (the threshold) when its best peak stands out of what the map's wrong places
        # score (the integrity rule asks for a margin more).
        good = best.psr > best.null_psr
        self._health.update(
            time.monotonic_ns(),
            best_inlier_count=self._health.low_inlier_threshold if good else 0,
            had_backbone_error=False,
        )
        if self._fdr is not None:
            self._fdr.record(
                FdrKind.MATCHER_FRAME_DONE,
                {
                    "frame_id": str(frame_id),
                    "candidates_input": len(candidates),
                    "candidates_dropped": result.candidates_dropped,
                    "best_tile_id": list(result.best.tile_id),
                    "best_psr": round(best.psr, 3),
                    "best_peak": round(best.peak, 4),
                    "ms": round((time.perf_counter() - t0) * 1e3, 2),
                },
            )
        return result

    def _working_level(self, frame: NavCameraFrame, calibration: CameraCalibration, gsd1: float) -> int:
        """The calibrated working level for this frame (module docstring, step 1): of the levels where the
        footprint's long side is within ``MIN_WORKING_SIDE_PX``..``MAX_WORKING_SIDE_PX``, the finest (its
        alignment is twice as fine), unless a coarser one tells a right place from a wrong one
        ``COARSER_GAIN`` times as well by the map's calibration (``right_psr_p5 / null_psr_max``: crop
        rows that repeat at the map's own resolution wash out one level down); with none in that range,
        the finest level whose footprint fits, else the coarsest."""
        alt = frame.alt_agl_m if frame.alt_agl_m is not None else 0.0
        side_m = 2.0 * alt * math.tan(calibration.hfov_rad / 2.0)
        levels = self._fields.calibrated_levels

        def side_px(level: int) -> float:
            return side_m / (gsd1 * 2 ** (level - 1))

        sized = [lv for lv in levels if MIN_WORKING_SIDE_PX <= side_px(lv) <= MAX_WORKING_SIDE_PX]
        if sized:
            best = sized[0]
            for level in sized[1:]:
                if self._separation(level) >= COARSER_GAIN * self._separation(best):
                    best = level
            return best
        fits = [lv for lv in levels if side_px(lv) <= MAX_WORKING_SIDE_PX]
        return fits[0] if fits else levels[-1]

    def _separation(self, level: int) -> float:
        cal = self._fields.calibration(level)
        return 0.0 if cal is None else cal.right_psr_p5 / max(cal.null_psr_max, 1e-6)

    def _discs(
        self, rerank_result: RerankResult, candidates: list[RerankCandidate], gsd: float, max_radius_px: float
    ) -> list[_Disc]:
        """Where to search (module docstring, step 2); radii in px of GSD ``gsd``."""
        prior = rerank_result.search
        if prior is not None and candidates:
            radius_px = max(MIN_RADIUS_PX, PRIOR_SIGMAS * prior.sigma_m / gsd)
            if radius_px <= max_radius_px:
                return [_Disc(candidates[0], prior.lat_deg, prior.lon_deg, radius_px)]
        discs = []
        if prior is not None and candidates:
            discs.append(_Disc(candidates[0], prior.lat_deg, prior.lon_deg, max_radius_px))
        for cand in candidates[len(discs) :]:
            handle = cand.tile_pixels_handle
            w, h = (int(v) for v in np.asarray(handle.pixels()).shape[1::-1])
            lon, lat = handle.chip_px_to_lonlat(np.array([(w - 1) / 2.0, (h - 1) / 2.0]))
            discs.append(_Disc(cand, float(np.ravel(lat)[0]), float(np.ravel(lon)[0]), max_radius_px))
        return discs

    def _match(
        self,
        frame: NavCameraFrame,
        rerank_result: RerankResult,
        candidates: list[RerankCandidate],
        calibration: CameraCalibration,
    ) -> MatchResult:
        frame_id = rerank_result.frame_id
        n_input = len(candidates)
        if n_input == 0:
            self._fail(frame_id, 0, 0, "no candidates")
        attitude, alt_agl_m = frame.attitude, frame.alt_agl_m
        if attitude is None or alt_agl_m is None:
            self._fail(frame_id, n_input, n_input, "the frame has no attitude or height")
            raise AssertionError("unreachable")  # _fail raises
        prior = rerank_result.search
        lat0 = prior.lat_deg if prior is not None else self._store.center_lonlat[1]
        gsd1 = float(self._store.grid.gsd_m_px(lat0))
        level = self._working_level(frame, calibration, gsd1)
        cal = self._fields.calibration(level)
        assert cal is not None  # a calibrated level
        gsd = gsd1 * 2 ** (level - 1)
        # Never search a wider disc than the map was calibrated for.
        discs = self._discs(rerank_result, candidates, gsd, min(MAX_RADIUS_PX, cal.radius_px))
        view = LevelView(self._fields, level)
        try:
            rect = rectify_to_map_frame(frame.image_bgr, calibration, attitude, alt_agl_m, gsd)
        except RectificationError as exc:
            err = MatcherBackboneError(str(exc), tile_id=None, phase="rectify")
            _LOG.error(LogEvent.C3_BACKBONE_ERROR, phase="rectify", error=str(exc), backbone=LABEL)
            raise err from exc
        valid = np.asarray(rect.image.any(axis=2), dtype=bool)
        template = Template(grey_of(rect.image), valid, _nadir_px(rect.H_frame_to_rect, calibration, frame))
        # What a wrong place scores for a footprint of this size (the calibration's peak is for its own
        # template: a correlation's spread falls as the square root of the pixels it sums).
        area_ratio = (cal.template_px[0] * cal.template_px[1]) / max(float(valid.sum()), 1.0)
        null_peak = cal.null_peak_max * math.sqrt(min(area_ratio, 1.0))
        survivors: list[CandidateMatchSet] = []
        dropped = 0
        start = self._start if self._since_full < FULL_SEARCH_EVERY else None
        self._since_full = 0 if start is None else self._since_full + 1
        for disc in discs:
            pred1 = self._store.lonlat_to_mosaic_px(np.array(disc.lon_deg), np.array(disc.lat_deg))
            pred = (to_level(float(pred1[0]), 1, level), to_level(float(pred1[1]), 1, level))
            found = search(template, view, pred, disc.radius_px, self._rotations, self._scales, start)
            if found is None:
                dropped += 1
                continue
            survivors.append(self._candidate(disc, found, level, gsd, cal.null_psr_max, null_peak, rect))
        _LOG.debug(
            LogEvent.C3_CANDIDATES,
            candidates=[
                (round(s.area.psr, 2), round(s.area.peak, 3)) for s in survivors if s.area is not None
            ],
            dropped=dropped,
        )
        if not survivors:
            self._start = None
            self._fail(frame_id, n_input, dropped, "no disc with the frame's footprint on the map")
        survivors.sort(key=lambda s: -s.area.psr if s.area is not None else 0.0)
        self._note_start(survivors[0].area)
        return MatchResult(
            frame_id=frame_id,
            per_candidate=survivors,
            best_candidate_idx=0,
            reprojection_residual_px=survivors[0].per_candidate_residual_px,
            matched_at=time.monotonic_ns(),
            matcher_label=LABEL,
            candidates_input=n_input,
            candidates_dropped=dropped,
        )

    def _note_start(self, best: AreaAlignment | None) -> None:
        """Keep the best hypothesis as the next search's start while its peak stands out."""
        if best is None or best.psr < START_PSR_FACTOR * best.null_psr:
            self._start = None
            return
        # The grid's own values (rounded as ``hypothesis_grid`` rounds them).
        self._start = Hypothesis(
            round(-math.degrees(best.heading_offset_rad), 6), round(best.height_scale, 6)
        )

    def _candidate(
        self,
        disc: _Disc,
        found: AreaSearch,
        level: int,
        gsd: float,
        null_psr: float,
        null_peak: float,
        rect: RectifiedQuery,
    ) -> CandidateMatchSet:
        """The candidate of one disc's search at working ``level`` (GSD ``gsd``)."""
        nadir1 = np.array([to_level(v, level, 1) for v in found.nadir_map_px], dtype=np.float64)
        lon, lat = self._store.mosaic_px_to_lonlat(nadir1)
        cfg = self._config.correlation
        area = AreaAlignment(
            nadir_lat_deg=float(lat),
            nadir_lon_deg=float(lon),
            # The rotation that brought the frame onto the map turns it against the autopilot's heading
            # error (OpenCV's sense is counter-clockwise on the image, north up: towards the west).
            heading_offset_rad=-math.radians(found.hypothesis.rotation_deg),
            heading_step_rad=math.radians(cfg.heading_step_deg),
            height_scale=found.hypothesis.scale,
            height_scale_step=cfg.height_step_frac,
            map_gsd_m_px=gsd,
            peak=found.peak,
            psr=found.psr,
            secondary_ratio=found.secondary_ratio,
            coverage=found.coverage,
            texture=found.texture,
            radius_m=found.radius_px * gsd,
            hypotheses_tried=found.hypotheses_tried,
            null_psr=float(null_psr),
            null_peak=float(null_peak),
        )
        tile_id: TileId = disc.candidate.tile_id
        none = CandidateMatchSet(
            tile_id=tile_id,
            inlier_count=0,
            inlier_correspondences=np.empty((0, 4), dtype=np.float32),
            ransac_outlier_count=0,
            per_candidate_residual_px=math.nan,
            area=area,
        )
        if found.patches_tried < PATCH_MIN_INLIERS:
            return none  # too few patches to judge the frame's parts by
        if found.patches.shape[0] < PATCH_MIN_INLIERS:
            tried_only = dataclasses.replace(area, patches_tried=found.patches_tried)
            return dataclasses.replace(none, area=tried_only)
        handle = disc.candidate.tile_pixels_handle
        lon_p, lat_p = self._store.mosaic_px_to_lonlat((found.patches[:, 2:4] + 0.5) * 2 ** (level - 1) - 0.5)
        corr = np.hstack(
            [rect.rect_to_frame_px(found.patches[:, 0:2]), handle.lonlat_to_chip_px(lon_p, lat_p)]
        ).astype(np.float32)
        result = self._ransac.filter(corr, threshold_px=self._config.ransac_threshold_px)
        n = result.inlier_count
        area = dataclasses.replace(area, patches_tried=found.patches_tried, patches_agreeing=n)
        if n < PATCH_MIN_INLIERS or n < PATCH_MIN_AGREEMENT * found.patches_tried:
            return dataclasses.replace(none, area=area)
        return CandidateMatchSet(
            tile_id=tile_id,
            inlier_count=n,
            inlier_correspondences=np.array(result.inlier_correspondences, dtype=np.float32, copy=True),
            ransac_outlier_count=int(result.ransac_outlier_count),
            per_candidate_residual_px=float(result.per_candidate_residual_px),
            area=area,
        )

    def _fail(self, frame_id: uuid.UUID, n_input: int, dropped: int, reason: str) -> NoReturn:
        fields = {
            "frame_id": str(frame_id),
            "backbone": LABEL,
            "best_inlier_count": 0,
            "threshold": 0,
            "candidates_input": n_input,
            "candidates_dropped": dropped,
            "reason": reason,
        }
        _LOG.error(LogEvent.C3_INSUFFICIENT_INLIERS, **{k: v for k, v in fields.items() if k != "frame_id"})
        if self._fdr is not None:
            self._fdr.record(FdrKind.MATCHER_INSUFFICIENT_INLIERS, fields)
        raise InsufficientInliersError(
            f"C3 {LABEL}: {reason}",
            frame_id=frame_id,
            best_inlier_count=0,
            threshold=0,
            candidates_input=n_input,
            candidates_dropped=dropped,
        )


def _nadir_px(
    h_frame_to_rect: np.ndarray, calibration: CameraCalibration, frame: NavCameraFrame
) -> tuple[float, float]:
    """Where the ground under the camera lies in the rectified frame (the nadir ray through the
    camera's own rotation: it need not be in the picture)."""
    assert frame.attitude is not None
    ray_cam = frame.attitude.R_ned_cam().T @ np.array([0.0, 0.0, 1.0])
    p = h_frame_to_rect @ (calibration.K @ ray_cam)
    return float(p[0] / p[2]), float(p[1] / p[2])


def create(
    config: MatcherConfig,
    map_fields: MapFields,
    health_window: RollingHealthWindow,
    ransac_filter: RansacFilter,
    fdr_client: FdrClient | None = None,
) -> OrientationCorrMatcher:
    """Registry factory for ``orientation_corr``: needs the cache's map fields with their calibration
    (``ValueError`` naming the command that makes them otherwise)."""
    return OrientationCorrMatcher(
        config=config,
        fields=map_fields,
        health_window=health_window,
        ransac_filter=ransac_filter,
        fdr_client=fdr_client,
    )
