"""C10: build a map cache from XYZ tiles: a ``{z}/{x}/{y}.{png,jpg,jpeg,webp}`` directory, or a tile
server URL template downloaded first by C11 (F1 pre-flight).

XYZ ("slippy map") tiles are already Web-Mercator at a fixed zoom, so the mosaic is assembled pixel
for pixel, without resampling: tile ``(x, y)`` lands at row ``(y - y0) * ts``, column ``(x - x0) * ts``.
``y`` counts from the north; a TMS directory (y from the south) is read with ``tms=True``.

Validity: a tile that is absent is a gap (all-zero pixels). In a tile with an alpha channel, alpha
below 128 is nodata and a black opaque pixel is lifted to 1 so it stays valid; in a tile without
alpha an exactly black pixel is nodata (the cache's convention, and what most servers put outside
their coverage). Tiles with less than ``min_tile_valid_fraction`` valid pixels are not listed.

``build_cache`` picks the builder from the ``--source`` string: a file (GeoTIFF), a directory (XYZ) or
an ``http(s)://`` URL template.
"""

from __future__ import annotations

import hashlib
import os
import re
import sys
import time
from collections.abc import Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from gps_denied_onboard.components.c6_tiles.georef import WebMercatorGrid
from gps_denied_onboard.components.c10_cache_build.geotiff import (
    build_cache_from_geotiff,
    check_build_params,
    finalize_cache,
    prepare_cache_dir,
    tile_range_for_bbox,
    up_to_date_manifest,
)
from gps_denied_onboard.components.c10_cache_build.manifest import (
    CacheBuildError,
    CacheManifest,
    SourceInfo,
    TileRange,
)
from gps_denied_onboard.components.c10_cache_build.shards import EngineSpec, ShardEngine, is_distributed

#: Sub-directory of a URL-built cache that keeps the downloaded tiles (for resume and rebuilds).
DOWNLOAD_DIR_NAME = "_download"
#: ``SourceInfo.kind`` values written by this module.
SOURCE_KIND_XYZ_DIR = "xyz_dir"
SOURCE_KIND_TILE_SERVER = "tile_server"
#: Pixels are copied, never resampled.
RESAMPLING_NONE = "none"
_MERC_CRS = "EPSG:3857"
_TILE_FILE = re.compile(r"^(\d+)\.(png|jpe?g|webp)$", re.IGNORECASE)
#: Alpha at or above this is a valid pixel (same threshold as the GeoTIFF builder's warped alpha).
_ALPHA_VALID_MIN = 128
#: Tiles decoded per batch (bounds memory; the decode threads release the GIL in OpenCV).
_DECODE_BATCH = 64


@dataclass(frozen=True)
class _TileFile:
    """One tile file: XYZ ``(x, y)`` (y from the north), its path and its path relative to the source."""

    x: int
    y: int
    path: Path
    rel_path: str


def build_cache_from_xyz_dir(
    source_dir: Path,
    out_dir: Path,
    *,
    zoom: int,
    bbox_lonlat: tuple[float, float, float, float] | None = None,
    tile_size_px: int | None = None,
    tms: bool = False,
    progress: bool = True,
    min_tile_valid_fraction: float = 0.5,
) -> CacheManifest:
    """Build (or confirm up to date) a cache in ``out_dir`` from the tiles in ``source_dir/{zoom}``.

    ``bbox_lonlat`` ``(west, south, east, north)`` degrees selects the tiles that cover it (default:
    the extent of the tiles present); tiles missing inside it are gaps. ``tile_size_px`` None takes
    the size of the tiles (all must be the same square size). ``tms`` reads y from the south.
    The manifest's source is ``xyz_dir`` with the sha256 of a canonical listing (scheme, then
    relative path, size and sha256 of every tile used), so a changed tile triggers a rebuild.

    Raises CacheBuildError for a missing directory or zoom, bad parameters, no tile in the bbox,
    an undecodable or wrongly sized tile, two files for one tile, or an empty result.
    """
    source_dir = Path(source_dir)
    return _build_from_dir(
        source_dir,
        Path(out_dir),
        zoom=zoom,
        bbox_lonlat=bbox_lonlat,
        tile_size_px=tile_size_px,
        tms=tms,
        progress=progress,
        min_tile_valid_fraction=min_tile_valid_fraction,
        source_kind=SOURCE_KIND_XYZ_DIR,
        source_path=str(source_dir.resolve()),
    )


