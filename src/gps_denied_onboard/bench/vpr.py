"""VPR benchmark: Recall@K of C2 (corpus-wide and prior-gated) and C2.5, and HNSW latency/memory.

``run_vpr_benchmark(map_path, strategies=("vlad", "vlad_xfeat"))`` builds a tile cache from the GeoTIFF
and, per strategy, its vocabulary, descriptors and HNSW index (timed); renders ``n_queries`` nav frames
with the SITL renderer (from ``frames_path`` for another date; 640x480, 70 deg HFOV, altitude in
``alt_range_m``, any heading, roll/pitch within +-3 deg); and scores them against the truth:
- a **true tile** is one whose matcher chip holds the ground under the principal point at least
  ``edge_margin`` x chip side inside its edges;
- **Recall@K**: the share of frames with a true tile among the first K, corpus-wide (F6) and prior-gated
  (prior = truth + N(0, ``prior_sigma_m``), radius as the pipeline's search region);
- post-rerank Recall@1/3 (``InlierRerank``, K=10 -> N=3), and the latency of embedding, retrieval and
  rerank (p50/p95);
- HNSW on ``synthetic_n`` random unit vectors: build time, file size, resident memory after a
  memory-mapped load, top-10 latency and recall against exact search.

Prints a table and returns the figures as a dict (also written to ``out/vpr_bench.json``). Every step in
full: docs/design.md, "`bench/vpr.py`: the VPR benchmark"; figures: docs/benchmarks.md, "C2 place
recognition".
"""

from __future__ import annotations

import json
import math
import tempfile
import time
import uuid
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gps_denied_onboard.camera.types import Attitude, CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c2_5_rerank.inlier_rerank import InlierRerank
from gps_denied_onboard.components.c2_vpr.protocol import SearchRegion, VprStrategy
from gps_denied_onboard.components.c2_vpr.vlad import LocalDescriber, VladParams, VladVpr
from gps_denied_onboard.components.c6_tiles.descriptor_index import DescriptorIndex, l2_normalise
from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.helpers.frame_rectifier import principal_ground_offset_m
from gps_denied_onboard.helpers.ransac_filter import RansacFilter

_EARTH_M_PER_DEG_LAT = 111_320.0


@dataclass(frozen=True)
class QueryFrame:
    """A rendered nav frame with its truth: ``centre_lat_deg``/``centre_lon_deg`` = ground point under
    the principal point; ``cam_lat_deg``/``cam_lon_deg`` = camera position."""

    frame: NavCameraFrame
    cam_lat_deg: float
    cam_lon_deg: float
    centre_lat_deg: float
    centre_lon_deg: float


def render_queries(
    frames_path: Path,
    store: TileStore,
    calib: CameraCalibration,
    *,
    n: int,
    alt_range_m: tuple[float, float],
    seed: int,
    max_tilt_deg: float = 3.0,
) -> list[QueryFrame]:
    """Render ``n`` frames at random poses over the map (see the module docstring)."""
    from gps_denied_onboard.sitl.render import MapRenderer  # SITL-only dependency

    renderer = MapRenderer(frames_path)
    rng = np.random.default_rng(seed)
    west, south, east, north = _intersect(renderer.bbox_lonlat, store.bbox_lonlat)
    lat_mid = (south + north) / 2.0
    m_per_deg_lon = _EARTH_M_PER_DEG_LAT * math.cos(math.radians(lat_mid))
    half_fp_m = alt_range_m[1] * math.tan(calib.hfov_rad / 2.0) * 0.8
    lon_lo, lon_hi = west + half_fp_m / m_per_deg_lon, east - half_fp_m / m_per_deg_lon
    lat_lo, lat_hi = south + half_fp_m / _EARTH_M_PER_DEG_LAT, north - half_fp_m / _EARTH_M_PER_DEG_LAT
    if lon_lo >= lon_hi or lat_lo >= lat_hi:
        raise ValueError(
            f"map too small for {alt_range_m[1]} m AGL frames (half footprint {half_fp_m:.0f} m)"
        )
    out: list[QueryFrame] = []
    for i in range(n):
        lat = float(rng.uniform(lat_lo, lat_hi))
        lon = float(rng.uniform(lon_lo, lon_hi))
        alt = float(rng.uniform(*alt_range_m))
        att = Attitude(
            math.radians(rng.uniform(-max_tilt_deg, max_tilt_deg)),
            math.radians(rng.uniform(-max_tilt_deg, max_tilt_deg)),
            math.radians(rng.uniform(0.0, 360.0)),
        )
        image = renderer.render(calib, lat, lon, alt, att)
        offset_m = principal_ground_offset_m(calib, att, alt)
        if offset_m is None:
            raise ValueError(f"frame {i}: the principal ray misses the ground (max_tilt_deg {max_tilt_deg})")
        d_north, d_east = offset_m
        c_lat = lat + d_north / _EARTH_M_PER_DEG_LAT
        c_lon = lon + d_east / (_EARTH_M_PER_DEG_LAT * math.cos(math.radians(lat)))
        frame = NavCameraFrame(uuid.uuid4(), i, 0, image, att, alt, time.monotonic_ns())
        out.append(QueryFrame(frame, lat, lon, c_lat, c_lon))
    return out


