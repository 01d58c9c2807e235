"""Weights-free classical strategy (OpenCV SIFT / ORB / AKAZE), label ``classical``.

The fallback that works on any machine without model files. Per frame: features of the (rectified)
query once, features of each candidate chip (from the tile-feature LRU when the chip was seen
recently), nearest-neighbour matching with Lowe's ratio test and a mutual-best check, then the shared
RANSAC in ``base.CandidateLoopMatcher``.

Known limit: classical features do not survive a large appearance gap (map and flight years apart,
seasons); learned strategies exist for that. Same-source imagery matches well.
"""

from __future__ import annotations

from typing import Final

import cv2
import numpy as np
import structlog

from gps_denied_onboard.components.c3_matcher.base import DEFAULT_TILE_CACHE_SIZE, CandidateLoopMatcher
from gps_denied_onboard.components.c3_matcher.features import Features, no_features
from gps_denied_onboard.components.c3_matcher.health import RollingHealthWindow
from gps_denied_onboard.components.c13_fdr.protocol import FdrClient
from gps_denied_onboard.config import MatcherConfig
from gps_denied_onboard.helpers.ransac_filter import RansacFilter

_LOG = structlog.get_logger(__name__)

LABEL: Final[str] = "classical"

#: Images are shrunk by this factor before detection. OpenCV's SIFT doubles its input internally, so
#: at 0.5 its finest octave sits at the map's native resolution: ~4x less work for the same features
#: at the scales that survive blur and resampling (measured in the PR: inliers and geo error on real
#: imagery stay far above the C3-IT-01 floor).
DEFAULT_DETECT_SCALE: Final[float] = 0.5

# Descriptor dimension / dtype per detector (for empty feature sets).
_DESCRIPTOR_LAYOUT: Final[dict[str, tuple[int, type]]] = {
    "sift": (128, np.float32),
    "orb": (32, np.uint8),
    "akaze": (61, np.uint8),
}


def _make_detector(name: str, max_features: int) -> cv2.Feature2D:
    if name == "sift":
        return cv2.SIFT.create(nfeatures=max_features)
    if name == "orb":
        return cv2.ORB.create(nfeatures=max_features)
    if name == "akaze":
        akaze = getattr(cv2, "AKAZE_create", None)
        if akaze is None:
            # OpenCV 5 moved AKAZE out of the main module; say so instead of an AttributeError.
            raise ValueError(
                f"classical_detector 'akaze' is not available in this OpenCV build ({cv2.__version__}); "
                "use 'sift' or 'orb'"
            )
        return akaze()
    raise ValueError(f"unknown classical_detector {name!r}; expected one of {sorted(_DESCRIPTOR_LAYOUT)}")


