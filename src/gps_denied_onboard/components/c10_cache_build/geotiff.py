"""C10: build a map cache from a georeferenced GeoTIFF (F1 pre-flight).

The source may be in any CRS rasterio reads. It is reprojected block by block (a few Mpx at a time,
so memory stays bounded for large orthophotos) into one Web-Mercator mosaic at zoom Z covering an
integer range of XYZ tiles, written as a memory-mappable ``.npy`` (see ``manifest`` for the layout).
Validity comes from the source's GDAL mask (nodata value, alpha band or internal mask) and is warped as
an alpha band, so bilinear resampling never blends nodata into the image. In the mosaic, nodata is an
all-zero pixel.

The per-tile work (read, warp, valid fractions) runs in shards on an engine (``shards``: in this process
by default, or on a Dask cluster), and an interrupted build resumes where it stopped.
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
import structlog
from rasterio.enums import ColorInterp, Resampling
from rasterio.errors import RasterioError
from rasterio.transform import Affine
from rasterio.warp import reproject, transform, transform_bounds
from rasterio.windows import Window, from_bounds

from gps_denied_onboard.components.c6_tiles.georef import WebMercatorGrid
from gps_denied_onboard.components.c6_tiles.types import TileId
from gps_denied_onboard.components.c10_cache_build.cell_crc import cell_crc32_table, write_cell_crc_table
from gps_denied_onboard.components.c10_cache_build.manifest import (
    CACHE_FORMAT_VERSION,
    MANIFEST_NAME,
    TILE_VALID_FRACTION_NAME,
    TILES_NAME,
    ArtifactInfo,
    CacheBuildError,
    CacheManifest,
    CacheManifestError,
    SourceInfo,
    TileRange,
    Verification,
    VprInfo,
    cell_crc_name,
    mosaic_name,
    sha256_file,
    write_json_atomic,
)
from gps_denied_onboard.components.c10_cache_build.shards import (
    EngineSpec,
    Shard,
    ShardEngine,
    ShardJournal,
    ShardOutput,
    discard_journal,
    engine_scope,
    run_shards,
    shards_of,
)
from gps_denied_onboard.constants import LogEvent
from gps_denied_onboard.geo import haversine_m

_log = structlog.get_logger(__name__)

MIN_ZOOM = 1
MAX_ZOOM = 22
#: Web-Mercator latitude limit, degrees.
_MAX_LAT_DEG = 85.05112878
#: Auto zoom never picks a mosaic coarser than the source by more than this factor.
_MAX_COARSENING = 1.05
#: Target pixels per reprojection block: bounds the working memory (~4 Mpx x 4 bands x 2).
_BLOCK_TARGET_PX = 4 << 20
#: Warped alpha at or above this is a valid pixel (half of the bilinear support is valid source).
_ALPHA_VALID_MIN = 128
_RESAMPLING = Resampling.bilinear
_MERC_CRS = "EPSG:3857"
_WGS84_CRS = "EPSG:4326"


@dataclass(frozen=True)
class _Plan:
    """What to build: zoom, tile range, mapped area and the source's ground GSD."""

    zoom: int
    tile_range: TileRange
    bbox_lonlat: tuple[float, float, float, float]
    source_gsd_m_px: float