def build_cache_from_url(
    url_template: str,
    out_dir: Path,
    *,
    zoom: int,
    bbox_lonlat: tuple[float, float, float, float],
    tile_size_px: int | None = None,
    progress: bool = True,
    min_tile_valid_fraction: float = 0.5,
    allow_failed_tiles: bool = False,
    max_tiles: int = 200_000,
    **downloader_options: Any,
) -> CacheManifest:
    """Download the tiles covering ``bbox_lonlat`` at ``zoom`` from ``url_template`` into
    ``out_dir/_download`` (kept: a re-run resumes there and fetches only what is missing), then build
    the cache from them.

    ``downloader_options`` go to ``TileDownloader`` (concurrency, rate_limit_per_s, max_retries,
    backoff_base_s, backoff_max_s, retry_after_max_s, timeout_s, user_agent, headers, subdomains).
    Tiles the server does not have (404) are gaps. Tiles that still failed after the retries make the
    build fail, naming them, unless ``allow_failed_tiles`` (they become gaps). The manifest's source is
    ``tile_server``: ``path`` holds the URL template with secret query values replaced by ``REDACTED``,
    ``sha256`` the listing hash of the tiles used; zoom and bbox are the manifest's own fields.

    Raises TileDownloadError (fatal HTTP status, bad template) or CacheBuildError.
    """
    # C11 is imported here: the GeoTIFF/XYZ paths must not need it.
    from gps_denied_onboard.components.c11_tile_download import TileDownloader

    check_build_params(zoom, bbox_lonlat, tile_size_px, min_tile_valid_fraction)
    if bbox_lonlat is None:
        raise CacheBuildError("a tile server source needs bbox_lonlat (W, S, E, N)", path=url_template)
    out_dir = Path(out_dir)
    download_dir = out_dir / DOWNLOAD_DIR_NAME
    downloader = TileDownloader(url_template, **downloader_options)
    summary = downloader.download(zoom, bbox_lonlat, download_dir, progress, max_tiles=max_tiles)
    if summary.downloaded + summary.skipped_existing == 0:
        raise CacheBuildError(
            f"the tile server has none of the {summary.requested} tiles of this area at zoom {zoom} "
            f"(first answer: {summary.failed[0].reason if summary.failed else 'none'}); "
            "check the zoom, the bbox and the server's coverage",
            path=downloader.redacted_template,
        )
    if summary.errors and not allow_failed_tiles:
        first = "; ".join(f"{f.z}/{f.x}/{f.y}: {f.reason}" for f in summary.errors[:3])
        raise CacheBuildError(
            f"{len(summary.errors)} of {summary.requested} tiles could not be downloaded (first: {first}); "
            "re-run to resume, or allow failed tiles to build with gaps",
            path=downloader.redacted_template,
        )
    return _build_from_dir(
        download_dir,
        out_dir,
        zoom=zoom,
        bbox_lonlat=bbox_lonlat,
        tile_size_px=tile_size_px,
        tms=False,
        progress=progress,
        min_tile_valid_fraction=min_tile_valid_fraction,
        source_kind=SOURCE_KIND_TILE_SERVER,
        source_path=downloader.redacted_template,
    )


