"""DISK + LightGlue strategy (seed AZ-345, production default), label ``disk_lightglue``.

DISK runs through the C7 ``InferenceRuntime`` (LightGlue-ONNX extractor layout, ``DISK_SIGNATURE``);
matching goes through the shared LightGlue helper; RANSAC, ranking, health and FDR are the shared loop
in ``base.CandidateLoopMatcher``. The engine is loaded when the strategy is built (by ``create``), so a
missing or mismatched model fails at start-up, never at the first frame.

Failure phases: ``disk_forward`` (a chip's forward pass), ``lightglue_match`` (a pair's match) drop
that candidate; ``disk_forward_query`` (the nav frame's forward pass) fails the whole frame with
``InsufficientInliersError`` - no candidate can be matched without query features.
"""

from __future__ import annotations

from typing import Final

import cv2
import numpy as np

from gps_denied_onboard.components.c3_matcher.base import (
    Features,
    LearnedPairMatcher,
    TileFeatureSource,
    require_runtimes,
)
from gps_denied_onboard.components.c3_matcher.health import RollingHealthWindow
from gps_denied_onboard.components.c7_inference.protocol import (
    EngineLoadError,
    EngineSignature,
    InferenceRuntime,
)
from gps_denied_onboard.components.c13_fdr.protocol import FdrClient
from gps_denied_onboard.config import MatcherConfig
from gps_denied_onboard.helpers.lightglue_runtime_protocol import LightGluePairMatcher
from gps_denied_onboard.helpers.onnx_signatures import extractor_signature
from gps_denied_onboard.helpers.ransac_filter import RansacFilter

LABEL: Final[str] = "disk_lightglue"

#: DISK descriptors are 128-D.
DISK_DESCRIPTOR_DIM: Final[int] = 128
#: The DISK U-Net downsamples 4 times: input sides must be multiples of 16.
DISK_SIDE_MULTIPLE: Final[int] = 16

#: LightGlue-ONNX DISK extractor layout (``helpers.onnx_signatures``): ``image`` (1, 3, H, W) float32
#: RGB in [0, 1], H and W multiples of 16 -> ``keypoints`` (1, N, 2) int64 or float32 (x, y) pixels of
#: the input tensor, ``scores`` (1, N) float32, ``descriptors`` (1, N, 128) float32.
DISK_SIGNATURE: Final[EngineSignature] = extractor_signature(
    "disk", channels=3, descriptor_dim=DISK_DESCRIPTOR_DIM
)


class DiskOutputError(ValueError):
    """The DISK engine returned tensors that do not follow ``DISK_SIGNATURE``."""


def preprocess_disk(image_bgr: np.ndarray, long_side_px: int) -> tuple[np.ndarray, tuple[float, float]]:
    """BGR (H, W, 3) uint8 -> ((1, 3, H', W') float32 RGB [0, 1], (sx, sy)).

    The image is resized so that its long side is ``long_side_px``, then zero-padded at the bottom and
    right to multiples of 16 (padding, not cropping, so no part of the chip is lost). ``(sx, sy)``:
    tensor px = original px * (sx, sy).
    """
    h, w = image_bgr.shape[:2]
    scale = long_side_px / float(max(h, w))
    new_w = max(1, round(w * scale))
    new_h = max(1, round(h * scale))
    interp = cv2.INTER_AREA if scale < 1.0 else cv2.INTER_LINEAR
    resized = (
        cv2.resize(image_bgr, (new_w, new_h), interpolation=interp) if (new_w, new_h) != (w, h) else image_bgr
    )
    pad_w = -new_w % DISK_SIDE_MULTIPLE
    pad_h = -new_h % DISK_SIDE_MULTIPLE
    rgb = cv2.cvtColor(resized, cv2.COLOR_BGR2RGB)
    tensor = np.zeros((1, 3, new_h + pad_h, new_w + pad_w), dtype=np.float32)
    tensor[0, :, :new_h, :new_w] = rgb.transpose(2, 0, 1).astype(np.float32) / 255.0
    return tensor, (new_w / w, new_h / h)


