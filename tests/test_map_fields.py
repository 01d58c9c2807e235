"""The map's orientation fields in the cache: built (``c10_cache_build/map_fields.py``), calibrated, and read
back by window with every cell checked (``c6_tiles/map_fields.py``). Real caches built from the procedural
demo map; the files are changed on disk to fault them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import gps_denied_onboard.components.c10_cache_build.map_fields as builder
from gps_denied_onboard.components.c6_tiles.map_fields import FIELD_LEVELS, MapFields, MapFieldsRefused
from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.components.c10_cache_build import build_cache_from_geotiff
from gps_denied_onboard.components.c10_cache_build.manifest import MANIFEST_NAME, Verification, content_sha256
from gps_denied_onboard.components.c10_cache_build.map_fields import (
    LEVELS,
    build_map_fields,
    field_file_names,
    level_fields,
)
from gps_denied_onboard.helpers.orientation_field import NODATA, dequantise, grey_of
from gps_denied_onboard.sitl.demo_map import generate_demo_map


@pytest.fixture(scope="module")
def demo_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("fields")
    tif = generate_demo_map(root / "map.tif", size_m=1600.0, gsd_m=0.5)
    cache = root / "cache"
    build_cache_from_geotiff(tif, cache, progress=False)
    build_map_fields(cache, progress=False)
    return cache


def _copy(src: Path, dst: Path) -> Path:
    dst.mkdir(parents=True)
    for f in src.iterdir():
        (dst / f.name).write_bytes(f.read_bytes())
    return dst


def test_the_levels_c10_writes_are_the_levels_c6_reads() -> None:
    assert tuple(LEVELS) == tuple(FIELD_LEVELS) == (1, 2, 3)


def test_a_built_cache_lists_its_fields_and_a_calibration_where_right_beats_wrong(demo_cache: Path) -> None:
    info = TileStore.open(demo_cache).manifest.map_fields
    assert info is not None and info.calibrated
    assert set(info.levels) == {1, 2, 3}
    for level in LEVELS:
        field_name, crc_name, _ = info.levels[level]
        assert {field_name, crc_name} <= set(info.files)
    assert set(info.calibrations) == {1, 2}
    assert all(c.samples >= 12 and c.level == level for level, c in info.calibrations.items())
    # The demo map's striped fields repeat at its own 0.5 m (a wrong place can score nearly as high as a
    # right one at level 1); one level down the stripes wash out and a right place stands far out of what
    # a wrong place scores. The calibration must show both: it is how the daemon chooses its level.
    l1, l2 = info.calibrations[1], info.calibrations[2]
    assert l2.right_psr_p5 > 2.0 * l2.null_psr_max and l2.right_peak_p5 > 2.0 * l2.null_peak_max
    assert l2.right_psr_p5 / l2.null_psr_max > 1.5 * (l1.right_psr_p5 / l1.null_psr_max)


def test_fields_built_in_bands_are_the_bytes_of_the_whole_map(
    demo_cache: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Bounded memory does not change a byte: a 256-row band with its halo gives what the whole map does."""
    cache = _copy(demo_cache, tmp_path / "cache")
    monkeypatch.setattr(builder, "BAND_ROWS", 256)
    build_map_fields(cache, force=True, progress=False)
    store = TileStore.open(cache)
    mosaic = np.asarray(store.mosaic)
    whole = level_fields(grey_of(mosaic), mosaic.any(axis=2))
    for level in LEVELS:
        banded = np.load(cache / field_file_names(level)[0])
        assert np.array_equal(banded, whole[level]), f"level {level}"


def test_building_again_is_a_no_op_and_force_rebuilds(demo_cache: Path, tmp_path: Path) -> None:
    cache = _copy(demo_cache, tmp_path / "cache")
    before = (cache / MANIFEST_NAME).read_bytes()
    again = build_map_fields(cache, progress=False)
    assert not again.built and (cache / MANIFEST_NAME).read_bytes() == before
    forced = build_map_fields(cache, force=True, progress=False)
    assert forced.built and forced.calibrated