def build_cache(
    source: str | Path,
    out_dir: Path,
    *,
    zoom: int | None = None,
    bbox_lonlat: tuple[float, float, float, float] | None = None,
    tile_size_px: int | None = None,
    tms: bool = False,
    progress: bool = True,
    min_tile_valid_fraction: float = 0.5,
    allow_failed_tiles: bool = False,
    downloader_options: Mapping[str, Any] | None = None,
    engine: EngineSpec | ShardEngine | None = None,
) -> CacheManifest:
    """Build a cache from whatever ``source`` names: an ``http(s)://`` URL template with ``{z}``,
    ``{x}``, ``{y}`` (needs ``zoom`` and ``bbox_lonlat``), a directory of XYZ tiles (needs ``zoom``
    unless it holds a single zoom level), or a GeoTIFF file (``zoom`` None: matched to its GSD;
    ``tile_size_px`` None: 256). ``tms`` applies to a directory (a TMS server uses ``{-y}`` in its
    template); ``allow_failed_tiles`` and ``downloader_options`` (``TileDownloader`` keywords) to a URL.
    ``engine`` (where the shards run, ``shards.EngineSpec``) applies to a GeoTIFF; the other sources are
    built in this process.

    Raises CacheBuildError (or TileDownloadError for a URL) naming what is wrong.
    """
    text = str(source)
    path = Path(text)
    if is_distributed(engine) and not path.is_file():
        raise CacheBuildError(
            "workers and a cluster address apply to a GeoTIFF source; XYZ tiles are built in this process",
            path=text,
        )
    if text.lower().startswith(("http://", "https://")):
        if zoom is None:
            raise CacheBuildError("a tile server source needs a zoom", path=text)
        if bbox_lonlat is None:
            raise CacheBuildError("a tile server source needs bbox_lonlat (W, S, E, N)", path=text)
        return build_cache_from_url(
            text,
            out_dir,
            zoom=zoom,
            bbox_lonlat=bbox_lonlat,
            tile_size_px=tile_size_px,
            progress=progress,
            min_tile_valid_fraction=min_tile_valid_fraction,
            allow_failed_tiles=allow_failed_tiles,
            **dict(downloader_options or {}),
        )
    if "://" in text:
        raise CacheBuildError("unsupported URL scheme, expected http:// or https://", path=text)
    if path.is_dir():
        return build_cache_from_xyz_dir(
            path,
            out_dir,
            zoom=zoom if zoom is not None else _single_zoom(path),
            bbox_lonlat=bbox_lonlat,
            tile_size_px=tile_size_px,
            tms=tms,
            progress=progress,
            min_tile_valid_fraction=min_tile_valid_fraction,
        )
    if path.is_file():
        return build_cache_from_geotiff(
            path,
            out_dir,
            zoom=zoom,
            bbox_lonlat=bbox_lonlat,
            tile_size_px=tile_size_px if tile_size_px is not None else 256,
            progress=progress,
            min_tile_valid_fraction=min_tile_valid_fraction,
            engine=engine,
        )
    raise CacheBuildError(
        "source not found: expected a GeoTIFF file, a directory of {z}/{x}/{y} tiles or an "
        "http(s):// URL template with {z}/{x}/{y}",
        path=text,
    )


