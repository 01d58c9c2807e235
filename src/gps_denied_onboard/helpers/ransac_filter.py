"""Shared RANSAC + median-residual helper (seed AZ-282), used by C3, C3.5 and C4.

One implementation of "fit a homography to putative correspondences, keep the inliers, report the
median reprojection residual" so that every matcher strategy ranks candidates by the same numbers.

Correspondence layout everywhere: ``(M, 4) float32`` rows ``(px_query, py_query, px_tile, py_tile)``.
The homography maps query pixels to tile pixels; residuals are measured in tile pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import cv2
import numpy as np

#: Method names accepted by ``RansacFilter`` -> OpenCV robust-estimator flags.
RANSAC_METHODS: Final[dict[str, int]] = {
    "usac_magsac": cv2.USAC_MAGSAC,
    "usac_accurate": cv2.USAC_ACCURATE,
    "ransac": cv2.RANSAC,
}

#: A homography needs 4 point pairs.
MIN_CORRESPONDENCES: Final[int] = 4

# |det(H)| below this (after normalising H[2,2] = 1) means the fit collapsed the query onto a line or
# a point: numerically a homography, physically no view of the ground.
_MIN_ABS_DET: Final[float] = 1e-6


@dataclass(frozen=True)
class RansacResult:
    """Outcome of one robust homography fit.

    - ``inlier_correspondences``: (I, 4) float32, the input rows kept as inliers, input order.
    - ``ransac_outlier_count``: M - I (all M when no model could be fitted).
    - ``per_candidate_residual_px``: MEDIAN of ||H(q) - t|| over the inliers, tile pixels;
      ``math.inf`` when there are no inliers.
    - ``homography``: (3, 3) float64 query px -> tile px with H[2, 2] = 1, or None when degenerate.
    - ``inlier_mask``: (M,) bool, which input rows are the inliers (None when no model was fitted).
    """

    inlier_correspondences: np.ndarray
    ransac_outlier_count: int
    per_candidate_residual_px: float
    homography: np.ndarray | None
    inlier_mask: np.ndarray | None = None

    @property
    def inlier_count(self) -> int:
        return int(self.inlier_correspondences.shape[0])


def _empty(outliers: int) -> RansacResult:
    return RansacResult(np.empty((0, 4), dtype=np.float32), outliers, math.inf, None)


class RansacFilter:
    """Robust homography fit with OpenCV's USAC (MAGSAC++ by default).

    Deterministic: OpenCV's USAC estimators seed their own generator, so equal inputs give equal
    outputs (the seed's AC-10 relies on this). Thread-safe: holds configuration only.
    """

    def __init__(self, method: str = "usac_magsac", confidence: float = 0.999, max_iters: int = 5000) -> None:
        if method not in RANSAC_METHODS:
            raise ValueError(f"unknown RANSAC method {method!r}; expected one of {sorted(RANSAC_METHODS)}")
        if not 0.0 < confidence < 1.0:
            raise ValueError(f"confidence must be in (0, 1), got {confidence!r}")
        if max_iters < 1:
            raise ValueError(f"max_iters must be >= 1, got {max_iters!r}")
        self._method = method
        self._flag = RANSAC_METHODS[method]
        self._confidence = float(confidence)
        self._max_iters = int(max_iters)

    @property
    def method(self) -> str:
        return self._method

    def filter(self, correspondences: np.ndarray, threshold_px: float) -> RansacResult:
        """Fit a homography query -> tile to ``correspondences`` (M, 4) and keep the inliers.

        An inlier is a row that the estimator keeps AND whose residual is <= ``threshold_px``
        (MAGSAC++ weights points softly and may keep some slightly beyond the threshold; the hard cut
        makes ``threshold_px`` mean the same for every method). Fewer than 4 rows, non-finite input or
        a degenerate fit give an empty result, never an exception: to the caller these are all "no
        geometric support for this candidate".
        """
        corr = np.asarray(correspondences)
        if corr.ndim != 2 or corr.shape[1] != 4:
            raise ValueError(f"correspondences must be (M, 4), got shape {corr.shape}")
        if not threshold_px > 0:
            raise ValueError(f"threshold_px must be > 0, got {threshold_px!r}")
        m = int(corr.shape[0])
        corr = corr.astype(np.float32, copy=False)
        if m < MIN_CORRESPONDENCES or not np.isfinite(corr).all():
            return _empty(m)
        query = np.ascontiguousarray(corr[:, :2])
        tile = np.ascontiguousarray(corr[:, 2:])
        try:
            homography, mask = cv2.findHomography(
                query,
                tile,
                self._flag,
                float(threshold_px),
                confidence=self._confidence,
                maxIters=self._max_iters,
            )
        except cv2.error:
            # OpenCV raises on some degenerate configurations (e.g. all points collinear).
            return _empty(m)
        if homography is None or mask is None or not np.isfinite(homography).all():
            return _empty(m)
        if abs(homography[2, 2]) < 1e-12:
            return _empty(m)
        homography = homography / homography[2, 2]
        if abs(np.linalg.det(homography)) < _MIN_ABS_DET:
            return _empty(m)
        projected = cv2.perspectiveTransform(query.reshape(-1, 1, 2).astype(np.float64), homography)
        residuals = np.linalg.norm(projected.reshape(-1, 2) - tile.astype(np.float64), axis=1)
        keep = (mask.ravel() > 0) & (residuals <= threshold_px)
        inliers = np.ascontiguousarray(corr[keep])
        if inliers.shape[0] == 0:
            return _empty(m)
        return RansacResult(
            inlier_correspondences=inliers,
            ransac_outlier_count=m - int(inliers.shape[0]),
            per_candidate_residual_px=float(np.median(residuals[keep])),
            homography=homography.astype(np.float64),
            inlier_mask=keep,
        )
