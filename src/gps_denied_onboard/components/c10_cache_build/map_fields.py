"""C10: the map's orientation fields and their calibration, for the area correlation (``orientation_corr``).

``gdnav cache build`` adds them to every cache it builds; ``gdnav cache fields`` adds them to an existing
one. A fix then does no map-side work: it reads a window of the fields (``c6_tiles/map_fields.py``).

**Files.** Per pyramid level (1: the mosaic's pixels; each level down half the resolution; three levels, so
that a fix can work at level 1 or 2 with the next one as its coarse level), ``field_l{L}.npy``: the
field of ``helpers/orientation_field.py`` quantised to (H, W, 2) int8, nodata marked; and
``field_l{L}_crc.npy``: the CRC-32 of every cell (one map tile: ``tile_size_px / 2**(L-1)`` px square),
taken as the field was written, so that the daemon checks what it reads without reading the whole map at
start-up. Both are listed in the manifest's ``map_fields`` block with their sizes and sha256, and the
block names the field definition (``FIELD_VERSION``) and the mosaic they were made from.

**Computed in bands** of ``BAND_ROWS`` rows with ``HALO_ROWS`` of context above and below: every kernel of
the field (blur, Sobel, the neighbourhood mean, the footprint margin) reaches fewer rows than the halo at
every level (the neighbourhood mean's 32 px at level 3 are 128 rows of the mosaic), so the result is the
same bytes as over the whole mosaic at once, in bounded memory.

**Calibration.** How strongly a right place and a wrong place answer on *this* map, measured on the map
itself, at each working level (1 and 2) the map has room for: ``CALIBRATION_SAMPLES`` templates of
``CALIBRATION_TEMPLATE_PX`` px of that level cut where the map has data, degraded like a frame (gain,
gamma, blur, noise: ``_degrade``), are searched in a disc of the largest radius the daemon searches
(``orientation_corr.MAX_RADIUS_PX``, or what fits the map): once with the truth inside the disc and once
with it outside. The daemon works at the level that keeps its footprint near the calibration's size, so
the statistics compare like with like whatever the map's resolution. The wrong places' peak-to-sidelobe
ratios and peaks are the level a real fix must clear (the integrity rule's ``min_psr`` and ``min_peak`` are
raised to a margin over them, ``c4_pose/integrity.py``); the right ones tell whether the map has the
structure to be found at all.
Templates from the map are kinder than frames from another date, so ``right_*`` is an upper bound; the
``null_*`` figures are what matters, and a wrong place is a wrong place whatever the date. The samples
come from a seeded generator: the same map gives the same calibration.

Crash safety as for tile features: the manifest is first rewritten without the block, the files are
streamed to temporary names, fsynced and renamed, then the block is written; the calibration is added in
a last manifest write. An interrupted build leaves a cache that verifies, with no fields or with fields
not yet calibrated (``orientation_corr`` refuses both and says which).
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
import zlib
from functools import partial
from pathlib import Path
from typing import Final

import cv2
import numpy as np
import structlog
from tqdm import tqdm

from gps_denied_onboard.components.c3_matcher.area_search import (
    FieldWindowSource,
    LevelView,
    Template,
    search,
)
from gps_denied_onboard.components.c6_tiles.map_fields import FIELD_LEVELS
from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.components.c6_tiles.types import TileStoreError
from gps_denied_onboard.components.c10_cache_build.manifest import (
    CacheBuildError,
    CacheManifest,
    CacheManifestError,
    FieldCalibration,
    MapFieldsInfo,
    Verification,
)
from gps_denied_onboard.components.c10_cache_build.npy_stream import NpyStream
from gps_denied_onboard.components.c10_cache_build.shards import (
    EngineSpec,
    ShardEngine,
    build_timestamp_utc,
    engine_scope,
    run_ordered,
)
from gps_denied_onboard.constants import LogEvent
from gps_denied_onboard.helpers.orientation_field import (
    FIELD_VERSION,
    downsample2,
    grey_of,
    orientation_field,
    quantise,
)

_log = structlog.get_logger(__name__)

#: Pyramid levels stored (1: the mosaic's pixels, each next one half the resolution): what C6 reads.
LEVELS: Final = FIELD_LEVELS
#: Working levels calibrated (a working level's coarse search runs one level down).
WORKING_LEVELS: Final = (1, 2)
#: Rows computed at once, and the context rows read above and below them (multiples of 4: the levels align).
BAND_ROWS: Final = 1024
HALO_ROWS: Final = 192
#: Templates per calibration (each searched twice: truth inside, truth outside the disc).
CALIBRATION_SAMPLES: Final = 24
#: Calibration template, level-1 px (width, height): the footprint of a 4:3 frame; smaller on a small map.
CALIBRATION_TEMPLATE_PX: Final = (256, 192)
#: Largest disc calibrated, level-1 px (``orientation_corr.MAX_RADIUS_PX``; kept in step by a test).
CALIBRATION_RADIUS_PX: Final = 192.0
#: Smallest disc worth calibrating, level-1 px (``orientation_corr.MIN_RADIUS_PX``).
CALIBRATION_MIN_RADIUS_PX: Final = 48.0
_SEED: Final = 20261128


def field_file_names(level: int) -> tuple[str, str]:
    """(field file, CRC file) of ``level``."""
    return f"field_l{level}.npy", f"field_l{level}_crc.npy"


@dataclasses.dataclass(frozen=True)
class MapFieldsBuild:
    """What ``build_map_fields`` did: the manifest after it, and whether it built (False = up to date)."""

    manifest: CacheManifest
    built: bool
    calibrated: bool


def build_map_fields(
    cache_dir: Path,
    *,
    force: bool = False,
    progress: bool = True,
    engine: EngineSpec | ShardEngine | None = None,
) -> MapFieldsBuild:
    """Add (or confirm up to date) the orientation fields and their calibration in the cache at
    ``cache_dir``. The fields' bands run on ``engine`` (``shards``: None in this process); the bytes are
    the same whatever it is. Raises ``CacheBuildError`` for a cache that does not verify or a write that
    fails."""
    cache_dir = Path(cache_dir)
    try:
        store = TileStore.open(cache_dir, Verification.FULL)
    except TileStoreError as exc:
        raise CacheBuildError(f"cache does not verify: {exc}", path=str(cache_dir)) from exc
    manifest = store.manifest
    mosaic_sha = manifest.artifacts[manifest.mosaic_name].sha256
    existing = manifest.map_fields
    t0 = time.monotonic()
    if existing is None or force or not _intact(existing, cache_dir, mosaic_sha):
        base = dataclasses.replace(manifest, map_fields=None)
        try:
            base.save(cache_dir)
            info = _write_fields(store, cache_dir, mosaic_sha, engine, progress)
            manifest = dataclasses.replace(base, map_fields=info)
            manifest.save(cache_dir)
        except OSError as exc:
            raise CacheBuildError(f"cannot write the map fields: {exc}", path=str(cache_dir)) from exc
        built = True
    else:
        info = existing
        built = False
    if not info.calibrated:
        from gps_denied_onboard.components.c6_tiles.map_fields import MapFields

        fields = MapFields.open(store, info, Verification.LIGHT)  # hashed just above or in _intact
        found = {level: calibrate(store, fields, level) for level in WORKING_LEVELS}
        calibrations = {level: c for level, c in found.items() if c is not None}
        info = dataclasses.replace(info, calibrations=calibrations, calibrated=True)
        manifest = dataclasses.replace(manifest, map_fields=info)
        try:
            manifest.save(cache_dir)
        except OSError as exc:
            raise CacheBuildError(f"cannot write the cache manifest: {exc}", path=str(cache_dir)) from exc
        built = True
    if built:
        _log.info(
            LogEvent.MAP_FIELDS_BUILT,
            cache_dir=str(cache_dir),
            version=info.version,
            bytes=sum(f.bytes for f in info.files.values()),
            calibrations={level: c.to_json() for level, c in info.calibrations.items()},
            seconds=round(time.monotonic() - t0, 2),
        )
    else:
        _log.info(LogEvent.MAP_FIELDS_UP_TO_DATE, cache_dir=str(cache_dir), version=info.version)
    return MapFieldsBuild(manifest, built, bool(info.calibrations))


def _intact(info: MapFieldsInfo, cache_dir: Path, mosaic_sha: str) -> bool:
    if info.version != FIELD_VERSION or info.mosaic_sha256 != mosaic_sha:
        return False
    if set(info.levels) != set(LEVELS):
        return False
    try:
        info.verify_files(cache_dir, Verification.FULL)
    except CacheManifestError:
        return False
    return True


def level_fields(grey: np.ndarray, valid: np.ndarray) -> dict[int, np.ndarray]:
    """The quantised field of every level of one image: level -> (H_L, W_L, 2) int8."""
    out: dict[int, np.ndarray] = {}
    g, v = grey, valid
    for level in LEVELS:
        if level > 1:
            g, v = downsample2(g, v)
        z, _ = orientation_field(g, v)
        out[level] = quantise(z, v)
    return out


def band_fields(mosaic_path: str, rows_px: tuple[int, int]) -> dict[int, np.ndarray]:
    """Mosaic rows ``rows_px`` = (r0, r1) of every level's field (level -> (rows, W_L, 2) int8), computed
    over the band and its halo: the same bytes as over the whole map.

    Runs in any process (a Dask worker of the build included): it reads the mosaic at ``mosaic_path``.
    """
    r0, r1 = rows_px
    mosaic = np.load(mosaic_path, mmap_mode="r")
    height = mosaic.shape[0]
    # r0 is a multiple of 4 rows from the top, so every level's rows align with the whole map's.
    a, b = max(0, r0 - HALO_ROWS), min(height, r1 + HALO_ROWS)
    band = np.asarray(mosaic[a:b])
    fields = level_fields(grey_of(band), np.asarray(band.any(axis=2), dtype=bool))
    return {
        level: np.ascontiguousarray(f[(r0 - a) >> (level - 1) : (r1 - a) >> (level - 1)])
        for level, f in fields.items()
    }


def _write_fields(
    store: TileStore,
    cache_dir: Path,
    mosaic_sha: str,
    engine: EngineSpec | ShardEngine | None = None,
    progress: bool = False,
) -> MapFieldsInfo:
    mosaic = store.mosaic
    height, width = mosaic.shape[:2]
    cell1 = store.tile_size_px
    streams = {level: NpyStream(cache_dir / field_file_names(level)[0]) for level in LEVELS}
    crcs = {level: [] for level in LEVELS}  # type: dict[int, list[np.ndarray]]
    pending = {level: np.empty((0, width >> (level - 1), 2), np.int8) for level in LEVELS}
    bands = [(r0, min(r0 + BAND_ROWS, height)) for r0 in range(0, height, BAND_ROWS)]
    work = partial(band_fields, str(cache_dir / store.manifest.mosaic_name))
    show = progress and sys.stderr.isatty()
    try:
        with (
            engine_scope(engine) as runner,
            tqdm(total=len(bands), unit="band", desc="orientation fields", disable=not show) as bar,
        ):
            # The bands are computed on the engine and streamed here in order.
            for (_, r1), fields in zip(bands, run_ordered(runner, work, bands), strict=True):
                bar.update(1)
                for level, rows in fields.items():
                    s = level - 1
                    streams[level].append(rows)
                    # CRC per cell, over whole rows of cells as they complete.
                    cell = cell1 >> s
                    pending[level] = np.concatenate([pending[level], rows])
                    while pending[level].shape[0] >= cell or (r1 == height and pending[level].shape[0]):
                        strip, pending[level] = pending[level][:cell], pending[level][cell:]
                        crcs[level].append(_strip_crcs(strip, cell))
        files = {}
        levels = {}
        for level in LEVELS:
            h_l, w_l = height >> (level - 1), width >> (level - 1)
            field_name, crc_name = field_file_names(level)
            files[field_name] = streams[level].finish(np.dtype(np.int8), (h_l, w_l, 2))
            table = np.stack(crcs[level]) if crcs[level] else np.zeros((0, 0), np.uint32)
            crc_stream = NpyStream(cache_dir / crc_name)
            crc_stream.append(table)
            files[crc_name] = crc_stream.finish(np.dtype(np.uint32), table.shape)
            levels[level] = (field_name, crc_name, cell1 >> (level - 1))
    finally:
        for stream in streams.values():
            stream.discard()
    return MapFieldsInfo(
        version=FIELD_VERSION,
        mosaic_sha256=mosaic_sha,
        levels=levels,
        files=files,
        stats={"created_utc": build_timestamp_utc()},
    )


def _strip_crcs(strip: np.ndarray, cell: int) -> np.ndarray:
    """CRC-32 of each ``cell``-wide block of one strip of rows (the last may be narrower)."""
    cols = -(-strip.shape[1] // cell)
    return np.array(
        [zlib.crc32(np.ascontiguousarray(strip[:, c * cell : (c + 1) * cell]).data) for c in range(cols)],
        dtype=np.uint32,
    )


class _RowMajorTrue:
    """The positions of a boolean image's true pixels in row-major order, as ``np.argwhere`` lists them,
    without listing them: ``self[k]`` is ``tuple(np.argwhere(mask)[k])`` from per-row counts (argwhere
    over a 4,000-tile map took 14 s and 3.6 GB)."""

    def __init__(self, mask: np.ndarray) -> None:
        self._mask = mask
        self._ends = np.cumsum(np.count_nonzero(mask, axis=1))

    def __len__(self) -> int:
        return int(self._ends[-1]) if self._ends.size else 0

    def __getitem__(self, k: int) -> tuple[int, int]:
        row = int(np.searchsorted(self._ends, k, side="right"))
        before = int(self._ends[row - 1]) if row else 0
        return row, int(np.flatnonzero(self._mask[row])[k - before])


def _degrade(grey: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``grey`` as another camera on another day might give it: gain, gamma, a slight blur, noise."""
    gained = np.clip(grey * rng.uniform(0.85, 1.15), 0.0, 255.0)
    curved = (255.0 * (gained / 255.0) ** rng.uniform(0.8, 1.25)).astype(np.float32)
    blurred = cv2.GaussianBlur(curved, (0, 0), 0.7)
    return (blurred + rng.normal(0.0, 4.0, blurred.shape)).astype(np.float32)