class DiskLightGlueMatcher(LearnedPairMatcher):
    """DISK features via C7 + shared LightGlue + shared RANSAC (see module docstring)."""

    label = LABEL
    query_phase = "disk_forward_query"
    tile_phase = "disk_forward"
    match_phase = "lightglue_match"

    def __init__(
        self,
        runtime: InferenceRuntime,
        lightglue_runtime: LightGluePairMatcher,
        ransac_filter: RansacFilter,
        fdr_client: FdrClient | None,
        health_window: RollingHealthWindow,
        config: MatcherConfig,
        tile_features: TileFeatureSource | None = None,
    ) -> None:
        """Loads the DISK engine from ``config.disk_weights_path`` (raises C7's ``EngineLoadError``)."""
        super().__init__(
            ransac_filter=ransac_filter, fdr_client=fdr_client, health_window=health_window, config=config
        )
        if not config.disk_weights_path:
            raise EngineLoadError(
                "not set; the disk_lightglue strategy needs a DISK ONNX model",
                path="matcher.disk_weights_path",
            )
        self._runtime = runtime
        self._lightglue_runtime = lightglue_runtime
        self._engine_id = runtime.load_engine(config.disk_weights_path, DISK_SIGNATURE)
        self._long_side_px = int(config.input_long_side_px)
        self._max_keypoints = int(config.max_keypoints)
        self._init_tile_features(str(config.disk_weights_path), tile_features)

    @property
    def engine_id(self) -> str:
        return self._engine_id

    # --- internals -----------------------------------------------------------------------------------
    def _forward(self, image_bgr: np.ndarray) -> Features:
        h, w = image_bgr.shape[:2]
        tensor, (sx, sy) = preprocess_disk(image_bgr, self._long_side_px)
        outputs = self._runtime.run(self._engine_id, {"image": tensor})
        try:
            kpts = np.asarray(outputs["keypoints"])
            scores = np.asarray(outputs["scores"])
            desc = np.asarray(outputs["descriptors"])
        except KeyError as exc:
            raise DiskOutputError(f"DISK output {exc} missing; got {sorted(outputs)}") from exc
        if kpts.ndim != 3 or kpts.shape[0] != 1 or kpts.shape[2] != 2:
            raise DiskOutputError(f"keypoints must be (1, N, 2), got {kpts.shape}")
        n = kpts.shape[1]
        if scores.shape != (1, n) or desc.ndim != 3 or desc.shape[:2] != (1, n):
            raise DiskOutputError(
                f"scores {scores.shape} / descriptors {desc.shape} do not match {n} keypoints"
            )
        pts = kpts[0].astype(np.float32)
        sc = scores[0].astype(np.float32)
        d = desc[0].astype(np.float32)
        # Keypoints in the zero padding are not on the image.
        new_w, new_h = w * sx, h * sy
        on_image = (pts[:, 0] >= 0) & (pts[:, 1] >= 0) & (pts[:, 0] < new_w) & (pts[:, 1] < new_h)
        pts, sc, d = pts[on_image], sc[on_image], d[on_image]
        if pts.shape[0] > self._max_keypoints:
            order = np.argsort(-sc, kind="stable")[: self._max_keypoints]
            pts, d = pts[order], d[order]
        # Back to the original image's pixels (pixel centres: (u + 0.5) / s - 0.5).
        pts = np.column_stack([(pts[:, 0] + 0.5) / sx - 0.5, (pts[:, 1] + 0.5) / sy - 0.5]).astype(np.float32)
        return Features(pts, np.ascontiguousarray(d, dtype=np.float32), (w, h))


def create(
    config: MatcherConfig,
    lightglue_runtime: LightGluePairMatcher,
    ransac_filter: RansacFilter,
    inference_runtime: InferenceRuntime,
    health_window: RollingHealthWindow,
    fdr_client: FdrClient | None = None,
    tile_features: TileFeatureSource | None = None,
) -> DiskLightGlueMatcher:
    """Registry factory for ``disk_lightglue``: builds the strategy, which loads the DISK engine now
    (``inference_runtime.load_engine(config.disk_weights_path, DISK_SIGNATURE)``)."""
    require_runtimes(
        "disk_lightglue", inference_runtime=inference_runtime, lightglue_runtime=lightglue_runtime
    )
    return DiskLightGlueMatcher(
        inference_runtime, lightglue_runtime, ransac_filter, fdr_client, health_window, config, tile_features
    )
