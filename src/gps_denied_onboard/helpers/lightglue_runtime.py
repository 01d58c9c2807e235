"""Shared LightGlue matching helper (seed AZ-278), used by C2.5 rerank and C3 matchers.

``LightGlueRuntime.match_pair`` matches two keypoint sets with a LightGlue-ONNX matcher model run by
the C7 ``InferenceRuntime`` or, when no model is configured, with a weights-free mutual nearest
neighbour on L2-normalised descriptors. ``FusedPipelineRuntime`` runs the fused extractor+LightGlue
layout on an image pair. Tensor layouts are documented in ``helpers.onnx_signatures``.

Both helpers serialise their calls with a lock: C2.5 and C3 share one instance.
"""

from __future__ import annotations

import threading
from typing import NamedTuple

import numpy as np
import structlog

from gps_denied_onboard.constants import LogEvent
from gps_denied_onboard.helpers.inference_contract import InferenceError, InferenceRuntime
from gps_denied_onboard.helpers.onnx_signatures import fused_pipeline_signature, lightglue_matcher_signature

_log = structlog.get_logger(__name__)

#: Valid values of ``LightGlueRuntime(fallback=...)``: what to do when no matcher model is configured.
FALLBACKS: tuple[str, ...] = ("mutual_nn", "none")


