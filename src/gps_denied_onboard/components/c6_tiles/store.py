"""C6 tile store: opens a checked map cache and serves tiles and page-cache-backed chips.

The mosaic is memory-mapped read-only, so pixels are paged in by the kernel on first touch and shared
with every other consumer.

Checked at open, then on read. ``TileStore.open`` checks the cache at the level it is given
(``Verification``, see ``c10_cache_build.manifest``): full (sha256 of every artifact, the mosaic
included: ``gdnav cache build``, ``gdnav preflight``) or light (the daemon's start: the manifest's own
hash, every artifact's size, the sha256 of the small tables, the mosaic's shape; it never reads the
mosaic, so it costs the same on any map). Either way the map is then read for the whole flight, and
bytes can change under a mapping after any check (flash wear, a failing SD card or eMMC page re-read
after eviction, another process writing the file). ``chip`` therefore copies the cells a chip covers,
checks each copy against the CRC-32 the build recorded for that cell (``c10_cache_build.cell_crc``) and
cuts the chip from the copy: the bytes checked are the bytes the matcher gets. A cell that fails is
corrupt for the rest of the run (never trusted again, even if its bytes come back): its pixels read as
nodata (zero, as off the map), so no fix is ever made from them, and it is logged
(``c6.cache.tile_corrupt``), counted (``corrupt_cells``) and reported to the listener (the daemon records
it in the FDR). CRC-32 detects corruption, not an adversary who can write the cache while the daemon runs
(who could as well change the daemon).

A cache built before the table was recorded still opens: the store computes the table at open from the
mosaic as it then reads (one pass over the whole mosaic, seconds for a large map) and logs a warning
naming the command that adds it (``gdnav cache build`` with the same source and directory adds the table
without rebuilding). Refusing it would ground a fleet's prepared caches on a software update; its open
costs what it cost before, no more, and the operator is told.

Pixel convention (chips and mosaic): OpenCV's, ``(x, y)`` with ``(0, 0)`` at the *centre* of the
top-left pixel, x east, y south. The Web-Mercator grid is corner-based, hence the 0.5 px offsets below.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from gps_denied_onboard.components.c6_tiles.georef import WebMercatorGrid
from gps_denied_onboard.components.c6_tiles.types import TileId, TileStoreError
from gps_denied_onboard.components.c10_cache_build.cell_crc import cell_crc32, cell_crc32_table
from gps_denied_onboard.components.c10_cache_build.manifest import (
    TILES_NAME,
    CacheManifest,
    CacheManifestError,
    Verification,
)
from gps_denied_onboard.constants import LogEvent

_log = structlog.get_logger(__name__)

#: Mean Earth radius, m (same as geo.haversine_m, so distances agree across stages).
_EARTH_MEAN_RADIUS_M = 6_371_008.8


class TileChip:
    """A square window of the mosaic around one tile; implements ``TilePixelsHandle``.

    ``pixels()`` is a read-only (h, w, 3) uint8 BGR array (h = w = size_px unless the mosaic is smaller):
    a verified copy of the mosaic (``TileStore.chip``), or a view of it where a caller built one.
    ``origin_px`` is the global Web-Mercator pixel (x, y) of the top-left corner of chip pixel (0, 0) at
    the store's zoom.
    """

    __slots__ = ("_grid", "_origin_px", "_pixels", "_tile_id")

    def __init__(
        self, tile_id: TileId, grid: WebMercatorGrid, pixels: np.ndarray, origin_px: tuple[int, int]
    ):
        self._tile_id = tile_id
        self._grid = grid
        self._pixels = pixels
        self._origin_px = origin_px

    @property
    def tile_id(self) -> TileId:
        return self._tile_id

    @property
    def origin_px(self) -> tuple[int, int]:
        return self._origin_px

    @property
    def size_px(self) -> tuple[int, int]:
        """(width, height) of the chip in pixels."""
        return int(self._pixels.shape[1]), int(self._pixels.shape[0])

    @property
    def gsd_m_px(self) -> float:
        """Ground sampling distance at the chip centre, metres per pixel."""
        w, h = self.size_px
        _, lat = self.chip_px_to_lonlat(np.array([(w - 1) / 2.0, (h - 1) / 2.0]))
        return self._grid.gsd_m_px(float(lat))

    @property
    def valid_fraction(self) -> float:
        """Fraction of chip pixels that are map data (nodata is an all-zero pixel). Reads the pixels."""
        return float(np.count_nonzero(self._pixels.any(axis=-1))) / max(
            1, self._pixels.shape[0] * self._pixels.shape[1]
        )

    def pixels(self) -> np.ndarray:
        """Read-only (h, w, 3) uint8 BGR pixels of the chip."""
        return self._pixels

    def chip_px_to_lonlat(self, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Chip pixel (..., 2) float (x, y) -> (lon_deg, lat_deg), each of shape (...)."""
        p = np.asarray(px, dtype=np.float64)
        return self._grid.px_to_lonlat(p + (np.asarray(self._origin_px, dtype=np.float64) + 0.5))

    def lonlat_to_chip_px(self, lon_deg: np.ndarray, lat_deg: np.ndarray) -> np.ndarray:
        """(lon_deg, lat_deg) of shape (...) -> chip pixel (..., 2) float64 (x, y)."""
        return self._grid.lonlat_to_px(lon_deg, lat_deg) - (
            np.asarray(self._origin_px, dtype=np.float64) + 0.5
        )


