"""C3 contracts (seed ``c3_cross_domain_matcher.md``)."""

from __future__ import annotations

import uuid
from dataclasses import dataclass

import numpy as np

from gps_denied_onboard.components.c6_tiles.types import TileId


@dataclass(frozen=True)
class AreaAlignment:
    """Where a whole rectified frame lies on the map: the answer of an area matcher (``orientation_corr``),
    which correlates the frame as one image instead of matching points (``c3_matcher/area_search.py``).

    The position is the ground under the camera; the rotation and scale that brought the frame onto the
    map measure the autopilot's heading and height errors. The evidence is the correlation's
    (``c4_pose/integrity.py`` judges it): ``psr`` the peak-to-sidelobe ratio over the search disc,
    ``peak`` the normalised peak, ``secondary_ratio`` the best sidelobe over the peak; ``null_psr`` and
    ``null_peak`` what a wrong place scores on this map for a footprint of this size (the cache's
    calibration).
    """

    nadir_lat_deg: float
    nadir_lon_deg: float
    #: True heading minus the autopilot's, as the winning rotation measured it, rad; and its grid step.
    heading_offset_rad: float
    heading_step_rad: float
    #: True height above ground over the autopilot's, as the winning scale measured it; and its grid step.
    height_scale: float
    height_scale_step: float
    #: The map's ground sampling distance where it was matched, m/px (level 1).
    map_gsd_m_px: float
    peak: float
    psr: float
    secondary_ratio: float
    #: Share of the footprint on map data at the peak, and of it with structure (mean |field|^2).
    coverage: float
    texture: float
    #: The disc searched around the prediction, m, and the hypotheses correlated over it.
    radius_m: float
    hypotheses_tried: int
    null_psr: float
    null_peak: float
    #: The footprint's patches tried (0: the peak was too weak to try them) and how many of them agree
    #: (the shared RANSAC's inliers among those placed).
    patches_tried: int = 0
    patches_agreeing: int = 0


@dataclass(frozen=True)
class CandidateMatchSet:
    tile_id: TileId
    inlier_count: int
    #: (I, 4) float32: (px_query, py_query, px_tile, py_tile); query = original nav-frame pixels,
    #: tile = pixels of the candidate's chip (``RerankCandidate.tile_pixels_handle``).
    inlier_correspondences: np.ndarray
    ransac_outlier_count: int
    #: Median (not mean) reprojection residual of the inliers, px.
    per_candidate_residual_px: float
    #: (I,) float32 matcher confidence of each inlier (LightGlue match scores, 0..1), None when the
    #: matcher gives none (classical, mutual nearest neighbour).
    inlier_scores: np.ndarray | None = None
    #: An area matcher's answer (then there are no point correspondences: ``inlier_count`` 0, an empty
    #: ``inlier_correspondences``, and C4 solves the pose from the alignment); None for point matchers.
    area: AreaAlignment | None = None


@dataclass(frozen=True)
class MatchResult:
    frame_id: uuid.UUID
    #: Survivors sorted by inlier_count desc, ties by residual asc; up to N=3 (an area matcher's by
    #: peak-to-sidelobe ratio desc).
    per_candidate: list[CandidateMatchSet]
    best_candidate_idx: int
    reprojection_residual_px: float
    matched_at: int  # monotonic_ns
    matcher_label: str
    candidates_input: int = 0
    candidates_dropped: int = 0

    @property
    def best(self) -> CandidateMatchSet:
        return self.per_candidate[self.best_candidate_idx]


@dataclass(frozen=True)
class MatcherHealth:
    """Rolling matcher health (see ``health.RollingHealthWindow``)."""

    #: Frames in a row whose best inlier count was below the low-inlier threshold (0 after a good one).
    consecutive_low_inlier: int
    #: Mean best-candidate inlier count over the frames of the last 60 s (0.0 when there were none).
    mean_inliers_60s: float
    #: Frames in the last 60 s, and how many of them had at least one backbone error.
    frames_60s: int = 0
    backbone_error_frames_60s: int = 0
