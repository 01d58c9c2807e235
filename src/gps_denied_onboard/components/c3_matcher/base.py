"""The per-candidate loop every C3 strategy runs (seed AZ-345 steps 3-11), implemented once.

A strategy supplies three hooks - extract features from the query image, from a candidate's chip, and
match two feature sets into putative correspondences - and this module does the rest, identically for
all strategies: query rectification, drop-and-continue (INV-4), the shared RANSAC, the deterministic
best-candidate order (INV-3), the residual WARN, exactly one health update per frame, the FDR records
and the ERROR logs. Keeping it in one place is what makes the strategies' numbers comparable.
"""

from __future__ import annotations

import abc
import functools
import time
from collections import OrderedDict
from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Final, NoReturn

import cv2
import numpy as np
import structlog

from gps_denied_onboard.camera.types import CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c2_5_rerank.types import RerankCandidate, RerankResult
from gps_denied_onboard.components.c3_matcher.errors import InsufficientInliersError, MatcherBackboneError
from gps_denied_onboard.components.c3_matcher.features import Features, TileFeatureSource
from gps_denied_onboard.components.c3_matcher.health import RollingHealthWindow
from gps_denied_onboard.components.c3_matcher.types import CandidateMatchSet, MatcherHealth, MatchResult
from gps_denied_onboard.components.c6_tiles.types import TileId, TilePixelsHandle
from gps_denied_onboard.components.c13_fdr.protocol import FdrClient
from gps_denied_onboard.config import MatcherConfig
from gps_denied_onboard.constants import FdrKind, LogEvent
from gps_denied_onboard.helpers.frame_rectifier import RectificationError, rectify_to_map_frame
from gps_denied_onboard.helpers.ransac_filter import RansacFilter

_LOG = structlog.get_logger(__name__)

#: Default number of tiles whose features are kept (see ``TileFeatureCache``).
DEFAULT_TILE_CACHE_SIZE: Final[int] = 16


class TileFeatureCache:
    """Small LRU of tile features, keyed by the chip's identity.

    Consecutive frames (~3 Hz) see largely the same top-N tiles, and a chip's features depend only on
    its pixels, so re-extracting them is wasted work on the hot path. Only features are kept (a few
    hundred kB per tile), never the page-cache-backed pixels. The key includes the chip's shape, GSD
    and the geographic position of its pixel (0, 0), so a chip cut differently around the same tile is
    a different entry.
    """

    def __init__(self, max_entries: int = DEFAULT_TILE_CACHE_SIZE) -> None:
        if max_entries < 0:
            raise ValueError(f"max_entries must be >= 0, got {max_entries!r}")
        self._max = int(max_entries)
        self._entries: OrderedDict[Hashable, Features] = OrderedDict()
        self.hits = 0
        self.misses = 0

    def __len__(self) -> int:
        return len(self._entries)

    def clear(self) -> None:
        self._entries.clear()

    @staticmethod
    def key_of(handle: TilePixelsHandle, shape: tuple[int, ...]) -> Hashable:
        lon0, lat0 = handle.chip_px_to_lonlat(np.zeros((1, 2), dtype=np.float64))
        return (
            tuple(handle.tile_id),
            tuple(shape),
            round(float(handle.gsd_m_px), 6),
            round(float(np.asarray(lon0).ravel()[0]), 8),
            round(float(np.asarray(lat0).ravel()[0]), 8),
        )

    def get_or_compute(self, key: Hashable, compute: Callable[[], Features]) -> Features:
        found = self._entries.get(key)
        if found is not None:
            self._entries.move_to_end(key)
            self.hits += 1
            return found
        self.misses += 1
        value = compute()
        if self._max:
            self._entries[key] = value
            while len(self._entries) > self._max:
                self._entries.popitem(last=False)
        return value


@dataclass(frozen=True)
class QueryView:
    """The image a strategy extracts query features from, and the way back to nav-frame pixels.

    ``image``: (h, w, 3) uint8 BGR; ``to_frame_px``: (N, 2) query-image px -> (N, 2) float32 original
    nav-frame px (None = the image IS the nav frame).
    """

    image: np.ndarray
    to_frame_px: Callable[[np.ndarray], np.ndarray] | None
    rectified: bool
    #: The GSD the query was rectified to, m/px: the coarser of the map's and the frame's (None = not
    #: rectified). Chips finer than this are downsampled to it before their features are extracted.
    match_gsd_m_px: float | None = None


class _NullFdrClient:
    """Used when the composition root wires no recorder (tools, tests): records go nowhere."""

    def record(self, kind: str, fields: Mapping[str, object]) -> None:
        return None


