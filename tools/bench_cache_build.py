"""Throughput of the sharded cache build for 1 and N workers, each stage timed, and the caches compared.

    nice -n 19 .venv/bin/python tools/bench_cache_build.py --work /tmp/gdnav_bench \\
        [--size-km 4] [--gsd-m 0.5] [--workers 1,2] [--json OUT]

Writes (once, then reuses) a synthetic GeoTIFF of ``--size-km`` square at ``--gsd-m`` in UTM 33N near
Vienna (procedural fields, roads and noise; tiled 256 px, uncompressed) under ``--work``, then for each
worker count builds the cache as ``gdnav cache build`` does (mosaic, then orientation fields and their
calibration) into ``--work/cache_wN`` with ``SOURCE_DATE_EPOCH`` fixed, timing each stage:

- ``source_sha256_s``: hashing the source (serial);
- ``engine_start_s``: starting the local cluster (0 in one process);
- ``shards_s``: the sharded stage (read, warp, write), and within it ``driver_write_s``, the driver
  writing and flushing the shards (serial: no worker can take it);
- ``publish_s``: the rest of the mosaic build (tile list, the mosaic's sha256, the manifest);
- ``fields_s``: the orientation fields, and within it (one worker only: the workers' own time is not
  seen from here) ``field_bands_s``, the bands' computation that the workers share; the rest (the
  mosaic's sha256 when the fields open the cache, streaming, CRCs, the fields' sha256) is serial;
- ``calibration_s``: the calibration (serial, about constant in the area).

Every cache is compared byte for byte with the first. Prints a table and the projection of the model in
docs/benchmarks.md ("Mission scale: the distributed build"). A one-off measurement tool: the daemon does
not use it.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from rasterio.transform import from_origin

from gps_denied_onboard.components.c10_cache_build import geotiff, map_fields
from gps_denied_onboard.components.c10_cache_build.manifest import sha256_file
from gps_denied_onboard.components.c10_cache_build.shards import EngineSpec, open_engine
from gps_denied_onboard.logging_setup import configure_logging

EPOCH_S = "1767225600"
_ROWS_PER_WRITE = 512


def write_source(path: Path, size_km: float, gsd_m: float) -> Path:
    """The synthetic GeoTIFF (skipped when ``path`` exists)."""
    if path.exists():
        return path
    n = round(size_km * 1000.0 / gsd_m)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    rng = np.random.default_rng(11)
    xx = np.arange(n, dtype=np.float32)[None, :]
    with rasterio.open(
        tmp,
        "w",
        driver="GTiff",
        width=n,
        height=n,
        count=3,
        dtype="uint8",
        crs="EPSG:32633",
        transform=from_origin(600_000.0, 5_340_000.0, gsd_m, gsd_m),
        tiled=True,
        blockxsize=256,
        blockysize=256,
    ) as dst:
        for r0 in range(0, n, _ROWS_PER_WRITE):
            rows = min(_ROWS_PER_WRITE, n - r0)
            yy = np.arange(r0, r0 + rows, dtype=np.float32)[:, None]
            # Fields of varying brightness, hedges, roads every ~300 m, and sensor noise.
            field = 110 + 35 * np.sign(np.sin(xx / 173.0 + 0.3 * np.sin(yy / 97.0)) * np.cos(yy / 131.0))
            field = field + 18 * np.sin(xx / 11.0 + yy / 17.0)
            road = ((xx + 0.4 * yy) % 600 < 8) | ((yy - 0.2 * xx) % 700 < 6)
            grey = np.where(road, 215.0, field) + rng.normal(0, 9, (rows, n))
            data = np.clip(np.stack([grey, grey * 0.92 + 8, grey * 0.8 + 18]), 1, 255).astype(np.uint8)
            dst.write(data, window=rasterio.windows.Window(0, r0, n, rows))
    os.replace(tmp, path)
    return path


class _Timers:
    """Wraps the build's own functions to time its stages from the outside."""

    def __init__(self, in_process: bool) -> None:
        self.t: dict[str, float] = {"field_bands_s": 0.0, "field_bands_cpu_s": 0.0, "warp_cpu_s": 0.0}
        self.shard_run: Any = None
        self._in_process = in_process

    @contextlib.contextmanager
    def installed(self) -> Iterator[None]:
        real_run = geotiff.run_shards
        real_sha, real_cal = geotiff.sha256_file, map_fields.calibrate
        real_band, real_warp = map_fields.band_fields, geotiff.warp_shard
        timers = self

        def band_fields(*args: Any, **kwargs: Any) -> Any:
            t0, c0 = time.monotonic(), time.process_time()
            out = real_band(*args, **kwargs)
            timers.t["field_bands_s"] += time.monotonic() - t0
            timers.t["field_bands_cpu_s"] += time.process_time() - c0
            return out

        def warp_shard(*args: Any, **kwargs: Any) -> Any:
            c0 = time.process_time()
            out = real_warp(*args, **kwargs)
            timers.t["warp_cpu_s"] += time.process_time() - c0
            return out

        def run_shards(*args: Any, **kwargs: Any) -> Any:
            timers.shard_run = real_run(*args, **kwargs)
            return timers.shard_run

        def sha(path: Path) -> str:
            t0 = time.monotonic()
            out = real_sha(path)
            timers.t.setdefault("source_sha256_s", time.monotonic() - t0)
            return out

        def calibrate(*args: Any, **kwargs: Any) -> Any:
            t0 = time.monotonic()
            out = real_cal(*args, **kwargs)
            timers.t["calibration_s"] = timers.t.get("calibration_s", 0.0) + time.monotonic() - t0
            return out

        geotiff.run_shards = run_shards  # type: ignore[assignment]
        geotiff.sha256_file, map_fields.calibrate = sha, calibrate  # type: ignore[assignment]
        if self._in_process:
            # The bands' own time is seen only in this process (a worker's copy is not wrapped).
            map_fields.band_fields = band_fields  # type: ignore[assignment]
            geotiff.warp_shard = warp_shard  # type: ignore[assignment]
        try:
            yield
        finally:
            geotiff.run_shards = real_run  # type: ignore[assignment]
            geotiff.sha256_file, map_fields.calibrate = real_sha, real_cal  # type: ignore[assignment]
            map_fields.band_fields = real_band  # type: ignore[assignment]
            geotiff.warp_shard = real_warp  # type: ignore[assignment]