def true_tiles(
    store: TileStore, lat_deg: float, lon_deg: float, chip_size_px: int, edge_margin: float
) -> set:
    """Tiles whose ``chip_size_px`` chip holds the point at least ``edge_margin`` x side from its edges."""
    radius = chip_size_px * store.gsd_m_px * 0.75
    out = set()
    margin = edge_margin * chip_size_px
    for tile_id, _ in store.tiles_near(lat_deg, lon_deg, radius):
        chip = store.chip(tile_id, chip_size_px)
        px = chip.lonlat_to_chip_px(np.array(lon_deg), np.array(lat_deg))
        w, h = chip.size_px
        if margin - 0.5 <= px[0] <= w - 0.5 - margin and margin - 0.5 <= px[1] <= h - 0.5 - margin:
            out.add(tile_id)
    return out


def evaluate_recall(
    store: TileStore,
    vpr: VprStrategy,
    calib: CameraCalibration,
    queries: Sequence[QueryFrame],
    *,
    rerank: InlierRerank | None = None,
    chip_size_px: int = 512,
    edge_margin: float = 0.125,
    prior_sigma_m: float = 30.0,
    seed: int = 0,
    ks: Sequence[int] = (1, 5, 10),
) -> dict[str, Any]:
    """Recall@K corpus-wide and prior-gated, post-rerank Recall@1/3, and per-stage latency (ms)."""
    rng = np.random.default_rng(seed + 1)
    kmax = max(ks)
    hits_wide = {k: 0 for k in ks}
    hits_gated = {k: 0 for k in ks}
    hits_rr = {1: 0, 3: 0}
    embed_ms: list[float] = []
    search_ms: list[float] = []
    rerank_ms: list[float] = []
    top1_true: list[float] = []
    top1_false: list[float] = []
    counted = 0
    for q in queries:
        truth = true_tiles(store, q.centre_lat_deg, q.centre_lon_deg, chip_size_px, edge_margin)
        if not truth:
            continue
        counted += 1
        t0 = time.perf_counter()
        query = vpr.embed_query(q.frame, calib)
        t1 = time.perf_counter()
        wide = vpr.retrieve_topk(query, kmax)
        t2 = time.perf_counter()
        embed_ms.append((t1 - t0) * 1e3)
        search_ms.append((t2 - t1) * 1e3)
        ranked = [c.tile_id for c in wide.candidates]
        for k in ks:
            hits_wide[k] += bool(truth.intersection(ranked[:k]))
        if wide.candidates:
            (top1_true if ranked[0] in truth else top1_false).append(wide.candidates[0].descriptor_distance)
        d_n, d_e = rng.normal(0.0, prior_sigma_m, 2)
        p_lat = q.centre_lat_deg + d_n / _EARTH_M_PER_DEG_LAT
        p_lon = q.centre_lon_deg + d_e / (_EARTH_M_PER_DEG_LAT * math.cos(math.radians(q.centre_lat_deg)))
        half_fp = float(q.frame.alt_agl_m or 0.0) * math.tan(calib.hfov_rad / 2.0)
        radius = min(max(3.0 * prior_sigma_m + half_fp, 60.0), 2000.0)
        gated = vpr.retrieve_topk(query, kmax, region=SearchRegion(p_lat, p_lon, radius))
        ranked_g = [c.tile_id for c in gated.candidates]
        for k in ks:
            hits_gated[k] += bool(truth.intersection(ranked_g[:k]))
        if rerank is not None:
            t3 = time.perf_counter()
            rr = rerank.rerank(q.frame, wide)
            rerank_ms.append((time.perf_counter() - t3) * 1e3)
            ranked_r = [c.tile_id for c in rr.candidates]
            for k in hits_rr:
                hits_rr[k] += bool(truth.intersection(ranked_r[:k]))
    n = max(counted, 1)
    out: dict[str, Any] = {
        "queries": counted,
        "recall_corpus": {f"@{k}": hits_wide[k] / n for k in ks},
        "recall_gated": {f"@{k}": hits_gated[k] / n for k in ks},
        "embed_ms": _pct(embed_ms),
        "search_ms": _pct(search_ms),
        "top1_distance_when_true": _pct(top1_true),
        "top1_distance_when_false": _pct(top1_false),
    }
    if rerank is not None:
        out["recall_rerank"] = {f"@{k}": hits_rr[k] / n for k in hits_rr}
        out["rerank_ms"] = _pct(rerank_ms)
    return out


