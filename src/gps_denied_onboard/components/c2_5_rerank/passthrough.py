"""``passthrough`` re-rank: keeps C2's order and attaches the tile chips (no inlier counting)."""

from __future__ import annotations

import time

from gps_denied_onboard.camera.types import NavCameraFrame
from gps_denied_onboard.components.c2_5_rerank.types import RerankCandidate, RerankResult
from gps_denied_onboard.components.c2_vpr.types import VprResult
from gps_denied_onboard.components.c6_tiles.store import TileStore


class PassthroughRerank:
    def __init__(self, tile_store: TileStore, *, top_n: int, chip_size_px: int) -> None:
        self._tiles = tile_store
        self._top_n = top_n
        self._chip_size_px = chip_size_px

    def rerank(self, frame: NavCameraFrame, vpr_result: VprResult) -> RerankResult:
        candidates = [
            RerankCandidate(
                tile_id=c.tile_id,
                tile_pixels_handle=self._tiles.chip(c.tile_id, self._chip_size_px),
                rerank_inliers=-1,
                vpr_distance=c.descriptor_distance,
            )
            for c in vpr_result.candidates[: self._top_n]
        ]
        return RerankResult(frame_id=frame.frame_id, candidates=candidates, reranked_at=time.monotonic_ns())
