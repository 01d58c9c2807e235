"""Generic ONNX global-descriptor backbone (NetVLAD, MixVPR, EigenPlaces, MegaLoc... exports).

Model contract (checked when the engine is loaded, never at the first frame)::

    <input_name>   (1, 3, H, W) float32   RGB, (pixel / 255 - mean) / std per channel
    -> <output_name> (1, D)     float32   global descriptor (L2-normalised here, whatever the export does)

``OnnxGlobalEncoder`` runs one image through C7's ``InferenceRuntime``; the image is the normalised
query (``query_norm``) or a map chip, resized to ``input_size``. ``model_sha256`` (of the ONNX file)
is recorded in the cache manifest by C10 and compared at start-up by ``OnnxGlobalVpr.from_cache``, so
the daemon refuses descriptors built with another model.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from gps_denied_onboard.components.c2_vpr.query_norm import QueryNormaliser
from gps_denied_onboard.components.c2_vpr.retrieval import (
    VPR_DESCRIPTORS_NAME,
    VPR_INDEX_NAME,
    VPR_META_NAME,
    IndexedVpr,
    check_cache_backbone,
)
from gps_denied_onboard.components.c2_vpr.types import IndexUnavailableError, VprBackboneError
from gps_denied_onboard.components.c6_tiles.descriptor_index import DescriptorIndex, l2_normalise
from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.components.c7_inference.protocol import (
    EngineLoadError,
    EngineSignature,
    InferenceError,
    InferenceRuntime,
    TensorSpec,
)
from gps_denied_onboard.components.c10_cache_build.manifest import sha256_file
from gps_denied_onboard.helpers import bounded_json

IMAGENET_MEAN: tuple[float, float, float] = (0.485, 0.456, 0.406)
IMAGENET_STD: tuple[float, float, float] = (0.229, 0.224, 0.225)


def global_descriptor_signature(
    label: str, *, input_name: str, output_name: str, input_size: tuple[int, int], dim: int
) -> EngineSignature:
    """(1, 3, H, W) float32 -> (1, D) float32; a model with dynamic H/W passes, fixed ones must match."""
    h, w = input_size
    return EngineSignature(
        label=label,
        inputs=(TensorSpec(input_name, 4, "float32", (1, 3, h, w)),),
        outputs=(TensorSpec(output_name, 2, "float32", (1, dim)),),
    )


class OnnxGlobalEncoder:
    """``GlobalEncoder`` over an ONNX model (see the module docstring).

    ``input_size``: (H, W) px fed to the model. ``mean``/``std``: per-channel RGB normalisation of
    [0, 1] pixels. ``dim``: expected descriptor size D. ``label``: backbone name recorded in the
    manifest and FDR (e.g. ``"megaloc"``). Raises ``EngineLoadError`` when the file is missing or its
    signature does not match.
    """

    def __init__(
        self,
        runtime: InferenceRuntime,
        model_path: str | Path,
        *,
        input_size: tuple[int, int],
        mean: Sequence[float] = IMAGENET_MEAN,
        std: Sequence[float] = IMAGENET_STD,
        output_name: str,
        dim: int,
        label: str,
        input_name: str = "input",
    ) -> None:
        h, w = (int(v) for v in input_size)
        if h < 8 or w < 8:
            raise ValueError(f"input_size must be at least 8x8, got {input_size!r}")
        if len(mean) != 3 or len(std) != 3 or any(s <= 0 for s in std):
            raise ValueError(f"mean and std need 3 values (std > 0), got {mean!r}, {std!r}")
        if dim < 1:
            raise ValueError(f"dim must be >= 1, got {dim}")
        path = str(model_path)
        if not Path(path).is_file():
            raise EngineLoadError("global-descriptor model file not found", path=path)
        self._runtime = runtime
        self._label = label
        self._dim = int(dim)
        self._size = (h, w)
        self._input_name = input_name
        self._output_name = output_name
        self._mean = np.asarray(mean, np.float32).reshape(1, 1, 3)
        self._std = np.asarray(std, np.float32).reshape(1, 1, 3)
        signature = global_descriptor_signature(
            label, input_name=input_name, output_name=output_name, input_size=(h, w), dim=dim
        )
        self._engine = runtime.load_engine(path, signature)
        self._model_sha256 = sha256_file(Path(path))

    @property
    def label(self) -> str:
        return self._label

    @property
    def dim(self) -> int:
        return self._dim

    @property
    def model_sha256(self) -> str:
        return self._model_sha256

    def preprocess(self, image_bgr: np.ndarray) -> np.ndarray:
        """(H0, W0, 3) uint8 BGR -> (1, 3, H, W) float32 model input."""
        img = np.asarray(image_bgr)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"image must be (H, W, 3) uint8, got {img.shape} {img.dtype}")
        h, w = self._size
        resized = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        rgb = cv2.cvtColor(resized, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
        x = (rgb - self._mean) / self._std
        return np.ascontiguousarray(x.transpose(2, 0, 1)[None])

    def embed_image(self, image_bgr: np.ndarray) -> np.ndarray:
        """Image -> (D,) float32 unit vector; ``VprBackboneError`` when the forward pass fails."""
        try:
            outputs = self._runtime.run(self._engine, {self._input_name: self.preprocess(image_bgr)})
        except InferenceError as exc:
            raise VprBackboneError(f"forward pass failed: {exc}", backbone=self._label) from exc
        out = np.asarray(outputs.get(self._output_name))
        if out.shape != (1, self._dim) or not np.isfinite(out).all():
            raise VprBackboneError(
                f"output {self._output_name!r} has shape {out.shape} (expected (1, {self._dim})) "
                "or is non-finite",
                backbone=self._label,
            )
        return l2_normalise(out[0].astype(np.float32))


class OnnxGlobalVpr(IndexedVpr):
    """C2 strategy over an ``OnnxGlobalEncoder`` and the cache's HNSW index."""

    @classmethod
    def from_cache(
        cls, tile_store: TileStore, encoder: OnnxGlobalEncoder, *, top1_distance_warn: float
    ) -> OnnxGlobalVpr:
        """Open the index built for ``encoder`` (same label and model sha256, else IndexUnavailableError).

        The query chip size is the one the tiles were described with (``vpr_meta.json``).
        """
        cache_dir = tile_store.cache_dir
        check_cache_backbone(
            tile_store.manifest,
            encoder.label,
            encoder.model_sha256,
            cache_dir=cache_dir,
            required_artifacts=(VPR_INDEX_NAME, VPR_DESCRIPTORS_NAME, VPR_META_NAME),
        )
        meta_path = cache_dir / VPR_META_NAME
        try:
            meta = bounded_json.loads(meta_path.read_bytes(), max_bytes=1 << 20, what="VPR metadata")
            chip_size_px = int(meta["chip_size_px"])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise IndexUnavailableError(f"cannot read VPR metadata: {exc!r}", path=str(meta_path)) from exc
        index = DescriptorIndex.load(
            cache_dir / VPR_INDEX_NAME, expected_dim=encoder.dim, expected_count=len(tile_store)
        )
        normaliser = QueryNormaliser(
            gsd_m_px=tile_store.gsd_m_px, chip_size_px=chip_size_px, backbone=encoder.label
        )
        return cls(encoder, tile_store, index, normaliser, top1_distance_warn=top1_distance_warn)