def calibrate(store: TileStore, fields: FieldWindowSource, level: int) -> FieldCalibration | None:
    """The map's calibration at working ``level`` (module docstring); None when the map has no room
    there for one template and a disc of ``CALIBRATION_MIN_RADIUS_PX`` around it."""
    f = 2 ** (level - 1)
    mosaic = store.mosaic
    valid1 = np.asarray(np.asarray(mosaic).any(axis=2), dtype=bool)
    valid = valid1
    for _ in range(level - 1):
        valid = downsample2(np.zeros(valid.shape, np.float32), valid)[1]
    valid = np.asarray(valid, dtype=np.uint8)
    height, width = valid.shape[:2]
    tw, th = CALIBRATION_TEMPLATE_PX
    # A smaller template on a small map: at most a third of its valid extent.
    # The valid extent from the rows and columns that hold data (not every valid pixel's coordinates:
    # those were 3.6 GB and 16 s on a 4,000-tile map).
    rows_with_data, cols_with_data = np.flatnonzero(valid.any(axis=1)), np.flatnonzero(valid.any(axis=0))
    if rows_with_data.size == 0:
        return None
    extent_x = int(cols_with_data[-1] - cols_with_data[0] + 1)
    extent_y = int(rows_with_data[-1] - rows_with_data[0] + 1)
    scale = min(1.0, extent_x / (3.0 * tw), extent_y / (3.0 * th))
    tw, th = max(32, int(tw * scale)), max(24, int(th * scale))
    radius = min(CALIBRATION_RADIUS_PX, (min(extent_x, extent_y) - max(tw, th)) / 4.0)
    if radius < CALIBRATION_MIN_RADIUS_PX:
        return None
    rng = np.random.default_rng(_SEED)
    # Where a template lies wholly on map data: its top-left corner in the summed-area table.
    sat = cv2.integral(valid)
    ok = (sat[th:, tw:] - sat[:-th, tw:] - sat[th:, :-tw] + sat[:-th, :-tw]) == tw * th
    corners = _RowMajorTrue(ok[: height - th + 1, : width - tw + 1])
    if len(corners) == 0:
        return None
    null_psr: list[float] = []
    null_peak: list[float] = []
    right_psr: list[float] = []
    right_peak: list[float] = []
    texture: list[float] = []
    attempts = 0
    while len(texture) < CALIBRATION_SAMPLES and attempts < 4 * CALIBRATION_SAMPLES:
        attempts += 1
        y0, x0 = corners[int(rng.integers(len(corners)))]
        grey = grey_of(np.asarray(mosaic[y0 * f : (y0 + th) * f, x0 * f : (x0 + tw) * f]))
        cut = np.ones(grey.shape, bool)
        for _ in range(level - 1):
            grey, cut = downsample2(grey, cut)
        template = Template(_degrade(grey, rng), np.ones((th, tw), bool), ((tw - 1) / 2.0, (th - 1) / 2.0))
        truth = (x0 + (tw - 1) / 2.0, y0 + (th - 1) / 2.0)
        a = rng.uniform(0.0, 2.0 * math.pi)
        d_right = rng.uniform(0.0, 0.7) * radius
        d_null = rng.uniform(1.3, 2.5) * radius
        view = LevelView(fields, level)
        right = search(
            template,
            view,
            (truth[0] + d_right * math.cos(a), truth[1] + d_right * math.sin(a)),
            radius,
        )
        null = search(
            template,
            view,
            (truth[0] + d_null * math.cos(a), truth[1] + d_null * math.sin(a)),
            radius,
        )
        if right is None or null is None:
            continue
        right_psr.append(right.psr)
        right_peak.append(right.peak)
        null_psr.append(null.psr)
        null_peak.append(null.peak)
        texture.append(right.texture)
    if len(texture) < CALIBRATION_SAMPLES // 2:
        return None
    return FieldCalibration(
        level=level,
        samples=len(texture),
        radius_px=float(radius),
        template_px=(tw, th),
        null_psr_max=round(float(np.max(null_psr)), 3),
        null_psr_p95=round(float(np.percentile(null_psr, 95)), 3),
        null_peak_max=round(float(np.max(null_peak)), 4),
        right_psr_p5=round(float(np.percentile(right_psr, 5)), 3),
        right_peak_p5=round(float(np.percentile(right_peak, 5)), 4),
        texture_p50=round(float(np.median(texture)), 4),
    )
