"""``inlier`` re-rank (C2.5): K VPR candidates -> the N with the most geometrically verified matches.

Per frame: the nav frame is normalised to the map frame (north-up, map GSD, chip-sized: the same
``QueryNormaliser`` as C2, shared so the warp is paid once), both it and each candidate's chip are
downscaled to ``work_size_px`` (cost), local features are matched (SIFT + ratio test, or ORB + Hamming
cross-check), and the shared ``RansacFilter`` counts homography inliers. Because both images are
north-up at the same scale, a correct tile's homography is close to a translation; fits whose linear
part scales by more than ``max_scale_change`` (either way) are counted as 0 inliers, which removes
most chance fits on repetitive texture. Candidates are sorted by inliers (descending), ties by VPR
distance (ascending), and the first ``top_n`` are returned with their chip handles.

Chip features are cached per tile (LRU, ``chip_cache_size``): consecutive frames retrieve mostly the
same tiles near the prior, so the steady-state cost is one query extraction plus K matches + RANSAC.
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Final, Literal

import cv2
import numpy as np
import structlog

from gps_denied_onboard.camera.types import CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c2_5_rerank.types import RerankCandidate, RerankResult
from gps_denied_onboard.components.c2_vpr.query_norm import QueryNormaliser
from gps_denied_onboard.components.c2_vpr.types import VprBackboneError, VprResult
from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.components.c6_tiles.types import TileId
from gps_denied_onboard.constants import LogEvent
from gps_denied_onboard.helpers.ransac_filter import RansacFilter

_log = structlog.get_logger(__name__)

LABEL: Final[str] = "inlier"
Detector = Literal["sift", "orb"]


@dataclass(frozen=True)
class _Features:
    """Keypoints (n, 2) float32 (x, y) at work size and descriptors (n, d) (float32 SIFT / uint8 ORB)."""

    points: np.ndarray
    descriptors: np.ndarray | None


class InlierRerank:
    """C2.5 strategy ``inlier`` (see the module docstring).

    ``calibration``: the nav camera's (fixed for the flight; the protocol passes only the frame).
    ``normaliser``: share the C2 strategy's (``IndexedVpr.normaliser``) to warp each frame once; when
    None one is built at the store's GSD and ``chip_size_px``. ``ransac_threshold_px`` is in
    work-size pixels. Single pipeline thread by contract; the chip cache is lock-protected anyway.
    """

    def __init__(
        self,
        tile_store: TileStore,
        *,
        calibration: CameraCalibration,
        ransac_filter: RansacFilter,
        top_n: int = 3,
        chip_size_px: int = 512,
        normaliser: QueryNormaliser | None = None,
        detector: Detector = "sift",
        work_size_px: int = 192,
        max_features: int = 400,
        ratio_test: float = 0.8,
        ransac_threshold_px: float = 3.0,
        max_scale_change: float = 1.5,
        chip_cache_size: int = 64,
    ) -> None:
        if top_n < 1:
            raise ValueError(f"top_n must be >= 1, got {top_n}")
        if detector not in ("sift", "orb"):
            raise ValueError(f"detector must be 'sift' or 'orb', got {detector!r}")
        if work_size_px < 64 or max_features < 8 or not 0 < ratio_test <= 1 or not max_scale_change > 1:
            raise ValueError(
                "work_size_px >= 64, max_features >= 8, 0 < ratio_test <= 1, max_scale_change > 1"
            )
        if normaliser is not None and normaliser.chip_size_px != chip_size_px:
            raise ValueError(
                f"normaliser makes {normaliser.chip_size_px} px queries but chips are {chip_size_px} px"
            )
        self._tiles = tile_store
        self._calib = calibration
        self._ransac = ransac_filter
        self._top_n = int(top_n)
        self._chip_size = int(chip_size_px)
        self._normaliser = normaliser or QueryNormaliser(
            gsd_m_px=tile_store.gsd_m_px, chip_size_px=chip_size_px, backbone=LABEL
        )
        self._detector: Detector = detector
        self._work = int(work_size_px)
        self._max_features = int(max_features)
        self._ratio = float(ratio_test)
        self._threshold = float(ransac_threshold_px)
        self._max_log_scale = math.log(max_scale_change)
        self._cache: OrderedDict[TileId, _Features] = OrderedDict()
        self._cache_size = int(chip_cache_size)
        self._lock = threading.Lock()
        norm = cv2.NORM_L2 if detector == "sift" else cv2.NORM_HAMMING
        self._matcher = cv2.BFMatcher(norm, crossCheck=detector == "orb")

    @property
    def top_n(self) -> int:
        return self._top_n

    def rerank(self, frame: NavCameraFrame, vpr_result: VprResult) -> RerankResult:
        """Top ``top_n`` of ``vpr_result``'s candidates by inlier count (see the module docstring).

        A frame that cannot be normalised (no attitude/altitude) keeps C2's order with
        ``rerank_inliers = -1``: there is nothing to verify against, and C3 decides.
        """
        t0 = time.perf_counter()
        try:
            query = self._normaliser.normalise(frame, self._calib)
        except VprBackboneError as exc:
            _log.warning(LogEvent.RERANK_DONE, frame=str(frame.frame_id), skipped=str(exc))
            return self._result(frame, [(c, -1) for c in vpr_result.candidates[: self._top_n]])
        q = self._features(query.image)
        scored = [(c, self._inliers(q, c.tile_id)) for c in vpr_result.candidates]
        # Stable sort on (-inliers, vpr distance): equal inputs give equal outputs.
        scored.sort(key=lambda item: (-item[1], item[0].descriptor_distance))
        result = self._result(frame, scored[: self._top_n])
        _log.debug(
            LogEvent.RERANK_DONE,
            frame=str(frame.frame_id),
            k=len(vpr_result.candidates),
            inliers=[s for _, s in scored],
            ms=round((time.perf_counter() - t0) * 1e3, 2),
        )
        return result

    def _result(self, frame: NavCameraFrame, picked: list) -> RerankResult:  # type: ignore[type-arg]
        candidates = [
            RerankCandidate(
                tile_id=c.tile_id,
                tile_pixels_handle=self._tiles.chip(c.tile_id, self._chip_size),
                rerank_inliers=int(score),
                vpr_distance=c.descriptor_distance,
            )
            for c, score in picked
        ]
        return RerankResult(frame_id=frame.frame_id, candidates=candidates, reranked_at=time.monotonic_ns())

    def _chip_features(self, tile_id: TileId) -> _Features:
        with self._lock:
            hit = self._cache.get(tile_id)
            if hit is not None:
                self._cache.move_to_end(tile_id)
                return hit
        feats = self._features(np.asarray(self._tiles.chip(tile_id, self._chip_size).pixels()))
        with self._lock:
            self._cache[tile_id] = feats
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return feats

    def _features(self, image_bgr: np.ndarray) -> _Features:
        """Features of a chip-like image at work size; 0-pixels (off footprint / nodata) are masked."""
        small = cv2.resize(image_bgr, (self._work, self._work), interpolation=cv2.INTER_AREA)
        grey = cv2.cvtColor(small, cv2.COLOR_BGR2GRAY)
        mask = cv2.erode((small.any(axis=2)).astype(np.uint8) * 255, np.ones((7, 7), np.uint8))
        if self._detector == "sift":
            det = cv2.SIFT_create(nfeatures=self._max_features)  # type: ignore[attr-defined]
        else:
            det = cv2.ORB_create(  # type: ignore[attr-defined]
                nfeatures=self._max_features, edgeThreshold=15, patchSize=15
            )
        kps, desc = det.detectAndCompute(grey, mask)
        if desc is None or not kps:
            return _Features(np.empty((0, 2), np.float32), None)
        return _Features(np.array([k.pt for k in kps], dtype=np.float32), desc)

    def _inliers(self, q: _Features, tile_id: TileId) -> int:
        t = self._chip_features(tile_id)
        if q.descriptors is None or t.descriptors is None or len(q.points) < 4 or len(t.points) < 4:
            return 0
        if self._detector == "sift":
            pairs = self._matcher.knnMatch(q.descriptors, t.descriptors, k=2)
            good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < self._ratio * p[1].distance]
        else:
            good = list(self._matcher.match(q.descriptors, t.descriptors))
        if len(good) < 4:
            return 0
        qi = np.fromiter((m.queryIdx for m in good), dtype=np.int64, count=len(good))
        ti = np.fromiter((m.trainIdx for m in good), dtype=np.int64, count=len(good))
        corr = np.hstack([q.points[qi], t.points[ti]]).astype(np.float32)
        fit = self._ransac.filter(corr, self._threshold)
        if fit.homography is None:
            return 0
        # Both images are north-up at the map GSD: a real match is near a translation.
        sv = np.linalg.svd(fit.homography[:2, :2], compute_uv=False)
        if sv[-1] <= 0 or max(abs(math.log(sv[0])), abs(math.log(sv[-1]))) > self._max_log_scale:
            return 0
        return fit.inlier_count