def hnsw_figures(
    dim: int,
    n: int = 100_000,
    *,
    n_queries: int = 500,
    seed: int = 0,
    work_dir: Path | None = None,
    ef_values: Sequence[int] = (16, 64, 128),
) -> dict[str, Any]:
    """Build/load/search figures of ``DescriptorIndex`` on ``n`` random unit vectors of ``dim``.

    Random vectors are the hardest case for HNSW (no low-dimensional structure): the 10 exact
    neighbours of a query are nearly equidistant, so ``recall10_vs_exact`` is a pessimistic figure;
    ``source_at1`` (the stored vector a query was made from is returned first) is the place-recognition
    figure.
    """
    rng = np.random.default_rng(seed)
    x = l2_normalise(rng.standard_normal((n, dim)).astype(np.float32))
    # Queries near stored vectors (noisy copies), like a real place query, plus exact ground truth.
    qi = rng.choice(n, n_queries, replace=False)
    queries = l2_normalise(x[qi] + 0.05 * rng.standard_normal((n_queries, dim)).astype(np.float32))
    t0 = time.perf_counter()
    index = DescriptorIndex.build(x)
    build_s = time.perf_counter() - t0
    with tempfile.TemporaryDirectory(dir=work_dir) as tmp:
        path = Path(tmp) / "hnsw.faiss"
        index.save(path)
        del index
        rss0 = _rss_mb()
        loaded = DescriptorIndex.load(path, expected_dim=dim)
        rss_load = _rss_mb() - rss0
        exact = np.argsort(-(queries @ x.T), axis=1)[:, :10]
        sweep = {}
        for ef in ef_values:
            index_ef = loaded if ef == loaded.ef_search else DescriptorIndex.load(path, ef_search=ef)
            lat, agree, found = [], 0, 0
            for i, q in enumerate(queries):
                t = time.perf_counter()
                hits = index_ef.search(q, 10)
                lat.append((time.perf_counter() - t) * 1e3)
                agree += len(set(hits.positions.tolist()) & set(exact[i].tolist()))
                found += int(qi[i] in hits.positions[:1])
            sweep[f"ef{ef}"] = {
                "top10_ms": _pct(lat),
                "recall10_vs_exact": round(agree / (10 * n_queries), 4),
                "source_at1": round(found / n_queries, 4),
            }
        # Gated search over a few hundred tiles (exact path) and a large subset (selector path).
        small = rng.choice(n, min(n, 300), replace=False)
        large = rng.choice(n, min(n, 20_000), replace=False)
        lat_small = [_timed(lambda q=q: loaded.search(q, 10, allowed=small)) for q in queries[:100]]
        lat_large = [_timed(lambda q=q: loaded.search(q, 10, allowed=large)) for q in queries[:100]]
        size_mb = path.stat().st_size / 1e6
        mmapped = loaded.mmapped
    return {
        "n": n,
        "dim": dim,
        "build_s": round(build_s, 2),
        "file_mb": round(size_mb, 1),
        "rss_after_load_mb": round(rss_load, 1),
        "mmapped": mmapped,
        "ef_sweep": sweep,
        "gated300_exact_ms": _pct(lat_small),
        "gated20k_selector_ms": _pct(lat_large),
    }