@dataclass(frozen=True, eq=False)
class TileCentreIndex:
    """Vectorised radius search over tile centres.

    ``tile_ids`` has N entries; ``lat_rad`` / ``lon_rad`` / ``cos_lat`` are float64 (N,) arrays of the
    centres. Ties in distance are broken by position in ``tile_ids`` (deterministic).
    """

    tile_ids: tuple[TileId, ...]
    lat_rad: np.ndarray
    lon_rad: np.ndarray
    cos_lat: np.ndarray

    @classmethod
    def from_tile_ids(cls, tile_ids: tuple[TileId, ...]) -> TileCentreIndex:
        lat = np.radians(np.fromiter((t.lat_deg for t in tile_ids), dtype=np.float64, count=len(tile_ids)))
        lon = np.radians(np.fromiter((t.lon_deg for t in tile_ids), dtype=np.float64, count=len(tile_ids)))
        return cls(tile_ids=tile_ids, lat_rad=lat, lon_rad=lon, cos_lat=np.cos(lat))

    def near(
        self, lat_deg: float, lon_deg: float, radius_m: float, k: int | None = None
    ) -> list[tuple[TileId, float]]:
        """Tiles whose centre is within ``radius_m`` ground metres, nearest first, at most ``k``."""
        if not (math.isfinite(radius_m) and radius_m >= 0.0):
            raise ValueError(f"radius_m must be a finite number >= 0, got {radius_m}")
        if k is not None and k < 1:
            raise ValueError(f"k must be >= 1 or None, got {k}")
        lat0, lon0 = math.radians(lat_deg), math.radians(lon_deg)
        # Latitude difference alone bounds the great-circle distance: a cheap prefilter.
        candidates = np.flatnonzero(np.abs(self.lat_rad - lat0) <= radius_m / _EARTH_MEAN_RADIUS_M + 1e-12)
        if candidates.size == 0:
            return []
        dlat = self.lat_rad[candidates] - lat0
        dlon = self.lon_rad[candidates] - lon0
        a = np.sin(dlat / 2.0) ** 2 + math.cos(lat0) * self.cos_lat[candidates] * np.sin(dlon / 2.0) ** 2
        dist = 2.0 * _EARTH_MEAN_RADIUS_M * np.arcsin(np.sqrt(np.clip(a, 0.0, 1.0)))
        inside = dist <= radius_m
        candidates, dist = candidates[inside], dist[inside]
        order = np.lexsort((candidates, dist))
        if k is not None:
            order = order[:k]
        picked, picked_dist = candidates[order].tolist(), dist[order].tolist()
        return [(self.tile_ids[i], float(d)) for i, d in zip(picked, picked_dist, strict=True)]