def decode_tile(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """Decode a tile image: (BGR (h, w, 3) uint8 with nodata all-zero, valid (h, w) bool).

    Accepts grey, grey+alpha, BGR, BGRA (palette PNGs arrive expanded) and 16-bit images (scaled
    to 8 bits). Raises ValueError when the bytes are not a decodable image.
    """
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None or image.size == 0:
        raise ValueError(f"not a decodable PNG/JPEG/WebP image ({len(data)} bytes)")
    if image.dtype == np.uint16:
        image = (np.asarray(image, dtype=np.uint16) >> 8).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise ValueError(f"unsupported pixel type {image.dtype}, expected 8 or 16 bits")
    if image.ndim == 2:
        image = image[..., None]
    channels = image.shape[2]
    if channels in (2, 4):
        alpha = image[..., -1]
        colour = image[..., :-1]
        valid = alpha >= _ALPHA_VALID_MIN
    else:
        colour, valid = image, None
    bgr = np.repeat(colour, 3, axis=2) if colour.shape[2] == 1 else np.ascontiguousarray(colour[..., :3])
    if valid is None:
        return bgr, np.asarray(bgr.any(axis=-1))
    bgr[~valid] = 0
    # All-zero means nodata in the mosaic, so an opaque black pixel is lifted to 1.
    bgr[valid & ~bgr.any(axis=-1)] = 1
    return bgr, valid


def scan_xyz_dir(source_dir: Path, zoom: int, *, tms: bool = False) -> dict[tuple[int, int], _TileFile]:
    """The tile files of ``source_dir/{zoom}`` keyed by XYZ (x, y) (y from the north).

    Files that are not ``{digits}.{png,jpg,jpeg,webp}`` (partial downloads, metadata) are ignored;
    two files for one tile raise CacheBuildError.
    """
    zoom_dir = source_dir / str(zoom)
    if not source_dir.is_dir():
        raise CacheBuildError("XYZ tile directory not found", path=str(source_dir))
    if not zoom_dir.is_dir():
        raise CacheBuildError(
            f"no zoom {zoom} in the XYZ tile directory (zoom levels present: {_zoom_levels(source_dir)})",
            path=str(source_dir),
        )
    last = (1 << zoom) - 1
    tiles: dict[tuple[int, int], _TileFile] = {}
    try:
        for x_entry in os.scandir(zoom_dir):
            if not (x_entry.is_dir() and x_entry.name.isdigit()):
                continue
            x = int(x_entry.name)
            for entry in os.scandir(x_entry.path):
                match = _TILE_FILE.match(entry.name)
                if match is None or not entry.is_file():
                    continue
                y = int(match.group(1))
                if x > last or y > last:
                    raise CacheBuildError(
                        f"tile {zoom}/{x}/{entry.name} is outside the zoom-{zoom} grid (0..{last})",
                        path=entry.path,
                    )
                if tms:
                    y = last - y
                rel_path = f"{zoom}/{x}/{entry.name}"
                if (x, y) in tiles:
                    raise CacheBuildError(
                        f"two files for one tile: {tiles[(x, y)].rel_path} and {rel_path}; keep one",
                        path=str(source_dir),
                    )
                tiles[(x, y)] = _TileFile(x=x, y=y, path=Path(entry.path), rel_path=rel_path)
    except OSError as exc:
        raise CacheBuildError(f"cannot list the XYZ tile directory: {exc}", path=str(zoom_dir)) from exc
    return tiles


def _build_from_dir(
    source_dir: Path,
    out_dir: Path,
    *,
    zoom: int,
    bbox_lonlat: tuple[float, float, float, float] | None,
    tile_size_px: int | None,
    tms: bool,
    progress: bool,
    min_tile_valid_fraction: float,
    source_kind: str,
    source_path: str,
) -> CacheManifest:
    t_start = time.monotonic()
    check_build_params(zoom, bbox_lonlat, tile_size_px, min_tile_valid_fraction)
    zoom = int(zoom)
    all_tiles = scan_xyz_dir(source_dir, zoom, tms=tms)
    if not all_tiles:
        raise CacheBuildError(f"no tile files at zoom {zoom}", path=str(source_dir / str(zoom)))
    present = _extent(all_tiles)
    tile_range = present if bbox_lonlat is None else tile_range_for_bbox(WebMercatorGrid(zoom), bbox_lonlat)
    used = sorted(
        (t for t in all_tiles.values() if _in_range(tile_range, t.x, t.y)), key=lambda t: (t.y, t.x)
    )
    if not used:
        raise CacheBuildError(
            f"no tile of zoom {zoom} inside bbox {tuple(bbox_lonlat or ())}: tiles present span "
            f"x {present.x0}..{present.x1}, y {present.y0}..{present.y1}, "
            f"lon/lat {_range_bbox_lonlat(zoom, present)}",
            path=str(source_dir),
        )
    area = _range_bbox_lonlat(zoom, _extent({(t.x, t.y): t for t in used}))
    if bbox_lonlat is not None:
        # Like the GeoTIFF builder: the mapped area is the request clipped to where data exists.
        area = (
            max(area[0], bbox_lonlat[0]),
            max(area[1], bbox_lonlat[1]),
            min(area[2], bbox_lonlat[2]),
            min(area[3], bbox_lonlat[3]),
        )
    ts = _detect_tile_size(used[0], tile_size_px)
    source_info = SourceInfo(
        kind=source_kind, path=source_path, sha256=_listing_sha256(used, tms=tms), crs=_MERC_CRS
    )
    existing = up_to_date_manifest(
        out_dir,
        source_info=source_info,
        zoom=zoom,
        tile_size_px=ts,
        tile_range=tile_range,
        bbox_lonlat=area,
        min_tile_valid_fraction=min_tile_valid_fraction,
        resampling=RESAMPLING_NONE,
    )
    if existing is not None:
        return existing
    shape = (tile_range.n_rows * ts, tile_range.n_cols * ts, 3)
    mosaic_tmp = prepare_cache_dir(out_dir, zoom=zoom, mosaic_shape=shape)
    fractions = np.zeros((tile_range.n_rows, tile_range.n_cols), dtype=np.float32)
    show = progress and sys.stderr.isatty()
    try:
        # open_memmap leaves the file sparse: unwritten (missing) tiles read as zero = nodata.
        mosaic = np.lib.format.open_memmap(mosaic_tmp, mode="w+", dtype=np.uint8, shape=shape)
        with (
            tqdm(total=len(used), unit="tile", desc=f"cache z{zoom}", disable=not show) as bar,
            ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1)) as pool,
        ):
            for tile, (bgr, valid) in _decoded(pool, used):
                if bgr.shape[:2] != (ts, ts):
                    raise CacheBuildError(
                        f"tile {tile.rel_path} is {bgr.shape[1]}x{bgr.shape[0]} px, expected {ts}x{ts} "
                        "like the others",
                        path=str(tile.path),
                    )
                row, col = tile.y - tile_range.y0, tile.x - tile_range.x0
                mosaic[row * ts : (row + 1) * ts, col * ts : (col + 1) * ts] = bgr
                fractions[row, col] = valid.mean()
                bar.update(1)
        mosaic.flush()
        del mosaic
    except OSError as exc:
        mosaic_tmp.unlink(missing_ok=True)
        raise CacheBuildError(f"cannot assemble the mosaic: {exc}", path=str(out_dir)) from exc
    except CacheBuildError:
        mosaic_tmp.unlink(missing_ok=True)
        raise
    return finalize_cache(
        out_dir,
        mosaic_tmp=mosaic_tmp,
        fractions=fractions,
        source_info=source_info,
        zoom=zoom,
        tile_size_px=ts,
        tile_range=tile_range,
        bbox_lonlat=area,
        min_tile_valid_fraction=min_tile_valid_fraction,
        resampling=RESAMPLING_NONE,
        t_start=t_start,
    )


