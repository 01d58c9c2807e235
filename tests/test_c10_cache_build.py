"""C10 cache build from GeoTIFF: real rasterio files in several CRSs, real reprojection."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
import zlib
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin
from rasterio.warp import transform as warp_transform

from gps_denied_onboard.components.c6_tiles import TileStore, TileStoreError, WebMercatorGrid
from gps_denied_onboard.components.c10_cache_build import (
    CacheBuildError,
    CacheManifest,
    build_cache_from_geotiff,
    choose_zoom,
)
from gps_denied_onboard.components.c10_cache_build.cell_crc import cell_crc32_table
from gps_denied_onboard.components.c10_cache_build.manifest import Verification, content_sha256, sha256_file

#: A known point (Vienna): the bright square of the synthetic sources is centred on it.
P_LON, P_LAT = 16.3, 48.2
NAIP = Path("/work/shared/data/naip_timeseries/naip/m_4709963_se_14_1_20090818.tif")
#: Square colour (R, G, B): distinct channels so a BGR/RGB swap is caught.
SQUARE_RGB = (250, 40, 10)


def _write_tiff(path: Path, crs: str, transform, data: np.ndarray, **profile) -> Path:  # type: ignore[no-untyped-def]
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=data.shape[2],
        height=data.shape[1],
        count=data.shape[0],
        dtype=data.dtype,
        crs=crs,
        transform=transform,
        **profile,
    ) as dst:
        dst.write(data)
    return path


def _square_source(
    path: Path, crs: str, *, size_px: int = 500, res_m: float = 4.0, bands: int = 3, nodata_left: bool = False
) -> Path:
    """A textured grey source in ``crs`` with a coloured 6x6 px square whose centre is exactly P."""
    x, y = warp_transform("EPSG:4326", crs, [P_LON], [P_LAT])
    if crs == "EPSG:4326":
        res_x = res_m / (111_320.0 * math.cos(math.radians(P_LAT)))
        res_y = res_m / 110_574.0
    else:
        res_x = res_y = res_m / (math.cos(math.radians(P_LAT)) if crs == "EPSG:3857" else 1.0)
    half = size_px // 2
    transform = from_origin(x[0] - half * res_x, y[0] + half * res_y, res_x, res_y)
    rng = np.random.default_rng(0)
    data = (90 + rng.integers(0, 30, size=(bands, size_px, size_px))).astype(np.uint8)
    for band, value in enumerate(SQUARE_RGB[: min(bands, 3)]):
        data[band, half - 3 : half + 3, half - 3 : half + 3] = value
    profile = {}
    if nodata_left:
        data[:, :, : size_px // 2 - 60] = 0
        profile["nodata"] = 0
    return _write_tiff(path, crs, transform, data, **profile)


def _square_centroid_px(mosaic: np.ndarray) -> np.ndarray:
    red, blue = mosaic[..., 2].astype(int), mosaic[..., 0].astype(int)
    rows, cols = np.nonzero((red > 180) & (blue < 60))
    return np.array([cols.mean(), rows.mean()])


@pytest.mark.parametrize("crs", ["EPSG:4326", "EPSG:3857", "EPSG:32633"])
def test_build_square_lands_at_its_lonlat_in_each_crs(tmp_path: Path, crs: str) -> None:
    """A square centred on P in a 4326/3857/UTM source lands on P's mosaic pixel within 1.5 px."""
    src = _square_source(tmp_path / "src.tif", crs)
    build_cache_from_geotiff(src, tmp_path / "cache", zoom=16, progress=False)
    store = TileStore.open(tmp_path / "cache")
    expected = store.lonlat_to_mosaic_px(P_LON, P_LAT)
    got = _square_centroid_px(np.asarray(store.mosaic))
    assert np.linalg.norm(got - expected) < 1.5, (crs, got, expected)