def build_once(source: Path, out: Path, workers: int) -> dict[str, Any]:
    """One full build (mosaic, fields, calibration) into a fresh ``out``; the stages' times."""
    shutil.rmtree(out, ignore_errors=True)
    timers = _Timers(in_process=workers == 1)
    load_before = os.getloadavg()[0]
    t = timers.t
    # One engine for both stages, as gdnav cache build does.
    with timers.installed(), contextlib.ExitStack() as stack:
        t0 = time.monotonic()
        engine = stack.enter_context(open_engine(EngineSpec(workers=workers)))
        t["engine_start_s"] = time.monotonic() - t0
        cpu = [_workers_cpu_s(engine)]
        t0 = time.monotonic()
        manifest = geotiff.build_cache_from_geotiff(source, out, progress=False, engine=engine)
        mosaic_s = time.monotonic() - t0
        cpu.append(_workers_cpu_s(engine))
        t1 = time.monotonic()
        map_fields.build_map_fields(out, progress=False, engine=engine)
        fields_total_s = time.monotonic() - t1
        cpu.append(_workers_cpu_s(engine))
        t_stop = time.monotonic()
    t["engine_stop_s"] = time.monotonic() - t_stop
    run = timers.shard_run
    total_s = t["engine_start_s"] + mosaic_s + fields_total_s + t["engine_stop_s"]
    tiles = manifest.tile_range.n_rows * manifest.tile_range.n_cols
    return {
        "workers": workers,
        "tiles": tiles,
        "shards": run.ran,
        "zoom": manifest.zoom,
        "mosaic_bytes": (out / manifest.mosaic_name).stat().st_size,
        "source_sha256_s": round(t["source_sha256_s"], 2),
        "engine_start_s": round(t["engine_start_s"], 2),
        "shards_s": round(run.seconds, 2),
        "driver_write_s": round(run.write_s, 2),
        "engine_stop_s": round(t["engine_stop_s"], 2),
        "publish_s": round(mosaic_s - t["source_sha256_s"] - run.seconds, 2),
        "fields_s": round(fields_total_s - t.get("calibration_s", 0.0), 2),
        "field_bands_s": round(t["field_bands_s"], 2) if workers == 1 else None,
        "calibration_s": round(t.get("calibration_s", 0.0), 2),
        # CPU seconds of the pieces the workers share: in this process with one worker, else the
        # worker processes' own CPU time over each stage.
        "warp_cpu_s": round(t["warp_cpu_s"], 2) if workers == 1 else round(cpu[1] - cpu[0], 2),
        "field_bands_cpu_s": round(t["field_bands_cpu_s"], 2) if workers == 1 else round(cpu[2] - cpu[1], 2),
        "total_s": round(total_s, 2),
        "shard_tiles_per_s": round(tiles / run.seconds, 1),
        "total_tiles_per_s": round(tiles / total_s, 1),
        "load_1min_before": round(load_before, 2),
        "load_1min_after": round(os.getloadavg()[0], 2),
    }


