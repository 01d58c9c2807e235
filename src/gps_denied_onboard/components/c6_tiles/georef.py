"""Web-Mercator (EPSG:3857) pixel georeference at one zoom level, vectorised.

Global pixel coordinates at zoom ``z`` with ``tile_size`` px tiles: x to the east and y to the south,
``(0, 0)`` at the north-west corner of the world (lon -180, lat +85.0511), ``tile_size * 2**z`` px
across. XYZ tile ``(x, y)`` covers global pixels ``[x*ts, (x+1)*ts) x [y*ts, (y+1)*ts)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

EARTH_RADIUS_WEBMERC_M = 6_378_137.0
_ORIGIN_SHIFT_M = math.pi * EARTH_RADIUS_WEBMERC_M


@dataclass(frozen=True)
class WebMercatorGrid:
    zoom: int
    tile_size_px: int = 256

    @property
    def world_px(self) -> float:
        return float(self.tile_size_px * (1 << self.zoom))

    @property
    def merc_m_per_px(self) -> float:
        """EPSG:3857 metres per pixel (ground metres per pixel = this x cos(lat))."""
        return 2.0 * _ORIGIN_SHIFT_M / self.world_px

    def gsd_m_px(self, lat_deg: float) -> float:
        """Ground sampling distance at a latitude, metres per pixel."""
        return self.merc_m_per_px * math.cos(math.radians(lat_deg))

    def lonlat_to_px(self, lon_deg, lat_deg) -> np.ndarray:  # type: ignore[no-untyped-def]
        """(lon, lat) degrees -> global pixel (x, y), shape (..., 2) float64."""
        lon = np.asarray(lon_deg, dtype=np.float64)
        lat = np.asarray(lat_deg, dtype=np.float64)
        x = (lon + 180.0) / 360.0 * self.world_px
        s = np.sin(np.radians(lat))
        y = (0.5 - np.log((1 + s) / (1 - s)) / (4 * math.pi)) * self.world_px
        return np.stack([x, y], axis=-1)

    def px_to_lonlat(self, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Global pixel (..., 2) -> (lon_deg, lat_deg), each (...)."""
        p = np.asarray(px, dtype=np.float64)
        lon = p[..., 0] / self.world_px * 360.0 - 180.0
        n = math.pi - 2.0 * math.pi * p[..., 1] / self.world_px
        lat = np.degrees(np.arctan(np.sinh(n)))
        return lon, lat

    def merc_to_px(self, x_m, y_m) -> np.ndarray:  # type: ignore[no-untyped-def]
        """EPSG:3857 metres -> global pixel (..., 2)."""
        x = (np.asarray(x_m, dtype=np.float64) + _ORIGIN_SHIFT_M) / self.merc_m_per_px
        y = (_ORIGIN_SHIFT_M - np.asarray(y_m, dtype=np.float64)) / self.merc_m_per_px
        return np.stack([x, y], axis=-1)

    def px_to_merc(self, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = np.asarray(px, dtype=np.float64)
        return p[..., 0] * self.merc_m_per_px - _ORIGIN_SHIFT_M, _ORIGIN_SHIFT_M - p[
            ..., 1
        ] * self.merc_m_per_px

    def tile_center_lonlat(self, x: int, y: int) -> tuple[float, float]:
        lon, lat = self.px_to_lonlat(np.array([(x + 0.5) * self.tile_size_px, (y + 0.5) * self.tile_size_px]))
        return float(lon), float(lat)

    def tile_of_lonlat(self, lon_deg: float, lat_deg: float) -> tuple[int, int]:
        px = self.lonlat_to_px(lon_deg, lat_deg)
        return int(px[0] // self.tile_size_px), int(px[1] // self.tile_size_px)