def test_build_auto_zoom_matches_source_gsd(tmp_path: Path) -> None:
    """zoom=None on a 4 m UTM source at 48.2 N picks zoom 15 (3.2 m), not 14 (6.4 m, coarser than 4 m)."""
    src = _square_source(tmp_path / "src.tif", "EPSG:32633", size_px=300)
    manifest = build_cache_from_geotiff(src, tmp_path / "cache", progress=False)
    assert manifest.zoom == 15


def test_choose_zoom_is_coarsest_not_coarser_than_source() -> None:
    """choose_zoom returns the coarsest zoom whose GSD is at most the source GSD (+5 %); NAIP's 5 m at
    47 N gets zoom 15 (3.3 m), not 14 (6.5 m)."""
    for gsd in (0.2846, 0.5, 1.0, 2.5, 4.0, 5.0, 7.0, 30.0):
        z = choose_zoom(gsd, 47.0)
        assert WebMercatorGrid(z).gsd_m_px(47.0) <= 1.05 * gsd
        assert WebMercatorGrid(z - 1).gsd_m_px(47.0) > 1.05 * gsd
    assert choose_zoom(5.0, 47.0) == 15


def test_build_manifest_records_every_artifact_hash(tmp_path: Path) -> None:
    """The manifest lists each artifact with its true size and sha256 and the required fields."""
    src = _square_source(tmp_path / "src.tif", "EPSG:32633", size_px=300)
    manifest = build_cache_from_geotiff(src, tmp_path / "cache", zoom=16, progress=False)
    raw = json.loads((tmp_path / "cache" / "manifest.json").read_text())
    assert raw["format_version"] == 1
    assert raw["source"]["kind"] == "geotiff" and raw["source"]["sha256"] == sha256_file(src)
    assert raw["vpr"] == {"backbone": "geo_prior", "model_sha256": None}
    assert set(raw["artifacts"]) == {
        "mosaic_z16.npy",
        "mosaic_z16_cell_crc32.npy",
        "tiles.json",
        "tile_valid_fraction.npy",
    }
    for name, info in raw["artifacts"].items():
        path = tmp_path / "cache" / name
        assert info == {"sha256": sha256_file(path), "bytes": path.stat().st_size}
    assert CacheManifest.load(tmp_path / "cache") == manifest
    tr = manifest.tile_range
    assert manifest.mosaic_shape == (tr.n_rows * 256, tr.n_cols * 256, 3)
    # The cells' CRC table is the CRC-32 of each tile's bytes of the mosaic as written.
    mosaic = np.load(tmp_path / "cache" / "mosaic_z16.npy", mmap_mode="r")
    table = np.load(tmp_path / "cache" / "mosaic_z16_cell_crc32.npy")
    assert table.dtype == np.uint32 and table.shape == (tr.n_rows, tr.n_cols)
    assert int(table[0, 1]) == zlib.crc32(np.ascontiguousarray(mosaic[:256, 256:512]).tobytes())
    np.testing.assert_array_equal(table, cell_crc32_table(mosaic, 256))
    # The manifest records the sha256 of its own content.
    assert raw["content_sha256"] == content_sha256(raw)


def test_build_rerun_same_inputs_is_idempotent(tmp_path: Path) -> None:
    """A second identical build skips the work: same manifest, same files, untouched mtimes."""
    src = _square_source(tmp_path / "src.tif", "EPSG:32633", size_px=300)
    out = tmp_path / "cache"
    first = build_cache_from_geotiff(src, out, zoom=16, progress=False)
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    second = build_cache_from_geotiff(src, out, zoom=16, progress=False)
    assert second == first
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before


def test_build_other_zoom_into_same_dir_replaces_old_mosaic(tmp_path: Path) -> None:
    """Rebuilding at another zoom leaves exactly one mosaic (and its cell CRC table) and a consistent
    cache."""
    src = _square_source(tmp_path / "src.tif", "EPSG:32633", size_px=300)
    out = tmp_path / "cache"
    build_cache_from_geotiff(src, out, zoom=16, progress=False)
    manifest = build_cache_from_geotiff(src, out, zoom=15, progress=False)
    assert manifest.zoom == 15
    assert sorted(p.name for p in out.glob("mosaic_z*")) == ["mosaic_z15.npy", "mosaic_z15_cell_crc32.npy"]
    assert sorted(p.name for p in out.iterdir()) == sorted([*manifest.artifacts, "manifest.json"])
    assert TileStore.open(out).zoom == 15