def _decoded(
    pool: ThreadPoolExecutor, tiles: list[_TileFile]
) -> Iterator[tuple[_TileFile, tuple[np.ndarray, np.ndarray]]]:
    """Decode tiles in parallel, yielding them in order, one batch in memory at a time."""
    for start in range(0, len(tiles), _DECODE_BATCH):
        batch = tiles[start : start + _DECODE_BATCH]
        yield from zip(batch, pool.map(_read_and_decode, batch), strict=True)


def _read_and_decode(tile: _TileFile) -> tuple[np.ndarray, np.ndarray]:
    try:
        data = tile.path.read_bytes()
        return decode_tile(data)
    except (OSError, ValueError) as exc:
        raise CacheBuildError(
            f"cannot read tile {tile.rel_path}: {exc}; delete it (a re-download fetches it again)",
            path=str(tile.path),
        ) from exc


def _detect_tile_size(tile: _TileFile, tile_size_px: int | None) -> int:
    bgr, _ = _read_and_decode(tile)
    height, width = bgr.shape[:2]
    if height != width:
        raise CacheBuildError(f"tile {tile.rel_path} is {width}x{height} px, expected square tiles")
    if tile_size_px is not None and tile_size_px != width:
        raise CacheBuildError(
            f"tiles are {width} px but tile_size_px {tile_size_px} was asked; XYZ tiles are not resampled",
            path=str(tile.path),
        )
    if not (16 <= width <= 4096):
        raise CacheBuildError(f"tile {tile.rel_path} is {width} px, expected 16..4096", path=str(tile.path))
    return width


def _listing_sha256(tiles: list[_TileFile], *, tms: bool) -> str:
    """sha256 of the canonical listing: a scheme line, then "rel_path<TAB>bytes<TAB>sha256" per tile
    in (y, x) order. Any changed, added or removed tile changes it."""
    listing = hashlib.sha256(b"tms\n" if tms else b"xyz\n")
    for tile in tiles:
        try:
            data = tile.path.read_bytes()
        except OSError as exc:
            raise CacheBuildError(f"cannot read tile {tile.rel_path}: {exc}", path=str(tile.path)) from exc
        line = f"{tile.rel_path}\t{len(data)}\t{hashlib.sha256(data).hexdigest()}\n"
        listing.update(line.encode("utf-8"))
    return listing.hexdigest()


def _extent(tiles: Mapping[tuple[int, int], _TileFile]) -> TileRange:
    xs = [x for x, _ in tiles]
    ys = [y for _, y in tiles]
    return TileRange(x0=min(xs), y0=min(ys), x1=max(xs), y1=max(ys))


def _in_range(tile_range: TileRange, x: int, y: int) -> bool:
    return tile_range.x0 <= x <= tile_range.x1 and tile_range.y0 <= y <= tile_range.y1


def _range_bbox_lonlat(zoom: int, tile_range: TileRange) -> tuple[float, float, float, float]:
    """(west, south, east, north) degrees of the outer edges of a tile range."""
    grid = WebMercatorGrid(zoom)
    ts = grid.tile_size_px
    west, north = grid.px_to_lonlat(np.array([tile_range.x0 * ts, tile_range.y0 * ts], dtype=np.float64))
    east, south = grid.px_to_lonlat(
        np.array([(tile_range.x1 + 1) * ts, (tile_range.y1 + 1) * ts], dtype=np.float64)
    )
    return float(west), float(south), float(east), float(north)


def _zoom_levels(source_dir: Path) -> list[int]:
    try:
        return sorted(int(p.name) for p in source_dir.iterdir() if p.is_dir() and p.name.isdigit())
    except OSError:
        return []


def _single_zoom(source_dir: Path) -> int:
    levels = _zoom_levels(source_dir)
    if len(levels) != 1:
        raise CacheBuildError(
            f"give a zoom: the XYZ tile directory holds zoom levels {levels or 'none'}", path=str(source_dir)
        )
    return levels[0]
