"""Appearance retrieval shared by every global-descriptor strategy (``vlad``, ONNX backbones).

A strategy is an *encoder* (normalised image -> (D,) unit vector; the same function describes map chips
at cache time and queries in flight) plus this retrieval: query normalisation (``query_norm``), the
C6 HNSW index, prior-gated or corpus-wide top-k, and the seed's logging table:

| level | event                                     | when                                        |
|-------|-------------------------------------------|---------------------------------------------|
| ERROR | ``c2.vpr.error``                          | ``VprBackboneError`` / ``IndexUnavailableError`` |
| WARN  | ``c2.vpr.top1_distance_above_threshold``  | top-1 distance > ``top1_distance_warn``     |
| INFO  | ``c2.vpr.ready``                          | strategy built (backbone, dim, corpus_size) |
| DEBUG | ``c2.vpr.topk``                           | every retrieval: the top-k distances        |

Distances are L2 between unit vectors, in [0, 2] (``d^2 = 2 - 2 cos``).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import Final, Protocol, runtime_checkable

import numpy as np
import structlog

from gps_denied_onboard.camera.types import CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c2_vpr.protocol import SearchRegion
from gps_denied_onboard.components.c2_vpr.query_norm import QueryNormaliser
from gps_denied_onboard.components.c2_vpr.types import (
    IndexUnavailableError,
    VprBackboneError,
    VprCandidate,
    VprQuery,
    VprResult,
)
from gps_denied_onboard.components.c6_tiles.descriptor_index import DescriptorIndex
from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.components.c10_cache_build.manifest import CacheManifest
from gps_denied_onboard.constants import LogEvent

_log = structlog.get_logger(__name__)

#: Cache artifacts common to every global-descriptor backbone.
VPR_INDEX_NAME: Final[str] = "vpr_index.faiss"
#: (N, D) float32 tile descriptors, row i = tile i (kept so the index can be rebuilt/re-tuned offline).
VPR_DESCRIPTORS_NAME: Final[str] = "vpr_descriptors.npy"
#: JSON: backbone, model sha256, dim, chip size, parameters, tile count (written by C10).
VPR_META_NAME: Final[str] = "vpr_meta.json"


@runtime_checkable
class GlobalEncoder(Protocol):
    """Image -> global descriptor. ``embed_image``: (H, W, 3) uint8 BGR (0 = invalid) -> (D,) float32,
    unit L2 norm. ``label`` is recorded in the manifest; ``model_sha256`` is the sha256 of the weights
    (ONNX file) or learned state (VLAD vocabulary), None when the encoder has none on disk."""

    @property
    def label(self) -> str: ...

    @property
    def dim(self) -> int: ...

    @property
    def model_sha256(self) -> str | None: ...

    def embed_image(self, image_bgr: np.ndarray) -> np.ndarray: ...


def check_cache_backbone(
    manifest: CacheManifest,
    label: str,
    model_sha256: str | None,
    *,
    cache_dir: Path,
    required_artifacts: Sequence[str] = (VPR_INDEX_NAME, VPR_DESCRIPTORS_NAME),
) -> None:
    """Refuse a cache whose descriptors were made by another backbone (label or model hash differ).

    ``model_sha256`` None skips the hash comparison (the VLAD vocabulary lives in the cache itself and
    is covered by the artifact hash gate). Raises ``IndexUnavailableError``.
    """
    recorded = manifest.vpr
    if recorded.backbone != label:
        raise IndexUnavailableError(
            f"cache descriptors were built with backbone {recorded.backbone!r}, this strategy is {label!r}; "
            f"rebuild the VPR index (gdnav cache vpr) with {label!r}",
            path=str(cache_dir),
        )
    if model_sha256 is not None and recorded.model_sha256 != model_sha256:
        raise IndexUnavailableError(
            f"cache descriptors were built with another {label!r} model (sha256 "
            f"{str(recorded.model_sha256)[:16]}..., loaded model {model_sha256[:16]}...)",
            path=str(cache_dir),
        )
    missing = [name for name in required_artifacts if name not in manifest.artifacts]
    if missing:
        raise IndexUnavailableError(f"manifest does not list VPR artifacts {missing}", path=str(cache_dir))


class IndexedVpr:
    """``VprStrategy`` over a ``GlobalEncoder`` and a C6 ``DescriptorIndex`` (see module docstring).

    ``top1_distance_warn``: WARN when the best candidate is farther than this (false-positive risk).
    Bind one instance to one pipeline thread (seed, race conditions).
    """

    def __init__(
        self,
        encoder: GlobalEncoder,
        tile_store: TileStore,
        index: DescriptorIndex,
        normaliser: QueryNormaliser,
        *,
        top1_distance_warn: float,
    ) -> None:
        if index.dim != encoder.dim:
            raise IndexUnavailableError(
                f"descriptor index has dimension {index.dim}, "
                f"backbone {encoder.label!r} produces {encoder.dim}",
                path=index.path,
            )
        if index.ntotal != len(tile_store):
            raise IndexUnavailableError(
                f"descriptor index holds {index.ntotal} vectors, the cache has {len(tile_store)} tiles",
                path=index.path,
            )
        if not top1_distance_warn > 0:
            raise ValueError(f"top1_distance_warn must be > 0, got {top1_distance_warn!r}")
        self._encoder = encoder
        self._tiles = tile_store
        self._index = index
        self._normaliser = normaliser
        self._warn = float(top1_distance_warn)
        self._position_of = {tile_id: i for i, tile_id in enumerate(tile_store.tile_ids)}
        _log.info(
            LogEvent.VPR_READY,
            backbone=encoder.label,
            dim=encoder.dim,
            corpus_size=index.ntotal,
            index_mmapped=index.mmapped,
            ef_search=index.ef_search,
        )

    @property
    def label(self) -> str:
        return self._encoder.label

    @property
    def encoder(self) -> GlobalEncoder:
        return self._encoder

    @property
    def normaliser(self) -> QueryNormaliser:
        """The query normaliser (share it with C2.5 so each frame is warped once)."""
        return self._normaliser

    def descriptor_dim(self) -> int:
        return self._encoder.dim

    def embed_query(self, frame: NavCameraFrame, calibration: CameraCalibration) -> VprQuery:
        """Normalise the frame to the map frame and describe it; ``VprBackboneError`` on failure
        (including a frame without attitude/altitude: no north-up query without heading)."""
        try:
            normalised = self._normaliser.normalise(frame, calibration)
            embedding = self._encoder.embed_image(normalised.image)
            if embedding.shape != (self._encoder.dim,) or not np.isfinite(embedding).all():
                raise VprBackboneError(
                    f"backbone returned shape {embedding.shape} "
                    f"(expected ({self._encoder.dim},)) or non-finite values",
                    backbone=self.label,
                    frame_id=frame.frame_id,
                )
        except VprBackboneError as exc:
            _log.error(LogEvent.VPR_ERROR, backbone=self.label, frame=str(frame.frame_id), error=str(exc))
            raise
        return VprQuery(frame.frame_id, embedding.astype(np.float32, copy=False), time.monotonic_ns())

    def retrieve_topk(self, query: VprQuery, k: int, *, region: SearchRegion | None = None) -> VprResult:
        """Top-k tiles by descriptor distance: within ``region`` (prior-gated) or corpus-wide (None).

        Raises ``IndexUnavailableError`` when the query does not fit the index (wrong dimension).
        """
        if k < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        emb = np.asarray(query.embedding, dtype=np.float32)
        if emb.shape != (self._index.dim,):
            exc = IndexUnavailableError(
                f"query embedding has shape {emb.shape}, index dimension is {self._index.dim}",
                path=self._index.path,
            )
            _log.error(LogEvent.VPR_ERROR, backbone=self.label, frame=str(query.frame_id), error=str(exc))
            raise exc
        allowed: np.ndarray | None = None
        if region is not None:
            near = self._tiles.tiles_near(region.center_lat_deg, region.center_lon_deg, region.radius_m)
            allowed = np.fromiter((self._position_of[t] for t, _ in near), dtype=np.int64, count=len(near))
        hits = self._index.search(emb, k, allowed=allowed)
        tile_ids = self._tiles.tile_ids
        dim = self._encoder.dim
        candidates = [
            VprCandidate(tile_ids[int(pos)], float(dist), dim)
            for pos, dist in zip(hits.positions.tolist(), hits.distances.tolist(), strict=True)
        ]
        distances = [round(c.descriptor_distance, 4) for c in candidates]
        _log.debug(
            LogEvent.VPR_TOPK,
            backbone=self.label,
            frame=str(query.frame_id),
            gated=region is not None,
            eligible=None if allowed is None else int(allowed.size),
            topk_distances=distances,
        )
        if candidates and candidates[0].descriptor_distance > self._warn:
            _log.warning(
                LogEvent.VPR_FAR_TOP1,
                backbone=self.label,
                frame=str(query.frame_id),
                top1_distance=distances[0],
                threshold=self._warn,
            )
        return VprResult(query.frame_id, candidates, time.monotonic_ns(), self.label)