def test_build_nodata_tiles_are_excluded(tmp_path: Path) -> None:
    """Tiles over the source's nodata half are not listed, and their mosaic pixels are all zero."""
    src = _square_source(tmp_path / "src.tif", "EPSG:32633", size_px=600, nodata_left=True)
    manifest = build_cache_from_geotiff(src, tmp_path / "cache", zoom=16, progress=False)
    store = TileStore.open(tmp_path / "cache")
    fractions = np.load(tmp_path / "cache" / "tile_valid_fraction.npy")
    assert fractions.shape == (manifest.tile_range.n_rows, manifest.tile_range.n_cols)
    assert (fractions == 0).any() and (fractions > 0.99).any()
    assert len(store) == int((fractions >= 0.5).sum())
    # The nodata/valid border is 60 source px (240 m) west of P; no listed tile centre may lie west of it.
    border_lon = P_LON - 240.0 / (111_320.0 * math.cos(math.radians(P_LAT)))
    assert all(t.lon_deg > border_lon - 0.0015 for t in store.tile_ids)
    west_px = store.lonlat_to_mosaic_px(border_lon - 0.004, P_LAT).round().astype(int)
    assert not store.mosaic[west_px[1], west_px[0]].any()


def test_build_alpha_band_masks_pixels(tmp_path: Path) -> None:
    """An RGBA source with alpha 0 on its top half gives nodata there and data below."""
    src = _square_source(tmp_path / "rgb.tif", "EPSG:32633", size_px=400)
    with rasterio.open(src) as ds:
        rgb, transform, crs = ds.read(), ds.transform, ds.crs
    alpha = np.full((1, 400, 400), 255, np.uint8)
    alpha[0, :150] = 0
    rgba = _write_tiff(tmp_path / "rgba.tif", crs.to_string(), transform, np.concatenate([rgb, alpha]))
    ci = rasterio.enums.ColorInterp
    with rasterio.open(rgba, "r+") as ds:
        ds.colorinterp = [ci.red, ci.green, ci.blue, ci.alpha]
    with rasterio.open(rgba) as ds:
        assert ds.colorinterp[3] == ci.alpha
    build_cache_from_geotiff(rgba, tmp_path / "cache", zoom=16, progress=False)
    store = TileStore.open(tmp_path / "cache")
    north = store.lonlat_to_mosaic_px(P_LON, P_LAT + 150 * 4.0 / 110_574.0).round().astype(int)
    assert not store.mosaic[north[1], north[0]].any()
    centre = store.lonlat_to_mosaic_px(P_LON + 0.001, P_LAT).round().astype(int)
    assert store.mosaic[centre[1], centre[0]].all()


def test_build_single_band_grey_is_replicated(tmp_path: Path) -> None:
    """A one-band grey source becomes a BGR mosaic with three equal channels."""
    src = _square_source(tmp_path / "grey.tif", "EPSG:32633", size_px=300, bands=1)
    build_cache_from_geotiff(src, tmp_path / "cache", zoom=16, progress=False)
    mosaic = np.asarray(TileStore.open(tmp_path / "cache").mosaic)
    valid = mosaic.any(axis=-1)
    assert valid.mean() > 0.3
    assert np.array_equal(mosaic[..., 0], mosaic[..., 1]) and np.array_equal(mosaic[..., 1], mosaic[..., 2])


