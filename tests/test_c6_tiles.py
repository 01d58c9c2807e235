"""C6 tile store: verification gate, radius search, and page-cache-backed chips on a real built cache."""

from __future__ import annotations

import json
import math
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
import rasterio
import structlog
from rasterio.transform import from_origin
from rasterio.warp import transform as warp_transform

from gps_denied_onboard.components.c6_tiles import (
    TileCentreIndex,
    TileChip,
    TileId,
    TilePixelsHandle,
    TileStore,
    TileStoreError,
)
from gps_denied_onboard.components.c10_cache_build import build_cache_from_geotiff
from gps_denied_onboard.components.c10_cache_build.manifest import (
    CacheManifest,
    Verification,
    read_by_window,
)
from gps_denied_onboard.constants import LogEvent
from gps_denied_onboard.geo import haversine_m

P_LON, P_LAT = 16.3, 48.2
ZOOM = 16


def _write_source(root: Path) -> Path:
    """A textured 4 m UTM GeoTIFF around (P_LAT, P_LON) whose western strip is nodata."""
    x, y = warp_transform("EPSG:4326", "EPSG:32633", [P_LON], [P_LAT])
    width, height = 900, 600
    data = (60 + np.random.default_rng(1).integers(0, 150, size=(3, height, width))).astype(np.uint8)
    data[:, :, :150] = 0
    src = root / "src.tif"
    with rasterio.open(
        src,
        "w",
        driver="GTiff",
        width=width,
        height=height,
        count=3,
        dtype="uint8",
        crs="EPSG:32633",
        transform=from_origin(x[0] - width * 2.0, y[0] + height * 2.0, 4.0, 4.0),
        nodata=0,
    ) as dst:
        dst.write(data)
    return src


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A zoom-16 cache built from a textured 4 m UTM source whose western strip is nodata."""
    root = tmp_path_factory.mktemp("c6")
    build_cache_from_geotiff(_write_source(root), root / "cache", zoom=ZOOM, progress=False)
    return root / "cache"


@pytest.fixture(scope="module")
def store(cache_dir: Path) -> TileStore:
    return TileStore.open(cache_dir)


def _copy(cache_dir: Path, tmp_path: Path) -> Path:
    out = tmp_path / "cache"
    shutil.copytree(cache_dir, out)
    return out


def test_open_valid_cache_exposes_geometry(store: TileStore) -> None:
    """A fresh cache opens with its zoom, tile list, read-only mmap mosaic and centre GSD."""
    assert store.zoom == ZOOM and store.tile_size_px == 256
    assert len(store) == store.manifest.tile_count == len(store.all_tiles()) > 10
    assert isinstance(store.mosaic, np.memmap) and not store.mosaic.flags.writeable
    assert store.mosaic.shape == tuple(store.manifest.mosaic_shape)
    lon_c, lat_c = store.center_lonlat
    w, s, e, n = store.bbox_lonlat
    assert w < lon_c < e and s < lat_c < n
    assert store.gsd_m_px == pytest.approx(156_543.034 / 2**ZOOM * math.cos(math.radians(lat_c)), rel=1e-6)


def _flip_middle_byte(cache_dir: Path) -> tuple[int, int]:
    """Flip one byte in the middle of the mosaic file (in place); return the (row, col) of its cell."""
    path, offset, shape = _mosaic_offset(cache_dir)
    ts = CacheManifest.load(cache_dir).tile_size_px
    row_px, col_px = shape[0] // 2, shape[1] // 2
    at = offset + (row_px * shape[1] + col_px) * 3 + 1
    with path.open("r+b") as f:
        f.seek(at)
        byte = f.read(1)[0]
        f.seek(at)
        f.write(bytes([byte ^ 0xFF]))
    return row_px // ts, col_px // ts


def test_full_open_refuses_a_corrupt_mosaic_byte_light_open_finds_it_on_read(
    cache_dir: Path, tmp_path: Path
) -> None:
    """One flipped byte in the middle of the mosaic: the full check refuses the cache naming the mosaic's
    sha256; the light check opens it without reading the mosaic (the byte is not found at open), and
    the first read of that cell finds it against the CRC the build recorded: nodata, counted, reported."""
    out = _copy(cache_dir, tmp_path)
    row, col = _flip_middle_byte(out)
    with pytest.raises(TileStoreError, match=rf"mosaic_z{ZOOM}\.npy.*sha256 mismatch"):
        TileStore.open(out, Verification.FULL)
    store = TileStore.open(out, Verification.LIGHT)
    assert store.verification is Verification.LIGHT
    seen: list[dict] = []
    store.on_corrupt = seen.append
    assert store.corrupt_cells == 0, "the light open looked at the mosaic's cells"
    ts, tr = store.tile_size_px, store.manifest.tile_range
    tile_id = next(t for t in store.tile_ids if store.tile_xyz(t)[:2] == (tr.x0 + col, tr.y0 + row))
    chip = store.chip(tile_id, ts)
    assert not chip.pixels().any(), "the corrupt cell reached the matcher"
    assert store.corrupt_cells == 1
    assert len(seen) == 1 and (seen[0]["x"], seen[0]["y"]) == (tr.x0 + col, tr.y0 + row)
    assert seen[0]["crc32_verified"] == int(np.load(out / store.manifest.cell_crc_name)[row, col])


def test_open_truncated_artifact_raises_even_without_hashes(cache_dir: Path, tmp_path: Path) -> None:
    """A truncated artifact is refused by its recorded size, by the light check too."""
    out = _copy(cache_dir, tmp_path)
    tiles = out / "tiles.json"
    tiles.write_bytes(tiles.read_bytes()[:-10])
    with pytest.raises(TileStoreError, match=r"tiles\.json.*bytes"):
        TileStore.open(out, Verification.LIGHT)


def test_light_open_refuses_a_mosaic_of_another_size(cache_dir: Path, tmp_path: Path) -> None:
    """A mosaic grown by a few bytes (same header) is refused by the light check, naming the file and
    both sizes, though it does not read the mosaic."""
    out = _copy(cache_dir, tmp_path)
    mosaic = out / f"mosaic_z{ZOOM}.npy"
    recorded = mosaic.stat().st_size
    with mosaic.open("ab") as f:
        f.write(b"\0" * 7)
    with pytest.raises(
        TileStoreError, match=rf"mosaic_z{ZOOM}\.npy.*{recorded + 7} bytes.*records {recorded}"
    ):
        TileStore.open(out, Verification.LIGHT)


def test_light_open_hashes_the_cell_crc_table(cache_dir: Path, tmp_path: Path) -> None:
    """The cell CRC table is small and read whole: the light check takes its sha256, so a table changed
    in place (same size) is refused, not trusted to check the mosaic."""
    out = _copy(cache_dir, tmp_path)
    name = CacheManifest.load(out).cell_crc_name
    table = np.load(out / name)
    table[0, 0] ^= 1
    np.save(out / name, table)
    with pytest.raises(TileStoreError, match=rf"{name}.*sha256 mismatch"):
        TileStore.open(out, Verification.LIGHT)


def test_tampered_manifest_is_refused_naming_the_file_and_its_hash(cache_dir: Path, tmp_path: Path) -> None:
    """A manifest edited after its build (one value changed, still valid JSON) fails its own content
    hash, at both levels, with an error naming manifest.json and the hash it records."""
    out = _copy(cache_dir, tmp_path)
    raw = json.loads((out / "manifest.json").read_text())
    raw["min_tile_valid_fraction"] = 0.25
    (out / "manifest.json").write_text(json.dumps(raw))
    for level in Verification:
        with pytest.raises(TileStoreError, match=r"content sha256 mismatch.*records .*manifest\.json"):
            TileStore.open(out, level)


def _make_old_cache(cache_dir: Path, tmp_path: Path) -> Path:
    """A copy of ``cache_dir`` as a build before the cell CRC table wrote it: no table, no manifest hash."""
    out = _copy(cache_dir, tmp_path)
    raw = json.loads((out / "manifest.json").read_text())
    name = f"mosaic_z{ZOOM}_cell_crc32.npy"
    del raw["artifacts"][name], raw["content_sha256"]
    (out / name).unlink()
    (out / "manifest.json").write_text(json.dumps(raw))
    return out


def test_old_cache_opens_with_a_warning_and_cache_build_adds_the_table(
    cache_dir: Path, tmp_path: Path
) -> None:
    """A cache built before the table opens: the table is computed at open (cells corrupted later are
    still found on read) and a warning names `gdnav cache build`; building again with the same source
    adds the table and the manifest's hash without rebuilding the mosaic."""
    out = _make_old_cache(cache_dir, tmp_path / "old")
    with structlog.testing.capture_logs() as logs:
        store = TileStore.open(out, Verification.LIGHT)
    warned = [e for e in logs if e["event"] == LogEvent.CACHE_OLD_FORMAT]
    assert len(warned) == 1 and "gdnav cache build" in warned[0]["action"]
    assert warned[0]["log_level"] == "warning"
    ts = store.tile_size_px
    tile_id = store.tiles_near(P_LAT, P_LON, 500.0, k=1)[0][0]
    x, y, _ = store.tile_xyz(tile_id)
    _overwrite_cell(out, y - store.manifest.tile_range.y0, x - store.manifest.tile_range.x0, ts, 0x5A)
    assert not store.chip(tile_id, ts).pixels().any() and store.corrupt_cells == 1

    out = _make_old_cache(cache_dir, tmp_path / "upgrade")
    mosaic = out / f"mosaic_z{ZOOM}.npy"
    mtime = mosaic.stat().st_mtime_ns
    manifest = build_cache_from_geotiff(_write_source(tmp_path), out, zoom=ZOOM, progress=False)
    assert mosaic.stat().st_mtime_ns == mtime, "the mosaic was rebuilt"
    assert manifest.has_cell_crc
    loaded = CacheManifest.load(out)
    assert loaded.has_cell_crc and loaded.content_sha256 is not None
    with structlog.testing.capture_logs() as logs:
        TileStore.open(out, Verification.LIGHT)
    assert not [e for e in logs if e["event"] == LogEvent.CACHE_OLD_FORMAT]