class TileStore:
    """Read-only view of a checked map cache (see ``c10_cache_build.manifest`` for the layout).

    Build with ``TileStore.open``; the daemon does so once at start-up and refuses to fly on a cache
    that fails its check (D-C10-3).
    """

    def __init__(
        self,
        cache_dir: Path,
        manifest: CacheManifest,
        mosaic: np.ndarray,
        tile_ids: tuple[TileId, ...],
        tile_xy: np.ndarray,
        cell_crc: np.ndarray,
        verification: Verification = Verification.FULL,
    ) -> None:
        """Prefer ``TileStore.open``. ``tile_xy`` is int64 (N, 2) XYZ (x, y) of ``tile_ids``; ``cell_crc``
        uint32 (rows, cols) the CRC-32 of every grid cell of ``mosaic``; ``verification`` the level the
        cache was checked at (the fields and tile features of this cache are opened at the same)."""
        self._cache_dir = cache_dir
        self._manifest = manifest
        self._grid = WebMercatorGrid(manifest.zoom, manifest.tile_size_px)
        self._mosaic = mosaic
        self._tile_ids = tile_ids
        self._tile_xy = tile_xy
        self._index_of = {tile_id: i for i, tile_id in enumerate(tile_ids)}
        self._centres = TileCentreIndex.from_tile_ids(tile_ids)
        tr = manifest.tile_range
        #: Global px of the mosaic's top-left corner.
        self._mosaic_origin_px = (tr.x0 * manifest.tile_size_px, tr.y0 * manifest.tile_size_px)
        #: CRC-32 of every grid cell, (rows, cols) uint32 (see the module docstring).
        self._cell_crc = cell_crc
        self._verification = verification
        self._corrupt: set[tuple[int, int]] = set()
        self._corrupt_lock = threading.Lock()
        #: Called once per newly corrupt cell with its description (the daemon records it in the FDR).
        self.on_corrupt: Callable[[dict[str, Any]], None] | None = None

    @classmethod
    def open(cls, cache_dir: Path, verification: Verification = Verification.FULL) -> TileStore:
        """Open and check a cache directory at ``verification``; raise TileStoreError naming what is wrong.

        Checks the format version and the manifest's own hash, that every artifact exists with its
        recorded size and the sha256 ``verification`` asks for (``CacheManifest.verify_artifacts``), that
        the mosaic has the recorded shape, the cell CRC table the mosaic's grid, and that the tile list
        agrees. A cache without a cell CRC table (built before it was recorded) has it computed here, with
        a warning (module docstring).
        """
        cache_dir = Path(cache_dir)
        verification = Verification(verification)
        t0 = time.monotonic()
        try:
            try:
                manifest = CacheManifest.load(cache_dir)
                manifest.verify_artifacts(cache_dir, verification)
            except CacheManifestError as exc:
                raise TileStoreError(exc.message, path=exc.path) from exc
            mosaic = _open_mosaic(cache_dir / manifest.mosaic_name, manifest)
            tile_ids, tile_xy = _load_tiles(cache_dir / TILES_NAME, manifest)
            if manifest.has_cell_crc:
                cell_crc = _load_cell_crc(cache_dir / manifest.cell_crc_name, manifest)
        except TileStoreError as exc:
            _log.error(LogEvent.CACHE_REFUSED, cache_dir=str(cache_dir), reason=str(exc))
            raise
        if not manifest.has_cell_crc:
            t_crc = time.monotonic()
            cell_crc = cell_crc32_table(mosaic, manifest.tile_size_px)
            _log.warning(
                LogEvent.CACHE_OLD_FORMAT,
                cache_dir=str(cache_dir),
                built_utc=manifest.created_utc,
                missing=manifest.cell_crc_name,
                manifest_hashed=manifest.content_sha256 is not None,
                crc_seconds=round(time.monotonic() - t_crc, 3),
                action="the cell CRC table was computed at open, reading the whole mosaic; add it with "
                f"`gdnav cache build --source <the same source> --out {cache_dir}`",
            )
        store = cls(cache_dir, manifest, mosaic, tile_ids, tile_xy, cell_crc, verification)
        _log.info(
            LogEvent.CACHE_OPENED,
            cache_dir=str(cache_dir),
            zoom=manifest.zoom,
            tile_count=len(tile_ids),
            mosaic_shape=list(manifest.mosaic_shape),
            verification=verification.value,
            cell_crc="recorded" if manifest.has_cell_crc else "computed at open",
            seconds=round(time.monotonic() - t0, 3),
        )
        return store

    # --- description -------------------------------------------------------------------------------
    @property
    def cache_dir(self) -> Path:
        return self._cache_dir

    @property
    def manifest(self) -> CacheManifest:
        return self._manifest

    @property
    def verification(self) -> Verification:
        """The level the cache was checked at when opened (its fields and tile features are opened at
        the same)."""
        return self._verification

    @property
    def grid(self) -> WebMercatorGrid:
        return self._grid

    @property
    def zoom(self) -> int:
        return self._manifest.zoom

    @property
    def tile_size_px(self) -> int:
        return self._manifest.tile_size_px

    @property
    def tile_ids(self) -> tuple[TileId, ...]:
        """Valid tiles, sorted by XYZ (y, x)."""
        return self._tile_ids

    @property
    def bbox_lonlat(self) -> tuple[float, float, float, float]:
        """Mapped area (west, south, east, north), degrees."""
        return self._manifest.bbox_lonlat

    @property
    def center_lonlat(self) -> tuple[float, float]:
        """(lon_deg, lat_deg) of the centre of ``bbox_lonlat``."""
        w, s, e, n = self._manifest.bbox_lonlat
        return (w + e) / 2.0, (s + n) / 2.0

    @property
    def gsd_m_px(self) -> float:
        """Ground sampling distance of the mosaic at the map centre, metres per pixel."""
        return self._grid.gsd_m_px(self.center_lonlat[1])

    @property
    def mosaic(self) -> np.ndarray:
        """Read-only memory-mapped (H, W, 3) uint8 BGR mosaic; all-zero pixels are nodata."""
        return self._mosaic

    def __len__(self) -> int:
        return len(self._tile_ids)

    def all_tiles(self) -> tuple[TileId, ...]:
        """Every valid tile (same as ``tile_ids``)."""
        return self._tile_ids

    def tile_xyz(self, tile_id: TileId) -> tuple[int, int, int]:
        """XYZ (x, y, zoom) of a tile of this cache."""
        x, y = self._tile_xy[self._index(tile_id)]
        return int(x), int(y), self.zoom

    # --- queries -----------------------------------------------------------------------------------
    def tiles_near(
        self, lat_deg: float, lon_deg: float, radius_m: float, k: int | None = None
    ) -> list[tuple[TileId, float]]:
        """Valid tiles whose centre is within ``radius_m`` ground metres, ``(tile_id, distance_m)``
        nearest first (ties by tile order), at most ``k``."""
        return self._centres.near(lat_deg, lon_deg, radius_m, k)

    @property
    def corrupt_cells(self) -> int:
        """Grid cells found corrupt on read so far (masked as nodata for the rest of the run)."""
        with self._corrupt_lock:
            return len(self._corrupt)

    def chip(self, tile_id: TileId, size_px: int) -> TileChip:
        """A ``size_px`` square chip centred on the tile, shifted to stay inside the mosaic.

        In a dimension where the mosaic is smaller than ``size_px`` the chip spans the whole mosaic. The
        pixels are a verified copy: a cell whose bytes no longer match its digest is nodata (zero).
        """
        if size_px < 1:
            raise ValueError(f"size_px must be >= 1, got {size_px}")
        x, y = self._tile_xy[self._index(tile_id)]
        ts = self.tile_size_px
        centre_col = (int(x) - self._manifest.tile_range.x0) * ts + ts // 2
        centre_row = (int(y) - self._manifest.tile_range.y0) * ts + ts // 2
        return self._chip_centred_on(tile_id, centre_col, centre_row, size_px)

    def chip_around(self, lat_deg: float, lon_deg: float, size_px: int) -> TileChip | None:
        """A ``size_px`` square chip centred on the ground point (``lat_deg``, ``lon_deg``), shifted to stay
        inside the mosaic like ``chip``; its ``tile_id`` is the valid tile whose centre is nearest the
        point. None when the point is off the mosaic (or the cache has no tile).

        The chip a tile gives is centred on the tile, up to half a tile from where the camera looks; cut
        around the ground under the camera it holds more of the frame's footprint (measured across dates
        in ``docs/benchmarks.md``, "Chips around the footprint")."""
        if size_px < 1:
            raise ValueError(f"size_px must be >= 1, got {size_px}")
        x, y = (float(v) for v in self.lonlat_to_mosaic_px(np.array(lon_deg), np.array(lat_deg)))
        height, width = self._mosaic.shape[:2]
        if not (0.0 <= x < width and 0.0 <= y < height):
            return None
        # The point is on the mosaic, so every tile centre is within its diagonal (twice: Mercator scale).
        nearest = self.tiles_near(lat_deg, lon_deg, 2.0 * math.hypot(width, height) * self.gsd_m_px, k=1)
        if not nearest:
            return None
        # The pixel whose top-left corner is nearest the point is the chip's centre, as ``chip`` takes a
        # tile's; 0.01 px of slack, so that a tile's centre read back from its id (lat/lon to 1e-7 deg, a
        # few thousandths of a pixel) gives the tile's own chip.
        return self._chip_centred_on(nearest[0][0], math.floor(x + 0.51), math.floor(y + 0.51), size_px)

    def _chip_centred_on(self, tile_id: TileId, centre_col: int, centre_row: int, size_px: int) -> TileChip:
        """The ``size_px`` chip centred on mosaic pixel (``centre_col``, ``centre_row``), shifted to stay
        inside the mosaic (spanning it where it is smaller), labelled ``tile_id``."""
        height, width = self._mosaic.shape[:2]
        col0, chip_w = _clamp_span(centre_col - size_px // 2, size_px, width)
        row0, chip_h = _clamp_span(centre_row - size_px // 2, size_px, height)
        pixels = self._verified(row0, col0, chip_h, chip_w)
        origin = (self._mosaic_origin_px[0] + col0, self._mosaic_origin_px[1] + row0)
        return TileChip(tile_id, self._grid, pixels, origin)

    def _verified(self, row0: int, col0: int, h: int, w: int) -> np.ndarray:
        """A read-only copy of mosaic[row0:row0+h, col0:col0+w], every cell it touches checked against its
        digest in the copy itself (corrupt cells zeroed)."""
        ts = self.tile_size_px
        r_lo, r_hi = row0 // ts, (row0 + h - 1) // ts
        c_lo, c_hi = col0 // ts, (col0 + w - 1) // ts
        block = np.array(self._mosaic[r_lo * ts : (r_hi + 1) * ts, c_lo * ts : (c_hi + 1) * ts])
        for r in range(r_lo, r_hi + 1):
            for c in range(c_lo, c_hi + 1):
                cell = block[(r - r_lo) * ts : (r - r_lo + 1) * ts, (c - c_lo) * ts : (c - c_lo + 1) * ts]
                with self._corrupt_lock:
                    known_bad = (r, c) in self._corrupt
                if known_bad:
                    cell[...] = 0
                    continue
                crc = cell_crc32(cell)
                if crc != int(self._cell_crc[r, c]):
                    self._report_corrupt(r, c, crc)
                    cell[...] = 0
        top, left = row0 - r_lo * ts, col0 - c_lo * ts
        out = block[top : top + h, left : left + w]
        out.flags.writeable = False
        return out

    def _report_corrupt(self, row: int, col: int, crc_read: int) -> None:
        with self._corrupt_lock:
            if (row, col) in self._corrupt:
                return
            self._corrupt.add((row, col))
            total = len(self._corrupt)
        tr = self._manifest.tile_range
        ts = self.tile_size_px
        centre = np.array([(col + 0.5) * ts - 0.5, (row + 0.5) * ts - 0.5])
        lon, lat = self.mosaic_px_to_lonlat(centre)
        info: dict[str, Any] = {
            "x": tr.x0 + col,
            "y": tr.y0 + row,
            "zoom": self.zoom,
            "lat_deg": round(float(lat), 7),
            "lon_deg": round(float(lon), 7),
            "crc32_verified": int(self._cell_crc[row, col]),
            "crc32_read": int(crc_read),
            "corrupt_cells": total,
            "mosaic": str(self._cache_dir / self._manifest.mosaic_name),
        }
        _log.error(LogEvent.CACHE_TILE_CORRUPT, action="masked as nodata for the rest of the run", **info)
        listener = self.on_corrupt
        if listener is not None:
            listener(info)

    def lonlat_to_mosaic_px(self, lon_deg: np.ndarray, lat_deg: np.ndarray) -> np.ndarray:
        """(lon_deg, lat_deg) of shape (...) -> mosaic pixel (..., 2) float64 (x, y), OpenCV convention."""
        return self._grid.lonlat_to_px(lon_deg, lat_deg) - (
            np.asarray(self._mosaic_origin_px, np.float64) + 0.5
        )

    def mosaic_px_to_lonlat(self, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mosaic pixel (..., 2) float (x, y) -> (lon_deg, lat_deg), each of shape (...)."""
        p = np.asarray(px, dtype=np.float64)
        return self._grid.px_to_lonlat(p + (np.asarray(self._mosaic_origin_px, np.float64) + 0.5))

    def _index(self, tile_id: TileId) -> int:
        try:
            return self._index_of[tile_id]
        except KeyError as exc:
            raise TileStoreError(
                f"tile {tuple(tile_id)} is not a valid tile of this cache (zoom {self.zoom})",
                path=str(self._cache_dir),
            ) from exc


def _clamp_span(start: int, size: int, extent: int) -> tuple[int, int]:
    """(start, length) of a window of ``size`` moved to lie inside ``[0, extent)``."""
    if size >= extent:
        return 0, extent
    return min(max(start, 0), extent - size), size


def _open_mosaic(path: Path, manifest: CacheManifest) -> np.ndarray:
    try:
        mosaic = np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise TileStoreError(f"cannot memory-map mosaic {path.name!r}: {exc}", path=str(path)) from exc
    if mosaic.dtype != np.uint8 or tuple(mosaic.shape) != tuple(manifest.mosaic_shape):
        raise TileStoreError(
            f"mosaic {path.name!r} is {mosaic.dtype} {mosaic.shape}, manifest records uint8 "
            f"{tuple(manifest.mosaic_shape)}",
            path=str(path),
        )
    return mosaic


def _load_cell_crc(path: Path, manifest: CacheManifest) -> np.ndarray:
    try:
        table = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise TileStoreError(f"cannot read the cell CRC table {path.name!r}: {exc}", path=str(path)) from exc
    ts = manifest.tile_size_px
    cells = (-(-manifest.mosaic_shape[0] // ts), -(-manifest.mosaic_shape[1] // ts))
    if table.dtype != np.uint32 or table.shape != cells:
        raise TileStoreError(
            f"cell CRC table {path.name!r} is {table.dtype} {table.shape}, expected uint32 {cells} "
            "(the mosaic's grid of cells)",
            path=str(path),
        )
    return table


def _load_tiles(path: Path, manifest: CacheManifest) -> tuple[tuple[TileId, ...], np.ndarray]:
    try:
        payload = json.loads(path.read_text(encoding="utf-8"))
        entries = payload["tiles"]
        xy = np.array([(int(t["x"]), int(t["y"])) for t in entries], dtype=np.int64).reshape(-1, 2)
        tile_ids = tuple(TileId.of(manifest.zoom, t["lat_deg"], t["lon_deg"]) for t in entries)
    except (OSError, ValueError, KeyError, TypeError, AttributeError, OverflowError, RecursionError) as exc:
        raise TileStoreError(f"malformed tile list {path.name!r}: {exc!r}"[:500], path=str(path)) from exc
    tr = manifest.tile_range
    in_range = (xy[:, 0] >= tr.x0) & (xy[:, 0] <= tr.x1) & (xy[:, 1] >= tr.y0) & (xy[:, 1] <= tr.y1)
    if len(tile_ids) != manifest.tile_count or not bool(np.all(in_range)):
        raise TileStoreError(
            f"tile list {path.name!r} disagrees with the manifest ({len(tile_ids)} tiles, "
            f"manifest records {manifest.tile_count} in range {vars(tr)})",
            path=str(path),
        )
    return tile_ids, xy
