"""C2.5 contracts: the N best tiles after re-ranking, with handles to their pixels."""

from __future__ import annotations

import uuid
from dataclasses import dataclass

from gps_denied_onboard.components.c6_tiles.types import TileId, TilePixelsHandle


@dataclass(frozen=True)
class RerankCandidate:
    tile_id: TileId
    #: Page-cache-backed pixels of the chip around the tile (C6); C3 decodes per call, never copies.
    tile_pixels_handle: TilePixelsHandle
    #: Rank score from C2.5 (cheap inlier count; -1 when C2.5 ran in passthrough mode).
    rerank_inliers: int
    #: C2 distance of this tile (see VprCandidate.descriptor_distance).
    vpr_distance: float


@dataclass(frozen=True)
class SearchPrior:
    """Where the estimate puts the camera at the frame's exposure, for a matcher that searches the map
    around it (C3 ``orientation_corr``): the ground point under the camera, and the horizontal 1-sigma
    of the estimate relative to the map (``EstimatorState.map_frame_cov_ne_m2``), m."""

    lat_deg: float
    lon_deg: float
    sigma_m: float


@dataclass(frozen=True)
class RerankResult:
    frame_id: uuid.UUID
    #: Up to N candidates, best first.
    candidates: list[RerankCandidate]
    reranked_at: int  # monotonic_ns
    #: The estimate the search started from (None: no estimate handed on, e.g. a tool matching one pair).
    search: SearchPrior | None = None
