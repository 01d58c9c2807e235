"""C10 cache build from a directory of XYZ tiles: real PNG/JPEG files, real mosaic, opened by C6."""

from __future__ import annotations

import hashlib
import json
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from gps_denied_onboard.components.c6_tiles import TileStore, WebMercatorGrid
from gps_denied_onboard.components.c10_cache_build import (
    CacheBuildError,
    CacheManifest,
    build_cache,
    build_cache_from_xyz_dir,
)

ZOOM = 12
X0, Y0 = 2200, 1400
N_COLS, N_ROWS = 4, 3
TS = 256


def _source_image(n_rows: int = N_ROWS, n_cols: int = N_COLS, ts: int = TS, seed: int = 0) -> np.ndarray:
    """Textured BGR image with no all-zero pixel (so every pixel is valid map data)."""
    rng = np.random.default_rng(seed)
    image = rng.integers(1, 256, size=(n_rows * ts, n_cols * ts, 3), dtype=np.uint8)
    # Smooth gradients on top of the noise keep JPEG honest about position.
    _, xx = np.mgrid[0 : n_rows * ts, 0 : n_cols * ts]
    image[..., 0] = (xx * 255 // (n_cols * ts - 1)).clip(1, 255)
    return image


def _write_tiles(
    root: Path,
    image: np.ndarray,
    *,
    ts: int = TS,
    ext: str = "png",
    skip: frozenset[tuple[int, int]] = frozenset(),
    tms: bool = False,
) -> Path:
    """Cut ``image`` into ``root/{ZOOM}/{x}/{y}.{ext}`` tiles starting at (X0, Y0)."""
    n_rows, n_cols = image.shape[0] // ts, image.shape[1] // ts
    for row in range(n_rows):
        for col in range(n_cols):
            x, y = X0 + col, Y0 + row
            if (x, y) in skip:
                continue
            file_y = (1 << ZOOM) - 1 - y if tms else y
            path = root / str(ZOOM) / str(x) / f"{file_y}.{ext}"
            path.parent.mkdir(parents=True, exist_ok=True)
            ok, data = cv2.imencode(f".{ext}", image[row * ts : (row + 1) * ts, col * ts : (col + 1) * ts])
            if not ok:
                raise RuntimeError(f"cannot encode {path}")
            path.write_bytes(data.tobytes())
    return root


def _tile_centre(x: int, y: int) -> tuple[float, float]:
    return WebMercatorGrid(ZOOM, TS).tile_center_lonlat(x, y)


def test_xyz_build_mosaic_equals_tiles_and_store_serves_chips(tmp_path: Path) -> None:
    """PNG tiles are assembled pixel-exact; TileStore opens the cache and tiles_near/chip work."""
    image = _source_image()
    src = _write_tiles(tmp_path / "tiles", image)
    manifest = build_cache_from_xyz_dir(src, tmp_path / "cache", zoom=ZOOM, progress=False)
    assert manifest.tile_count == N_ROWS * N_COLS
    assert manifest.tile_size_px == TS
    assert (manifest.tile_range.x0, manifest.tile_range.y0) == (X0, Y0)
    assert manifest.source.kind == "xyz_dir"
    store = TileStore.open(tmp_path / "cache")
    np.testing.assert_array_equal(np.asarray(store.mosaic), image)
    # The XYZ path records the cells' CRC table like the GeoTIFF path: one entry per tile, its bytes.
    table = np.load(tmp_path / "cache" / manifest.cell_crc_name)
    assert manifest.has_cell_crc and table.shape == (N_ROWS, N_COLS)
    assert int(table[1, 2]) == zlib.crc32(image[TS : 2 * TS, 2 * TS : 3 * TS].tobytes())
    lon, lat = _tile_centre(X0 + 2, Y0 + 1)
    nearest, dist_m = store.tiles_near(lat, lon, radius_m=5000.0, k=3)[0]
    assert store.tile_xyz(nearest)[:2] == (X0 + 2, Y0 + 1)
    assert dist_m < 1.0
    chip = store.chip(nearest, TS)
    np.testing.assert_array_equal(chip.pixels(), image[TS : 2 * TS, 2 * TS : 3 * TS])
    # The georeference of the chip agrees with the tile grid: its centre is the tile centre.
    c_lon, c_lat = chip.chip_px_to_lonlat(np.array([(TS - 1) / 2.0, (TS - 1) / 2.0]))
    assert abs(float(c_lon) - lon) < 1e-9 and abs(float(c_lat) - lat) < 1e-9


def test_xyz_build_missing_tile_is_a_gap(tmp_path: Path) -> None:
    """A tile absent from the directory is all-zero in the mosaic and not listed."""
    image = _source_image()
    gap = (X0 + 1, Y0 + 2)
    src = _write_tiles(tmp_path / "tiles", image, skip=frozenset({gap}))
    manifest = build_cache_from_xyz_dir(src, tmp_path / "cache", zoom=ZOOM, progress=False)
    assert manifest.tile_count == N_ROWS * N_COLS - 1
    mosaic = np.load(tmp_path / "cache" / manifest.mosaic_name)
    assert not mosaic[2 * TS : 3 * TS, TS : 2 * TS].any()
    np.testing.assert_array_equal(mosaic[: 2 * TS], image[: 2 * TS])
    listed = {(t["x"], t["y"]) for t in json.loads((tmp_path / "cache" / "tiles.json").read_text())["tiles"]}
    assert gap not in listed and len(listed) == manifest.tile_count
    fractions = np.load(tmp_path / "cache" / "tile_valid_fraction.npy")
    assert fractions[2, 1] == 0.0 and fractions[0, 0] == 1.0


def test_xyz_build_bbox_selects_covering_tiles(tmp_path: Path) -> None:
    """A bbox between two tile centres selects exactly the 2x2 tiles that cover it."""
    image = _source_image()
    src = _write_tiles(tmp_path / "tiles", image)
    west, north = _tile_centre(X0 + 1, Y0)
    east, south = _tile_centre(X0 + 2, Y0 + 1)
    manifest = build_cache_from_xyz_dir(
        src, tmp_path / "cache", zoom=ZOOM, bbox_lonlat=(west, south, east, north), progress=False
    )
    tr = manifest.tile_range
    assert (tr.x0, tr.x1, tr.y0, tr.y1) == (X0 + 1, X0 + 2, Y0, Y0 + 1)
    np.testing.assert_allclose(manifest.bbox_lonlat, (west, south, east, north), atol=1e-12)
    mosaic = np.load(tmp_path / "cache" / manifest.mosaic_name)
    np.testing.assert_array_equal(mosaic, image[0 : 2 * TS, TS : 3 * TS])


def test_xyz_build_bbox_outside_tiles_raises(tmp_path: Path) -> None:
    """A bbox with no tile of the directory raises, naming where the tiles are."""
    src = _write_tiles(tmp_path / "tiles", _source_image())
    with pytest.raises(CacheBuildError, match="no tile of zoom 12 inside bbox"):
        build_cache_from_xyz_dir(
            src, tmp_path / "cache", zoom=ZOOM, bbox_lonlat=(-10.0, -10.0, -9.0, -9.0), progress=False
        )


def test_xyz_build_tms_flag_flips_rows(tmp_path: Path) -> None:
    """A TMS directory (y from the south) read with tms=True gives the same mosaic as XYZ."""
    image = _source_image()
    src = _write_tiles(tmp_path / "tiles", image, tms=True)
    manifest = build_cache_from_xyz_dir(src, tmp_path / "cache", zoom=ZOOM, tms=True, progress=False)
    assert (manifest.tile_range.y0, manifest.tile_range.y1) == (Y0, Y0 + N_ROWS - 1)
    np.testing.assert_array_equal(np.load(tmp_path / "cache" / manifest.mosaic_name), image)


def test_xyz_build_jpeg_512_tiles_detects_size(tmp_path: Path) -> None:
    """512 px JPEG tiles: the tile size is detected and the pixels survive within JPEG error."""
    image = cv2.GaussianBlur(_source_image(2, 2, 512), (0, 0), 3)
    image[image == 0] = 1
    src = _write_tiles(tmp_path / "tiles", image, ts=512, ext="jpg")
    manifest = build_cache_from_xyz_dir(src, tmp_path / "cache", zoom=ZOOM, progress=False)
    assert manifest.tile_size_px == 512
    assert manifest.mosaic_shape == (1024, 1024, 3)
    mosaic = np.load(tmp_path / "cache" / manifest.mosaic_name)
    assert np.abs(mosaic.astype(int) - image.astype(int)).mean() < 3.0
    store = TileStore.open(tmp_path / "cache")
    assert len(store) == 4


def test_xyz_build_tile_size_mismatch_with_request_raises(tmp_path: Path) -> None:
    """Asking for 512 px tiles from a 256 px directory raises (XYZ tiles are never resampled)."""
    src = _write_tiles(tmp_path / "tiles", _source_image())
    with pytest.raises(CacheBuildError, match="tiles are 256 px but tile_size_px 512"):
        build_cache_from_xyz_dir(src, tmp_path / "cache", zoom=ZOOM, tile_size_px=512, progress=False)


def test_xyz_build_mixed_tile_sizes_raises(tmp_path: Path) -> None:
    """One tile of another size raises, naming that tile."""
    src = _write_tiles(tmp_path / "tiles", _source_image())
    odd = src / str(ZOOM) / str(X0 + 3) / f"{Y0 + 2}.png"
    odd.write_bytes(cv2.imencode(".png", np.full((128, 128, 3), 9, np.uint8))[1].tobytes())
    with pytest.raises(CacheBuildError, match=f"{X0 + 3}/{Y0 + 2}.png is 128x128"):
        build_cache_from_xyz_dir(src, tmp_path / "cache", zoom=ZOOM, progress=False)
    assert not (tmp_path / "cache" / "manifest.json").exists()


def test_xyz_build_alpha_transparent_pixels_are_nodata(tmp_path: Path) -> None:
    """Transparent pixels of a BGRA tile become nodata; opaque black stays valid (lifted to 1)."""
    root = tmp_path / "tiles"
    tile = np.full((TS, TS, 4), 255, np.uint8)
    tile[..., :3] = 80
    tile[:, : TS // 4, 3] = 0  # left quarter transparent
    tile[0, TS - 1, :3] = 0  # an opaque black pixel
    path = root / str(ZOOM) / str(X0) / f"{Y0}.png"
    path.parent.mkdir(parents=True)
    path.write_bytes(cv2.imencode(".png", tile)[1].tobytes())
    manifest = build_cache_from_xyz_dir(root, tmp_path / "cache", zoom=ZOOM, progress=False)
    mosaic = np.load(tmp_path / "cache" / manifest.mosaic_name)
    assert not mosaic[:, : TS // 4].any()
    assert (mosaic[0, TS - 1] == 1).all()
    fractions = np.load(tmp_path / "cache" / "tile_valid_fraction.npy")
    assert fractions[0, 0] == pytest.approx(0.75)


def test_xyz_build_rerun_is_idempotent_and_changed_tile_rebuilds(tmp_path: Path) -> None:
    """Same tiles: the manifest is returned untouched; one changed tile: the cache is rebuilt."""
    image = _source_image()
    src = _write_tiles(tmp_path / "tiles", image)
    first = build_cache_from_xyz_dir(src, tmp_path / "cache", zoom=ZOOM, progress=False)
    mtime = (tmp_path / "cache" / "manifest.json").stat().st_mtime_ns
    again = build_cache_from_xyz_dir(src, tmp_path / "cache", zoom=ZOOM, progress=False)
    assert again == first
    assert (tmp_path / "cache" / "manifest.json").stat().st_mtime_ns == mtime
    changed = image.copy()
    changed[:TS, :TS] = 7
    _write_tiles(src, changed)
    rebuilt = build_cache_from_xyz_dir(src, tmp_path / "cache", zoom=ZOOM, progress=False)
    assert rebuilt.source.sha256 != first.source.sha256
    np.testing.assert_array_equal(np.asarray(TileStore.open(tmp_path / "cache").mosaic), changed)


def test_xyz_manifest_source_sha256_is_the_canonical_listing(tmp_path: Path) -> None:
    """source.sha256 equals sha256 of "xyz" + (relative path, size, sha256) per tile in (y, x) order."""
    src = _write_tiles(tmp_path / "tiles", _source_image())
    manifest = build_cache_from_xyz_dir(src, tmp_path / "cache", zoom=ZOOM, progress=False)
    listing = hashlib.sha256(b"xyz\n")
    for y in range(Y0, Y0 + N_ROWS):
        for x in range(X0, X0 + N_COLS):
            data = (src / str(ZOOM) / str(x) / f"{y}.png").read_bytes()
            listing.update(f"{ZOOM}/{x}/{y}.png\t{len(data)}\t{hashlib.sha256(data).hexdigest()}\n".encode())
    assert manifest.source.sha256 == listing.hexdigest()
    assert manifest.source.path == str(src.resolve())
    assert CacheManifest.load(tmp_path / "cache") == manifest


def test_xyz_build_corrupt_tile_raises_naming_it(tmp_path: Path) -> None:
    """A tile file that is not an image raises, naming the file; no manifest is written."""
    src = _write_tiles(tmp_path / "tiles", _source_image())
    (src / str(ZOOM) / str(X0 + 1) / f"{Y0 + 1}.png").write_bytes(b"<html>not a tile</html>")
    with pytest.raises(CacheBuildError, match=f"{ZOOM}/{X0 + 1}/{Y0 + 1}.png"):
        build_cache_from_xyz_dir(src, tmp_path / "cache", zoom=ZOOM, progress=False)
    assert not (tmp_path / "cache" / "manifest.json").exists()


def test_xyz_build_duplicate_tile_raises(tmp_path: Path) -> None:
    """Two files for one tile (png and jpg) are ambiguous and raise."""
    src = _write_tiles(tmp_path / "tiles", _source_image())
    _write_tiles(src, _source_image(1, 1), ext="jpg")
    with pytest.raises(CacheBuildError, match="two files for one tile"):
        build_cache_from_xyz_dir(src, tmp_path / "cache", zoom=ZOOM, progress=False)


def test_xyz_build_missing_zoom_raises_listing_levels(tmp_path: Path) -> None:
    """A zoom the directory does not have raises, listing the zoom levels it has."""
    src = _write_tiles(tmp_path / "tiles", _source_image())
    with pytest.raises(CacheBuildError, match=r"no zoom 13 .*present: \[12\]"):
        build_cache_from_xyz_dir(src, tmp_path / "cache", zoom=13, progress=False)


def test_build_cache_dispatches_directory_with_single_zoom(tmp_path: Path) -> None:
    """build_cache on a directory builds from XYZ tiles, taking its only zoom level."""
    src = _write_tiles(tmp_path / "tiles", _source_image())
    manifest = build_cache(str(src), tmp_path / "cache", progress=False)
    assert manifest.source.kind == "xyz_dir" and manifest.zoom == ZOOM


def test_build_cache_dispatches_file_to_geotiff(tmp_path: Path) -> None:
    """build_cache on a file builds from a GeoTIFF (tile size defaults to 256)."""
    tif = tmp_path / "ortho.tif"
    data = np.random.default_rng(1).integers(1, 255, size=(3, 64, 64), dtype=np.uint8)
    with rasterio.open(
        tif,
        "w",
        driver="GTiff",
        width=64,
        height=64,
        count=3,
        dtype="uint8",
        crs="EPSG:3857",
        transform=from_origin(1_800_000.0, 6_140_000.0, 20.0, 20.0),
    ) as dst:
        dst.write(data)
    # A 1.3 km source fills a fraction of one tile: accept any valid pixel.
    manifest = build_cache(tif, tmp_path / "cache", min_tile_valid_fraction=0.01, progress=False)
    assert manifest.source.kind == "geotiff" and manifest.tile_size_px == 256
    assert len(TileStore.open(tmp_path / "cache")) == manifest.tile_count >= 1


@pytest.mark.parametrize("source", ["does/not/exist", "ftp://example.invalid/{z}/{x}/{y}.png"])
def test_build_cache_unknown_source_raises(tmp_path: Path, source: str) -> None:
    """A source that is neither a file, a directory nor an http(s) URL raises with what is expected."""
    with pytest.raises(CacheBuildError, match="expected"):
        build_cache(source, tmp_path / "cache", zoom=ZOOM, progress=False)


def test_build_cache_url_without_bbox_raises(tmp_path: Path) -> None:
    """A URL source without a bbox raises before any request is made."""
    with pytest.raises(CacheBuildError, match="needs bbox_lonlat"):
        build_cache("http://127.0.0.1:9/{z}/{x}/{y}.png", tmp_path / "cache", zoom=ZOOM, progress=False)