def build_cache_from_geotiff(
    source: Path,
    out_dir: Path,
    *,
    zoom: int | None = None,
    bbox_lonlat: tuple[float, float, float, float] | None = None,
    tile_size_px: int = 256,
    progress: bool = True,
    min_tile_valid_fraction: float = 0.5,
    engine: EngineSpec | ShardEngine | None = None,
) -> CacheManifest:
    """Build (or confirm up to date) a tile cache in ``out_dir`` from the GeoTIFF ``source``.

    ``zoom`` None picks the zoom whose ground GSD at the map centre is closest to the source's (never
    coarser than 1.5x it). ``bbox_lonlat`` ``(west, south, east, north)`` degrees restricts the area;
    it is intersected with the source footprint. Tiles with less than ``min_tile_valid_fraction`` valid
    pixels are map gaps and are not listed. When ``out_dir`` already holds a complete cache of the same
    source (sha256), zoom, area and tile size, nothing is rebuilt and its manifest is returned.
    ``engine`` says where the shards run (a ``shards.EngineSpec``, an engine already open, or None: in
    this process); the cache is the same bytes whatever it says. An interrupted build into the same
    ``out_dir`` resumes.

    Raises CacheBuildError for a missing/unreadable source, bad parameters, no overlap, or an empty result.
    """
    t_start = time.monotonic()
    source = Path(source)
    out_dir = Path(out_dir)
    check_build_params(zoom, bbox_lonlat, tile_size_px, min_tile_valid_fraction)
    with open_source(source) as dataset:
        plan = _plan(dataset, zoom, bbox_lonlat, tile_size_px, source)
        source_info = SourceInfo(
            kind="geotiff", path=str(source.resolve()), sha256=sha256_file(source), crs=str(dataset.crs)
        )
        existing = up_to_date_manifest(
            out_dir,
            source_info=source_info,
            zoom=plan.zoom,
            tile_size_px=tile_size_px,
            tile_range=plan.tile_range,
            bbox_lonlat=plan.bbox_lonlat,
            min_tile_valid_fraction=min_tile_valid_fraction,
            resampling=_RESAMPLING.name,
        )
        if existing is not None:
            discard_journal(out_dir)
            return existing
        return _build(
            dataset,
            source_info,
            plan,
            out_dir,
            tile_size_px,
            min_tile_valid_fraction,
            progress,
            t_start,
            engine,
        )


def choose_zoom(source_gsd_m_px: float, lat_deg: float, tile_size_px: int = 256) -> int:
    """The coarsest zoom whose ground GSD at ``lat_deg`` is not coarser than the source's (5 % slack).

    A cache coarser than its source throws away map detail the matcher needs: with NAIP (5 m) the
    nearest-ratio zoom was 14 (6.5 m), where a 600 m AGL nav frame rectified to the map shrank to
    ~80 px and cross-date matching found 6-10 inliers. One zoom finer costs 4x the tiles, not more.
    """
    for z in range(MIN_ZOOM, MAX_ZOOM + 1):
        if WebMercatorGrid(z, tile_size_px).gsd_m_px(lat_deg) <= _MAX_COARSENING * source_gsd_m_px:
            return z
    return MAX_ZOOM


def check_build_params(
    zoom: int | None,
    bbox_lonlat: tuple[float, float, float, float] | None,
    tile_size_px: int | None,
    min_tile_valid_fraction: float,
) -> None:
    """Validate the parameters every cache source shares; raise CacheBuildError naming the bad one.

    ``tile_size_px`` None means "detect from the source" (XYZ tiles) and is not checked here.
    """
    if zoom is not None and not (MIN_ZOOM <= int(zoom) <= MAX_ZOOM):
        raise CacheBuildError(f"zoom {zoom} out of range, expected {MIN_ZOOM}..{MAX_ZOOM}")
    if tile_size_px is not None and not (16 <= tile_size_px <= 4096):
        raise CacheBuildError(f"tile_size_px {tile_size_px} out of range, expected 16..4096")
    if not (0.0 < min_tile_valid_fraction <= 1.0):
        raise CacheBuildError(f"min_tile_valid_fraction {min_tile_valid_fraction} must be in (0, 1]")
    if bbox_lonlat is not None:
        if len(bbox_lonlat) != 4 or not all(math.isfinite(v) for v in bbox_lonlat):
            raise CacheBuildError(f"bbox_lonlat must be 4 finite numbers (W, S, E, N), got {bbox_lonlat!r}")
        west, south, east, north = bbox_lonlat
        if not (west < east and south < north):
            # Antimeridian-crossing boxes would need two mosaics; not supported.
            raise CacheBuildError(f"bbox_lonlat must satisfy W < E and S < N, got {bbox_lonlat!r}")