NULL_FDR: Final[FdrClient] = _NullFdrClient()


def _tile_list(tile_id: TileId | None) -> list[object] | None:
    return None if tile_id is None else list(tile_id)


class CandidateLoopMatcher(abc.ABC):
    """Base of every ``CrossDomainMatcher`` strategy; subclasses implement the three hooks.

    Class attributes name the strategy (``label``, the FDR provenance) and the phases reported in
    ``MatcherBackboneError`` for failures in each hook. Any exception a hook raises is wrapped as a
    ``MatcherBackboneError`` of that phase (a hook may raise one itself with a finer phase): on a
    per-candidate hook it drops the candidate, on the query hook it fails the whole frame.
    """

    label: ClassVar[str]
    query_phase: ClassVar[str]
    tile_phase: ClassVar[str]
    match_phase: ClassVar[str]
    #: Warp the frame north-up at the map's GSD when attitude and altitude are known.
    rectify_query: ClassVar[bool] = True

    def __init__(
        self,
        *,
        ransac_filter: RansacFilter,
        fdr_client: FdrClient | None,
        health_window: RollingHealthWindow,
        config: MatcherConfig,
        tile_cache_size: int = DEFAULT_TILE_CACHE_SIZE,
    ) -> None:
        self._ransac_filter = ransac_filter
        self._fdr = fdr_client if fdr_client is not None else NULL_FDR
        self._health_window = health_window
        self._config = config
        self._tile_cache = TileFeatureCache(tile_cache_size)
        #: Precomputed features of the cache's chips (learned strategies; see ``LearnedPairMatcher``).
        self._tile_features: TileFeatureSource | None = None

    # --- hooks ---------------------------------------------------------------------------------------
    @abc.abstractmethod
    def extract_query(self, image_bgr: np.ndarray) -> Features:
        """Features of the query image (called once per frame)."""

    @abc.abstractmethod
    def extract_tile(self, chip_bgr: np.ndarray) -> Features:
        """Features of one candidate chip (read-only view; do not keep it)."""

    @abc.abstractmethod
    def match_features(self, query: Features, tile: Features) -> np.ndarray:
        """Putative correspondences (M, 4) float32 (x_query, y_query, x_tile, y_tile), before RANSAC;
        or (M, 5) with the matcher's confidence of each match (0..1) in the last column."""

    # --- CrossDomainMatcher ----------------------------------------------------------------------------
    @property
    def tile_cache(self) -> TileFeatureCache:
        return self._tile_cache

    @property
    def tile_features(self) -> TileFeatureSource | None:
        """The precomputed tile features this matcher uses, if any."""
        return self._tile_features

    def health_snapshot(self) -> MatcherHealth:
        return self._health_window.snapshot()

    def match(
        self, frame: NavCameraFrame, rerank_result: RerankResult, calibration: CameraCalibration
    ) -> MatchResult:
        """See ``CrossDomainMatcher.match``."""
        cfg = self._config
        frame_id = rerank_result.frame_id
        candidates = list(rerank_result.candidates)
        log = _LOG.bind(frame_id=str(frame_id), matcher=self.label)
        state = _FrameState()
        try:
            if frame.frame_id != frame_id:
                raise ValueError(f"rerank result is for frame {frame_id}, not for frame {frame.frame_id}")
            return self._match(frame, candidates, calibration, frame_id, cfg, log, state)
        finally:
            # Exactly one health update per frame, whatever happened (seed AC-8); the normal paths set
            # it themselves, this catches an unexpected error so the health signal never goes silent.
            if not state.health_updated:
                self._health_window.update(
                    time.monotonic_ns(), best_inlier_count=0, had_backbone_error=state.backbone_errors > 0
                )

    def _match(
        self,
        frame: NavCameraFrame,
        candidates: list[RerankCandidate],
        calibration: CameraCalibration,
        frame_id: object,
        cfg: MatcherConfig,
        log: structlog.typing.FilteringBoundLogger,
        state: _FrameState,
    ) -> MatchResult:
        n_input = len(candidates)
        if n_input == 0:
            self._fail(frame_id, log, state, n_input=0, dropped=0, best=0, reason="no candidates")

        query_view = self._query_view(frame, calibration, candidates, log)
        try:
            query = self.extract_query(query_view.image)
        except Exception as exc:
            # Without query features no candidate can be matched: the frame fails as a whole, after
            # reporting the backbone error like a per-candidate one (phase tells them apart).
            err = self._as_backbone_error(exc, None, self.query_phase)
            self._report_backbone_error(frame_id, err, log, state)
            self._fail(
                frame_id, log, state, n_input=n_input, dropped=n_input, best=0, reason=str(err), cause=err
            )

        survivors: list[CandidateMatchSet] = []
        dropped = 0
        for cand in candidates:
            tile_id = cand.tile_id
            handle = cand.tile_pixels_handle
            # Match at the coarser GSD: a chip finer than the query is brought down to the query's GSD
            # (same scale for both, and fewer pixels to extract from); its matches are scaled back.
            chip_scale = 1.0
            if query_view.match_gsd_m_px is not None:
                chip_scale = min(1.0, float(handle.gsd_m_px) / query_view.match_gsd_m_px)
            try:
                chip = handle.pixels()
                small = _downsampled_size(chip.shape, chip_scale)
                key = (TileFeatureCache.key_of(handle, chip.shape), small)
                tile = self._tile_cache.get_or_compute(
                    key, functools.partial(self._tile_features_of, handle, chip, small, state, log)
                )
                chip_hw = chip.shape[:2]
                del chip  # never outlive the call: the handle owns the pixels
            except Exception as exc:
                self._report_backbone_error(
                    frame_id, self._as_backbone_error(exc, tile_id, self.tile_phase), log, state
                )
                dropped += 1
                continue
            try:
                corr = self.match_features(query, tile)
                corr, scores = _check_correspondences(corr)
            except Exception as exc:
                self._report_backbone_error(
                    frame_id, self._as_backbone_error(exc, tile_id, self.match_phase), log, state
                )
                dropped += 1
                continue
            result = self._ransac_filter.filter(corr, threshold_px=cfg.ransac_threshold_px)
            n_inliers = int(result.inlier_correspondences.shape[0])
            if n_inliers == 0:
                log.debug(LogEvent.C3_ZERO_INLIERS, tile_id=list(tile_id), putative=int(corr.shape[0]))
                dropped += 1
                continue
            inliers = np.array(result.inlier_correspondences, dtype=np.float32, copy=True)
            inlier_scores = None
            if scores is not None and result.inlier_mask is not None:
                inlier_scores = np.ascontiguousarray(scores[result.inlier_mask])
            if query_view.to_frame_px is not None:
                inliers[:, :2] = query_view.to_frame_px(inliers[:, :2])
            if small is not None:
                # Pixel centres: x_small + 0.5 = (x + 0.5) * small_w / w.
                factors = np.array([chip_hw[1] / small[0], chip_hw[0] / small[1]], dtype=np.float32)
                inliers[:, 2:4] = (inliers[:, 2:4] + 0.5) * factors - 0.5
            survivors.append(
                CandidateMatchSet(
                    tile_id=tile_id,
                    inlier_count=n_inliers,
                    inlier_correspondences=inliers,
                    ransac_outlier_count=int(result.ransac_outlier_count),
                    per_candidate_residual_px=float(result.per_candidate_residual_px),
                    inlier_scores=inlier_scores,
                )
            )

        log.debug(
            LogEvent.C3_CANDIDATES,
            candidates=[(s.inlier_count, round(s.per_candidate_residual_px, 3)) for s in survivors],
            dropped=dropped,
            rectified=query_view.rectified,
            tiles_precomputed=state.tiles_precomputed,
        )
        best_inliers = max((s.inlier_count for s in survivors), default=0)
        if not survivors or best_inliers < cfg.min_inliers_threshold:
            self._fail(
                frame_id,
                log,
                state,
                n_input=n_input,
                dropped=dropped,
                best=best_inliers,
                reason="no candidate reached min_inliers_threshold",
            )

        # INV-3: deterministic order, inliers desc then median residual asc (sorted() is stable).
        survivors.sort(key=lambda s: (-s.inlier_count, s.per_candidate_residual_px))
        best = survivors[0]
        if best.per_candidate_residual_px > cfg.residual_warn_threshold_px:
            log.warning(
                LogEvent.C3_RESIDUAL_ABOVE_THRESHOLD,
                residual_px=best.per_candidate_residual_px,
                threshold_px=cfg.residual_warn_threshold_px,
                tile_id=list(best.tile_id),
            )
        now = time.monotonic_ns()
        self._health_window.update(
            now, best_inlier_count=best.inlier_count, had_backbone_error=state.backbone_errors > 0
        )
        state.health_updated = True
        self._fdr.record(
            FdrKind.MATCHER_FRAME_DONE,
            {
                "frame_id": str(frame_id),
                "candidates_input": n_input,
                "candidates_dropped": dropped,
                "best_inlier_count": best.inlier_count,
                "best_residual_px": best.per_candidate_residual_px,
                "best_tile_id": list(best.tile_id),
            },
        )
        return MatchResult(
            frame_id=frame_id,  # type: ignore[arg-type]
            per_candidate=survivors,
            best_candidate_idx=0,
            reprojection_residual_px=best.per_candidate_residual_px,
            matched_at=time.monotonic_ns(),
            matcher_label=self.label,
            candidates_input=n_input,
            candidates_dropped=dropped,
        )

    # --- helpers -------------------------------------------------------------------------------------
    def _query_view(
        self,
        frame: NavCameraFrame,
        calibration: CameraCalibration,
        candidates: list[RerankCandidate],
        log: structlog.typing.FilteringBoundLogger,
    ) -> QueryView:
        if not self.rectify_query or frame.attitude is None or frame.alt_agl_m is None:
            return QueryView(frame.image_bgr, None, rectified=False)
        # One query extraction serves all candidates, so rectify at the first chip's GSD (candidates
        # come from one zoom level and differ in GSD by far less than features tolerate), or at the
        # frame's own nadir GSD when that is coarser: upsampling the frame to a finer map adds pixels to
        # extract from and no detail to match (the chips are brought down to it instead).
        gsd = max(float(candidates[0].tile_pixels_handle.gsd_m_px), frame.alt_agl_m / calibration.fx_px)
        try:
            rect = rectify_to_map_frame(frame.image_bgr, calibration, frame.attitude, frame.alt_agl_m, gsd)
        except RectificationError as exc:
            # Still matchable raw with rotation-invariant features; the reason goes to the debug log.
            log.debug("c3.matcher.rectification_skipped", reason=str(exc))
            return QueryView(frame.image_bgr, None, rectified=False)
        return QueryView(rect.image, rect.rect_to_frame_px, rectified=True, match_gsd_m_px=gsd)

    def _tile_features_of(
        self,
        handle: TilePixelsHandle,
        chip: np.ndarray,
        small: tuple[int, int] | None,
        state: _FrameState,
        log: structlog.typing.FilteringBoundLogger,
    ) -> Features:
        """A chip's features: precomputed when the chip is used as cut (no downsampling) and the set has
        this very chip, else extracted now."""
        source = self._tile_features
        if small is None and source is not None:
            try:
                found = source.lookup(handle, (int(chip.shape[1]), int(chip.shape[0])))
            except Exception as exc:
                # An unreadable entry costs a live extraction, never the candidate.
                log.error(
                    LogEvent.TILE_FEATURES_CORRUPT,
                    tile_id=list(handle.tile_id),
                    error=f"{type(exc).__name__}: {exc}",
                    action="extracted live",
                )
                found = None
            if found is not None:
                state.tiles_precomputed += 1
                return found
        return self._extract_tile_at(chip, small)

    def _extract_tile_at(self, chip: np.ndarray, size: tuple[int, int] | None) -> Features:
        """Tile features of ``chip``, downsampled to ``size`` (width, height) first when given; the
        keypoints are then in the downsampled chip's pixels (the candidate loop maps matches back)."""
        if size is None:
            return self.extract_tile(chip)
        return self.extract_tile(cv2.resize(chip, size, interpolation=cv2.INTER_AREA))

    @staticmethod
    def _as_backbone_error(exc: Exception, tile_id: TileId | None, phase: str) -> MatcherBackboneError:
        if isinstance(exc, MatcherBackboneError):
            return exc
        err = MatcherBackboneError(f"{type(exc).__name__}: {exc}", tile_id=tile_id, phase=phase)
        err.__cause__ = exc
        return err

    def _report_backbone_error(
        self,
        frame_id: object,
        err: MatcherBackboneError,
        log: structlog.typing.FilteringBoundLogger,
        state: _FrameState,
    ) -> None:
        state.backbone_errors += 1
        cause = err.__cause__ if err.__cause__ is not None else err
        log.error(
            LogEvent.C3_BACKBONE_ERROR,
            tile_id=_tile_list(err.tile_id),
            phase=err.phase,
            error=f"{type(cause).__name__}: {cause}",
            backbone=self.label,
        )
        self._fdr.record(
            FdrKind.MATCHER_BACKBONE_ERROR,
            {
                "frame_id": str(frame_id),
                "tile_id": _tile_list(err.tile_id),
                "phase": err.phase,
                "error": f"{type(cause).__name__}: {cause}",
                "matcher_label": self.label,
            },
        )

    def _fail(
        self,
        frame_id: object,
        log: structlog.typing.FilteringBoundLogger,
        state: _FrameState,
        *,
        n_input: int,
        dropped: int,
        best: int,
        reason: str,
        cause: BaseException | None = None,
    ) -> NoReturn:
        threshold = self._config.min_inliers_threshold
        fields = {
            "frame_id": str(frame_id),
            "backbone": self.label,
            "best_inlier_count": best,
            "threshold": threshold,
            "candidates_input": n_input,
            "candidates_dropped": dropped,
            "reason": reason,
        }
        log.error(LogEvent.C3_INSUFFICIENT_INLIERS, **{k: v for k, v in fields.items() if k != "frame_id"})
        self._fdr.record(FdrKind.MATCHER_INSUFFICIENT_INLIERS, fields)
        # The seed reports a failed frame to the health window as 0 inliers, whatever the best was.
        self._health_window.update(
            time.monotonic_ns(), best_inlier_count=0, had_backbone_error=state.backbone_errors > 0
        )
        state.health_updated = True
        raise InsufficientInliersError(
            f"C3 {self.label}: {reason}",
            frame_id=frame_id,  # type: ignore[arg-type]
            best_inlier_count=best,
            threshold=threshold,
            candidates_input=n_input,
            candidates_dropped=dropped,
        ) from cause