def test_build_black_valid_pixels_stay_valid(tmp_path: Path) -> None:
    """Truly black map pixels (no nodata declared) are lifted to 1 so they are not read as nodata."""
    x, y = warp_transform("EPSG:4326", "EPSG:32633", [P_LON], [P_LAT])
    data = np.zeros((3, 200, 200), np.uint8)
    src = _write_tiff(tmp_path / "black.tif", "EPSG:32633", from_origin(x[0] - 400, y[0] + 400, 4, 4), data)
    manifest = build_cache_from_geotiff(src, tmp_path / "cache", zoom=16, progress=False)
    store = TileStore.open(tmp_path / "cache")
    assert manifest.tile_count > 0
    px = store.lonlat_to_mosaic_px(P_LON, P_LAT).round().astype(int)
    assert store.mosaic[px[1], px[0]].tolist() == [1, 1, 1]


def test_build_bbox_restricts_area(tmp_path: Path) -> None:
    """A bbox inside the source becomes the mapped area and yields fewer tiles than the full build."""
    src = _square_source(tmp_path / "src.tif", "EPSG:32633", size_px=600)
    full = build_cache_from_geotiff(src, tmp_path / "full", zoom=16, progress=False)
    bbox = (P_LON - 0.004, P_LAT - 0.003, P_LON + 0.004, P_LAT + 0.003)
    part = build_cache_from_geotiff(src, tmp_path / "part", zoom=16, bbox_lonlat=bbox, progress=False)
    assert np.allclose(part.bbox_lonlat, bbox)
    assert 0 < part.tile_count < full.tile_count


def test_build_missing_source_raises(tmp_path: Path) -> None:
    """A missing source file is a CacheBuildError naming the path."""
    with pytest.raises(CacheBuildError, match="not found") as info:
        build_cache_from_geotiff(tmp_path / "nope.tif", tmp_path / "cache", progress=False)
    assert info.value.path == str(tmp_path / "nope.tif")


def test_build_non_raster_source_raises(tmp_path: Path) -> None:
    """A file that is not a raster is a CacheBuildError, not a GDAL traceback."""
    bogus = tmp_path / "bogus.tif"
    bogus.write_text("not a tiff")
    with pytest.raises(CacheBuildError, match="not a raster"):
        build_cache_from_geotiff(bogus, tmp_path / "cache", progress=False)


def test_build_bbox_without_overlap_raises(tmp_path: Path) -> None:
    """A bbox far from the source footprint is rejected with both boxes in the message."""
    src = _square_source(tmp_path / "src.tif", "EPSG:32633", size_px=100)
    with pytest.raises(CacheBuildError, match="does not overlap"):
        build_cache_from_geotiff(src, tmp_path / "cache", bbox_lonlat=(0.0, 0.0, 1.0, 1.0), progress=False)


@pytest.mark.parametrize("zoom", [0, 23])
def test_build_zoom_out_of_range_raises(tmp_path: Path, zoom: int) -> None:
    """Zoom outside 1..22 is rejected before any work."""
    src = _square_source(tmp_path / "src.tif", "EPSG:32633", size_px=100)
    with pytest.raises(CacheBuildError, match="zoom"):
        build_cache_from_geotiff(src, tmp_path / "cache", zoom=zoom, progress=False)


def test_build_all_nodata_source_raises_empty_result(tmp_path: Path) -> None:
    """A source that is entirely nodata yields 'empty result' and no cache."""
    x, y = warp_transform("EPSG:4326", "EPSG:32633", [P_LON], [P_LAT])
    data = np.zeros((3, 100, 100), np.uint8)
    src = _write_tiff(tmp_path / "empty.tif", "EPSG:32633", from_origin(x[0], y[0], 4, 4), data, nodata=0)
    with pytest.raises(CacheBuildError, match="empty result"):
        build_cache_from_geotiff(src, tmp_path / "cache", zoom=16, progress=False)
    assert not (tmp_path / "cache" / "manifest.json").exists()


def test_build_failed_rebuild_never_looks_complete(tmp_path: Path) -> None:
    """A rebuild that fails midway removes the old manifest first, so the store refuses the directory."""
    good = _square_source(tmp_path / "good.tif", "EPSG:32633", size_px=200)
    out = tmp_path / "cache"
    build_cache_from_geotiff(good, out, zoom=16, progress=False)
    x, y = warp_transform("EPSG:4326", "EPSG:32633", [P_LON], [P_LAT])
    empty = _write_tiff(
        tmp_path / "empty.tif",
        "EPSG:32633",
        from_origin(x[0], y[0], 4, 4),
        np.zeros((3, 50, 50), np.uint8),
        nodata=0,
    )
    with pytest.raises(CacheBuildError):
        build_cache_from_geotiff(empty, out, zoom=16, progress=False)
    with pytest.raises(TileStoreError, match="manifest"):
        TileStore.open(out)