def open_source(source: Path) -> Any:
    """The source GeoTIFF opened and checked (``_check_dataset``), for a ``with`` block; CacheBuildError
    naming the file when it is missing, unreadable or unusable."""
    if not source.is_file():
        raise CacheBuildError("source GeoTIFF not found", path=str(source))
    try:
        dataset = rasterio.open(source)
    except RasterioError as exc:
        raise CacheBuildError(f"not a raster file rasterio can read: {exc}", path=str(source)) from exc
    try:
        _check_dataset(dataset, source)
    except BaseException:
        dataset.close()
        raise
    return dataset


def _check_dataset(dataset: rasterio.io.DatasetReader, source: Path) -> None:
    if dataset.crs is None:
        raise CacheBuildError("raster has no CRS (not georeferenced)", path=str(source))
    if dataset.transform.is_identity:
        raise CacheBuildError("raster has no geotransform (not georeferenced)", path=str(source))
    if dataset.dtypes[0] != "uint8":
        raise CacheBuildError(
            f"expected 8-bit imagery, got {dataset.dtypes[0]}; convert first "
            "(e.g. gdal_translate -ot Byte -scale)",
            path=str(source),
        )


def _source_bbox_lonlat(dataset: rasterio.io.DatasetReader) -> tuple[float, float, float, float]:
    west, south, east, north = transform_bounds(dataset.crs, _WGS84_CRS, *dataset.bounds, densify_pts=21)
    return west, max(south, -_MAX_LAT_DEG), east, min(north, _MAX_LAT_DEG)


def _source_ground_gsd_m_px(dataset: rasterio.io.DatasetReader, lon_deg: float, lat_deg: float) -> float:
    """Ground metres per source pixel at (lon, lat): geometric mean of the two pixel axes."""
    xs, ys = transform(_WGS84_CRS, dataset.crs, [lon_deg], [lat_deg])
    col, row = ~dataset.transform @ (xs[0], ys[0])
    cx, cy = dataset.transform @ (col, row)
    ex, ey = dataset.transform @ (col + 1.0, row)
    sx, sy = dataset.transform @ (col, row + 1.0)
    lons, lats = transform(dataset.crs, _WGS84_CRS, [cx, ex, sx], [cy, ey, sy])
    d_east = float(haversine_m(lats[0], lons[0], lats[1], lons[1]))
    d_south = float(haversine_m(lats[0], lons[0], lats[2], lons[2]))
    return math.sqrt(d_east * d_south)


def _plan(
    dataset: rasterio.io.DatasetReader,
    zoom: int | None,
    bbox_lonlat: tuple[float, float, float, float] | None,
    tile_size_px: int,
    source: Path,
) -> _Plan:
    src_w, src_s, src_e, src_n = _source_bbox_lonlat(dataset)
    if bbox_lonlat is None:
        area = (src_w, src_s, src_e, src_n)
    else:
        area = (
            max(src_w, bbox_lonlat[0]),
            max(src_s, bbox_lonlat[1]),
            min(src_e, bbox_lonlat[2]),
            min(src_n, bbox_lonlat[3]),
        )
        if not (area[0] < area[2] and area[1] < area[3]):
            raise CacheBuildError(
                f"bbox {tuple(bbox_lonlat)} does not overlap the source footprint "
                f"{(src_w, src_s, src_e, src_n)} (lon/lat degrees)",
                path=str(source),
            )
    centre_lon, centre_lat = (area[0] + area[2]) / 2.0, (area[1] + area[3]) / 2.0
    source_gsd = _source_ground_gsd_m_px(dataset, centre_lon, centre_lat)
    chosen = int(zoom) if zoom is not None else choose_zoom(source_gsd, centre_lat, tile_size_px)
    tile_range = tile_range_for_bbox(WebMercatorGrid(chosen, tile_size_px), area)
    return _Plan(zoom=chosen, tile_range=tile_range, bbox_lonlat=area, source_gsd_m_px=source_gsd)