def test_read_by_window_names_the_windowed_artifacts() -> None:
    """The light check skips the sha256 of exactly the files read by window (the VPR names are
    c2_vpr's); the tables read whole at open are hashed."""
    from gps_denied_onboard.components.c2_vpr.retrieval import (
        VPR_DESCRIPTORS_NAME,
        VPR_INDEX_NAME,
        VPR_META_NAME,
    )
    from gps_denied_onboard.components.c2_vpr.vlad import VLAD_VOCABULARY_NAME
    from gps_denied_onboard.components.c3_matcher.tile_features import file_names
    from gps_denied_onboard.components.c10_cache_build.map_fields import field_file_names

    keypoints, descriptors, table = file_names("xfeat")
    field, field_crc = field_file_names(2)
    windowed = {f"mosaic_z{ZOOM}.npy", VPR_INDEX_NAME, VPR_DESCRIPTORS_NAME, keypoints, descriptors, field}
    whole = {f"mosaic_z{ZOOM}_cell_crc32.npy", "tiles.json", "tile_valid_fraction.npy", VPR_META_NAME}
    whole |= {VLAD_VOCABULARY_NAME, table, field_crc}
    assert all(read_by_window(n) for n in windowed)
    assert not any(read_by_window(n) for n in whole)


def test_open_missing_artifact_raises(cache_dir: Path, tmp_path: Path) -> None:
    """A deleted artifact is named in the error."""
    out = _copy(cache_dir, tmp_path)
    (out / "tile_valid_fraction.npy").unlink()
    with pytest.raises(TileStoreError, match=r"tile_valid_fraction\.npy.*missing"):
        TileStore.open(out)


