"""C3 errors (seed): per-candidate backbone failure and the all-candidates-failed condition."""

from __future__ import annotations

import uuid

from gps_denied_onboard.components.c6_tiles.types import TileId


class MatcherError(RuntimeError):
    """Base of C3 errors."""


class MatcherBackboneError(MatcherError):
    """The backbone (extractor or matcher) failed on one candidate; the candidate is dropped."""

    def __init__(self, message: str, *, tile_id: TileId | None, phase: str) -> None:
        super().__init__(f"{message} (tile={tile_id}, phase={phase})")
        self.tile_id = tile_id
        self.phase = phase


class InsufficientInliersError(MatcherError):
    """No candidate reached ``min_inliers_threshold`` RANSAC inliers; C5 falls back to VIO-only."""

    def __init__(
        self,
        message: str,
        *,
        frame_id: uuid.UUID,
        best_inlier_count: int,
        threshold: int,
        candidates_input: int,
        candidates_dropped: int,
    ) -> None:
        super().__init__(
            f"{message} (frame={frame_id}, best={best_inlier_count}, threshold={threshold}, "
            f"candidates={candidates_input}, dropped={candidates_dropped})"
        )
        self.frame_id = frame_id
        self.best_inlier_count = best_inlier_count
        self.threshold = threshold
        self.candidates_input = candidates_input
        self.candidates_dropped = candidates_dropped


class StrategyNotLinkedError(MatcherError, LookupError):
    """The configured strategy name is not in the registry; the message lists the valid names."""
