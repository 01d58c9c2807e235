"""XFeat strategy (seed AZ-347, the lightweight alternate), label ``xfeat``.

XFeat runs through the C7 ``InferenceRuntime`` as an ONNX export in the LightGlue-ONNX separate-extractor
layout (``helpers.onnx_signatures.XFEAT_EXTRACTOR``)::

    image        (1, C, H, W)  float32   C = 1: grey in [0, 1]; C = 3: RGB in [0, 1] (XFeat averages the
                                         channels itself); H, W multiples of 32
    -> keypoints   (1, N, 2)   float32 (int64 accepted)  pixel (x, y) of the input tensor
       scores      (1, N)      float32
       descriptors (1, N, 64)  float32

C is read from the model's declared input when the engine is loaded, so grey and colour exports both
work; a model whose descriptors are not 64-D, or whose C is neither 1 nor 3, is refused at start-up
(``EngineLoadError``). Matching goes through the shared ``LightGlueRuntime.match_pair`` (a LighterGlue /
LightGlue model for 64-D descriptors when configured, else its mutual-nearest-neighbour fallback); RANSAC,
ranking, health and FDR are the shared loop in ``base.CandidateLoopMatcher``.

Failure phases: ``xfeat_forward`` (a chip's forward pass) and ``lightglue_match`` (a pair's match) drop
that candidate; ``xfeat_forward_query`` (the nav frame's) fails the whole frame.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Final

import cv2
import numpy as np
import structlog

from gps_denied_onboard.components.c3_matcher.features import Features, no_features
from gps_denied_onboard.components.c3_matcher.learned import (
    LearnedPairMatcher,
    strongest,
    tensor_to_image_px,
    unpack_extractor_outputs,
)
from gps_denied_onboard.components.c7_inference.protocol import (
    EngineLoadError,
    EngineSignature,
    InferenceError,
    InferenceRuntime,
)
from gps_denied_onboard.helpers.lightglue_runtime_protocol import LightGluePairMatcher
from gps_denied_onboard.helpers.onnx_signatures import XFEAT_EXTRACTOR

_LOG = structlog.get_logger(__name__)

LABEL: Final[str] = "xfeat"

#: XFeat descriptors are 64-D.
XFEAT_DESCRIPTOR_DIM: Final[int] = 64
#: XFeat's backbone downsamples by 32 (its own preprocessing cuts inputs to multiples of 32).
XFEAT_SIDE_MULTIPLE: Final[int] = 32
#: Input channel counts an XFeat export may declare.
XFEAT_CHANNELS: Final[tuple[int, ...]] = (1, 3)
#: Channel count used when the runtime cannot say (or the model leaves C dynamic): XFeat's native input.
DEFAULT_XFEAT_CHANNELS: Final[int] = 1

#: See the module docstring; identical to ``helpers.onnx_signatures.XFEAT_EXTRACTOR``.
XFEAT_SIGNATURE: Final[EngineSignature] = XFEAT_EXTRACTOR


class XFeatOutputError(ValueError):
    """The XFeat engine returned tensors that do not follow ``XFEAT_SIGNATURE``."""


def xfeat_input_size(width_px: int, height_px: int, long_side_px: int) -> tuple[int, int]:
    """(w, h) of the tensor an image of (``width_px``, ``height_px``) is resized to.

    The long side is scaled to ``long_side_px``, then each side is rounded to the nearest multiple of 32
    (at least 32). Like XFeat's own preprocessing this resizes rather than pads: a zero border would be
    a strong false edge for a detector with no mask, and the slightly different x/y scales are undone
    exactly when keypoints are mapped back.
    """
    if width_px <= 0 or height_px <= 0:
        raise ValueError(f"image size must be positive, got {width_px}x{height_px}")
    if long_side_px < XFEAT_SIDE_MULTIPLE:
        raise ValueError(f"long_side_px must be >= {XFEAT_SIDE_MULTIPLE}, got {long_side_px}")
    scale = long_side_px / float(max(width_px, height_px))
    m = XFEAT_SIDE_MULTIPLE
    return (
        max(m, round(width_px * scale / m) * m),
        max(m, round(height_px * scale / m) * m),
    )


def preprocess_xfeat(
    image_bgr: np.ndarray, long_side_px: int, channels: int
) -> tuple[np.ndarray, tuple[float, float]]:
    """BGR (H, W, 3) uint8 -> ((1, C, H', W') float32 in [0, 1], (sx, sy)); tensor px = image px * (sx, sy).

    ``channels`` 1 gives grey (OpenCV's BT.601 weights), 3 gives RGB; H', W' from ``xfeat_input_size``.
    """
    if channels not in XFEAT_CHANNELS:
        raise ValueError(f"XFeat input channels must be one of {XFEAT_CHANNELS}, got {channels}")
    if image_bgr.ndim != 3 or image_bgr.shape[2] != 3 or image_bgr.dtype != np.uint8:
        raise ValueError(f"expected (H, W, 3) uint8 BGR, got {image_bgr.shape} {image_bgr.dtype}")
    h, w = image_bgr.shape[:2]
    new_w, new_h = xfeat_input_size(w, h, long_side_px)
    if (new_w, new_h) != (w, h):
        interp = cv2.INTER_AREA if new_w * new_h < w * h else cv2.INTER_LINEAR
        image_bgr = cv2.resize(image_bgr, (new_w, new_h), interpolation=interp)
    if channels == 1:
        planes = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY)[None]
    else:
        planes = image_bgr[:, :, ::-1].transpose(2, 0, 1)  # RGB planes, a view
    # One pass into the C-contiguous tensor: uint8 -> float32, times float32(1/255), as the model was fed.
    tensor = np.empty((1, *planes.shape), dtype=np.float32)
    np.multiply(planes, np.float32(1.0 / 255.0), out=tensor[0], dtype=np.float32)
    return tensor, (new_w / w, new_h / h)


def model_input_channels(runtime: InferenceRuntime, engine_id: str, path: str) -> int:
    """C declared by the loaded model's ``image`` input.

    Uses the runtime's ``engine_info`` when it has one (C7's ONNX runtime does; the protocol does not
    require it). Unknown or dynamic C -> ``DEFAULT_XFEAT_CHANNELS``. Raises ``EngineLoadError`` for a
    fixed C other than 1 or 3 (the signature leaves C open because XFeat exports come in both).
    """
    engine_info = getattr(runtime, "engine_info", None)
    if not callable(engine_info):
        return DEFAULT_XFEAT_CHANNELS
    inputs = getattr(engine_info(engine_id), "inputs", ())
    spec = next((s for s in inputs if getattr(s, "name", None) == "image"), None)
    shape = getattr(spec, "shape", None)
    if not shape or len(shape) != 4 or shape[1] is None:
        return DEFAULT_XFEAT_CHANNELS
    channels = int(shape[1])
    if channels not in XFEAT_CHANNELS:
        raise EngineLoadError(
            f"model does not match signature '{XFEAT_SIGNATURE.label}': input 'image' has C={channels} "
            f"(model shape {list(shape)}), expected C in {list(XFEAT_CHANNELS)}",
            path=path,
        )
    return channels


def _check_lightglue_descriptor_dim(
    runtime: InferenceRuntime, lightglue_runtime: LightGluePairMatcher
) -> None:
    """Refuse at start-up a LightGlue model that was built for descriptors other than XFeat's 64-D.

    Best effort: only possible when the LightGlue model lives in the same runtime and that runtime can
    describe it; otherwise a mismatch shows up as per-candidate ``lightglue_match`` errors.
    """
    engine_id = getattr(lightglue_runtime, "engine_id", None)
    engine_info = getattr(runtime, "engine_info", None)
    if engine_id is None or not callable(engine_info):
        return
    try:
        info = engine_info(engine_id)
    except InferenceError:
        return  # loaded in another runtime: nothing to check here
    spec = next((s for s in getattr(info, "inputs", ()) if getattr(s, "name", None) == "desc0"), None)
    shape = getattr(spec, "shape", None)
    if shape and len(shape) == 3 and shape[2] is not None and int(shape[2]) != XFEAT_DESCRIPTOR_DIM:
        raise EngineLoadError(
            f"LightGlue matcher takes {shape[2]}-D descriptors (input 'desc0' {list(shape)}); "
            f"XFeat gives {XFEAT_DESCRIPTOR_DIM}-D: use a LighterGlue/LightGlue model trained on XFeat",
            path=str(getattr(info, "path", engine_id)),
        )


class XFeatMatcher(LearnedPairMatcher):
    """XFeat features via C7 + shared LightGlue helper + shared RANSAC (see module docstring).

    The engine comes from ``config.xfeat_weights_path``; refused (``EngineLoadError``) when the model does
    not match ``XFEAT_SIGNATURE`` (D != 64, C not in {1, 3}) or the configured LightGlue model.
    """

    label = LABEL
    query_phase = "xfeat_forward_query"
    tile_phase = "xfeat_forward"
    weights_field = "xfeat_weights_path"
    signature = XFEAT_SIGNATURE
    model_needed = "an XFeat ONNX model"

    def _check_model(self) -> None:
        self._channels = model_input_channels(self._runtime, self._engine_id, self._model_path)
        if self._lightglue_runtime is not None:
            _check_lightglue_descriptor_dim(self._runtime, self._lightglue_runtime)
        _LOG.debug(
            "c3.matcher.xfeat_engine",
            strategy=self.label,
            engine_id=self._engine_id,
            input_channels=self._channels,
            lightglue_mode=getattr(self._lightglue_runtime, "mode", None),
        )

    @property
    def input_channels(self) -> int:
        """C fed to the model: 1 (grey) or 3 (RGB)."""
        return self._channels

    # --- internals -----------------------------------------------------------------------------------
    def _forward(self, image_bgr: np.ndarray) -> Features:
        h, w = image_bgr.shape[:2]
        tensor, (sx, sy) = preprocess_xfeat(image_bgr, self._long_side_px, self._channels)
        outputs = self._runtime.run(self._engine_id, {"image": tensor})
        pts, scores, desc = unpack_xfeat_outputs(outputs)
        if pts.shape[0] == 0:
            return no_features((w, h), XFEAT_DESCRIPTOR_DIM)
        # Exports with a fixed top-k may emit points off the tensor (or NaN) for empty slots.
        tw, th = tensor.shape[3], tensor.shape[2]
        valid = (
            np.isfinite(pts).all(axis=1)
            & (pts[:, 0] >= 0)
            & (pts[:, 1] >= 0)
            & (pts[:, 0] < tw)
            & (pts[:, 1] < th)
        )
        pts, desc = strongest(pts[valid], scores[valid], desc[valid], self._max_keypoints)
        return Features(tensor_to_image_px(pts, sx, sy), np.ascontiguousarray(desc, dtype=np.float32), (w, h))


def unpack_xfeat_outputs(outputs: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Model outputs -> keypoints (N, 2) float32, scores (N,) float32, descriptors (N, 64) float32."""
    return unpack_extractor_outputs(outputs, "XFeat", XFeatOutputError, XFEAT_DESCRIPTOR_DIM)


#: Registry factory for ``xfeat``: builds the strategy, which loads the XFeat engine now.
create = XFeatMatcher.create