def test_open_without_manifest_raises(tmp_path: Path) -> None:
    """A directory without a manifest (not a cache, or an unfinished build) is refused."""
    with pytest.raises(TileStoreError, match="no cache manifest"):
        TileStore.open(tmp_path)


def test_open_unknown_format_version_raises(cache_dir: Path, tmp_path: Path) -> None:
    """A manifest of another format version is refused with the expected version in the message."""
    out = _copy(cache_dir, tmp_path)
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["format_version"] = 2
    (out / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(TileStoreError, match="format_version 2, expected 1"):
        TileStore.open(out)


def test_tiles_near_sorted_within_radius_matches_brute_force(store: TileStore) -> None:
    """tiles_near returns exactly the tiles within the radius, nearest first, with true distances."""
    radius = 700.0
    got = store.tiles_near(P_LAT, P_LON, radius)
    lats = np.array([t.lat_deg for t in store.tile_ids])
    lons = np.array([t.lon_deg for t in store.tile_ids])
    dist = haversine_m(P_LAT, P_LON, lats, lons)
    expected = {t for t, d in zip(store.tile_ids, dist, strict=True) if d <= radius}
    assert {t for t, _ in got} == expected and len(got) >= 4
    distances = [d for _, d in got]
    assert distances == sorted(distances) and distances[-1] <= radius
    for tile_id, d in got:
        assert d == pytest.approx(
            float(haversine_m(P_LAT, P_LON, tile_id.lat_deg, tile_id.lon_deg)), abs=1e-6
        )


def test_tiles_near_k_and_empty_and_bad_radius(store: TileStore) -> None:
    """k keeps the k nearest; a far query is empty; a negative radius is a ValueError."""
    full = store.tiles_near(P_LAT, P_LON, 2_000.0)
    assert store.tiles_near(P_LAT, P_LON, 2_000.0, k=3) == full[:3]
    assert store.tiles_near(0.0, 0.0, 1_000.0) == []
    with pytest.raises(ValueError, match="radius_m"):
        store.tiles_near(P_LAT, P_LON, -1.0)


def test_tile_centre_index_breaks_ties_by_order() -> None:
    """Equal distances come back in tile order, so results are deterministic."""
    ids = (TileId.of(16, 48.0, 16.001), TileId.of(16, 48.0, 15.999), TileId.of(16, 48.0, 16.001))
    got = TileCentreIndex.from_tile_ids(ids).near(48.0, 16.0, 1_000.0)
    assert [t for t, _ in got] == [ids[0], ids[1], ids[2]]


def test_tiles_near_latency_100k_tile_centres() -> None:
    """A radius query over 100k tile centres stays fast (vectorised); prints the median latency."""
    n_side = 317
    xs, ys = np.meshgrid(np.arange(n_side), np.arange(n_side))
    lats = 48.0 + ys.ravel() * 0.002
    lons = 16.0 + xs.ravel() * 0.003
    ids = tuple(TileId.of(16, la, lo) for la, lo in zip(lats.tolist(), lons.tolist(), strict=True))
    index = TileCentreIndex.from_tile_ids(ids)
    assert len(ids) > 100_000
    times = []
    for i in range(50):
        t0 = time.perf_counter()
        got = index.near(48.3 + i * 1e-4, 16.5, 1_500.0, k=10)
        times.append(time.perf_counter() - t0)
    assert len(got) == 10
    median_ms = 1e3 * float(np.median(times))
    print(f"\ntiles_near over {len(ids)} tile centres: median {median_ms:.2f} ms (k=10, r=1.5 km)")
    assert median_ms < 50.0


def test_chip_is_readonly_verified_copy_of_mosaic(store: TileStore) -> None:
    """chip.pixels() is a (size, size, 3) uint8 read-only copy of the mmap mosaic's window (the bytes
    checked against the digests are the bytes handed out)."""
    tile_id = store.tiles_near(P_LAT, P_LON, 500.0, k=1)[0][0]
    chip = store.chip(tile_id, 400)
    pixels = chip.pixels()
    assert isinstance(chip, TilePixelsHandle) and isinstance(chip, TileChip)
    assert pixels.shape == (400, 400, 3) and pixels.dtype == np.uint8
    assert not np.shares_memory(pixels, store.mosaic)
    tr, ts = store.manifest.tile_range, store.tile_size_px
    col0, row0 = chip.origin_px[0] - tr.x0 * ts, chip.origin_px[1] - tr.y0 * ts
    assert np.array_equal(pixels, store.mosaic[row0 : row0 + 400, col0 : col0 + 400])
    assert not pixels.flags.writeable
    assert chip.tile_id == tile_id
    assert store.corrupt_cells == 0


def _mosaic_offset(cache_dir: Path) -> tuple[Path, int, tuple[int, ...]]:
    """(mosaic path, byte offset of pixel (0, 0), shape) of a cache's .npy mosaic."""
    path = cache_dir / CacheManifest.load(cache_dir).mosaic_name
    arr = np.load(path, mmap_mode="r")
    return path, int(arr.offset), tuple(arr.shape)


def _overwrite_cell(cache_dir: Path, row: int, col: int, ts: int, value: int) -> None:
    """Write ``value`` into every byte of mosaic cell (row, col) in place (the daemon's mapping sees it),
    as a failing flash page or another process would."""
    path, offset, shape = _mosaic_offset(cache_dir)
    width = shape[1]
    with path.open("r+b") as f:
        for r in range(row * ts, (row + 1) * ts):
            f.seek(offset + (r * width + col * ts) * 3)
            f.write(bytes([value]) * (ts * 3))


def test_chip_masks_a_cell_corrupted_after_open_and_reports_it_once(cache_dir: Path, tmp_path: Path) -> None:
    """A cell whose bytes change on disk after the cache was verified reads as nodata in every chip that
    covers it, is reported once (log + listener) and stays masked after its bytes come back; chips that
    do not cover it are unchanged."""
    out = _copy(cache_dir, tmp_path)
    store = TileStore.open(out)
    seen: list[dict] = []
    store.on_corrupt = seen.append
    ts = store.tile_size_px
    tile_id = store.tiles_near(P_LAT, P_LON, 500.0, k=1)[0][0]
    x, y, _ = store.tile_xyz(tile_id)
    row, col = y - store.manifest.tile_range.y0, x - store.manifest.tile_range.x0
    before = np.array(store.chip(tile_id, ts).pixels())
    assert before.any()
    original = np.array(store.mosaic[row * ts : (row + 1) * ts, col * ts : (col + 1) * ts])
    _overwrite_cell(out, row, col, ts, 0x5A)
    assert (store.mosaic[row * ts, col * ts] == 0x5A).all(), "the mapping does not see the file"
    chip = store.chip(tile_id, ts)
    assert not chip.pixels().any(), "corrupt pixels reached the matcher"
    assert store.corrupt_cells == 1
    assert len(seen) == 1 and (seen[0]["x"], seen[0]["y"], seen[0]["zoom"]) == (x, y, store.zoom)
    assert seen[0]["crc32_read"] != seen[0]["crc32_verified"]
    big = store.chip(tile_id, 3 * ts).pixels()  # covers the cell and its neighbours
    assert not big[ts : 2 * ts, ts : 2 * ts].any() and big[:ts].any()
    assert len(seen) == 1, "one corruption reported twice"
    # the bytes come back: the cell stays untrusted for the rest of the run
    path, offset, shape = _mosaic_offset(out)
    with path.open("r+b") as f:
        for r in range(ts):
            f.seek(offset + ((row * ts + r) * shape[1] + col * ts) * 3)
            f.write(original[r].tobytes())
    assert not store.chip(tile_id, ts).pixels().any()
    # a chip away from the cell is exact
    far = max(store.tile_ids, key=lambda t: abs(store.tile_xyz(t)[0] - x) + abs(store.tile_xyz(t)[1] - y))
    far_chip = store.chip(far, ts)
    fx, fy, _ = store.tile_xyz(far)
    fr, fc = fy - store.manifest.tile_range.y0, fx - store.manifest.tile_range.x0
    assert np.array_equal(far_chip.pixels(), store.mosaic[fr * ts : (fr + 1) * ts, fc * ts : (fc + 1) * ts])


def test_open_and_chip_measure_the_check_cost(store: TileStore, cache_dir: Path) -> None:
    """The light open reads the manifest and the small tables, the full one every byte; a verified chip
    costs one copy and a CRC of the cells it covers (prints the figures for docs/benchmarks.md)."""
    t0 = time.perf_counter()
    TileStore.open(cache_dir, Verification.FULL)
    full_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    TileStore.open(cache_dir, Verification.LIGHT)
    elapsed = time.perf_counter() - t0
    mib = store.mosaic.nbytes / 2**20
    tile_id = store.tiles_near(P_LAT, P_LON, 500.0, k=1)[0][0]
    t0 = time.perf_counter()
    for _ in range(50):
        store.chip(tile_id, 512)
    chip_ms = (time.perf_counter() - t0) / 50 * 1e3
    print(
        f"\nlight open: {elapsed * 1e3:.1f} ms, full open: {full_s * 1e3:.1f} ms for {mib:.1f} MiB; "
        f"verified 512 px chip: {chip_ms:.2f} ms"
    )
    assert store.corrupt_cells == 0


def test_chip_georeference_round_trips_below_0_01_px(store: TileStore) -> None:
    """chip px -> lon/lat -> chip px round-trips to < 0.01 px, and the chip centre is the tile centre."""
    tile_id = store.tiles_near(P_LAT, P_LON, 500.0, k=1)[0][0]
    chip = store.chip(tile_id, 512)
    px = np.random.default_rng(2).uniform(0, 511, size=(200, 2))
    lon, lat = chip.chip_px_to_lonlat(px)
    assert np.abs(chip.lonlat_to_chip_px(lon, lat) - px).max() < 0.01
    centre = chip.lonlat_to_chip_px(np.array([tile_id.lon_deg]), np.array([tile_id.lat_deg]))[0]
    assert np.allclose(centre, [255.5, 255.5], atol=0.05)
    assert chip.gsd_m_px == pytest.approx(store.grid.gsd_m_px(tile_id.lat_deg), rel=1e-4)


def test_chip_pixels_agree_with_mosaic_lookup(store: TileStore) -> None:
    """The chip pixel at a lon/lat is the mosaic pixel at the same lon/lat."""
    tile_id = store.tile_ids[len(store) // 2]
    chip = store.chip(tile_id, 300)
    lon, lat = chip.chip_px_to_lonlat(np.array([[17.0, 203.0]]))
    mosaic_px = store.lonlat_to_mosaic_px(lon, lat)[0].round().astype(int)
    assert np.array_equal(chip.pixels()[203, 17], store.mosaic[mosaic_px[1], mosaic_px[0]])
    back_lon, back_lat = store.mosaic_px_to_lonlat(store.lonlat_to_mosaic_px(lon, lat))
    assert back_lon == pytest.approx(lon, abs=1e-10) and back_lat == pytest.approx(lat, abs=1e-10)


def test_chip_near_mosaic_edge_stays_inside(store: TileStore) -> None:
    """A chip around a corner tile is shifted to lie fully inside the mosaic."""
    height, width = store.mosaic.shape[:2]
    corner = max(store.tile_ids, key=lambda t: (t.lon_deg, -t.lat_deg))  # east-most, then south-most
    chip = store.chip(corner, 600)
    x0 = chip.origin_px[0] - store.manifest.tile_range.x0 * 256
    y0 = chip.origin_px[1] - store.manifest.tile_range.y0 * 256
    assert chip.pixels().shape == (600, 600, 3)
    assert 0 <= x0 <= width - 600 and 0 <= y0 <= height - 600
    assert x0 == width - 600


def test_chip_larger_than_mosaic_uses_whole_extent(store: TileStore) -> None:
    """A chip larger than the mosaic spans the whole mosaic in that dimension."""
    height, width = store.mosaic.shape[:2]
    chip = store.chip(store.tile_ids[0], max(height, width) + 100)
    assert chip.pixels().shape == (height, width, 3)
    assert chip.size_px == (width, height)


def test_chip_valid_fraction_reflects_nodata(store: TileStore) -> None:
    """A chip over the western nodata border has valid_fraction < 1; an interior one has 1."""
    west = min(store.tile_ids, key=lambda t: (t.lon_deg, t.lat_deg))
    assert store.chip(west, 512).valid_fraction < 0.95
    interior = store.tiles_near(P_LAT, P_LON + 0.005, 300.0, k=1)[0][0]
    assert store.chip(interior, 128).valid_fraction == 1.0


def test_chip_unknown_tile_raises(store: TileStore) -> None:
    """Asking for a tile that is not in the cache is a TileStoreError naming it."""
    with pytest.raises(TileStoreError, match="not a valid tile"):
        store.chip(TileId.of(ZOOM, 0.0, 0.0), 256)


def test_chip_around_is_centred_on_the_ground_point(store: TileStore) -> None:
    """A chip around a ground point has that point at its centre pixel, the mosaic's pixels, and the id
    of the tile whose centre is nearest; a tile's own centre gives the tile's chip."""
    height, width = store.mosaic.shape[:2]
    lon_a, lat_a = store.mosaic_px_to_lonlat(np.array([width * 0.6 + 0.3, height * 0.5 - 0.2]))
    lat, lon = float(lat_a), float(lon_a)
    chip = store.chip_around(lat, lon, 300)
    assert chip is not None
    centre = chip.lonlat_to_chip_px(np.array([lon]), np.array([lat]))[0]
    assert np.abs(centre - 149.5).max() <= 1.0  # the window starts on a whole pixel
    assert chip.tile_id == store.tiles_near(lat, lon, 1000.0, k=1)[0][0]
    lon_px, lat_px = chip.chip_px_to_lonlat(np.array([[10.0, 250.0]]))
    mosaic_px = store.lonlat_to_mosaic_px(lon_px, lat_px)[0].round().astype(int)
    assert np.array_equal(chip.pixels()[250, 10], store.mosaic[mosaic_px[1], mosaic_px[0]])
    tile_id = store.tile_ids[len(store) // 2]
    own = store.chip_around(tile_id.lat_deg, tile_id.lon_deg, 512)
    assert own is not None and own.origin_px == store.chip(tile_id, 512).origin_px


def test_chip_around_off_the_mosaic_is_none_and_near_its_edge_stays_inside(store: TileStore) -> None:
    """A point off the map gives no chip; one near its edge gives a chip shifted inside, like ``chip``."""
    west, south, east, north = store.bbox_lonlat
    assert store.chip_around(north + 0.05, east + 0.05, 256) is None
    width = store.mosaic.shape[1]
    chip = store.chip_around((south + north) / 2.0, east - 1e-5, 256)
    assert chip is not None and chip.pixels().shape == (256, 256, 3)
    assert chip.origin_px[0] - store.manifest.tile_range.x0 * 256 == width - 256
    with pytest.raises(ValueError, match="size_px"):
        store.chip_around(south, west, 0)
