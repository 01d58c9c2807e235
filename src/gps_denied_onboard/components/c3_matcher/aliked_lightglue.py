"""ALIKED + LightGlue strategy (seed: secondary learned matcher), label ``aliked_lightglue``.

ALIKED runs through the C7 ``InferenceRuntime`` as an ONNX extractor in the LightGlue-ONNX layout
(exported by ``gdnav models export``); matching goes through the shared ``LightGlueRuntime`` (the
LightGlue-ONNX matcher when ``lightglue_weights_path`` is set, else mutual nearest neighbours at
``ALIKED_MNN_MIN_SIMILARITY``); RANSAC, ranking, health, FDR and logs are the shared candidate loop, tile
features come from its cache.

Input: every image is letterboxed into the model's fixed ``(1, 3, H, W)`` (a dynamic model: resized to
``input_long_side_px``, padded to multiples of 32), keypoints mapped back to the original pixels; the
query is rectified north-up at the map GSD (ALIKED is not rotation invariant).
Failure phases: ``aliked_forward`` and ``lightglue_match`` drop that candidate; ``aliked_forward_query``
fails the frame. Why each choice (scale, the cosine floor), measured: docs/design.md,
"`c3_matcher/aliked_lightglue.py`".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import cv2
import numpy as np

from gps_denied_onboard.components.c3_matcher.features import Features, no_features
from gps_denied_onboard.components.c3_matcher.learned import (
    LearnedPairMatcher,
    strongest,
    unpack_extractor_outputs,
)
from gps_denied_onboard.components.c7_inference.protocol import EngineLoadError, EngineSignature
from gps_denied_onboard.helpers.onnx_signatures import extractor_signature

LABEL: Final[str] = "aliked_lightglue"

#: The ALIKED encoder pools by 2, 4 and 4: input sides must be multiples of 32.
ALIKED_SIDE_MULTIPLE: Final[int] = 32
#: Descriptor sizes of the official variants (t16/n16: 64/128; n32: 128).
ALIKED_DESCRIPTOR_DIMS: Final[tuple[int, ...]] = (64, 128)

#: LightGlue-ONNX ALIKED extractor layout (``models.export``): ``image`` (1, 3, H, W) float32 RGB in
#: [0, 1] -> ``keypoints`` (1, N, 2) float32 (x, y) px of the input tensor, ``scores`` (1, N) float32,
#: ``descriptors`` (1, N, D) float32 L2-normalised, D in ``ALIKED_DESCRIPTOR_DIMS``.
ALIKED_SIGNATURE: Final[EngineSignature] = extractor_signature("aliked", channels=3, descriptor_dim=None)

#: Cosine floor for the helper's mutual-NN fallback with ALIKED descriptors (measured, see above).
ALIKED_MNN_MIN_SIMILARITY: Final[float] = 0.5

#: Keypoints closer than this to the black outside of a rectified query (or to the letterbox padding)
#: sit on an artificial edge, not on ground texture: dropped.
_INVALID_BORDER_PX: Final[int] = 4


class AlikedOutputError(ValueError):
    """The ALIKED engine returned tensors that do not follow ``ALIKED_SIGNATURE``."""


@dataclass(frozen=True)
class Letterbox:
    """How an image was placed into the model's input tensor.

    ``tensor``: (1, 3, H, W) float32 RGB in [0, 1]; ``scale``: tensor px per original px (same on both
    axes, so the aspect ratio and angles are kept); ``content_wh``: (w, h) px of the resized image in the
    tensor's top-left corner (the rest is zero padding).
    """

    tensor: np.ndarray
    scale: float
    content_wh: tuple[int, int]


def fit_scale(image_hw: tuple[int, int], input_hw: tuple[int, int]) -> float:
    """Largest scale at which an image of ``image_hw`` = (h, w) fits in ``input_hw`` = (H, W)."""
    return min(input_hw[1] / float(image_hw[1]), input_hw[0] / float(image_hw[0]))


def letterbox(image_bgr: np.ndarray, input_hw: tuple[int, int], scale: float | None = None) -> Letterbox:
    """BGR (h, w, 3) uint8 -> the model input of size ``input_hw`` = (H, W) (see ``Letterbox``).

    ``scale``: tensor px per image px; None or a scale at which the image would not fit = ``fit_scale``.
    """
    h, w = image_bgr.shape[:2]
    in_h, in_w = input_hw
    largest = fit_scale((h, w), input_hw)
    scale = largest if scale is None or scale > largest else float(scale)
    new_w = min(in_w, max(1, round(w * scale)))
    new_h = min(in_h, max(1, round(h * scale)))
    interp = cv2.INTER_AREA if scale < 1.0 else cv2.INTER_LINEAR
    resized = (
        cv2.resize(image_bgr, (new_w, new_h), interpolation=interp) if (new_w, new_h) != (w, h) else image_bgr
    )
    rgb = cv2.cvtColor(resized, cv2.COLOR_BGR2RGB)
    tensor = np.zeros((1, 3, in_h, in_w), dtype=np.float32)
    tensor[0, :, :new_h, :new_w] = rgb.transpose(2, 0, 1).astype(np.float32) * np.float32(1.0 / 255.0)
    return Letterbox(tensor, scale, (new_w, new_h))


def dynamic_input_hw(image_hw: tuple[int, int], long_side_px: int) -> tuple[int, int]:
    """Input (H, W) for a dynamic-size model: long side ``long_side_px``, both sides rounded up to 32."""
    h, w = image_hw
    scale = long_side_px / float(max(h, w))

    def up(v: float) -> int:
        return max(ALIKED_SIDE_MULTIPLE, -(-round(v) // ALIKED_SIDE_MULTIPLE) * ALIKED_SIDE_MULTIPLE)

    return up(h * scale), up(w * scale)


def _valid_image_mask(image_bgr: np.ndarray) -> np.ndarray | None:
    """(h, w) bool of pixels away from a black no-data region, or None when the image has none.

    A rectified query is black outside the camera footprint (recognised by black image corners, as in
    the classical strategy); its boundary is a strong artificial edge that would attract keypoints.
    """
    gray = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY)
    if gray[[0, 0, -1, -1], [0, -1, 0, -1]].all():
        return None
    k = 2 * _INVALID_BORDER_PX + 1
    return cv2.erode((gray > 0).astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)


class AlikedLightGlueMatcher(LearnedPairMatcher):
    """ALIKED features via C7 + shared LightGlue + shared RANSAC (see module docstring); the engine comes
    from ``config.aliked_weights_path``."""

    label = LABEL
    query_phase = "aliked_forward_query"
    tile_phase = "aliked_forward"
    weights_field = "aliked_weights_path"
    signature = ALIKED_SIGNATURE
    model_needed = "an ALIKED ONNX model (gdnav models export --weights-dir DIR --out DIR)"

    def _check_model(self) -> None:
        self._input_hw, self._descriptor_dim = self._model_layout()

    @property
    def input_hw(self) -> tuple[int, int] | None:
        """The model's fixed input (H, W) px, or None for a dynamic-size model."""
        return self._input_hw

    # --- internals -----------------------------------------------------------------------------------
    def _model_layout(self) -> tuple[tuple[int, int] | None, int | None]:
        """The loaded model's fixed input (H, W) (None when dynamic) and descriptor size D.

        Read from the model itself when the runtime exposes ``engine_info`` (ONNX Runtime does); a
        runtime without it is treated as dynamic-size. A fixed size that is not a multiple of 32 cannot
        be an ALIKED export: refused at load time, naming the file.
        """
        info_of = getattr(self._runtime, "engine_info", None)
        if info_of is None:
            return None, None
        info = info_of(self._engine_id)
        image = next((s for s in info.inputs if s.name == "image"), None)
        desc = next((s for s in info.outputs if s.name == "descriptors"), None)
        dim = desc.shape[2] if desc is not None and desc.shape is not None else None
        if isinstance(dim, int) and dim not in ALIKED_DESCRIPTOR_DIMS:
            raise EngineLoadError(
                f"descriptors have D={dim}; an ALIKED export has D in {ALIKED_DESCRIPTOR_DIMS}",
                path=self._model_path,
            )
        if image is None or image.shape is None:
            return None, dim
        h, w = image.shape[2], image.shape[3]
        if not (isinstance(h, int) and isinstance(w, int)):
            return None, dim
        if h % ALIKED_SIDE_MULTIPLE or w % ALIKED_SIDE_MULTIPLE:
            raise EngineLoadError(
                f"input is {h}x{w}; ALIKED needs sides that are multiples of {ALIKED_SIDE_MULTIPLE}",
                path=self._model_path,
            )
        return (h, w), dim

    def _forward(self, image_bgr: np.ndarray) -> Features:
        h, w = image_bgr.shape[:2]
        input_hw = self._input_hw or dynamic_input_hw((h, w), self._long_side_px)
        box = letterbox(image_bgr, input_hw)
        outputs = self._runtime.run(self._engine_id, {"image": box.tensor})
        pts, sc, d = unpack_extractor_outputs(outputs, "ALIKED", AlikedOutputError)
        dim = int(d.shape[1])
        # Back to the original image's pixels (pixel centres: (u + 0.5) / s - 0.5).
        orig = (pts + np.float32(0.5)) / np.float32(box.scale) - np.float32(0.5)
        # Keypoints in (or at the edge of) the letterbox padding are not on the image; fixed-top-k
        # models always return N points, so a small image fills the rest with these.
        cw, ch = box.content_wh
        b = float(_INVALID_BORDER_PX)
        keep = (pts[:, 0] < cw - b) & (pts[:, 1] < ch - b) & (pts[:, 0] >= 0) & (pts[:, 1] >= 0)
        keep &= (orig[:, 0] > -0.5) & (orig[:, 1] > -0.5) & (orig[:, 0] < w - 0.5) & (orig[:, 1] < h - 0.5)
        valid = _valid_image_mask(image_bgr)
        if valid is not None:
            xi = np.clip(np.rint(orig[:, 0]).astype(np.int64), 0, w - 1)
            yi = np.clip(np.rint(orig[:, 1]).astype(np.int64), 0, h - 1)
            keep &= valid[yi, xi]
        orig, sc, d = orig[keep], sc[keep], d[keep]
        if orig.shape[0] == 0:
            return no_features((w, h), dim)
        orig, d = strongest(orig, sc, d, self._max_keypoints)
        return Features(
            np.ascontiguousarray(orig, dtype=np.float32), np.ascontiguousarray(d, dtype=np.float32), (w, h)
        )


#: Registry factory for ``aliked_lightglue``: builds the strategy, which loads the ALIKED engine now
#: (``inference_runtime.load_engine(config.aliked_weights_path, ALIKED_SIGNATURE)``).
create = AlikedLightGlueMatcher.create
