"""C3 ``xfeat_mnn``: XFeat through the real ONNX Runtime, matched by mutual nearest neighbours.

The contract tests run the real XFeat export (``registry_models_fixture``) on real NAIP imagery (a 2009
map cache, a rotated 2020 frame); the matching rule is also checked on its own against a brute-force
definition of "mutual".
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("onnx")

from conftest import REPO_ROOT, shared_path
from gps_denied_onboard.components.c3_matcher import CrossDomainMatcher, RollingHealthWindow, registry
from gps_denied_onboard.components.c3_matcher.features import Features
from gps_denied_onboard.components.c3_matcher.xfeat_mnn import (
    XFEAT_MNN_MIN_SIMILARITY,
    XFeatMnnMatcher,
    create,
    match_mutual_nn,
)
from gps_denied_onboard.components.c4_pose.integrity import MatchEvidence
from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.components.c7_inference.onnx_runtime import OnnxInferenceRuntime
from gps_denied_onboard.components.c7_inference.protocol import EngineLoadError
from gps_denied_onboard.components.c10_cache_build import build_cache
from gps_denied_onboard.components.c10_cache_build.manifest import CacheManifest
from gps_denied_onboard.components.c10_cache_build.tile_features import build_tile_features
from gps_denied_onboard.config import Config, MatcherConfig, load_config
from gps_denied_onboard.constants import FdrKind
from gps_denied_onboard.helpers.ransac_filter import RansacFilter
from gps_denied_onboard.runtime_root.compose import _matcher_deps, open_tile_features
from registry_models_fixture import registry_models  # noqa: F401 - session fixture
from test_c3_matcher_contract import FakeFdrClient
from test_tile_features import CountingRuntime, rotated_frame_over_tile

NAIP = ("data", "naip_timeseries", "naip")
NAIP_2009 = "m_4709963_se_14_1_20090818.tif"
NAIP_2020 = "m_4709963_se_14_1_20200831.tif"


def _brute_force_mutual(d0: np.ndarray, d1: np.ndarray) -> set[tuple[int, int]]:
    """Pairs (i, j) where j is i's most similar descriptor and i is j's, by the definition."""
    a = d0 / np.linalg.norm(d0, axis=1, keepdims=True)
    b = d1 / np.linalg.norm(d1, axis=1, keepdims=True)
    sim = a @ b.T
    return {
        (i, j)
        for i in range(sim.shape[0])
        for j in [int(np.argmax(sim[i]))]
        if int(np.argmax(sim[:, j])) == i
    }


def _features(rng: np.random.Generator, n: int, image_size: tuple[int, int]) -> Features:
    kp = rng.uniform(0, image_size[0], (n, 2)).astype(np.float32)
    return Features(kp, rng.normal(size=(n, 64)).astype(np.float32), image_size)


def _model_paths(model_dir: Path) -> tuple[Path, Path]:
    from gps_denied_onboard.helpers.model_manifest import verify_model_dir
    from gps_denied_onboard.models.learned_export import family_models

    extractor, lighterglue = family_models(verify_model_dir(model_dir), "xfeat")  # type: ignore[misc]
    return model_dir / extractor.file, model_dir / lighterglue.file


def _runtime() -> CountingRuntime:
    return CountingRuntime(OnnxInferenceRuntime(intra_op_threads=2, providers=["CPUExecutionProvider"]))


def _daemon_config(cache: Path, matcher: MatcherConfig) -> Config:
    base = load_config(REPO_ROOT / "config" / "sitl.yaml", ())
    return dataclasses.replace(base, cache=dataclasses.replace(base.cache, dir=str(cache)), matcher=matcher)


# --- the matching rule --------------------------------------------------------------------------------------
def _pairs(query: Features, tile: Features, corr: np.ndarray) -> list[tuple[int, int]]:
    """(query index, tile index) of each correspondence, found back from its keypoints."""
    qi = [int(np.flatnonzero((query.keypoints_px == row[:2]).all(axis=1))[0]) for row in corr]
    ti = [int(np.flatnonzero((tile.keypoints_px == row[2:]).all(axis=1))[0]) for row in corr]
    return list(zip(qi, ti, strict=True))


def test_mnn_matches_are_exactly_the_mutual_nearest_neighbours() -> None:
    """Without a floor every returned pair is mutual, every mutual pair is returned, each index at most
    once, and the correspondences are the two keypoints, with no confidence column. With the default
    floor, the mutual pairs whose cosine reaches it."""
    rng = np.random.default_rng(3)
    query, tile = _features(rng, 300, (640, 480)), _features(rng, 500, (512, 512))
    # Half the tile's descriptors are noisy copies of query descriptors: many mutual pairs, not all.
    tile.descriptors[:150] = query.descriptors[:150] + rng.normal(scale=0.3, size=(150, 64))
    corr = match_mutual_nn(query, tile, min_similarity=-1.0)
    assert corr.dtype == np.float32 and corr.ndim == 2 and corr.shape[1] == 4
    pairs = _pairs(query, tile, corr)
    expected = _brute_force_mutual(query.descriptors, tile.descriptors)
    assert set(pairs) == expected and len(pairs) == len(expected)
    assert len({i for i, _ in pairs}) == len(pairs) and len({j for _, j in pairs}) == len(pairs)
    assert len(expected) > 150  # the copies and some chance pairs of random descriptors

    a = query.descriptors / np.linalg.norm(query.descriptors, axis=1, keepdims=True)
    b = tile.descriptors / np.linalg.norm(tile.descriptors, axis=1, keepdims=True)
    floored = set(_pairs(query, tile, match_mutual_nn(query, tile)))
    assert floored == {(i, j) for i, j in expected if a[i] @ b[j] >= XFEAT_MNN_MIN_SIMILARITY}
    assert 140 <= len(floored) < len(expected)


def test_mnn_ties_go_to_the_lower_index_as_argmax_both_ways() -> None:
    """Descriptors with many equal similarities: exactly the pairs of argmax both ways (first index wins)."""
    rng = np.random.default_rng(5)
    for _ in range(50):
        query, tile = _features(rng, 40, (64, 64)), _features(rng, 30, (64, 64))
        query.descriptors[:] = rng.integers(-1, 2, query.descriptors.shape)
        tile.descriptors[:] = rng.integers(-1, 2, tile.descriptors.shape)
        query.descriptors[:, 0] = tile.descriptors[:, 0] = 2  # no zero vector
        query.descriptors[:, 3:] = tile.descriptors[:, 3:] = 0  # 3-D: ties are common
        pairs = _pairs(query, tile, match_mutual_nn(query, tile, min_similarity=-1.0))
        assert set(pairs) == _brute_force_mutual(query.descriptors, tile.descriptors)


def test_mnn_no_features_gives_no_matches() -> None:
    """An image with no keypoints on either side gives an empty (0, 4) set, not an error."""
    rng = np.random.default_rng(0)
    empty = Features(np.empty((0, 2), np.float32), np.empty((0, 64), np.float32), (64, 64))
    for a, b in ((empty, _features(rng, 10, (64, 64))), (_features(rng, 10, (64, 64)), empty)):
        assert match_mutual_nn(a, b).shape == (0, 4)


# --- registry and composition root --------------------------------------------------------------------------
def test_xfeat_mnn_is_registered_and_takes_no_lightglue() -> None:
    """``xfeat_mnn`` is in the registry; its factory takes no LightGlue helper, so the composition root
    builds none (no LightGlue model is loaded), while ``xfeat`` still gets one."""
    assert "xfeat_mnn" in registry.available_strategies()
    assert not registry.takes("xfeat_mnn", "lightglue_runtime")
    assert registry.takes("xfeat", "lightglue_runtime")
    base = load_config(REPO_ROOT / "config" / "sitl.yaml", ())
    pre = {"c7_inference": object()}
    for strategy, has_lightglue in (("xfeat_mnn", False), ("xfeat", True)):
        config = dataclasses.replace(
            base, matcher=dataclasses.replace(base.matcher, strategy=strategy, lightglue_weights_path=None)
        )
        deps = _matcher_deps(config, pre, RansacFilter(), FakeFdrClient(), RollingHealthWindow(25))  # type: ignore[arg-type]
        assert ("lightglue_runtime" in deps) is has_lightglue
        assert deps["inference_runtime"] is pre["c7_inference"]


def test_xfeat_mnn_missing_weights_path_refused() -> None:
    """No ``matcher.xfeat_weights_path`` -> EngineLoadError naming the key; no runtime -> ValueError."""
    rt = OnnxInferenceRuntime(intra_op_threads=1, providers=["CPUExecutionProvider"])
    config = MatcherConfig(strategy="xfeat_mnn")
    with pytest.raises(EngineLoadError, match=r"matcher\.xfeat_weights_path"):
        create(config, RansacFilter(), rt, RollingHealthWindow(25))
    with pytest.raises(ValueError, match="inference_runtime"):
        create(config, RansacFilter(), None, RollingHealthWindow(25))  # type: ignore[arg-type]


# --- the real export on real imagery ------------------------------------------------------------------------
def test_real_xfeat_mnn_matches_a_2020_frame_to_its_2009_chip_with_shared_tile_features(
    registry_models: Callable[[str], Path],  # noqa: F811
    tmp_path: Path,
) -> None:
    """Real XFeat export, real ORT, 2009 NAIP cache, a rotated 2020 frame: the true chip wins with inliers
    on the true homography and no confidences; the ``xfeat`` tile-feature set serves ``xfeat_mnn`` (the
    composition root opens it for this strategy), giving exactly the live result with one extraction."""
    extractor, _lighterglue = _model_paths(registry_models("xfeat"))
    cache = tmp_path / "c2009"
    build_cache(shared_path(*NAIP, NAIP_2009), cache, progress=False)
    frames = tmp_path / "c2020"
    build_cache(shared_path(*NAIP, NAIP_2020), frames, progress=False, zoom=CacheManifest.load(cache).zoom)
    config = MatcherConfig(strategy="xfeat_mnn", xfeat_weights_path=str(extractor), min_inliers_threshold=25)

    def build(tile_features: object = None) -> tuple[XFeatMnnMatcher, CountingRuntime]:
        rt = _runtime()
        m = registry.create_matcher(
            "xfeat_mnn",
            config=config,
            ransac_filter=RansacFilter(),
            inference_runtime=rt,
            health_window=RollingHealthWindow(25),
            fdr_client=None,
            tile_features=tile_features,
        )
        assert isinstance(m, XFeatMnnMatcher) and isinstance(m, CrossDomainMatcher)
        return m, rt

    live, live_rt = build()
    assert live.extractor_identity.strategy == "xfeat"
    build_tile_features(cache, live, progress=False)
    store = TileStore.open(cache)
    fdr = FakeFdrClient()
    feats = open_tile_features(_daemon_config(cache, config), store, fdr)  # type: ignore[arg-type]
    assert feats is not None and fdr.of(FdrKind.TILE_FEATURES)[0]["used"] is True
    pre, pre_rt = build(feats)

    # A 2020 frame, rotated 8 deg and scaled 1.05, centred on tile 10's chip (same Web-Mercator grid).
    src = TileStore.open(frames)
    frame, rerank, calib, frame_to_mosaic = rotated_frame_over_tile(store, src, config.chip_size_px)
    tile = store.tile_ids[10]
    chip = store.chip(tile, config.chip_size_px)
    t0 = time.perf_counter()
    result = pre.match(frame, rerank, calib)
    pre_ms = (time.perf_counter() - t0) * 1e3
    result_live = live.match(frame, rerank, calib)
    best = result.best
    print(f"xfeat_mnn NAIP 2020 -> 2009: {best.inlier_count} inliers, {pre_ms:.0f} ms with tile features")

    assert result.matcher_label == "xfeat_mnn"
    assert best.tile_id == tile and best.inlier_count >= 25
    assert best.inlier_scores is None
    assert MatchEvidence.of_candidate(best, (calib.width_px, calib.height_px)).mean_confidence is None
    # The inliers lie on the true frame -> chip mapping (chip px = mosaic px - the chip's origin).
    origin = np.array(
        [
            chip.origin_px[0] - store.manifest.tile_range.x0 * store.tile_size_px,
            chip.origin_px[1] - store.manifest.tile_range.y0 * store.tile_size_px,
        ]
    )
    q = best.inlier_correspondences[:, :2].astype(np.float64)
    mapped = (frame_to_mosaic @ np.column_stack([q, np.ones(len(q))]).T).T[:, :2] - origin
    err = np.linalg.norm(mapped - best.inlier_correspondences[:, 2:], axis=1)
    assert np.median(err) < 2.0
    # Shared tile features: the same result as live, and only the query was extracted.
    assert [(c.tile_id, c.inlier_count) for c in result.per_candidate] == [
        (c.tile_id, c.inlier_count) for c in result_live.per_candidate
    ]
    np.testing.assert_array_equal(best.inlier_correspondences, result_live.best.inlier_correspondences)
    assert pre_rt.extractor_calls == 1
    assert live_rt.extractor_calls == len(store) + 1 + len(rerank.candidates)  # build + query + N


# --- cross-date evidence: what the integrity rule gets from mutual nearest neighbours ----------------------
#: Frames per date, and how far (m) from the truth the ground under the principal point may land for a
#: solution to count as right (6 map pixels at zoom 15; cross-date right solutions measured 10-12 m p50).
CROSS_DATE_FRAMES = 6
RIGHT_SOLUTION_M = 20.0


@pytest.mark.slow
@pytest.mark.realdata
def test_real_xfeat_mnn_cross_date_evidence_passes_only_for_right_fixes(
    registry_models: Callable[[str], Path],  # noqa: F811
    tmp_path: Path,
) -> None:
    """NAIP 2009 map, frames of 2014 and 2020 at 1200 m AGL (``naip_cross_date``'s), the chip around the
    footprint first and two far chips (``gdnav bench matcher --first-chip footprint``), the real export:
    every candidate whose evidence would pass the integrity rule's thresholds (``integrity.min_inliers``,
    ``min_inlier_ratio``, ``min_spread_share``) is the true chip with a right solution; no far chip does
    (each is matched, so the test sees their evidence); the true chip wins every solved frame."""
    import cv2

    from gps_denied_onboard.bench.matcher import render_bench_frames, with_cache_candidates
    from gps_denied_onboard.camera.types import CameraCalibration
    from gps_denied_onboard.components.c3_matcher.errors import InsufficientInliersError
    from gps_denied_onboard.config import IntegrityConfig
    from gps_denied_onboard.geo import haversine_m

    extractor, _lighterglue = _model_paths(registry_models("xfeat"))
    cache = tmp_path / "c2009"
    build_cache(shared_path(*NAIP, NAIP_2009), cache, progress=False)
    store = TileStore.open(cache)
    config = MatcherConfig(strategy="xfeat_mnn", xfeat_weights_path=str(extractor))
    matcher = registry.create_matcher(
        "xfeat_mnn",
        config=config,
        ransac_filter=RansacFilter(),
        inference_runtime=_runtime(),
        health_window=RollingHealthWindow(config.min_inliers_threshold),
        fdr_client=None,
    )
    calib = CameraCalibration.from_hfov(640, 480, 70.0)
    size = (calib.width_px, calib.height_px)
    rule = IntegrityConfig()
    solved, wrong_chips_seen, passed = 0, 0, []
    for date in ("m_4709963_se_14_1_20140720.tif", NAIP_2020):
        frames = render_bench_frames(
            shared_path(*NAIP, NAIP_2009),
            calib,
            n_frames=CROSS_DATE_FRAMES,
            n_candidates=1,
            chip_size_px=config.chip_size_px,
            alt_agl_m=1200.0,
            seed=5,
            frames_path=shared_path(*NAIP, date),
        )
        frames = with_cache_candidates(
            frames, store, n_candidates=3, chip_size_px=config.chip_size_px, seed=5, first_chip="footprint"
        )
        for bf in frames:
            try:
                result = matcher.match(bf.frame, bf.rerank_result(), calib)
            except InsufficientInliersError:
                continue
            solved += 1
            true_id = bf.candidates[0].tile_id
            assert result.best.tile_id == true_id, (date, bf.frame.seq)
            for cand in result.per_candidate:
                ev = MatchEvidence.of_candidate(cand, size)
                assert ev.mean_confidence is None
                passes = (
                    ev.inlier_count >= rule.min_inliers
                    and ev.inlier_ratio >= rule.min_inlier_ratio
                    and ev.spread_share >= rule.min_spread_share
                )
                if cand.tile_id != true_id:
                    wrong_chips_seen += 1
                    assert not passes, (date, bf.frame.seq, ev)
                    continue
                # Where the inliers put the ground under the principal point, against the truth.
                corr = cand.inlier_correspondences.astype(np.float64)
                h_mat, _ = cv2.findHomography(corr[:, :2], corr[:, 2:4], 0)
                p = np.array([calib.cx_px, calib.cy_px, 1.0]) @ h_mat.T
                lon, lat = bf.candidates[0].chip_px_to_lonlat(np.array([[p[0] / p[2], p[1] / p[2]]]))
                error_m = float(haversine_m(bf.centre_lonlat[1], bf.centre_lonlat[0], lat[0], lon[0]))
                if passes:
                    passed.append((date, bf.frame.seq, ev.inlier_ratio, error_m))
                    assert error_m <= RIGHT_SOLUTION_M, (date, bf.frame.seq, ev, error_m)
    print(f"xfeat_mnn cross-date: {solved} of {2 * CROSS_DATE_FRAMES} solved, evidence passed by {passed}")
    assert solved >= CROSS_DATE_FRAMES, solved
    assert wrong_chips_seen >= solved, wrong_chips_seen
