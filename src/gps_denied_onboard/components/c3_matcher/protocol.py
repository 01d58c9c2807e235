"""C3 strategy interface (seed ``c3_cross_domain_matcher.md`` § 2)."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from gps_denied_onboard.camera.types import CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c2_5_rerank.types import RerankResult
from gps_denied_onboard.components.c3_matcher.types import MatcherHealth, MatchResult


@runtime_checkable
class CrossDomainMatcher(Protocol):
    """Matches one nav frame against the top-N re-ranked map chips.

    Single-threaded by contract (INV-1): one pipeline worker calls ``match``; ``health_snapshot`` may
    be called from any thread.
    """

    def match(
        self, frame: NavCameraFrame, rerank_result: RerankResult, calibration: CameraCalibration
    ) -> MatchResult:
        """RANSAC-filtered correspondences per surviving candidate, best first.

        Per-candidate backbone failures are dropped (INV-4), never raised. Raises
        ``InsufficientInliersError`` when no candidate reaches ``min_inliers_threshold``.
        """
        ...

    def health_snapshot(self) -> MatcherHealth:
        """Rolling health (consecutive low-inlier frames, mean inliers over 60 s)."""
        ...
