"""C2 strategy interface (seed), with the search region that makes retrieval prior-gated."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from gps_denied_onboard.camera.types import CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c2_vpr.types import VprQuery, VprResult


@dataclass(frozen=True)
class SearchRegion:
    """Tiles whose centres lie within ``radius_m`` ground metres of the centre (nominal flight).
    ``None`` instead of a region means corpus-wide search (F6 re-localisation)."""

    center_lat_deg: float
    center_lon_deg: float
    radius_m: float


@runtime_checkable
class VprStrategy(Protocol):
    def embed_query(self, frame: NavCameraFrame, calibration: CameraCalibration) -> VprQuery: ...

    def retrieve_topk(self, query: VprQuery, k: int, *, region: SearchRegion | None = None) -> VprResult: ...

    def descriptor_dim(self) -> int: ...