@pytest.mark.realdata
def test_build_naip_real_geotiff_matches_source_colours(tmp_path: Path) -> None:
    """The real 4-band NAIP (EPSG:26914, 5 m, nodata 0) builds at zoom 15 and keeps its colours."""
    if not NAIP.is_file():
        pytest.skip(f"real imagery not available: {NAIP} is missing (/work/shared/data not mounted)")
    t0 = time.monotonic()
    manifest = build_cache_from_geotiff(NAIP, tmp_path / "cache", zoom=15, progress=False)
    seconds = time.monotonic() - t0
    tiles_in_range = manifest.tile_range.n_rows * manifest.tile_range.n_cols
    print(
        f"\nNAIP z15 build: {tiles_in_range} tiles in {seconds:.3f} s "
        f"= {tiles_in_range / seconds:.1f} tiles/s"
    )
    store = TileStore.open(tmp_path / "cache")
    assert len(store) > 0
    with rasterio.open(NAIP) as ds:
        src_bounds = rasterio.warp.transform_bounds(ds.crs, "EPSG:4326", *ds.bounds, densify_pts=21)
        w, s, e, n = store.bbox_lonlat
        assert src_bounds[0] <= w < e <= src_bounds[2] and src_bounds[1] <= s < n <= src_bounds[3]
        # Sample an interior grid, away from the rotated footprint's nodata corners.
        lons, lats = np.meshgrid(np.linspace(w, e, 16)[2:-2], np.linspace(s, n, 12)[2:-2])
        xs, ys = warp_transform("EPSG:4326", ds.crs, lons.ravel(), lats.ravel())
        src_rgb = np.array([v[:3] for v in ds.sample(zip(xs, ys, strict=True))], dtype=float)
    px = store.lonlat_to_mosaic_px(lons.ravel(), lats.ravel()).round().astype(int)
    mosaic_rgb = np.asarray(store.mosaic)[px[:, 1], px[:, 0], ::-1].astype(float)
    diff = np.abs(mosaic_rgb - src_rgb)
    # Bilinear at 3.3 m from 5 m source differs per pixel on texture; the bulk must agree closely.
    assert np.median(diff) < 12.0, np.median(diff)
    assert np.corrcoef(mosaic_rgb.ravel(), src_rgb.ravel())[0, 1] > 0.9


def test_cli_build_ends_with_the_full_check_and_rebuilds_a_damaged_cache(tmp_path: Path) -> None:
    """`gdnav cache build` verifies every file's sha256 at its end; run again on a cache whose mosaic lost
    a byte in the middle (same size: a light check passes it), it rebuilds instead of calling it up to
    date, and the rebuilt cache verifies."""
    src = _square_source(tmp_path / "src.tif", "EPSG:32633", size_px=300)
    out = tmp_path / "cache"
    cmd = [sys.executable, "-m", "gps_denied_onboard.cli", "cache", "build", "--source", str(src)]
    cmd += ["--out", str(out), "--zoom", "16", "--no-fields", "--quiet"]
    first = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    assert first.returncode == 0, first.stderr
    assert "sha256 of every file verified" in first.stdout
    mosaic = out / "mosaic_z16.npy"
    good = mosaic.read_bytes()
    data = bytearray(good)
    data[len(data) // 2] ^= 0xFF
    mosaic.write_bytes(bytes(data))
    TileStore.open(out, Verification.LIGHT)  # the light check does not read the mosaic
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    assert again.returncode == 0, again.stderr
    assert "sha256 of every file verified" in again.stdout
    assert mosaic.read_bytes() == good