def tile_range_for_bbox(grid: WebMercatorGrid, bbox_lonlat: tuple[float, float, float, float]) -> TileRange:
    """The XYZ tiles at ``grid``'s zoom that cover ``(west, south, east, north)`` degrees."""
    west, south, east, north = bbox_lonlat
    ts = grid.tile_size_px
    nw = grid.lonlat_to_px(west, min(north, _MAX_LAT_DEG)) / ts
    se = grid.lonlat_to_px(east, max(south, -_MAX_LAT_DEG)) / ts
    last = (1 << grid.zoom) - 1
    # An east/south edge exactly on a tile border must not pull in the next (empty) tile.
    x0, y0 = min(max(math.floor(nw[0]), 0), last), min(max(math.floor(nw[1]), 0), last)
    return TileRange(
        x0=x0,
        y0=y0,
        x1=min(max(math.ceil(se[0]) - 1, x0), last),
        y1=min(max(math.ceil(se[1]) - 1, y0), last),
    )


def up_to_date_manifest(
    out_dir: Path,
    *,
    source_info: SourceInfo,
    zoom: int,
    tile_size_px: int,
    tile_range: TileRange,
    bbox_lonlat: tuple[float, float, float, float],
    min_tile_valid_fraction: float,
    resampling: str,
) -> CacheManifest | None:
    """The existing manifest when it describes exactly this build and every artifact verifies in full
    (sha256: a damaged cache is rebuilt, not declared up to date).

    A cache built before the mosaic's cell CRC table was recorded gets it here and keeps everything else
    (VPR, fields, tile features). Logs ``CACHE_UP_TO_DATE`` when it returns one.
    """
    if not (out_dir / MANIFEST_NAME).is_file():
        return None
    try:
        existing = CacheManifest.load(out_dir)
        existing.verify_artifacts(out_dir, Verification.LIGHT)  # sizes first: cheap
    except CacheManifestError:
        return None
    same = (
        existing.source.kind == source_info.kind
        and existing.source.sha256 == source_info.sha256
        and existing.zoom == zoom
        and existing.tile_size_px == tile_size_px
        and existing.tile_range == tile_range
        and existing.min_tile_valid_fraction == min_tile_valid_fraction
        and existing.resampling == resampling
        and np.allclose(existing.bbox_lonlat, bbox_lonlat, rtol=0.0, atol=1e-12)
    )
    if not same:
        return None
    try:
        existing.verify_artifacts(out_dir, Verification.FULL)
    except CacheManifestError:
        return None
    added = not existing.has_cell_crc
    if added:
        existing = _with_cell_crc_table(out_dir, existing)
    _log.info(
        LogEvent.CACHE_UP_TO_DATE,
        cache_dir=str(out_dir),
        zoom=existing.zoom,
        tile_count=existing.tile_count,
        cell_crc_added=added,
    )
    return existing


def _with_cell_crc_table(out_dir: Path, manifest: CacheManifest) -> CacheManifest:
    """Write the mosaic's cell CRC table (``cell_crc``) beside it, and the manifest listing it (with its
    content hash); return that manifest."""
    name = cell_crc_name(manifest.zoom)
    path = out_dir / name
    try:
        mosaic = np.load(out_dir / manifest.mosaic_name, mmap_mode="r", allow_pickle=False)
        write_cell_crc_table(path, cell_crc32_table(mosaic, manifest.tile_size_px))
        del mosaic
        artifacts = dict(manifest.artifacts)
        artifacts[name] = ArtifactInfo(sha256=sha256_file(path), bytes=path.stat().st_size)
        updated = dataclasses.replace(manifest, artifacts=artifacts)
        updated.save(out_dir)
    except OSError as exc:
        raise CacheBuildError(f"cannot add the cell CRC table: {exc}", path=str(path)) from exc
    return updated


