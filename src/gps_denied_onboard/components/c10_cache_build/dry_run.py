"""C10: what a GeoTIFF cache build would make and how long it would take, without building it
(``gdnav cache build --dry-run``).

**Sizes** are exact for every ``.npy`` artifact (its header and its shape follow from the tile range) and
an upper bound for ``tiles.json`` (every tile of the range listed; the build drops map gaps).

**Times** come from small timed samples taken here, on this machine, never from a table:

- the source's and the artifacts' sha256 from hashing ``_HASH_SAMPLE_BYTES`` in memory;
- the mosaic from warping ``sample_shards`` real shards of the plan (the middle ones) with the
  build's own worker function, divided by the number of workers (the shards are independent);
- the orientation fields from computing them over the sampled shards' pixels, divided by the number of
  workers (the bands are independent), plus hashing the mosaic and the fields;
- two stages are stated, not sampled: a local cluster's start and stop (``CLUSTER_START_S_STATED``), and
  the calibration (``CALIBRATION_*_STATED``: a fixed number of template searches plus passes over the
  valid mask), each measured on CPU-A (docs/benchmarks.md, "Mission scale: the distributed build").

The parallel stages are divided by the number of workers as if each had a core of its own; on a machine
whose cores others use, the build takes longer (the benchmark states by how much).
"""

from __future__ import annotations

import hashlib
import io
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import numpy as np

from gps_denied_onboard.components.c6_tiles.georef import WebMercatorGrid
from gps_denied_onboard.components.c6_tiles.types import TileId
from gps_denied_onboard.components.c10_cache_build.geotiff import (
    _blocks,
    _plan,
    check_build_params,
    open_source,
    warp_job,
    warp_shard,
)
from gps_denied_onboard.components.c10_cache_build.manifest import (
    MANIFEST_NAME,
    TILE_VALID_FRACTION_NAME,
    TILES_NAME,
    mosaic_name,
)
from gps_denied_onboard.components.c10_cache_build.shards import EngineSpec, ShardOutput, shards_of

#: Bytes hashed to time sha256 on this machine.
_HASH_SAMPLE_BYTES: Final = 64 << 20
#: The calibration's time, stated (not sampled): both working levels, fitted to GeoVision (171 tiles,
#: 1.9 s) and the 3,721-tile benchmark map (15.7 s) on CPU-A.
CALIBRATION_FIXED_S_STATED: Final = 1.2
CALIBRATION_S_PER_TILE_STATED: Final = 0.0039
#: A local Dask cluster's start and stop, stated: 1.9-3.0 s on CPU-A under load (2 workers).
CLUSTER_START_S_STATED: Final = 2.5
#: A manifest is a few kB (its tile list is in tiles.json); stated.
_MANIFEST_BYTES_STATED: Final = 8 << 10
#: Hashes the build takes of the mosaic: when it is published, and when the fields open the cache.
_MOSAIC_HASH_PASSES: Final = 2


@dataclass(frozen=True)
class StageEstimate:
    """One stage of the build: its name, the estimated seconds, and where the figure comes from."""

    name: str
    seconds: float
    basis: str


@dataclass(frozen=True)
class BuildEstimate:
    """A dry run's answer: the plan, each artifact's size on disk (bytes) and each stage's time."""

    zoom: int
    gsd_m_px: float
    tile_count: int
    n_rows_tiles: int
    n_cols_tiles: int
    shard_count: int
    workers: int
    artifacts: dict[str, int]
    stages: list[StageEstimate]

    def lines(self) -> list[str]:
        """The estimate as a person reads it."""
        out = [
            f"zoom {self.zoom} ({self.gsd_m_px:.3f} m/px at the centre): {self.n_cols_tiles} x "
            f"{self.n_rows_tiles} = {self.tile_count} tiles in {self.shard_count} shards, "
            f"{self.workers} worker(s)",
            "size on disk:",
        ]
        for name, size in self.artifacts.items():
            out.append(f"  {name:<28} {_size_text(size):>10}")
        out.append(f"  {'total':<28} {_size_text(sum(self.artifacts.values())):>10}")
        out.append("estimated time:")
        for stage in self.stages:
            out.append(f"  {stage.name:<28} {_time_text(stage.seconds):>10}   {stage.basis}")
        out.append(f"  {'total':<28} {_time_text(sum(s.seconds for s in self.stages)):>10}")
        return out