def test_a_window_reads_the_fields_and_off_the_map_is_nodata(demo_cache: Path) -> None:
    store = TileStore.open(demo_cache)
    fields = MapFields.open(store)
    expected, expected_valid = dequantise(np.load(demo_cache / field_file_names(2)[0]))
    z, valid = fields.window(2, 100, 120, 64, 48)
    assert np.array_equal(z, expected[120:168, 100:164]) and np.array_equal(
        valid, expected_valid[120:168, 100:164]
    )
    z, valid = fields.window(1, -10, -5, 20, 10)
    assert not valid[:5].any() and not valid[:, :10].any() and not z[:5].any()


def test_a_cell_corrupted_after_open_reads_as_nodata_and_is_reported_once(
    demo_cache: Path, tmp_path: Path
) -> None:
    cache = _copy(demo_cache, tmp_path / "cache")
    store = TileStore.open(cache)
    fields = MapFields.open(store)
    reports: list[dict] = []
    fields.on_corrupt = reports.append
    cell = store.tile_size_px
    path = cache / field_file_names(1)[0]
    mapped = np.load(path, mmap_mode="r")
    rows, cols = mapped.shape[0] // cell, mapped.shape[1] // cell
    r, c = rows // 2, cols // 2  # a cell inside the map
    assert fields.window(1, c * cell, r * cell, cell, cell)[1].all()
    # Flip bytes of that cell on disk, under the memory map.
    offset = mapped.offset + ((r * cell + 7) * mapped.shape[1] + c * cell + 5) * 2  # type: ignore[attr-defined]
    with open(path, "r+b") as fh:
        fh.seek(offset)
        raw = fh.read(8)
        fh.seek(offset)
        fh.write(bytes(b ^ 0x55 for b in raw))
    z, valid = fields.window(1, c * cell - 4, r * cell, cell + 8, 16)
    assert not valid[:, 4:-4].any() and not z[:, 4:-4].any()
    assert valid[:, :4].all() and valid[:, -4:].all()  # the cells beside it are intact
    fields.window(1, c * cell, r * cell, 8, 8)
    assert len(reports) == 1 and (reports[0]["level"], reports[0]["row"], reports[0]["col"]) == (1, r, c)
    assert fields.corrupt_cells == 1


def test_fields_of_another_mosaic_or_definition_or_none_are_refused(demo_cache: Path, tmp_path: Path) -> None:
    # Each manifest below is hashed afresh, as a build that wrote it would (an edit alone fails the
    # manifest's own hash before the fields are looked at).
    cache = _copy(demo_cache, tmp_path / "cache")
    manifest_path = cache / MANIFEST_NAME

    def write(payload: dict) -> None:
        payload["content_sha256"] = content_sha256(payload)
        manifest_path.write_text(json.dumps(payload))

    payload = json.loads(manifest_path.read_text())
    payload["map_fields"]["mosaic_sha256"] = "0" * 64
    write(payload)
    with pytest.raises(MapFieldsRefused, match="another mosaic"):
        MapFields.open(TileStore.open(cache))
    payload["map_fields"]["version"] = "orientation-v0"
    write(payload)
    with pytest.raises(MapFieldsRefused, match="definition 'orientation-v0'"):
        MapFields.open(TileStore.open(cache))
    payload["map_fields"] = None
    write(payload)
    with pytest.raises(MapFieldsRefused, match="gdnav cache fields") as excinfo:
        MapFields.open(TileStore.open(cache))
    assert excinfo.value.absent


def test_a_truncated_field_file_is_refused_by_its_recorded_size(demo_cache: Path, tmp_path: Path) -> None:
    cache = _copy(demo_cache, tmp_path / "cache")
    path = cache / field_file_names(3)[0]
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(MapFieldsRefused, match="truncated or replaced"):
        MapFields.open(TileStore.open(cache), verification=Verification.LIGHT)


def test_a_map_too_small_for_a_calibration_gets_fields_but_no_calibration(tmp_path: Path) -> None:
    tif = generate_demo_map(tmp_path / "small.tif", size_m=100.0, gsd_m=0.5)
    cache = tmp_path / "cache"
    build_cache_from_geotiff(tif, cache, progress=False)
    result = build_map_fields(cache, progress=False)
    info = result.manifest.map_fields
    assert info is not None and info.calibrated and not info.calibrations and not result.calibrated
    # Nodata outside the map's footprint is marked in every level.
    level3 = np.load(cache / field_file_names(3)[0])
    assert (level3[..., 0] == NODATA).any()