def _band_plan(dataset: rasterio.io.DatasetReader) -> tuple[tuple[int, ...], np.ndarray | None]:
    """Source band indexes read as (R, G, B) or (grey,), and a (256, 3) RGB palette LUT or None."""
    interp = list(dataset.colorinterp)
    if all(ci in interp for ci in (ColorInterp.red, ColorInterp.green, ColorInterp.blue)):
        return tuple(
            interp.index(ci) + 1 for ci in (ColorInterp.red, ColorInterp.green, ColorInterp.blue)
        ), None
    if dataset.count >= 3:
        # 4-band RGBN (NAIP) and unlabelled multiband rasters: the first three bands are R, G, B.
        return (1, 2, 3), None
    if interp and interp[0] == ColorInterp.palette:
        lut = np.zeros((256, 3), dtype=np.uint8)
        for index, rgba in dataset.colormap(1).items():
            if 0 <= index < 256:
                lut[index] = rgba[:3]
        return (1,), lut
    return (1,), None


def _blocks(tile_range: TileRange, tile_size_px: int) -> list[tuple[int, int, int, int]]:
    """Blocks of whole tiles ``(row0, col0, n_rows, n_cols)`` in tile units, row-major."""
    tiles_per_block = max(1, _BLOCK_TARGET_PX // (tile_size_px * tile_size_px))
    n_cols = min(tile_range.n_cols, tiles_per_block)
    n_rows = max(1, min(tile_range.n_rows, tiles_per_block // n_cols))
    return [
        (r, c, min(n_rows, tile_range.n_rows - r), min(n_cols, tile_range.n_cols - c))
        for r in range(0, tile_range.n_rows, n_rows)
        for c in range(0, tile_range.n_cols, n_cols)
    ]


def _warp_block(
    dataset: rasterio.io.DatasetReader,
    bands: tuple[int, ...],
    lut: np.ndarray | None,
    dst_transform: Affine,
    dst_shape: tuple[int, int],
    decimation: int,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Warp the source onto one mosaic block: (BGR (h, w, 3) uint8, valid (h, w) bool), None if no overlap."""
    height, width = dst_shape
    west, north = dst_transform @ (0, 0)
    east, south = dst_transform @ (width, height)
    src_bounds = transform_bounds(_MERC_CRS, dataset.crs, west, south, east, north, densify_pts=21)
    window = from_bounds(*src_bounds, transform=dataset.transform)
    # Pad for the bilinear kernel, snap outwards to whole pixels, clip to the raster.
    col0 = max(math.floor(window.col_off) - 2, 0)
    row0 = max(math.floor(window.row_off) - 2, 0)
    col1 = min(math.ceil(window.col_off + window.width) + 2, dataset.width)
    row1 = min(math.ceil(window.row_off + window.height) + 2, dataset.height)
    if col1 <= col0 or row1 <= row0:
        return None
    window = Window(col0, row0, col1 - col0, row1 - row0)
    # A source much finer than the mosaic is box-filtered on read, so the warp does not alias.
    out_h = max(1, math.ceil(window.height / decimation))
    out_w = max(1, math.ceil(window.width / decimation))
    data = dataset.read(
        list(bands),
        window=window,
        out_shape=(len(bands), out_h, out_w),
        resampling=Resampling.average if decimation > 1 else Resampling.nearest,
    )
    mask = dataset.dataset_mask(window=window, out_shape=(out_h, out_w))
    if lut is not None:
        data = np.moveaxis(lut[data[0]], -1, 0)
    src_transform = dataset.window_transform(window) @ Affine.scale(
        window.width / out_w, window.height / out_h
    )
    src = np.concatenate([data, mask[None]], axis=0)
    dst = np.zeros((src.shape[0], height, width), dtype=np.uint8)
    alpha = src.shape[0]
    reproject(
        src,
        dst,
        src_transform=src_transform,
        src_crs=dataset.crs,
        dst_transform=dst_transform,
        dst_crs=_MERC_CRS,
        src_alpha=alpha,
        dst_alpha=alpha,
        resampling=_RESAMPLING,
    )
    valid = dst[-1] >= _ALPHA_VALID_MIN
    colour = dst[:-1]
    if colour.shape[0] == 1:
        colour = np.repeat(colour, 3, axis=0)
    bgr = np.ascontiguousarray(np.moveaxis(colour[::-1], 0, -1))
    bgr[~valid] = 0
    # All-zero means nodata in the mosaic, so a truly black valid pixel is lifted to 1.
    bgr[valid & ~bgr.any(axis=-1)] = 1
    return bgr, valid


def _remove_stale(out_dir: Path, keep: set[str]) -> None:
    """Delete artifacts of an earlier build that this build does not produce (e.g. another zoom)."""
    for path in out_dir.iterdir():
        name = path.name
        ours = name.startswith("mosaic_z") and (name.endswith(".npy") or name.endswith(".npy.tmp"))
        ours = ours or name in {
            TILES_NAME + ".tmp",
            TILE_VALID_FRACTION_NAME + ".tmp",
            MANIFEST_NAME + ".tmp",
        }
        if ours and name not in keep and path.is_file():
            path.unlink()


def prepare_cache_dir(out_dir: Path, *, zoom: int, mosaic_shape: tuple[int, int, int]) -> Path:
    """Make ``out_dir`` ready for a build and return the temporary mosaic path to fill.

    Removes the manifest first (from here until a new one is written the cache reads as incomplete),
    checks the free space for the mosaic and deletes mosaics of earlier builds (e.g. another zoom).
    """
    mosaic_bytes = mosaic_shape[0] * mosaic_shape[1] * mosaic_shape[2]
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / MANIFEST_NAME).unlink(missing_ok=True)
        free = shutil.disk_usage(out_dir).free
    except OSError as exc:
        raise CacheBuildError(f"cannot prepare the cache directory: {exc}", path=str(out_dir)) from exc
    if mosaic_bytes > free:
        raise CacheBuildError(
            f"mosaic needs {mosaic_bytes / 1e9:.2f} GB at zoom {zoom}, only {free / 1e9:.2f} GB free",
            path=str(out_dir),
        )
    _remove_stale(out_dir, keep=set())
    return out_dir / (mosaic_name(zoom) + ".tmp")


def finalize_cache(
    out_dir: Path,
    *,
    mosaic_tmp: Path,
    fractions: np.ndarray,
    source_info: SourceInfo,
    zoom: int,
    tile_size_px: int,
    tile_range: TileRange,
    bbox_lonlat: tuple[float, float, float, float],
    min_tile_valid_fraction: float,
    resampling: str,
    t_start: float,
    created_utc: str | None = None,
) -> CacheManifest:
    """Publish a filled mosaic: tile list, valid fractions, the cells' CRC table (``cell_crc``), artifact
    hashes and, last, the manifest.

    ``fractions`` is float32 (n_rows, n_cols): the valid-pixel fraction of every tile of ``tile_range``.
    ``created_utc`` is the manifest's time stamp (None: now).
    Raises CacheBuildError when no tile reaches ``min_tile_valid_fraction`` (the temporary mosaic is
    removed) or on an I/O error.
    """
    ts = tile_size_px
    tr = tile_range
    grid = WebMercatorGrid(zoom, ts)
    shape = (tr.n_rows * ts, tr.n_cols * ts, 3)
    mosaic_file = mosaic_name(zoom)
    n_tiles = tr.n_rows * tr.n_cols
    rows, cols = np.nonzero(fractions >= min_tile_valid_fraction)
    if rows.size == 0:
        mosaic_tmp.unlink(missing_ok=True)
        raise CacheBuildError(
            f"empty result: no tile at zoom {zoom} has >= {min_tile_valid_fraction:.0%} valid pixels "
            "(source all nodata in the requested area?)",
            path=source_info.path,
        )
    tiles = []
    # np.nonzero is row-major, so the list is sorted by (y, x): a stable tile order for every consumer.
    for row, col in zip(rows.tolist(), cols.tolist(), strict=True):
        x, y = tr.x0 + col, tr.y0 + row
        lon, lat = grid.tile_center_lonlat(x, y)
        tile_id = TileId.of(zoom, lat, lon)
        tiles.append(
            {
                "x": x,
                "y": y,
                "zoom": tile_id.zoom,
                "lat_deg": tile_id.lat_deg,
                "lon_deg": tile_id.lon_deg,
                "valid_fraction": round(float(fractions[row, col]), 6),
            }
        )
    try:
        os.replace(mosaic_tmp, out_dir / mosaic_file)
        write_json_atomic(out_dir / TILES_NAME, {"zoom": zoom, "tile_size_px": ts, "tiles": tiles})
        fractions_tmp = out_dir / (TILE_VALID_FRACTION_NAME + ".tmp")
        with open(fractions_tmp, "wb") as fh:
            np.save(fh, fractions.astype(np.float32, copy=False))
        os.replace(fractions_tmp, out_dir / TILE_VALID_FRACTION_NAME)
        mosaic = np.load(out_dir / mosaic_file, mmap_mode="r", allow_pickle=False)
        write_cell_crc_table(out_dir / cell_crc_name(zoom), cell_crc32_table(mosaic, ts))
        del mosaic
        artifacts = {
            name: ArtifactInfo(sha256=sha256_file(out_dir / name), bytes=(out_dir / name).stat().st_size)
            for name in (mosaic_file, cell_crc_name(zoom), TILES_NAME, TILE_VALID_FRACTION_NAME)
        }
        manifest = CacheManifest(
            format_version=CACHE_FORMAT_VERSION,
            created_utc=created_utc or datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
            source=source_info,
            zoom=zoom,
            tile_size_px=ts,
            tile_range=tr,
            bbox_lonlat=bbox_lonlat,
            mosaic_shape=shape,
            tile_count=len(tiles),
            min_tile_valid_fraction=min_tile_valid_fraction,
            resampling=resampling,
            vpr=VprInfo(backbone="geo_prior", model_sha256=None),
            artifacts=artifacts,
        )
        manifest.save(out_dir)
    except OSError as exc:
        raise CacheBuildError(f"cannot write cache artifacts: {exc}", path=str(out_dir)) from exc
    seconds = time.monotonic() - t_start
    _log.info(
        LogEvent.CACHE_BUILT,
        cache_dir=str(out_dir),
        source_kind=source_info.kind,
        zoom=zoom,
        tile_count=len(tiles),
        tiles_in_range=n_tiles,
        seconds=round(seconds, 3),
        tiles_per_s=round(n_tiles / seconds, 1) if seconds > 0 else None,
        mosaic_shape=list(shape),
    )
    return manifest


@dataclass(frozen=True)
class WarpJob:
    """What a worker needs to warp any shard of one build (picklable, so it travels to Dask workers).

    ``source_path``: the GeoTIFF, a path every worker can open. ``bands`` / ``lut``: ``_band_plan``.
    ``origin_x_m`` / ``origin_y_m``: Web-Mercator metres of the tile range's north-west corner;
    ``res_m_px``: Mercator metres per mosaic px; ``decimation``: the source read's box-filter factor.
    """

    source_path: str
    bands: tuple[int, ...]
    lut: np.ndarray | None
    origin_x_m: float
    origin_y_m: float
    res_m_px: float
    tile_size_px: int
    decimation: int


def warp_shard(job: WarpJob, shard: Shard) -> ShardOutput:
    """Warp the source onto one shard's block of tiles: its pixels and its tiles' valid fractions.

    Runs in any process (a Dask worker included): it opens the source itself and writes nothing.
    """
    ts = job.tile_size_px
    r0, c0 = shard.row0_tiles * ts, shard.col0_tiles * ts
    res = job.res_m_px
    dst_transform = Affine(res, 0.0, job.origin_x_m + c0 * res, 0.0, -res, job.origin_y_m - r0 * res)
    shape = (shard.n_rows_tiles * ts, shard.n_cols_tiles * ts)
    with rasterio.open(job.source_path) as dataset:
        warped = _warp_block(dataset, job.bands, job.lut, dst_transform, shape, job.decimation)
    if warped is None:
        return ShardOutput(
            shard.index, None, np.zeros((shard.n_rows_tiles, shard.n_cols_tiles), dtype=np.float32)
        )
    bgr, valid = warped
    fractions = valid.reshape(shard.n_rows_tiles, ts, shard.n_cols_tiles, ts).mean(axis=(1, 3))
    return ShardOutput(shard.index, bgr, fractions.astype(np.float32))


def warp_job(dataset: rasterio.io.DatasetReader, source_path: str, plan: _Plan, tile_size_px: int) -> WarpJob:
    """The ``WarpJob`` of building ``plan`` from ``dataset`` (opened from ``source_path``)."""
    ts = tile_size_px
    tr = plan.tile_range
    grid = WebMercatorGrid(plan.zoom, ts)
    bands, lut = _band_plan(dataset)
    decimation = max(
        1, int(grid.gsd_m_px((plan.bbox_lonlat[1] + plan.bbox_lonlat[3]) / 2) / plan.source_gsd_m_px)
    )
    origin_x, origin_y = grid.px_to_merc(np.array([tr.x0 * ts, tr.y0 * ts], dtype=np.float64))
    return WarpJob(
        source_path=source_path,
        bands=bands,
        lut=lut,
        origin_x_m=float(origin_x),
        origin_y_m=float(origin_y),
        res_m_px=float(grid.merc_m_per_px),
        tile_size_px=ts,
        decimation=decimation,
    )


def build_identity(
    source_info: SourceInfo, plan: _Plan, tile_size_px: int, job: WarpJob, shards: list[Shard]
) -> dict[str, Any]:
    """Everything the mosaic's bytes depend on: the journal of a build of another identity is not resumed."""
    return {
        "format_version": CACHE_FORMAT_VERSION,
        "source_sha256": source_info.sha256,
        "zoom": plan.zoom,
        "tile_size_px": tile_size_px,
        "tile_range": vars(plan.tile_range),
        "bbox_lonlat": list(plan.bbox_lonlat),
        "resampling": _RESAMPLING.name,
        "alpha_valid_min": _ALPHA_VALID_MIN,
        "decimation": job.decimation,
        "bands": list(job.bands),
        "shards": [[s.row0_tiles, s.col0_tiles, s.n_rows_tiles, s.n_cols_tiles] for s in shards],
    }


def _build(
    dataset: rasterio.io.DatasetReader,
    source_info: SourceInfo,
    plan: _Plan,
    out_dir: Path,
    tile_size_px: int,
    min_tile_valid_fraction: float,
    progress: bool,
    t_start: float,
    engine: EngineSpec | ShardEngine | None,
) -> CacheManifest:
    ts = tile_size_px
    tr = plan.tile_range
    shape = (tr.n_rows * ts, tr.n_cols * ts, 3)
    job = warp_job(dataset, source_info.path, plan, ts)
    shards = shards_of(_blocks(tr, ts))
    identity = build_identity(source_info, plan, ts, job, shards)
    mosaic_tmp = out_dir / (mosaic_name(plan.zoom) + ".tmp")
    journal = ShardJournal.resume(out_dir, identity, mosaic_tmp, shape)
    try:
        if journal is None:
            prepare_cache_dir(out_dir, zoom=plan.zoom, mosaic_shape=shape)
            journal = ShardJournal.start(out_dir, identity, mosaic_tmp, shape)
        else:
            (out_dir / MANIFEST_NAME).unlink(missing_ok=True)
        with engine_scope(engine) as runner:
            run = run_shards(
                journal,
                shards,
                partial(warp_shard, job),
                runner,
                tile_range=tr,
                tile_size_px=ts,
                progress=progress,
                desc=f"cache z{plan.zoom}",
            )
    except (RasterioError, OSError) as exc:
        raise CacheBuildError(f"reprojection failed: {exc}", path=source_info.path) from exc
    manifest = finalize_cache(
        out_dir,
        mosaic_tmp=mosaic_tmp,
        fractions=run.fractions,
        source_info=source_info,
        zoom=plan.zoom,
        tile_size_px=ts,
        tile_range=tr,
        bbox_lonlat=plan.bbox_lonlat,
        min_tile_valid_fraction=min_tile_valid_fraction,
        resampling=_RESAMPLING.name,
        t_start=t_start,
        created_utc=journal.created_utc,
    )
    journal.remove()
    return manifest