#: Strategies ``run_vpr_benchmark`` can measure (``vpr.strategy`` names).
BENCH_STRATEGIES: tuple[str, ...] = ("vlad", "vlad_xfeat")


def run_vpr_benchmark(
    map_path: Path,
    *,
    zoom: int | None = None,
    n_queries: int = 60,
    seed: int = 0,
    out: Path | None = None,
    frames_path: Path | None = None,
    alt_range_m: tuple[float, float] = (100.0, 150.0),
    tile_size_px: int = 256,
    chip_size_px: int = 512,
    strategies: Sequence[str] = ("vlad",),
    vlad_params: VladParams | None = None,
    xfeat_params: VladParams | None = None,
    model_dir: Path | None = None,
    intra_op_threads: int = 2,
    synthetic_n: int = 100_000,
    rerank: bool = True,
) -> dict[str, Any]:
    """Build a cache from ``map_path``, then for each of ``strategies`` its VLAD index, and measure recall
    and latency on the same rendered frames (module docstring).

    ``vlad_params`` / ``xfeat_params``: the ``vlad`` / ``vlad_xfeat`` parameters (defaults:
    ``VladParams(chip_size_px=...)`` / ``default_xfeat_params``). ``model_dir``: the verified model
    directory holding the XFeat extractor (``vlad_xfeat``). For NAIP-like 5 m/px maps use
    ``alt_range_m`` of ~1500-2500 m (a 640 px frame then spans a few hundred map pixels) with
    ``zoom=16, tile_size_px=128`` (3.3 m/px ground, 420 m tiles).
    """
    from gps_denied_onboard.components.c10_cache_build.geotiff import build_cache_from_geotiff
    from gps_denied_onboard.components.c10_cache_build.vpr_index import build_vlad_index

    unknown = [name for name in strategies if name not in BENCH_STRATEGIES]
    if unknown or not strategies:
        raise ValueError(f"strategies {list(strategies)}: expected some of {', '.join(BENCH_STRATEGIES)}")
    runs: list[tuple[str, VladParams, LocalDescriber | None]] = []
    for name in strategies:
        if name == "vlad":
            runs.append((name, vlad_params or VladParams(chip_size_px=chip_size_px), None))
        else:
            from gps_denied_onboard.components.c2_vpr.learned_local import (
                XFeatDescriber,
                default_xfeat_params,
                find_xfeat_extractor,
            )
            from gps_denied_onboard.components.c7_inference import OnnxInferenceRuntime

            path = find_xfeat_extractor(Path(model_dir) if model_dir is not None else Path("models"))
            xfeat = XFeatDescriber(OnnxInferenceRuntime(intra_op_threads=intra_op_threads), path)
            runs.append((name, xfeat_params or default_xfeat_params(chip_size_px), xfeat))
    tmp = None
    if out is None:
        tmp = tempfile.TemporaryDirectory(prefix="gdnav-vpr-bench-")
        out = Path(tmp.name)
    out = Path(out)
    try:
        cache = out / "cache"
        t0 = time.perf_counter()
        build_cache_from_geotiff(Path(map_path), cache, zoom=zoom, tile_size_px=tile_size_px, progress=False)
        tiles_s = time.perf_counter() - t0
        calib = CameraCalibration.from_hfov(640, 480, 70.0)
        queries = render_queries(
            Path(frames_path or map_path),
            TileStore.open(cache),
            calib,
            n=n_queries,
            alt_range_m=alt_range_m,
            seed=seed,
        )
        per_strategy: dict[str, Any] = {}
        dim = 0
        for name, params, describer in runs:
            t0 = time.perf_counter()
            build_vlad_index(cache, params, describer=describer, progress=False, force=True)
            vpr_build_s = time.perf_counter() - t0
            store = TileStore.open(cache)
            vpr = VladVpr.from_cache(store, top1_distance_warn=2.0, describer=describer)
            rr = None
            if rerank:
                rr = InlierRerank(
                    store,
                    calibration=calib,
                    ransac_filter=RansacFilter(),
                    top_n=3,
                    chip_size_px=params.chip_size_px,
                    normaliser=vpr.normaliser,
                )
            figures = evaluate_recall(
                store, vpr, calib, queries, rerank=rr, chip_size_px=params.chip_size_px, seed=seed
            )
            dim = dim or vpr.descriptor_dim()
            per_strategy[name] = {
                "params": asdict(params),
                "dim": vpr.descriptor_dim(),
                "vpr_build_s": round(vpr_build_s, 2),
                **figures,
            }
        store = TileStore.open(cache)
        result: dict[str, Any] = {
            "map": str(map_path),
            "frames": str(frames_path or map_path),
            "zoom": store.zoom,
            "tile_size_px": store.tile_size_px,
            "gsd_m_px": round(store.gsd_m_px, 3),
            "tiles": len(store),
            "alt_range_m": list(alt_range_m),
            "cache_build_s": round(tiles_s, 2),
            "strategies": per_strategy,
        }
        if synthetic_n > 0:
            result["hnsw"] = hnsw_figures(dim, synthetic_n, seed=seed, work_dir=out)
        _print_table(result)
        (out / "vpr_bench.json").write_text(json.dumps(result, indent=1), encoding="utf-8")
        return result
    finally:
        if tmp is not None:
            tmp.cleanup()