def normalize_keypoints(kpts_px: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """Pixel keypoints -> LightGlue's normalised frame.

    ``kpts_px``: (N, 2) float, pixel (x, y). ``image_size``: (w, h) in px of the image the keypoints
    belong to. Returns (N, 2) float32::

        kpts_n = (kpts_px - size / 2) / (max(size) / 2),   size = (w, h)

    (the LightGlue / LightGlue-ONNX convention: centred, scaled by the longer side so that the aspect
    ratio is kept; the longer axis spans [-1, 1]).
    """
    w, h = image_size
    if w <= 0 or h <= 0:
        raise ValueError(f"image_size must be positive (w, h), got {image_size}")
    size = np.array([w, h], dtype=np.float32)
    shift = size / np.float32(2.0)
    scale = np.float32(max(w, h)) / np.float32(2.0)
    return ((np.asarray(kpts_px, dtype=np.float32) - shift) / scale).astype(np.float32)


def _empty_matches() -> tuple[np.ndarray, np.ndarray]:
    return np.zeros((0, 2), dtype=np.int64), np.zeros((0,), dtype=np.float32)


def mutual_nearest_neighbours(
    desc0: np.ndarray, desc1: np.ndarray, *, min_similarity: float
) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours by cosine similarity (weights-free matcher).

    ``desc0`` (N0, D), ``desc1`` (N1, D) float. Rows are L2-normalised, similarity = cosine; pair
    (i, j) is kept when j is i's best match, i is j's best match, and the similarity is
    ``>= min_similarity``. Ties go to the lower index (deterministic). Returns matches (M, 2) int64
    sorted by i, and their similarities (M,) float32.
    """
    if desc0.shape[0] == 0 or desc1.shape[0] == 0:
        return _empty_matches()
    d0 = desc0.astype(np.float32, copy=False)
    d1 = desc1.astype(np.float32, copy=False)
    d0 = d0 / np.maximum(np.linalg.norm(d0, axis=1, keepdims=True), np.float32(1e-12))
    d1 = d1 / np.maximum(np.linalg.norm(d1, axis=1, keepdims=True), np.float32(1e-12))
    sim = d0 @ d1.T
    nn01 = np.argmax(sim, axis=1)
    idx0 = np.arange(sim.shape[0])
    best = sim[idx0, nn01]
    # i is j's best when sim[i, j] is column j's maximum and no earlier row reaches it. Row-wise
    # reductions only: numpy's argmax(axis=0) copies the matrix transposed (at 2048 x 2048 it costs
    # more than the product itself). Columns whose maximum is reached twice are resolved one by one.
    col_max = sim.max(axis=0)
    mutual = best == col_max[nn01]
    at_max = sim == col_max
    # Every column reaches its (non-NaN) maximum at least once, so as many hits as columns means no column
    # reaches it twice: one count over the whole matrix instead of a sum down each column.
    if np.isnan(col_max).any() or np.count_nonzero(at_max) != sim.shape[1]:
        for j in np.flatnonzero(at_max.sum(axis=0) > 1):
            mutual &= (nn01 != j) | (idx0 == np.argmax(at_max[:, j]))
    keep = mutual & (best >= min_similarity)
    matches = np.stack([idx0[keep], nn01[keep]], axis=1).astype(np.int64)
    return matches, best[keep].astype(np.float32)


def _check_features(name: str, kpts: np.ndarray, desc: np.ndarray) -> None:
    if kpts.ndim != 2 or kpts.shape[1] != 2:
        raise ValueError(f"{name}: keypoints must be (N, 2), got {kpts.shape}")
    if desc.ndim != 2 or desc.shape[0] != kpts.shape[0]:
        raise ValueError(f"{name}: descriptors must be (N={kpts.shape[0]}, D), got {desc.shape}")


def _validate_matches(
    label: str,
    matches: np.ndarray,
    scores: np.ndarray,
    n0: int,
    n1: int,
    names: tuple[str, str] = ("matches0", "mscores0"),
) -> tuple[np.ndarray, np.ndarray]:
    """Model output -> (M, 2) int64 and (M,) float32, or InferenceError naming what is wrong."""
    if matches.ndim != 2 or matches.shape[1] != 2:
        raise InferenceError(f"{label}: {names[0]} must be (M, 2), model returned {matches.shape}")
    if scores.shape != (matches.shape[0],):
        raise InferenceError(
            f"{label}: {names[1]} must be (M,) with M={matches.shape[0]}, model returned {scores.shape}"
        )
    matches = matches.astype(np.int64, copy=False)
    if matches.shape[0]:
        bad = (matches[:, 0] < 0) | (matches[:, 0] >= n0) | (matches[:, 1] < 0) | (matches[:, 1] >= n1)
        if bad.any():
            first = matches[np.flatnonzero(bad)[0]].tolist()
            raise InferenceError(
                f"{label}: {int(bad.sum())} match indices out of range (N0={n0}, N1={n1}), first {first}"
            )
    return matches, scores.astype(np.float32, copy=False)


class LightGlueRuntime:
    """Shared LightGlue matcher handle (one per process, used by C2.5 and C3).

    ``runtime``: the C7 ``InferenceRuntime`` that owns the session. ``matcher_path``: a LightGlue-ONNX
    matcher model (loaded and checked against ``lightglue_matcher_signature(descriptor_dim)`` here, at
    construction; ``EngineLoadError`` if it is missing or does not match), or None for no model.
    ``min_score``: matches with a model score below this are dropped. ``fallback``: without a model,
    ``"mutual_nn"`` matches by mutual nearest neighbour (cosine ``>= mnn_min_similarity``); ``"none"``
    makes a missing model an error (``ValueError``). ``descriptor_dim`` pins D in the signature check.
    """

    def __init__(
        self,
        runtime: InferenceRuntime,
        matcher_path: str | None,
        *,
        min_score: float = 0.0,
        fallback: str = "mutual_nn",
        mnn_min_similarity: float = 0.75,
        descriptor_dim: int | None = None,
    ) -> None:
        if fallback not in FALLBACKS:
            raise ValueError(f"unknown LightGlue fallback '{fallback}'; valid: {', '.join(FALLBACKS)}")
        if matcher_path is None and fallback == "none":
            raise ValueError("no LightGlue matcher model configured and fallback='none'")
        if not -1.0 <= mnn_min_similarity <= 1.0:
            raise ValueError(f"mnn_min_similarity is a cosine in [-1, 1], got {mnn_min_similarity}")
        self._runtime = runtime
        self._min_score = float(min_score)
        self._mnn_min_similarity = float(mnn_min_similarity)
        self._lock = threading.Lock()
        self._engine_id: str | None = None
        if matcher_path is not None:
            self._engine_id = runtime.load_engine(matcher_path, lightglue_matcher_signature(descriptor_dim))
        _log.info(
            LogEvent.LIGHTGLUE_READY,
            mode=self.mode,
            matcher_path=matcher_path,
            engine_id=self._engine_id,
            min_score=self._min_score,
            mnn_min_similarity=self._mnn_min_similarity if self._engine_id is None else None,
        )

    @property
    def engine_id(self) -> str | None:
        """C7 engine id of the matcher model, or None when the fallback is used."""
        return self._engine_id

    @property
    def mode(self) -> str:
        """``"lightglue"`` (model) or ``"mutual_nn"`` (fallback): for logs and FDR provenance."""
        return "lightglue" if self._engine_id is not None else "mutual_nn"

    def match_pair(
        self,
        kpts0: np.ndarray,
        desc0: np.ndarray,
        kpts1: np.ndarray,
        desc1: np.ndarray,
        *,
        image_size0: tuple[int, int],
        image_size1: tuple[int, int],
    ) -> tuple[np.ndarray, np.ndarray]:
        """Match one image pair.

        ``kpts0`` (N0, 2) float32 pixel (x, y) in image 0, ``desc0`` (N0, D) float32; same for image 1.
        ``image_size0``/``image_size1``: (w, h) px of the images the keypoints come from; keypoints are
        normalised per image as ``(k - size/2) / (max(size)/2)`` before the model sees them.

        Returns ``matches`` (M, 2) int64 (index into kpts0, index into kpts1) and ``scores`` (M,)
        float32 (model confidence, or cosine similarity for the fallback). Zero keypoints on either
        side returns empty arrays without running the model.

        Raises ``ValueError`` on malformed inputs (shapes, D mismatch, sizes) and ``InferenceError``
        when the model fails or returns malformed or out-of-range matches.
        """
        kpts0 = np.asarray(kpts0)
        kpts1 = np.asarray(kpts1)
        desc0 = np.asarray(desc0)
        desc1 = np.asarray(desc1)
        _check_features("image 0", kpts0, desc0)
        _check_features("image 1", kpts1, desc1)
        if desc0.shape[1] != desc1.shape[1]:
            raise ValueError(
                f"descriptor sizes differ: image 0 D={desc0.shape[1]}, image 1 D={desc1.shape[1]}"
            )
        n0, n1 = kpts0.shape[0], kpts1.shape[0]
        norm0 = normalize_keypoints(kpts0, image_size0)
        norm1 = normalize_keypoints(kpts1, image_size1)
        if n0 == 0 or n1 == 0:
            return _empty_matches()
        with self._lock:
            if self._engine_id is None:
                return mutual_nearest_neighbours(desc0, desc1, min_similarity=self._mnn_min_similarity)
            outputs = self._runtime.run(
                self._engine_id,
                {
                    "kpts0": np.ascontiguousarray(norm0[None]),
                    "kpts1": np.ascontiguousarray(norm1[None]),
                    "desc0": np.ascontiguousarray(desc0[None], dtype=np.float32),
                    "desc1": np.ascontiguousarray(desc1[None], dtype=np.float32),
                },
            )
        try:
            raw_matches, raw_scores = outputs["matches0"], outputs["mscores0"]
        except KeyError as exc:
            raise InferenceError(
                f"{self._engine_id}: model output {exc} missing (got {sorted(outputs)})"
            ) from exc
        matches, scores = _validate_matches(
            self._engine_id, np.asarray(raw_matches), np.asarray(raw_scores), n0, n1
        )
        keep = scores >= self._min_score
        return matches[keep], scores[keep]


class FusedMatch(NamedTuple):
    """One image pair matched by the fused pipeline.

    ``kpts0`` (N0, 2) / ``kpts1`` (N1, 2) float32 pixel (x, y) in each input image; ``matches`` (M, 2)
    int64 (index into kpts0, index into kpts1); ``scores`` (M,) float32.
    """

    kpts0: np.ndarray
    kpts1: np.ndarray
    matches: np.ndarray
    scores: np.ndarray


class FusedPipelineRuntime:
    """Fused extractor+LightGlue model (``images`` (2B,C,H,W) -> keypoints, matches, mscores).

    The model is loaded and checked at construction (``EngineLoadError`` on a missing or mismatched
    file). ``min_score`` drops lower-scored matches.
    """

    def __init__(self, runtime: InferenceRuntime, pipeline_path: str, *, min_score: float = 0.0) -> None:
        self._runtime = runtime
        self._min_score = float(min_score)
        self._lock = threading.Lock()
        self._engine_id = runtime.load_engine(pipeline_path, fused_pipeline_signature())

    @property
    def engine_id(self) -> str:
        """C7 engine id of the pipeline model."""
        return self._engine_id

    def match_images(self, img0: np.ndarray, img1: np.ndarray) -> FusedMatch:
        """Match two images of the same shape, (C, H, W) float32 in [0, 1].

        Raises ``ValueError`` for mismatched shapes, ``InferenceError`` when the model fails or returns
        malformed or out-of-range matches.
        """
        img0 = np.asarray(img0, dtype=np.float32)
        img1 = np.asarray(img1, dtype=np.float32)
        if img0.ndim != 3 or img0.shape != img1.shape:
            raise ValueError(f"images must both be (C, H, W) of one shape, got {img0.shape} and {img1.shape}")
        with self._lock:
            outputs = self._runtime.run(
                self._engine_id, {"images": np.ascontiguousarray(np.stack([img0, img1]))}
            )
        label = self._engine_id
        keypoints = np.asarray(outputs["keypoints"])
        matches = np.asarray(outputs["matches"])
        scores = np.asarray(outputs["mscores"])
        if keypoints.ndim != 3 or keypoints.shape[0] != 2 or keypoints.shape[2] != 2:
            raise InferenceError(f"{label}: keypoints must be (2, N, 2) for one pair, got {keypoints.shape}")
        if matches.ndim != 2 or matches.shape[1] != 3:
            raise InferenceError(f"{label}: matches must be (M, 3), model returned {matches.shape}")
        if matches.shape[0] and not np.all(matches[:, 0] == 0):
            raise InferenceError(
                f"{label}: pair index out of range for one pair: {np.unique(matches[:, 0]).tolist()}"
            )
        n = keypoints.shape[1]
        pair_matches, pair_scores = _validate_matches(
            label, matches[:, 1:], scores, n, n, ("matches[:, 1:]", "mscores")
        )
        keep = pair_scores >= self._min_score
        kpts = keypoints.astype(np.float32)
        return FusedMatch(kpts[0], kpts[1], pair_matches[keep], pair_scores[keep])
