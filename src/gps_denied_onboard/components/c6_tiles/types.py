"""C6 contracts: tile identity and page-cache-backed tile pixels."""

from __future__ import annotations

from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np


class TileId(NamedTuple):
    """Composite tile id ``(zoom, lat, lon)`` (seed): zoom level and the tile centre in degrees,
    rounded to 7 decimals (~1 cm) so that ids compare equal across processes."""

    zoom: int
    lat_deg: float
    lon_deg: float

    @classmethod
    def of(cls, zoom: int, lat_deg: float, lon_deg: float) -> TileId:
        return cls(int(zoom), round(float(lat_deg), 7), round(float(lon_deg), 7))


@runtime_checkable
class TilePixelsHandle(Protocol):
    """A reference to a georeferenced map chip around one tile, backed by the page cache.

    ``pixels()`` returns read-only (H, W, 3) uint8 BGR pixels of the map mosaic around the tile (the
    tile store hands out a copy verified against the cache's digests); ``chip_px_to_lonlat`` maps chip
    pixel coordinates (N, 2) float (x, y) to (lon_deg, lat_deg) arrays of shape (N,); ``gsd_m_px`` is the
    chip's ground sampling distance.
    """

    @property
    def tile_id(self) -> TileId: ...

    @property
    def gsd_m_px(self) -> float: ...

    def pixels(self) -> np.ndarray: ...

    def chip_px_to_lonlat(self, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

    def lonlat_to_chip_px(self, lon_deg: np.ndarray, lat_deg: np.ndarray) -> np.ndarray: ...


class TileStoreError(RuntimeError):
    """The tile cache cannot be opened or used (missing, tampered, truncated, wrong format)."""

    def __init__(self, message: str, *, path: str | None = None) -> None:
        super().__init__(f"{message} ({path})" if path else message)
        self.path = path
