"""Matching rules for ``xfeat_mnn`` side by side: the evidence the integrity rule would judge, per rule.

    .venv/bin/python tools/mnn_rules.py replay "RULE" --fdr FDR --sequential --truth report.json [...]

    .venv/bin/python tools/mnn_rules.py --map MAP_2009.tif --frames-from FRAMES_2014.tif \
        [--frames-from FRAMES_2020.tif] --cache CACHE --model-dir MODELS [--frames 40] [--candidates 3] \
        [--alt 1200] [--seed 0] [--out rules.json]

Frames and chips as ``gdnav bench matcher --frames-from ... --cache ... --first-chip footprint`` makes
them (``bench.matcher.render_bench_frames``, ``with_cache_candidates``: the chip around the footprint
first, then chips far from it). XFeat features are extracted once per frame (rectified query, as
``match()`` does) and once per chip (the cache's precomputed set); every rule then matches the same
features, and RANSAC keeps its inliers. Per rule and frame: each candidate's putative matches, inliers,
inlier ratio and spread (``c4_pose.integrity.MatchEvidence``), the best candidate (``match()``'s order)
and where its inliers put the ground under the principal point against the truth (the benchmark's
centre error). A best candidate passes the integrity rule's first test with the configured
``integrity.*`` thresholds and ``matcher.min_inliers_threshold``; a rival candidate with at least
``ambiguity_inlier_share`` of its inliers refuses it (the wrong chips are far away: a rival pose there
disagrees). C4's pose and the prior test are not run here (``gdnav replay --sequential`` runs them).

Right: the best candidate is the true chip and its centre error is at most ``RIGHT_M``; wrong: anything
else solved. The timing per rule is one candidate's match + RANSAC on cached features, the rules
interleaved per candidate so that the load weighs on all alike. ``replay "RULE" ...`` runs ``gdnav replay``
with ``xfeat_mnn`` matching by that rule instead (the whole fix path in flight: pose, integrity rule,
estimator). A one-off measurement tool for ``docs/benchmarks.md``: the daemon does not use it.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from gps_denied_onboard.bench.matcher import _centre_error_m, render_bench_frames, with_cache_candidates
from gps_denied_onboard.camera.types import CameraCalibration
from gps_denied_onboard.components.c3_matcher import xfeat_mnn
from gps_denied_onboard.components.c3_matcher.features import Features
from gps_denied_onboard.components.c3_matcher.health import RollingHealthWindow
from gps_denied_onboard.components.c3_matcher.registry import create_matcher
from gps_denied_onboard.components.c3_matcher.tile_features import PrecomputedTileFeatures
from gps_denied_onboard.components.c4_pose.integrity import hull_share
from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.components.c7_inference.onnx_runtime import OnnxInferenceRuntime
from gps_denied_onboard.components.c10_cache_build.manifest import Verification
from gps_denied_onboard.config import IntegrityConfig, MatcherConfig
from gps_denied_onboard.helpers.frame_rectifier import RectificationError, rectify_to_map_frame
from gps_denied_onboard.helpers.lightglue_runtime import mutual_nearest_neighbours
from gps_denied_onboard.helpers.ransac_filter import RansacFilter

#: A right solution: the true chip, and the ground under the principal point within this of the truth.
RIGHT_M = 20.0

Rule = Callable[[Features, Features], np.ndarray]


def _unit(d: np.ndarray) -> np.ndarray:
    d = d.astype(np.float32, copy=False)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), np.float32(1e-12))


def _corr(query: Features, tile: Features, pairs: np.ndarray) -> np.ndarray:
    return np.hstack([query.keypoints_px[pairs[:, 0]], tile.keypoints_px[pairs[:, 1]]]).astype(np.float32)


def _mnn_pairs(q: np.ndarray, t: np.ndarray, floor: float) -> tuple[np.ndarray, np.ndarray]:
    """(pairs (M, 2), their cosines) of the mutual nearest neighbours (the daemon's helper)."""
    return mutual_nearest_neighbours(q, t, min_similarity=floor)


def _second_best(q: np.ndarray, t: np.ndarray, pairs: np.ndarray, axis: int) -> np.ndarray:
    """Each pair's second-best cosine in its query row (axis 1) or its tile column (axis 0)."""
    if axis == 1:
        sim = _unit(q[pairs[:, 0]]) @ _unit(t).T
        return np.partition(sim, -2, axis=1)[:, -2]
    sim = _unit(t[pairs[:, 1]]) @ _unit(q).T
    return np.partition(sim, -2, axis=1)[:, -2]


def rule_mnn(floor: float) -> Rule:
    def rule(query: Features, tile: Features) -> np.ndarray:
        pairs, _ = _mnn_pairs(query.descriptors, tile.descriptors, floor)
        return _corr(query, tile, pairs)

    return rule


def rule_ratio(max_ratio: float, floor: float = 0.7, both: bool = False) -> Rule:
    """MNN + Lowe's ratio: the nearest descriptor distance over the second nearest, query -> tile
    (and tile -> query with ``both``), at most ``max_ratio``; distance = sqrt(2 - 2 cos)."""

    def rule(query: Features, tile: Features) -> np.ndarray:
        pairs, best = _mnn_pairs(query.descriptors, tile.descriptors, floor)
        if pairs.shape[0] == 0 or tile.count < 2 or query.count < 2:
            return _corr(query, tile, pairs[:0])
        d1 = np.sqrt(np.maximum(2.0 - 2.0 * best, 0.0))
        second = _second_best(query.descriptors, tile.descriptors, pairs, 1)
        keep = d1 <= max_ratio * np.sqrt(np.maximum(2.0 - 2.0 * second, 0.0))
        if both:
            second_c = _second_best(query.descriptors, tile.descriptors, pairs, 0)
            keep &= d1 <= max_ratio * np.sqrt(np.maximum(2.0 - 2.0 * second_c, 0.0))
        return _corr(query, tile, pairs[keep])

    return rule


def rule_top_k(k: int, floor: float = 0.7) -> Rule:
    def rule(query: Features, tile: Features) -> np.ndarray:
        pairs, best = _mnn_pairs(query.descriptors, tile.descriptors, floor)
        order = np.argsort(-best, kind="stable")[:k]
        return _corr(query, tile, pairs[np.sort(order)])

    return rule


def rule_keypoints(n: int, floor: float = 0.7) -> Rule:
    """MNN on the first ``n`` keypoints of each set (XFeat's top-k output is in score order)."""
    inner = rule_mnn(floor)

    def rule(query: Features, tile: Features) -> np.ndarray:
        q = Features(query.keypoints_px[:n], query.descriptors[:n], query.image_size)
        t = Features(tile.keypoints_px[:n], tile.descriptors[:n], tile.image_size)
        return inner(q, t)

    return rule


def rules() -> dict[str, Rule]:
    return {
        "mnn cos>=0.7 (main)": lambda q, t: xfeat_mnn.match_mutual_nn(q, t),
        "mnn cos>=0.8": rule_mnn(0.8),
        "mnn cos>=0.85": rule_mnn(0.85),
        "ratio 0.98": rule_ratio(0.98),
        "ratio 0.95": rule_ratio(0.95),
        "ratio 0.9": rule_ratio(0.9),
        "ratio 0.95 both": rule_ratio(0.95, both=True),
        "top 100": rule_top_k(100),
        "top 150": rule_top_k(150),
        "top 200": rule_top_k(200),
        "top 300": rule_top_k(300),
        "kp 1024": rule_keypoints(1024),
        "kp 512": rule_keypoints(512),
    }


def _pct(values: list[float], q: float) -> float | None:
    return round(float(np.percentile(values, q)), 3) if values else None


def replay_with_rule(name: str, replay_args: list[str]) -> int:
    """``gdnav replay replay_args`` with ``xfeat_mnn`` matching by the rule ``name`` of ``rules()``."""
    from gps_denied_onboard.cli import main as gdnav

    rule = rules()[name]
    xfeat_mnn.XFeatMnnMatcher.match_features = lambda self, q, t: rule(q, t)  # type: ignore[method-assign,assignment]
    return gdnav(["replay", *replay_args])


def main() -> int:
    if len(sys.argv) > 2 and sys.argv[1] == "replay":
        return replay_with_rule(sys.argv[2], sys.argv[3:])
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--map", type=Path, required=True)
    ap.add_argument("--frames-from", type=Path, action="append", required=True)
    ap.add_argument("--cache", type=Path, required=True)
    ap.add_argument("--model-dir", type=Path, required=True)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--candidates", type=int, default=3)
    ap.add_argument("--alt", type=float, default=1200.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", default="", help="comma-separated rule names (default: all)")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()

    integ = IntegrityConfig()
    calib = CameraCalibration.from_hfov(640, 480, 70.0)
    cfg = MatcherConfig(strategy="xfeat_mnn", xfeat_weights_path=str(args.model_dir / "xfeat-k2048.onnx"))
    ransac = RansacFilter("usac_magsac", cfg.ransac_confidence, cfg.ransac_max_iters)
    runtime = OnnxInferenceRuntime(intra_op_threads=2, providers=("CPUExecutionProvider",))
    matcher = create_matcher(
        "xfeat_mnn",
        config=cfg,
        ransac_filter=ransac,
        health_window=RollingHealthWindow(cfg.min_inliers_threshold),
        inference_runtime=runtime,
        fdr_client=None,
    )
    assert isinstance(matcher, xfeat_mnn.XFeatMnnMatcher)
    store = TileStore.open(args.cache, Verification.FULL)
    pre = PrecomputedTileFeatures.open(store, matcher.extractor_identity, Verification.FULL)
    chosen = rules()
    if args.only:
        chosen = {k: v for k, v in chosen.items() if k in args.only.split(",")}
    load0 = os.getloadavg()
    report: dict[str, Any] = {"load_start": load0, "args": {k: str(v) for k, v in vars(args).items()}}
    for frames_path in args.frames_from:
        frames = render_bench_frames(
            args.map,
            calib,
            n_frames=args.frames,
            n_candidates=1,
            chip_size_px=cfg.chip_size_px,
            alt_agl_m=args.alt,
            seed=args.seed,
            frames_path=frames_path,
        )
        frames = with_cache_candidates(
            frames,
            store,
            n_candidates=args.candidates,
            chip_size_px=cfg.chip_size_px,
            seed=args.seed,
            first_chip="footprint",
        )
        per_rule: dict[str, dict[str, list[Any]]] = {name: {"rows": [], "ms": []} for name in chosen}
        for bf in frames:
            frame = bf.frame
            assert frame.attitude is not None
            gsd = max(float(bf.candidates[0].gsd_m_px), args.alt / calib.fx_px)
            try:
                rect = rectify_to_map_frame(frame.image_bgr, calib, frame.attitude, args.alt, gsd)
                image, to_frame = rect.image, rect.rect_to_frame_px
            except RectificationError:
                image, to_frame = frame.image_bgr, None
            query = matcher.extract_query(image)
            tiles = []
            for chip in bf.candidates:
                px = chip.pixels()
                found = pre.lookup(chip, (int(px.shape[1]), int(px.shape[0])))
                tiles.append(found if found is not None else matcher.extract_tile(px))
            ev: dict[str, list[dict[str, Any]]] = {name: [] for name in chosen}
            for i, tile in enumerate(tiles):
                for name, rule in chosen.items():
                    t0 = time.perf_counter()
                    corr = rule(query, tile)
                    res = ransac.filter(corr, threshold_px=cfg.ransac_threshold_px)
                    per_rule[name]["ms"].append((time.perf_counter() - t0) * 1e3)
                    inl = np.array(res.inlier_correspondences, dtype=np.float32, copy=True)
                    if to_frame is not None and inl.shape[0]:
                        inl[:, :2] = to_frame(inl[:, :2])
                    n = int(inl.shape[0])
                    ev[name].append(
                        {
                            "cand": i,
                            "putative": int(corr.shape[0]),
                            "inliers": n,
                            "ratio": n / corr.shape[0] if corr.shape[0] else 0.0,
                            "spread": hull_share(inl[:, :2], (calib.width_px, calib.height_px)) if n else 0.0,
                            "inl": inl,
                        }
                    )
            for name in chosen:
                cands = sorted(ev[name], key=lambda e: -e["inliers"])
                best = cands[0]
                row: dict[str, Any] = {k: best[k] for k in ("cand", "putative", "inliers", "ratio", "spread")}
                row["true_chip"] = next(e for e in ev[name] if e["cand"] == 0)["inliers"]
                solved = best["inliers"] >= cfg.min_inliers_threshold
                row["solved"] = solved
                err = math.nan
                if solved:
                    err = _centre_error_m(best["inl"], bf.candidates[best["cand"]], bf, calib)
                row["error_m"] = None if math.isnan(err) else round(err, 2)
                row["right"] = bool(solved and best["cand"] == 0 and err <= RIGHT_M)
                rival = cands[1]["inliers"] if len(cands) > 1 else 0
                wrong_chip = max(
                    (e for e in ev[name] if e["cand"] != 0), key=lambda e: e["inliers"], default=None
                )
                if wrong_chip is not None:
                    row["wrong_chip"] = [
                        wrong_chip["inliers"],
                        wrong_chip["putative"],
                        round(wrong_chip["ratio"], 4),
                    ]
                row["rival_share"] = rival / best["inliers"] if best["inliers"] else 0.0
                reason = None
                if not solved:
                    reason = "insufficient_inliers"
                elif best["inliers"] < integ.min_inliers:
                    reason = "too_few_inliers"
                elif best["ratio"] < integ.min_inlier_ratio:
                    reason = "low_inlier_ratio"
                elif best["spread"] < integ.min_spread_share:
                    reason = "narrow_spread"
                elif rival >= integ.ambiguity_inlier_share * best["inliers"]:
                    reason = "ambiguous_candidates"
                row["refused"] = reason
                per_rule[name]["rows"].append(row)
        summary = {}
        for name, data in per_rule.items():
            rows = data["rows"]
            solved = [r for r in rows if r["solved"]]
            right = [r for r in solved if r["right"]]
            wrong = [r for r in solved if not r["right"]]
            acc = [r for r in solved if r["refused"] is None]
            summary[name] = {
                "frames": len(rows),
                "solved": len(solved),
                "right": len(right),
                "wrong": len(wrong),
                "accepted": len(acc),
                "accepted_right": sum(r["right"] for r in acc),
                "accepted_wrong": sum(not r["right"] for r in acc),
                "refused": {
                    k: sum(r["refused"] == k for r in rows) for k in {r["refused"] for r in rows} if k
                },
                "ratio_right_p5_p50": [_pct([r["ratio"] for r in right], q) for q in (5, 50)],
                "ratio_wrong_p50_p95_max": [_pct([r["ratio"] for r in wrong], q) for q in (50, 95, 100)],
                "inliers_right_p5_p50": [_pct([r["inliers"] for r in right], q) for q in (5, 50)],
                "putative_right_p50": _pct([r["putative"] for r in right], 50),
                "inliers_wrong_p50_max": [_pct([r["inliers"] for r in wrong], q) for q in (50, 100)],
                "true_chip_inliers_p50": _pct([r["true_chip"] for r in rows], 50),
                "wrong_chip_inliers_p50_max": [
                    _pct([r["wrong_chip"][0] for r in rows if "wrong_chip" in r], q) for q in (50, 100)
                ],
                "wrong_chip_ratio_p50_p95_max": [
                    _pct([r["wrong_chip"][2] for r in rows if "wrong_chip" in r], q) for q in (50, 95, 100)
                ],
                "ms_per_candidate_p50_p95": [_pct(data["ms"], q) for q in (50, 95)],
                "wrong_errors_m": sorted(r["error_m"] for r in wrong if r["error_m"] is not None),
            }
            print(frames_path.name, name, json.dumps(summary[name]), flush=True)
        report[frames_path.name] = {"summary": summary, "rows": {k: v["rows"] for k, v in per_rule.items()}}
    report["load_end"] = os.getloadavg()
    print("load", load0, report["load_end"])
    if args.out:
        args.out.write_text(json.dumps(report, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
