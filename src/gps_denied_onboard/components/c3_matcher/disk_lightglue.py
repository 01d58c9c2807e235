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

from gps_denied_onboard.components.c3_matcher.features import Features
from gps_denied_onboard.components.c3_matcher.learned import (
    LearnedPairMatcher,
    strongest,
    tensor_to_image_px,
    unpack_extractor_outputs,
)
from gps_denied_onboard.components.c7_inference.protocol import EngineSignature
from gps_denied_onboard.helpers.onnx_signatures import extractor_signature

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
    """DISK features via C7 + shared LightGlue + shared RANSAC (see module docstring); the engine comes
    from ``config.disk_weights_path``."""

    label = LABEL
    query_phase = "disk_forward_query"
    tile_phase = "disk_forward"
    weights_field = "disk_weights_path"
    signature = DISK_SIGNATURE
    model_needed = "a DISK ONNX model"

    def _forward(self, image_bgr: np.ndarray) -> Features:
        h, w = image_bgr.shape[:2]
        tensor, (sx, sy) = preprocess_disk(image_bgr, self._long_side_px)
        outputs = self._runtime.run(self._engine_id, {"image": tensor})
        pts, sc, d = unpack_extractor_outputs(outputs, "DISK", DiskOutputError)
        # Keypoints in the zero padding are not on the image.
        new_w, new_h = w * sx, h * sy
        on_image = (pts[:, 0] >= 0) & (pts[:, 1] >= 0) & (pts[:, 0] < new_w) & (pts[:, 1] < new_h)
        pts, d = strongest(pts[on_image], sc[on_image], d[on_image], self._max_keypoints)
        return Features(tensor_to_image_px(pts, sx, sy), np.ascontiguousarray(d, dtype=np.float32), (w, h))


#: Registry factory for ``disk_lightglue``: builds the strategy, which loads the DISK engine now
#: (``inference_runtime.load_engine(config.disk_weights_path, DISK_SIGNATURE)``).
create = DiskLightGlueMatcher.create
