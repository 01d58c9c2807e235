"""C3 contracts (seed ``c3_cross_domain_matcher.md``)."""

from __future__ import annotations

import uuid
from dataclasses import dataclass

import numpy as np

from gps_denied_onboard.components.c6_tiles.types import TileId


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


@dataclass(frozen=True)
class MatchResult:
    frame_id: uuid.UUID
    #: Survivors sorted by inlier_count desc, ties by residual asc; up to N=3.
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