def _workers_cpu_s(engine: Any) -> float:
    """Total CPU seconds of the engine's worker processes so far (0 for the in-process engine)."""
    client = getattr(engine, "_client", None)
    if client is None:
        return 0.0
    return float(sum(client.run(time.process_time).values()))


def same_files(a: Path, b: Path) -> bool:
    names_a = sorted(p.name for p in a.iterdir())
    if names_a != sorted(p.name for p in b.iterdir()):
        return False
    return all(sha256_file(a / n) == sha256_file(b / n) for n in names_a)


def model(row1: dict[str, Any], network_s_per_tile: float) -> dict[str, float]:
    """The projection's coefficients from the one-worker build (docs/benchmarks.md states the model):
    per tile, the work any worker can do (warp, field bands), the driver's share of the shards (writing
    them, and ``network_s_per_tile`` to receive them), the serial work (hashes, publishing, streaming the
    fields, the calibration)."""
    tiles = row1["tiles"]
    # CPU seconds, not wall: on a machine others share, a worker's wall time is its core's other load.
    worker_s_per_tile = (row1["warp_cpu_s"] + row1["field_bands_cpu_s"]) / tiles
    driver_s_per_tile = row1["driver_write_s"] / tiles + network_s_per_tile
    fields_serial_s = row1["fields_s"] - row1["field_bands_s"]
    # The calibration passes over the whole valid mask: serial, and counted per tile (its searches'
    # fixed ~1 s is small beside it on a map of thousands of tiles).
    serial_s = row1["source_sha256_s"] + row1["publish_s"] + fields_serial_s + row1["calibration_s"]
    return {
        "worker_s_per_tile": worker_s_per_tile,
        "driver_s_per_tile": driver_s_per_tile,
        "serial_s_per_tile": serial_s / tiles,
    }


def project(m: dict[str, float], tiles: int, machines: int, start_s: float) -> float:
    """T(N) = start + tiles * serial + max(tiles * worker / N, tiles * driver)."""
    shards = max(tiles * m["worker_s_per_tile"] / machines, tiles * m["driver_s_per_tile"])
    return start_s + tiles * m["serial_s_per_tile"] + shards


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--size-km", type=float, default=4.0)
    ap.add_argument("--gsd-m", type=float, default=0.5)
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--network-ms-per-tile", type=float, default=1.6)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    os.environ["SOURCE_DATE_EPOCH"] = EPOCH_S
    configure_logging("warning", json=False)
    source = write_source(args.work / f"src_{args.size_km:g}km_{args.gsd_m:g}m.tif", args.size_km, args.gsd_m)
    rows = []
    for workers in (int(w) for w in args.workers.split(",")):
        rows.append(build_once(source, args.work / f"cache_w{workers}", workers))
        print(json.dumps(rows[-1]), flush=True)
    first = args.work / f"cache_w{rows[0]['workers']}"
    identical = {r["workers"]: same_files(first, args.work / f"cache_w{r['workers']}") for r in rows}
    print(f"byte-identical to {rows[0]['workers']} worker(s): {identical}")
    m = model(rows[0], args.network_ms_per_tile / 1000.0)
    start_s = max((r["engine_start_s"] + r["engine_stop_s"] for r in rows), default=0.0)
    projections = {
        label: {n: round(project(m, tiles, n, start_s if n > 1 else 0.0)) for n in (1, 2, 4, 8, 16, 32, 64)}
        for label, tiles in (("this_map", rows[0]["tiles"]), ("50km_z18", 117_000), ("50km_z19", 468_000))
    }
    print("model:", json.dumps({k: round(v * 1000, 3) for k, v in m.items()}), "(ms per tile)")
    print("projected seconds by machines:", json.dumps(projections))
    if args.json:
        args.json.write_text(
            json.dumps(
                {"rows": rows, "identical": identical, "model": m, "projections": projections}, indent=1
            )
        )
    return 0 if all(identical.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