class ClassicalMatcher(CandidateLoopMatcher):
    """OpenCV features + ratio test + mutual check + shared RANSAC (see module docstring)."""

    label = LABEL
    query_phase = "classical_extract_query"
    tile_phase = "classical_extract_tile"
    match_phase = "classical_match"

    def __init__(
        self,
        ransac_filter: RansacFilter,
        fdr_client: FdrClient | None,
        health_window: RollingHealthWindow,
        config: MatcherConfig,
        *,
        tile_cache_size: int = DEFAULT_TILE_CACHE_SIZE,
        detect_scale: float = DEFAULT_DETECT_SCALE,
    ) -> None:
        if not 0.1 <= detect_scale <= 1.0:
            raise ValueError(f"detect_scale must be in [0.1, 1], got {detect_scale!r}")
        super().__init__(
            ransac_filter=ransac_filter,
            fdr_client=fdr_client,
            health_window=health_window,
            config=config,
            tile_cache_size=tile_cache_size,
        )
        self._detector_name = config.classical_detector
        self._detector = _make_detector(self._detector_name, config.max_features)
        self._max_features = int(config.max_features)
        self._ratio = float(config.ratio_test)
        self._binary = self._detector_name in ("orb", "akaze")
        self._detect_scale = float(detect_scale)

    @property
    def detector_name(self) -> str:
        return self._detector_name

    # --- hooks ---------------------------------------------------------------------------------------
    def extract_query(self, image_bgr: np.ndarray) -> Features:
        return self._extract(image_bgr)

    def extract_tile(self, chip_bgr: np.ndarray) -> Features:
        return self._extract(chip_bgr)

    def match_features(self, query: Features, tile: Features) -> np.ndarray:
        if query.count < 2 or tile.count < 2:
            return np.empty((0, 4), dtype=np.float32)
        if self._binary:
            qi, ti = self._match_binary(query.descriptors, tile.descriptors)
        else:
            qi, ti = self._match_float(query.descriptors, tile.descriptors)
        return np.hstack([query.keypoints_px[qi], tile.keypoints_px[ti]]).astype(np.float32)

    # --- internals -----------------------------------------------------------------------------------
    def _extract(self, image_bgr: np.ndarray) -> Features:
        h, w = image_bgr.shape[:2]
        gray = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY)
        scale = self._detect_scale
        if scale != 1.0:
            gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        # The black outside of a rectified query's footprint is not texture, and its edge would give
        # strong false corners: mask it (recognised by black image corners).
        mask = None
        if not gray[[0, 0, -1, -1], [0, -1, 0, -1]].all():
            mask = cv2.erode((gray > 0).astype(np.uint8) * 255, np.ones((7, 7), np.uint8))
        keypoints, descriptors = self._detector.detectAndCompute(gray, mask)
        dim, dtype = _DESCRIPTOR_LAYOUT[self._detector_name]
        if descriptors is None or len(keypoints) == 0:
            return no_features((w, h), dim, dtype)
        if len(keypoints) > self._max_features:
            # AKAZE has no feature budget of its own: keep the strongest responses.
            order = np.argsort([-kp.response for kp in keypoints], kind="stable")[: self._max_features]
            keypoints = [keypoints[i] for i in order]
            descriptors = descriptors[order]
        pts = np.array([kp.pt for kp in keypoints], dtype=np.float64).reshape(-1, 2)
        if scale != 1.0:
            pts = (pts + 0.5) / scale - 0.5  # back to the input image's pixel centres
        pts = pts.astype(np.float32)
        desc: np.ndarray = np.ascontiguousarray(descriptors, dtype=dtype)
        return Features(pts, desc, (w, h))

    def _match_float(self, dq: np.ndarray, dt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # One distance matrix serves both directions (forward 2-NN + reverse 1-NN): cheaper than two
        # brute-force passes. Squared L2 distances, so the ratio is squared too.
        d2 = dq @ dt.T
        d2 *= -2.0
        d2 += np.einsum("ij,ij->i", dq, dq)[:, None]
        d2 += np.einsum("ij,ij->i", dt, dt)[None, :]
        np.maximum(d2, 0.0, out=d2)
        best = np.argmin(d2, axis=1)
        two = np.partition(d2, 1, axis=1)[:, :2]
        reverse = np.argmin(d2, axis=0)
        rows = np.arange(dq.shape[0])
        keep = (two[:, 0] < (self._ratio**2) * two[:, 1]) & (reverse[best] == rows)
        return rows[keep], best[keep]

    def _match_binary(self, dq: np.ndarray, dt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        bf = cv2.BFMatcher(cv2.NORM_HAMMING)
        forward = bf.knnMatch(dq, dt, k=2)
        reverse = {m.queryIdx: m.trainIdx for m in bf.match(dt, dq)}
        qi: list[int] = []
        ti: list[int] = []
        for pair in forward:
            if len(pair) < 2:
                continue
            m, n = pair
            if m.distance < self._ratio * n.distance and reverse.get(m.trainIdx) == m.queryIdx:
                qi.append(m.queryIdx)
                ti.append(m.trainIdx)
        return np.asarray(qi, dtype=np.int64), np.asarray(ti, dtype=np.int64)


def create(
    config: MatcherConfig,
    ransac_filter: RansacFilter,
    health_window: RollingHealthWindow,
    fdr_client: FdrClient | None = None,
) -> ClassicalMatcher:
    """Registry factory for ``classical`` (no model files to load)."""
    return ClassicalMatcher(ransac_filter, fdr_client, health_window, config)