def estimate_geotiff_build(
    source: Path,
    *,
    zoom: int | None = None,
    bbox_lonlat: tuple[float, float, float, float] | None = None,
    tile_size_px: int = 256,
    engine: EngineSpec | None = None,
    fields: bool = True,
    sample_shards: int = 1,
) -> BuildEstimate:
    """What ``build_cache_from_geotiff`` (and, with ``fields``, the orientation fields) would make from
    ``source``, and the time of each stage, estimated from samples timed here (module docstring).

    ``engine``'s workers divide the mosaic stage (a running cluster's size is not asked: ``workers``
    is taken as given). Nothing is written. Raises CacheBuildError like the build.
    """
    engine = engine or EngineSpec()
    source = Path(source)
    check_build_params(zoom, bbox_lonlat, tile_size_px, 0.5)
    with open_source(source) as dataset:
        plan = _plan(dataset, zoom, bbox_lonlat, tile_size_px, source)
        job = warp_job(dataset, str(source.resolve()), plan, tile_size_px)
    ts = tile_size_px
    tr = plan.tile_range
    height, width = tr.n_rows * ts, tr.n_cols * ts
    grid = WebMercatorGrid(plan.zoom, ts)
    shards = shards_of(_blocks(tr, ts))
    n_tiles = tr.n_rows * tr.n_cols

    artifacts = {
        mosaic_name(plan.zoom): _npy_bytes(np.uint8, (height, width, 3)),
        TILES_NAME: _tiles_json_bytes(grid, tr.x0, tr.y0, tr.n_cols, tr.n_rows, plan.zoom, ts),
        TILE_VALID_FRACTION_NAME: _npy_bytes(np.float32, (tr.n_rows, tr.n_cols)),
    }
    if fields:
        from gps_denied_onboard.components.c10_cache_build.map_fields import LEVELS, field_file_names

        for level in LEVELS:
            s = level - 1
            field_name, crc_name = field_file_names(level)
            artifacts[field_name] = _npy_bytes(np.int8, (height >> s, width >> s, 2))
            artifacts[crc_name] = _npy_bytes(np.uint32, (tr.n_rows, tr.n_cols))
    artifacts[MANIFEST_NAME] = _MANIFEST_BYTES_STATED

    hash_s_per_byte = _time_sha256()
    first = max(0, len(shards) // 2 - sample_shards // 2)
    sample = shards[first : first + max(1, sample_shards)]
    t0 = time.perf_counter()
    outputs = [warp_shard(job, shard) for shard in sample]
    warp_s_per_tile = (time.perf_counter() - t0) / max(1, sum(s.n_tiles for s in sample))
    sample_tiles = sum(s.n_tiles for s in sample)
    workers = engine.workers
    mosaic_bytes = artifacts[mosaic_name(plan.zoom)]
    stages = []
    if engine.distributed:
        stages.append(StageEstimate("cluster start and stop", CLUSTER_START_S_STATED, "stated: measured"))
    stages += [
        StageEstimate(
            "source sha256",
            source.stat().st_size * hash_s_per_byte,
            f"timed: sha256 of {_HASH_SAMPLE_BYTES >> 20} MiB here",
        ),
        StageEstimate(
            "mosaic (read, warp, write)",
            n_tiles * warp_s_per_tile / workers,
            f"timed sample: {len(sample)} shard(s), {sample_tiles} tiles, "
            f"{1000 * warp_s_per_tile:.1f} ms/tile, over {workers} worker(s)",
        ),
        StageEstimate(
            "publish (tiles, sha256)",
            mosaic_bytes * hash_s_per_byte,
            "timed: sha256 rate x the mosaic's size",
        ),
    ]
    if fields:
        fields_s_per_px = _time_fields(outputs)
        field_bytes = sum(v for k, v in artifacts.items() if k.startswith("field_l"))
        stages.append(
            StageEstimate(
                "orientation fields",
                height * width * fields_s_per_px / workers
                + (_MOSAIC_HASH_PASSES - 1) * mosaic_bytes * hash_s_per_byte
                + field_bytes * hash_s_per_byte,
                f"timed sample: fields of the sampled shards, {1e9 * fields_s_per_px:.0f} ns/px over "
                f"{workers} worker(s), + sha256 of the mosaic and the fields",
            )
        )
        stages.append(
            StageEstimate(
                "calibration",
                CALIBRATION_FIXED_S_STATED + n_tiles * CALIBRATION_S_PER_TILE_STATED,
                f"stated: {CALIBRATION_FIXED_S_STATED} s + {1000 * CALIBRATION_S_PER_TILE_STATED} ms/tile, "
                "fitted on two maps",
            )
        )
    return BuildEstimate(
        zoom=plan.zoom,
        gsd_m_px=grid.gsd_m_px((plan.bbox_lonlat[1] + plan.bbox_lonlat[3]) / 2),
        tile_count=n_tiles,
        n_rows_tiles=tr.n_rows,
        n_cols_tiles=tr.n_cols,
        shard_count=len(shards),
        workers=workers,
        artifacts=artifacts,
        stages=stages,
    )


def _npy_bytes(dtype: type[np.generic], shape: tuple[int, ...]) -> int:
    """Exact size of a ``.npy`` of ``dtype`` and ``shape`` (format 1.0 header, as the build writes)."""
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        head,
        {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)), "fortran_order": False, "shape": shape},
    )
    return len(head.getvalue()) + int(np.prod(shape)) * np.dtype(dtype).itemsize