@dataclass
class _FrameState:
    """Mutable per-frame bookkeeping shared by ``match`` and its ``finally``."""

    backbone_errors: int = 0
    health_updated: bool = False
    #: Candidates whose tile features came from the precomputed set (not from the in-memory LRU).
    tiles_precomputed: int = 0


def _downsampled_size(shape: tuple[int, ...], scale: float) -> tuple[int, int] | None:
    """(width, height) of a chip of ``shape`` downsampled by ``scale``; None when it stays as is
    (``scale`` within 2 % of 1: not worth a resampling)."""
    if scale >= 0.98:
        return None
    h, w = int(shape[0]), int(shape[1])
    return max(16, round(w * scale)), max(16, round(h * scale))


def _check_correspondences(corr: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """((M, 4) float32 correspondences, (M,) float32 confidences or None) from a hook's output."""
    arr = np.asarray(corr)
    if arr.ndim != 2 or arr.shape[1] not in (4, 5):
        raise ValueError(f"strategy returned correspondences of shape {arr.shape}, expected (M, 4) or (M, 5)")
    arr = arr.astype(np.float32, copy=False)
    if arr.shape[1] == 4:
        return arr, None
    return np.ascontiguousarray(arr[:, :4]), np.ascontiguousarray(arr[:, 4])


def match_with_lightglue(lightglue_runtime: Any, query: Features, tile: Features) -> np.ndarray:
    """Correspondences (M, 4) float32 (query x, y, tile x, y in original pixels) from the shared LightGlue
    helper's index pairs, with LightGlue's match score as a fifth column when a LightGlue model ran;
    the learned strategies' common ``match_features``. Malformed output from the
    helper (wrong shape, indices outside either keypoint set) is a ValueError, which the candidate loop
    treats as a backbone failure of that candidate (drop-and-continue)."""
    if query.count == 0 or tile.count == 0:
        return np.empty((0, 4), dtype=np.float32)
    matches, scores = lightglue_runtime.match_pair(
        query.keypoints_px,
        query.descriptors,
        tile.keypoints_px,
        tile.descriptors,
        image_size0=query.image_size,
        image_size1=tile.image_size,
    )
    idx = np.asarray(matches)
    if idx.size == 0:
        return np.empty((0, 4), dtype=np.float32)
    if idx.ndim != 2 or idx.shape[1] != 2:
        raise ValueError(f"LightGlue returned matches of shape {idx.shape}, expected (M, 2)")
    idx = idx.astype(np.int64, copy=False)
    if (idx < 0).any() or (idx[:, 0] >= query.count).any() or (idx[:, 1] >= tile.count).any():
        raise ValueError(
            f"LightGlue returned indices outside the keypoint sets ({query.count}, {tile.count})"
        )
    corr = np.hstack([query.keypoints_px[idx[:, 0]], tile.keypoints_px[idx[:, 1]]]).astype(np.float32)
    # LightGlue's match scores are the confidences the integrity rule weighs (c4_pose/integrity.py);
    # the mutual-NN fallback's cosine similarities are not calibrated confidences, so none are given.
    conf = np.asarray(scores, dtype=np.float32).reshape(-1) if scores is not None else None
    if getattr(lightglue_runtime, "mode", None) == "lightglue" and conf is not None and conf.size == len(idx):
        return np.hstack([corr, conf[:, None]])
    return corr