def _print_table(r: dict[str, Any]) -> None:
    rows = [
        ("map", f"{r['map']} (frames: {r['frames']})"),
        ("cache", f"z{r['zoom']} tile {r['tile_size_px']} px, {r['gsd_m_px']} m/px, {r['tiles']} tiles"),
        ("build", f"tiles {r['cache_build_s']} s"),
    ]
    for name, f in r["strategies"].items():
        p = f["params"]
        rows += [
            (
                name,
                f"{p['descriptor']} k={p['n_clusters']} pca={p['pca_dim']} dim={f['dim']} "
                f"work {p['work_size_px']} px; vpr build {f['vpr_build_s']} s; {f['queries']} queries "
                f"at {r['alt_range_m']} m AGL",
            ),
            (f"{name} recall corpus", _fmt(f["recall_corpus"])),
            (f"{name} recall gated", _fmt(f["recall_gated"])),
        ]
        if "recall_rerank" in f:
            rows.append((f"{name} recall rerank", _fmt(f["recall_rerank"])))
            rows.append((f"{name} rerank ms", _fmt(f["rerank_ms"])))
        rows += [(f"{name} embed ms", _fmt(f["embed_ms"])), (f"{name} search ms", _fmt(f["search_ms"]))]
    if "hnsw" in r:
        h = r["hnsw"]
        rows += [
            (
                "hnsw",
                f"{h['n']} x {h['dim']}: build {h['build_s']} s, file {h['file_mb']} MB, "
                f"rss after mmap load {h['rss_after_load_mb']} MB",
            ),
            *(
                (
                    f"hnsw {ef} top10",
                    _fmt(v["top10_ms"]) + f"  recall@10 vs exact {v['recall10_vs_exact']}"
                    f"  source@1 {v['source_at1']}",
                )
                for ef, v in h["ef_sweep"].items()
            ),
            (
                "hnsw gated ms",
                f"300 exact {_fmt(h['gated300_exact_ms'])}; 20k selector {_fmt(h['gated20k_selector_ms'])}",
            ),
        ]
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"{key:<{width}}  {value}")


def _fmt(d: dict[str, Any]) -> str:
    return "  ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in d.items())


def _pct(values: Sequence[float]) -> dict[str, float]:
    if not values:
        return {}
    arr = np.asarray(values, dtype=np.float64)
    return {"p50": round(float(np.percentile(arr, 50)), 3), "p95": round(float(np.percentile(arr, 95)), 3)}


def _timed(fn) -> float:  # type: ignore[no-untyped-def]
    t = time.perf_counter()
    fn()
    return (time.perf_counter() - t) * 1e3


def _rss_mb() -> float:
    with open("/proc/self/statm", encoding="ascii") as fh:
        return int(fh.read().split()[1]) * 4096 / 1e6


def _intersect(
    a: tuple[float, float, float, float], b: tuple[float, float, float, float]
) -> tuple[float, float, float, float]:
    return max(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), min(a[3], b[3])