def _tiles_json_bytes(
    grid: WebMercatorGrid, x0: int, y0: int, n_cols: int, n_rows: int, zoom: int, tile_size_px: int
) -> int:
    """An upper bound of ``tiles.json``: every tile of the range listed, each as long as the longest of a
    sample along the range's diagonal (written as the build writes it)."""
    n = n_cols * n_rows
    steps = min(64, n)
    longest = 0
    for i in range(steps):
        col, row = (i * (n_cols - 1)) // max(1, steps - 1), (i * (n_rows - 1)) // max(1, steps - 1)
        lon, lat = grid.tile_center_lonlat(x0 + col, y0 + row)
        tile_id = TileId.of(zoom, lat, lon)
        entry = {
            "x": x0 + col,
            "y": y0 + row,
            "zoom": tile_id.zoom,
            "lat_deg": tile_id.lat_deg,
            "lon_deg": tile_id.lon_deg,
            "valid_fraction": 0.123456,
        }
        text = json.dumps({"tiles": [entry]}, indent=1, sort_keys=True)
        longest = max(longest, len(text) - len(json.dumps({"tiles": []}, indent=1)))
    head = len(json.dumps({"tile_size_px": tile_size_px, "tiles": [], "zoom": zoom}, indent=1)) + 1
    return head + n * (longest + 2)


def _time_sha256() -> float:
    """Seconds per byte of sha256 here."""
    data = bytes(_HASH_SAMPLE_BYTES)
    t0 = time.perf_counter()
    hashlib.sha256(data).digest()
    return (time.perf_counter() - t0) / len(data)


def _time_fields(outputs: list[ShardOutput]) -> float:
    """Seconds per mosaic px of the orientation fields (every level) over the sampled shards' pixels.

    The build's bands are 1024 rows with 192-row halos; a shard is 256 rows with no halo, and the two
    per-px costs came out within 5 % of each other on the benchmark map, so none is added."""
    from gps_denied_onboard.components.c10_cache_build.map_fields import level_fields
    from gps_denied_onboard.helpers.orientation_field import grey_of

    # Once on a small image first: the first call pays for imports and OpenCV's set-up.
    level_fields(np.zeros((64, 64), np.float32), np.ones((64, 64), bool))
    px = 0
    t0 = time.perf_counter()
    for output in outputs:
        if output.bgr is None:
            continue
        level_fields(grey_of(output.bgr), np.asarray(output.bgr.any(axis=2), dtype=bool))
        px += output.bgr.shape[0] * output.bgr.shape[1]
    elapsed = time.perf_counter() - t0
    return elapsed / px if px else 0.0


def _size_text(n_bytes: int) -> str:
    for unit, scale in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n_bytes >= scale:
            return f"{n_bytes / scale:.1f} {unit}"
    return f"{n_bytes} B"


def _time_text(seconds: float) -> str:
    if seconds >= 3600:
        return f"{seconds / 3600:.1f} h"
    if seconds >= 60:
        return f"{seconds / 60:.1f} min"
    return f"{seconds:.1f} s"
