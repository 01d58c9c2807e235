"""``geo_prior``: ranks cached tiles by ground distance from the estimator's prior.

It has no appearance descriptor (dimension 0), so it can only search a region; corpus-wide search
raises ``IndexUnavailableError``. It is the weights-free retrieval used while the prior is good, and
the baseline that appearance-based strategies are measured against.
"""

from __future__ import annotations

import time

import numpy as np

from gps_denied_onboard.camera.types import CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c2_vpr.protocol import SearchRegion
from gps_denied_onboard.components.c2_vpr.types import (
    IndexUnavailableError,
    VprCandidate,
    VprQuery,
    VprResult,
)
from gps_denied_onboard.components.c6_tiles.store import TileStore

LABEL = "geo_prior"


class GeoPriorVpr:
    def __init__(self, tile_store: TileStore) -> None:
        self._tiles = tile_store

    def descriptor_dim(self) -> int:
        return 0

    def embed_query(self, frame: NavCameraFrame, calibration: CameraCalibration) -> VprQuery:
        return VprQuery(frame.frame_id, np.zeros((0,), dtype=np.float32), time.monotonic_ns())

    def retrieve_topk(self, query: VprQuery, k: int, *, region: SearchRegion | None = None) -> VprResult:
        if region is None:
            raise IndexUnavailableError(
                "geo_prior has no appearance index; corpus-wide search needs an appearance VPR strategy"
            )
        near = self._tiles.tiles_near(region.center_lat_deg, region.center_lon_deg, region.radius_m, k)
        return VprResult(
            frame_id=query.frame_id,
            candidates=[VprCandidate(tile_id, float(dist_m), 0) for tile_id, dist_m in near],
            retrieved_at=time.monotonic_ns(),
            backbone_label=LABEL,
        )
