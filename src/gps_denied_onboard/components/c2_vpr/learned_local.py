"""Learned local descriptors for VLAD (``vlad_xfeat``): a registry extractor's keypoint descriptors.

``XFeatDescriber`` is a ``vlad.LocalDescriber``: it runs the exported XFeat extractor (``gdnav models
export``, LightGlue-ONNX separate layout, ``c3_matcher.xfeat.XFEAT_SIGNATURE``) through C7's
``InferenceRuntime`` on a chip or a normalised query, and returns the descriptors of its best keypoints::

    image (S, S, 3) uint8 BGR, 0 = invalid
      -> resized so its long side is ``VladParams.work_size_px`` (multiple of 32), grey or RGB as the
         model declares (``c3_matcher.xfeat.preprocess_xfeat``, the matcher's own preprocessing)
      -> keypoints (1, N, 2), scores (1, N), descriptors (1, N, 64)
      -> keypoints on or near invalid pixels dropped (``INVALID_MARGIN_PX``: the zero border of a
         rectified query, map nodata), then at most ``VladParams.max_keypoints`` by score
      -> (n, 64) float32 descriptors (XFeat's, unit L2 norm)

``model_sha256`` (of the ONNX file) is recorded in the cache manifest when the vocabulary and index are
built (``c10_cache_build.vpr_index``), and ``VladVpr.from_cache`` refuses a cache built with another model.
Everything else (vocabulary from the cache's own chips, VLAD, PCA-whitening, the HNSW index, query
normalisation: north-up at the map's GSD, so no rotation search) is ``vlad``'s, unchanged.

Why XFeat, and the settings tried: docs/design.md, "`c2_vpr/learned_local.py`"; docs/benchmarks.md,
"Learned local descriptors".
"""

from __future__ import annotations

from pathlib import Path
from typing import Final

import cv2
import numpy as np

from gps_denied_onboard.components.c2_vpr.types import VprBackboneError
from gps_denied_onboard.components.c2_vpr.vlad import VladParams
from gps_denied_onboard.components.c3_matcher.xfeat import (
    XFEAT_SIGNATURE,
    model_input_channels,
    preprocess_xfeat,
    unpack_xfeat_outputs,
)
from gps_denied_onboard.components.c7_inference.protocol import (
    EngineLoadError,
    InferenceError,
    InferenceRuntime,
)
from gps_denied_onboard.components.c10_cache_build.manifest import sha256_file
from gps_denied_onboard.helpers.model_manifest import (
    PRECISION_FP32,
    ModelDirError,
    entry_precision,
    verify_model_dir,
)

#: A keypoint closer than this to an invalid pixel (px of the model input) is dropped: XFeat's
#: descriptors are read from a 1/8-resolution map whose receptive field spans a few cells.
INVALID_MARGIN_PX: Final[int] = 12


def default_xfeat_params(chip_size_px: int = 512) -> VladParams:
    """The ``vlad_xfeat`` defaults (measured in the module docstring)."""
    return VladParams(
        descriptor="xfeat",
        n_clusters=64,
        pca_dim=256,
        work_size_px=chip_size_px,
        max_keypoints=1024,
        chip_size_px=chip_size_px,
    )


def find_xfeat_extractor(model_dir: str | Path) -> Path:
    """The XFeat extractor of a ``gdnav models export`` directory, after its manifest's hashes verify.

    Raises ``ModelDirError`` when the directory does not verify or holds no XFeat extractor.
    """
    root = Path(model_dir)
    entries = verify_model_dir(root)
    for entry in entries:
        if (
            entry.params.get("family") == "xfeat"
            and entry.params.get("role") == "extractor"
            and entry_precision(entry) == PRECISION_FP32  # the vocabulary was learned on its descriptors
        ):
            return root / entry.file
    raise ModelDirError(
        "no XFeat extractor in the manifest (run gdnav models export --family xfeat)", path=str(root)
    )


class XFeatDescriber:
    """``LocalDescriber`` ``xfeat`` over an exported XFeat extractor (see the module docstring).

    Raises ``EngineLoadError`` when the file is missing or does not follow ``XFEAT_SIGNATURE``.
    Thread-safe as far as the runtime is (C7's ONNX runtime is).
    """

    name: Final[str] = "xfeat"

    def __init__(self, runtime: InferenceRuntime, model_path: str | Path) -> None:
        path = str(model_path)
        if not Path(path).is_file():
            raise EngineLoadError("XFeat extractor model file not found", path=path)
        self._runtime = runtime
        self._path = path
        self._engine_id = runtime.load_engine(path, XFEAT_SIGNATURE)
        self._channels = model_input_channels(runtime, self._engine_id, path)
        self._model_sha256 = sha256_file(Path(path))

    @property
    def model_sha256(self) -> str:
        return self._model_sha256

    @property
    def model_path(self) -> str:
        return self._path

    def describe(self, image_bgr: np.ndarray, params: VladParams) -> np.ndarray:
        """(H, W, 3) uint8 BGR -> (n, 64) float32; ``VprBackboneError`` when the forward pass fails."""
        img = np.asarray(image_bgr)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"image must be (H, W, 3) uint8, got {img.shape} {img.dtype}")
        tensor, _ = preprocess_xfeat(img, params.work_size_px, self._channels)
        th, tw = tensor.shape[2], tensor.shape[3]
        valid = np.asarray(img.any(axis=2), dtype=np.uint8)
        if not valid.any():
            return np.empty((0, 64), np.float32)
        try:
            outputs = self._runtime.run(self._engine_id, {"image": tensor})
            pts, scores, desc = unpack_xfeat_outputs(outputs)
        except (InferenceError, ValueError) as exc:
            raise VprBackboneError(f"XFeat forward pass failed: {exc}", backbone="vlad_xfeat") from exc
        if pts.shape[0] == 0:
            return np.empty((0, desc.shape[1]), np.float32)
        if not valid.all():
            small = cv2.resize(valid, (tw, th), interpolation=cv2.INTER_NEAREST)
        else:
            small = np.ones((th, tw), np.uint8)
        k = 2 * INVALID_MARGIN_PX + 1
        eroded = cv2.erode(small, np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=1)
        finite = np.isfinite(pts).all(axis=1) & np.isfinite(desc).all(axis=1)
        xi = np.clip(np.nan_to_num(pts[:, 0]), 0, tw - 1).astype(np.int64)
        yi = np.clip(np.nan_to_num(pts[:, 1]), 0, th - 1).astype(np.int64)
        inside = (pts[:, 0] >= 0) & (pts[:, 1] >= 0) & (pts[:, 0] < tw) & (pts[:, 1] < th)
        keep = finite & inside & (eroded[yi, xi] > 0)
        scores, desc = scores[keep], desc[keep]
        if desc.shape[0] > params.max_keypoints:
            order = np.argsort(-scores, kind="stable")[: params.max_keypoints]
            desc = desc[order]
        return np.ascontiguousarray(desc, dtype=np.float32)
