"""C3 contract (seed AZ-345 AC-1..AC-12) on DiskLightGlueMatcher, plus the shared pieces: registry,
health window, base loop (query failure, rectified query), DISK preprocessing.

Fakes only at component boundaries, as the seed allows: FakeInferenceRuntime, FakeLightGlueRuntime,
FakeRansacFilter, FakeFdrClient and synthetic frames/chips. The last test runs the strategy through the
real C7 ONNX runtime and the real LightGlue helper with small ONNX models it builds itself.
"""

from __future__ import annotations

import math
import time
import uuid
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pytest
from structlog.testing import capture_logs

from gps_denied_onboard.camera.types import Attitude, CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c2_5_rerank.types import RerankCandidate, RerankResult
from gps_denied_onboard.components.c3_matcher import (
    CrossDomainMatcher,
    InsufficientInliersError,
    RollingHealthWindow,
    StrategyNotLinkedError,
    available_strategies,
    create_matcher,
    register_strategy,
)
from gps_denied_onboard.components.c3_matcher.classical import ClassicalMatcher
from gps_denied_onboard.components.c3_matcher.disk_lightglue import (
    DISK_SIGNATURE,
    DiskLightGlueMatcher,
    preprocess_disk,
)
from gps_denied_onboard.components.c3_matcher.registry import _STRATEGY_REGISTRY
from gps_denied_onboard.components.c6_tiles.types import TileId, TilePixelsHandle
from gps_denied_onboard.components.c7_inference.protocol import EngineLoadError
from gps_denied_onboard.config import MatcherConfig
from gps_denied_onboard.constants import FdrKind, LogEvent
from gps_denied_onboard.helpers.frame_rectifier import rectify_to_map_frame
from gps_denied_onboard.helpers.ransac_filter import RansacFilter, RansacResult

CALIB = CameraCalibration.from_hfov(640, 480, 70.0)
CONFIG = MatcherConfig(
    strategy="disk_lightglue",
    disk_weights_path="/models/disk.onnx",
    min_inliers_threshold=60,
    residual_warn_threshold_px=2.5,
)


# --- fakes at the component boundaries ---------------------------------------------------------------
class FakeInferenceRuntime:
    """DISK engine double: deterministic keypoints on a grid; raises on the listed call numbers."""

    def __init__(self, fail_on_calls: tuple[int, ...] = (), n_keypoints: int = 200) -> None:
        self.fail_on_calls = set(fail_on_calls)
        self.n_keypoints = n_keypoints
        self.calls = 0
        self.loaded: list[tuple[str, object]] = []
        self.input_shapes: list[tuple[int, ...]] = []

    def load_engine(self, path: str, signature: object = None) -> str:
        self.loaded.append((path, signature))
        return "disk-0"

    def run(self, engine_id: str, inputs: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        self.calls += 1
        if self.calls in self.fail_on_calls:
            raise RuntimeError("CUDA error: an illegal memory access was encountered")
        image = inputs["image"]
        self.input_shapes.append(image.shape)
        _, _, h, w = image.shape
        n = self.n_keypoints
        xs = (np.arange(n) * 7) % (w - 1)
        ys = (np.arange(n) * 13) % (h - 1)
        kpts = np.stack([xs, ys], axis=1)[None].astype(np.int64)
        scores = np.linspace(1.0, 0.1, n, dtype=np.float32)[None]
        desc = np.tile(np.eye(128, dtype=np.float32)[np.arange(n) % 128], (1, 1))[None]
        return {"keypoints": kpts, "scores": scores, "descriptors": desc}

    def provider(self, engine_id: str) -> str:
        return "CPUExecutionProvider"


class FakeLightGlueRuntime:
    """LightGlue double: matches i <-> i; raises on the listed call numbers."""

    def __init__(self, fail_on_calls: tuple[int, ...] = ()) -> None:
        self.fail_on_calls = set(fail_on_calls)
        self.calls = 0

    def match_pair(self, kpts0, desc0, kpts1, desc1, *, image_size0, image_size1):  # type: ignore[no-untyped-def]
        self.calls += 1
        if self.calls in self.fail_on_calls:
            raise RuntimeError("lightglue engine failed")
        m = min(len(kpts0), len(kpts1))
        idx = np.arange(m, dtype=np.int64)
        return np.stack([idx, idx], axis=1), np.ones(m, dtype=np.float32)


class FakeRansacFilter:
    """RANSAC double: returns scripted (inliers, residual) per call, in call order."""

    def __init__(self, script: list[tuple[int, float]]) -> None:
        self.script = list(script)
        self.calls: list[tuple[int, float]] = []

    def filter(self, correspondences: np.ndarray, threshold_px: float) -> RansacResult:
        self.calls.append((int(correspondences.shape[0]), threshold_px))
        inliers, residual = self.script[(len(self.calls) - 1) % len(self.script)]
        rows = (np.arange(inliers * 4, dtype=np.float32).reshape(inliers, 4) % 300.0).astype(np.float32)
        return RansacResult(rows, 50, residual if inliers else math.inf, np.eye(3) if inliers else None)


class FakeFdrClient:
    def __init__(self) -> None:
        self.records: list[tuple[str, dict[str, object]]] = []

    def record(self, kind: str, fields: Mapping[str, object]) -> None:
        self.records.append((kind, dict(fields)))

    def of(self, kind: str) -> list[dict[str, object]]:
        return [f for k, f in self.records if k == kind]


class SpyHealthWindow(RollingHealthWindow):
    """The real window, recording each update call."""

    def __init__(self) -> None:
        super().__init__(CONFIG.min_inliers_threshold)
        self.updates: list[tuple[int, int, bool]] = []

    def update(self, now_ns: int, *, best_inlier_count: int, had_backbone_error: bool) -> None:
        self.updates.append((now_ns, best_inlier_count, had_backbone_error))
        super().update(now_ns, best_inlier_count=best_inlier_count, had_backbone_error=had_backbone_error)


class SyntheticChip:
    """TilePixelsHandle over a synthetic 512x512 chip."""

    def __init__(self, n: int) -> None:
        rng = np.random.default_rng(n)
        self._pixels = rng.integers(0, 255, (512, 512, 3), dtype=np.uint8)
        self._pixels.setflags(write=False)
        self._tile_id = TileId.of(18, 50.0 + n * 0.001, 30.0)
        self.pixel_calls = 0

    @property
    def tile_id(self) -> TileId:
        return self._tile_id

    @property
    def gsd_m_px(self) -> float:
        return 0.3

    def pixels(self) -> np.ndarray:
        self.pixel_calls += 1
        return self._pixels

    def chip_px_to_lonlat(self, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = np.asarray(px, dtype=np.float64).reshape(-1, 2)
        return 30.0 + p[:, 0] * 1e-6, self._tile_id.lat_deg - p[:, 1] * 1e-6

    def lonlat_to_chip_px(self, lon_deg: np.ndarray, lat_deg: np.ndarray) -> np.ndarray:
        return np.column_stack(
            [(np.asarray(lon_deg) - 30.0) / 1e-6, (self._tile_id.lat_deg - np.asarray(lat_deg)) / 1e-6]
        )


def _frame(attitude: Attitude | None = None, alt_agl_m: float | None = None) -> NavCameraFrame:
    image = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    return NavCameraFrame(uuid.uuid4(), 1, 0, image, attitude, alt_agl_m, time.monotonic_ns())


def _rerank(frame: NavCameraFrame, n: int = 3) -> RerankResult:
    chips = [SyntheticChip(i) for i in range(n)]
    return RerankResult(
        frame.frame_id, [RerankCandidate(c.tile_id, c, -1, 0.1 * i) for i, c in enumerate(chips)], 0
    )


def _disk(
    script: list[tuple[int, float]],
    *,
    runtime: FakeInferenceRuntime | None = None,
    lightglue: FakeLightGlueRuntime | None = None,
    config: MatcherConfig = CONFIG,
) -> tuple[DiskLightGlueMatcher, FakeFdrClient, SpyHealthWindow, FakeRansacFilter]:
    fdr, health, ransac = FakeFdrClient(), SpyHealthWindow(), FakeRansacFilter(script)
    matcher = DiskLightGlueMatcher(
        runtime or FakeInferenceRuntime(),
        lightglue or FakeLightGlueRuntime(),
        ransac,
        fdr,
        health,
        config,  # type: ignore[arg-type]
    )
    return matcher, fdr, health, ransac


def _events(logs: list[dict[str, object]], event: str) -> list[dict[str, object]]:
    return [entry for entry in logs if entry["event"] == event]


# --- AC-1..AC-12 ---------------------------------------------------------------------------------------
def test_ac01_disk_lightglue_conforms_to_protocol() -> None:
    """AC-1: DiskLightGlueMatcher (and ClassicalMatcher) are CrossDomainMatchers."""
    matcher, *_ = _disk([(100, 1.0)])
    classical = ClassicalMatcher(RansacFilter(), None, RollingHealthWindow(25), MatcherConfig())
    assert isinstance(matcher, CrossDomainMatcher)
    assert isinstance(classical, CrossDomainMatcher)


def test_ac02_best_candidate_tie_broken_by_lower_residual() -> None:
    """AC-2: inliers [120, 80, 120] with residuals [1.4, 1.0, 1.1] -> order (120, 1.1), (120, 1.4), 80."""
    matcher, *_ = _disk([(120, 1.4), (80, 1.0), (120, 1.1)])
    frame = _frame()
    rerank = _rerank(frame)
    result = matcher.match(frame, rerank, CALIB)
    assert result.best_candidate_idx == 0
    got = [(c.inlier_count, c.per_candidate_residual_px) for c in result.per_candidate]
    assert got == [(120, 1.1), (120, 1.4), (80, 1.0)]
    assert result.per_candidate[0].tile_id == rerank.candidates[2].tile_id
    assert result.reprojection_residual_px == 1.1
    assert result.matcher_label == "disk_lightglue"
    assert result.frame_id == frame.frame_id


def test_ac03_disk_forward_failure_drops_candidate_and_continues() -> None:
    """AC-3: DISK forward raising on the 2nd candidate drops it; one ERROR log + one FDR record."""
    runtime = FakeInferenceRuntime(fail_on_calls=(3,))  # call 1 = query, 2 = cand 1, 3 = cand 2
    matcher, fdr, _, _ = _disk([(100, 1.0), (90, 1.2)], runtime=runtime)
    frame = _frame()
    rerank = _rerank(frame)
    with capture_logs() as logs:
        result = matcher.match(frame, rerank, CALIB)
    assert len(result.per_candidate) == 2
    assert result.candidates_dropped == 1 and result.candidates_input == 3
    errors = _events(logs, LogEvent.C3_BACKBONE_ERROR)
    assert len(errors) == 1
    assert errors[0]["log_level"] == "error"
    assert errors[0]["phase"] == "disk_forward"
    assert errors[0]["tile_id"] == list(rerank.candidates[1].tile_id)
    records = fdr.of(FdrKind.MATCHER_BACKBONE_ERROR)
    assert len(records) == 1 and records[0]["phase"] == "disk_forward"
    assert records[0]["tile_id"] == list(rerank.candidates[1].tile_id)
    assert {c.tile_id for c in result.per_candidate} == {
        rerank.candidates[0].tile_id,
        rerank.candidates[2].tile_id,
    }


def test_ac04_lightglue_failure_drops_candidate_with_phase() -> None:
    """AC-4: LightGlue raising on the 1st candidate drops it with phase lightglue_match."""
    matcher, fdr, _, _ = _disk([(100, 1.0)], lightglue=FakeLightGlueRuntime(fail_on_calls=(1,)))
    frame = _frame()
    rerank = _rerank(frame)
    with capture_logs() as logs:
        result = matcher.match(frame, rerank, CALIB)
    assert [c.tile_id for c in result.per_candidate] == [
        rerank.candidates[1].tile_id,
        rerank.candidates[2].tile_id,
    ]
    errors = _events(logs, LogEvent.C3_BACKBONE_ERROR)
    assert [e["phase"] for e in errors] == ["lightglue_match"]
    assert [r["phase"] for r in fdr.of(FdrKind.MATCHER_BACKBONE_ERROR)] == ["lightglue_match"]


def test_ac05_all_below_threshold_raises_insufficient_inliers() -> None:
    """AC-5: every candidate < 60 inliers -> InsufficientInliersError, ERROR log, FDR, health(0, False)."""
    matcher, fdr, health, _ = _disk([(59, 1.0), (30, 1.0), (10, 1.0)])
    frame = _frame()
    with capture_logs() as logs, pytest.raises(InsufficientInliersError) as info:
        matcher.match(frame, _rerank(frame), CALIB)
    assert info.value.best_inlier_count == 59 and info.value.threshold == 60
    assert len(_events(logs, LogEvent.C3_INSUFFICIENT_INLIERS)) == 1
    assert _events(logs, LogEvent.C3_INSUFFICIENT_INLIERS)[0]["log_level"] == "error"
    assert len(fdr.of(FdrKind.MATCHER_INSUFFICIENT_INLIERS)) == 1
    assert fdr.of(FdrKind.MATCHER_FRAME_DONE) == []
    assert [(u[1], u[2]) for u in health.updates] == [(0, False)]


def test_ac06_all_forwards_fail_raises_with_per_candidate_logs() -> None:
    """AC-6: every candidate's DISK forward raises -> per-candidate ERRORs + final ERROR; health(0, True)."""
    runtime = FakeInferenceRuntime(fail_on_calls=(2, 3, 4))
    matcher, fdr, health, ransac = _disk([(100, 1.0)], runtime=runtime)
    frame = _frame()
    with capture_logs() as logs, pytest.raises(InsufficientInliersError) as info:
        matcher.match(frame, _rerank(frame), CALIB)
    assert info.value.candidates_dropped == 3
    assert len(_events(logs, LogEvent.C3_BACKBONE_ERROR)) == 3
    assert len(_events(logs, LogEvent.C3_INSUFFICIENT_INLIERS)) == 1
    assert len(fdr.of(FdrKind.MATCHER_BACKBONE_ERROR)) == 3
    assert len(fdr.of(FdrKind.MATCHER_INSUFFICIENT_INLIERS)) == 1
    assert ransac.calls == []
    assert [(u[1], u[2]) for u in health.updates] == [(0, True)]


def test_ac07_residual_above_threshold_warns_once() -> None:
    """AC-7: best residual 4.2 > 2.5 -> one WARN with residual_px and threshold_px."""
    matcher, *_ = _disk([(120, 4.2), (80, 1.0)])
    frame = _frame()
    with capture_logs() as logs:
        matcher.match(frame, _rerank(frame, 2), CALIB)
    warns = _events(logs, LogEvent.C3_RESIDUAL_ABOVE_THRESHOLD)
    assert len(warns) == 1
    assert warns[0]["log_level"] == "warning"
    assert warns[0]["residual_px"] == 4.2 and warns[0]["threshold_px"] == 2.5


def test_ac07_residual_below_threshold_does_not_warn() -> None:
    """AC-7 (negative): best residual under the threshold -> no WARN."""
    matcher, *_ = _disk([(120, 1.2)])
    frame = _frame()
    with capture_logs() as logs:
        matcher.match(frame, _rerank(frame, 1), CALIB)
    assert _events(logs, LogEvent.C3_RESIDUAL_ABOVE_THRESHOLD) == []


def test_ac08_health_updated_exactly_once_per_match_on_every_outcome() -> None:
    """AC-8: success, partial drop and all-failed each give exactly one update with the right values."""
    runtime = FakeInferenceRuntime(fail_on_calls=(3, 6, 7, 8))
    # frame 1: calls 1-4 (cand 2 fails); frame 2: query at 5, all candidates fail (6-8)
    matcher, _, health, _ = _disk([(100, 1.0), (70, 1.0)], runtime=runtime)
    matcher.tile_cache.clear()
    f1 = _frame()
    result = matcher.match(f1, _rerank(f1), CALIB)
    assert health.updates[-1][1:] == (result.best.inlier_count, True)
    assert len(health.updates) == 1
    matcher.tile_cache.clear()
    f2 = _frame()
    with pytest.raises(InsufficientInliersError):
        matcher.match(f2, _rerank(f2), CALIB)
    assert len(health.updates) == 2 and health.updates[-1][1:] == (0, True)
    matcher.tile_cache.clear()
    f3 = _frame()
    matcher.match(f3, _rerank(f3), CALIB)
    assert len(health.updates) == 3 and health.updates[-1][1:] == (100, False)


def test_ac09_inlier_correspondences_are_float32_i_by_4() -> None:
    """AC-9: every CandidateMatchSet has (inlier_count, 4) float32 correspondences."""
    matcher, *_ = _disk([(120, 1.4), (80, 1.0), (64, 1.1)])
    frame = _frame()
    result = matcher.match(frame, _rerank(frame), CALIB)
    for cand in result.per_candidate:
        assert cand.inlier_correspondences.shape == (cand.inlier_count, 4)
        assert cand.inlier_correspondences.dtype == np.float32


def test_ac10_same_inputs_give_identical_results() -> None:
    """AC-10: three calls on the same inputs return identical per-candidate content."""
    matcher, *_ = _disk([(120, 1.4), (80, 1.0), (120, 1.1)])
    frame = _frame()
    rerank = _rerank(frame)
    results = [matcher.match(frame, rerank, CALIB) for _ in range(3)]
    for r in results[1:]:
        assert r.best_candidate_idx == results[0].best_candidate_idx
        for a, b in zip(r.per_candidate, results[0].per_candidate, strict=True):
            assert a.tile_id == b.tile_id and a.inlier_count == b.inlier_count
            assert a.per_candidate_residual_px == b.per_candidate_residual_px
            assert np.array_equal(a.inlier_correspondences, b.inlier_correspondences)


def test_ac11_registry_wires_disk_lightglue_with_shared_helpers() -> None:
    """AC-11: create_matcher builds it, loads DISK at create time, logs ready once, shares helpers."""
    runtime, lightglue, ransac = FakeInferenceRuntime(), FakeLightGlueRuntime(), RansacFilter()
    with capture_logs() as logs:
        matcher = create_matcher(
            "disk_lightglue",
            config=CONFIG,
            lightglue_runtime=lightglue,
            ransac_filter=ransac,
            inference_runtime=runtime,
            health_window=RollingHealthWindow(CONFIG.min_inliers_threshold),
            fdr_client=FakeFdrClient(),
        )
    assert isinstance(matcher, DiskLightGlueMatcher)
    assert matcher._lightglue_runtime is lightglue
    assert matcher._ransac_filter is ransac
    assert runtime.loaded == [(CONFIG.disk_weights_path, DISK_SIGNATURE)]
    ready = _events(logs, LogEvent.C3_READY)
    assert len(ready) == 1 and ready[0]["log_level"] == "info"
    assert ready[0]["strategy"] == "disk_lightglue"
    assert ready[0]["min_inliers_threshold"] == 60 and ready[0]["residual_warn_threshold_px"] == 2.5


def test_ac12_frame_done_record_has_seed_fields() -> None:
    """AC-12: one matcher.frame_done record with exactly the seed's fields and values."""
    runtime = FakeInferenceRuntime(fail_on_calls=(3,))
    matcher, fdr, _, _ = _disk([(120, 1.1), (90, 1.5)], runtime=runtime)
    frame = _frame()
    rerank = _rerank(frame)
    matcher.match(frame, rerank, CALIB)
    records = fdr.of(FdrKind.MATCHER_FRAME_DONE)
    assert records == [
        {
            "frame_id": str(frame.frame_id),
            "candidates_input": 3,
            "candidates_dropped": 1,
            "best_inlier_count": 120,
            "best_residual_px": 1.1,
            "best_tile_id": list(rerank.candidates[0].tile_id),
        }
    ]


# --- beyond the ACs: the shared loop, registry, health window, preprocessing --------------------------
def test_c3_query_forward_failure_fails_frame_once() -> None:
    """A failing query forward logs phase disk_forward_query, raises, and updates health once."""
    matcher, fdr, health, ransac = _disk([(100, 1.0)], runtime=FakeInferenceRuntime(fail_on_calls=(1,)))
    frame = _frame()
    with capture_logs() as logs, pytest.raises(InsufficientInliersError) as info:
        matcher.match(frame, _rerank(frame), CALIB)
    assert info.value.candidates_dropped == 3
    assert [e["phase"] for e in _events(logs, LogEvent.C3_BACKBONE_ERROR)] == ["disk_forward_query"]
    assert len(fdr.of(FdrKind.MATCHER_INSUFFICIENT_INLIERS)) == 1
    assert ransac.calls == [] and [(u[1], u[2]) for u in health.updates] == [(0, True)]


def test_c3_zero_inlier_candidate_dropped_without_backbone_error() -> None:
    """A candidate with zero RANSAC inliers is dropped (DEBUG log), not reported as a backbone error."""
    matcher, fdr, health, _ = _disk([(0, math.inf), (100, 1.0), (90, 1.0)])
    frame = _frame()
    with capture_logs() as logs:
        result = matcher.match(frame, _rerank(frame), CALIB)
    assert result.candidates_dropped == 1 and len(result.per_candidate) == 2
    assert len(_events(logs, LogEvent.C3_ZERO_INLIERS)) == 1
    assert fdr.of(FdrKind.MATCHER_BACKBONE_ERROR) == []
    assert health.updates[-1][1:] == (100, False)


def test_c3_empty_rerank_result_raises_insufficient_inliers() -> None:
    """No candidates at all -> InsufficientInliersError, health updated once."""
    matcher, _, health, _ = _disk([(100, 1.0)])
    frame = _frame()
    with pytest.raises(InsufficientInliersError):
        matcher.match(frame, RerankResult(frame.frame_id, [], 0), CALIB)
    assert len(health.updates) == 1


def test_c3_mismatched_frame_id_is_rejected() -> None:
    """A rerank result for another frame is a wiring error, and still counts once in health."""
    matcher, _, health, _ = _disk([(100, 1.0)])
    frame = _frame()
    with pytest.raises(ValueError, match="not for frame"):
        matcher.match(frame, _rerank(_frame()), CALIB)
    assert len(health.updates) == 1


def test_c3_tile_features_cached_across_frames() -> None:
    """The second frame over the same chips runs DISK on the query only."""
    runtime = FakeInferenceRuntime()
    matcher, *_ = _disk([(100, 1.0)], runtime=runtime)
    f1 = _frame()
    rerank = _rerank(f1)
    matcher.match(f1, rerank, CALIB)
    assert runtime.calls == 4
    f2 = _frame()
    matcher.match(f2, RerankResult(f2.frame_id, rerank.candidates, 0), CALIB)
    assert runtime.calls == 5
    assert matcher.tile_cache.hits == 3


def test_c3_rectified_query_maps_inliers_back_to_frame_pixels() -> None:
    """With attitude and altitude the query is rectified; inlier query px are mapped back to the frame."""

    class PassthroughRansac(FakeRansacFilter):
        def filter(self, correspondences: np.ndarray, threshold_px: float) -> RansacResult:
            self.received = correspondences.copy()
            return RansacResult(correspondences[:80].copy(), 0, 1.0, np.eye(3))

    ransac = PassthroughRansac([])
    runtime = FakeInferenceRuntime()
    health = SpyHealthWindow()
    matcher = DiskLightGlueMatcher(runtime, FakeLightGlueRuntime(), ransac, None, health, CONFIG)  # type: ignore[arg-type]
    attitude, alt = Attitude(0.02, -0.03, math.radians(75.0)), 120.0
    frame = _frame(attitude, alt)
    result = matcher.match(frame, _rerank(frame, 1), CALIB)
    rect = rectify_to_map_frame(frame.image_bgr, CALIB, attitude, alt, 0.3)
    # DISK saw the rectified query, not the 640x480 frame.
    assert runtime.input_shapes[0] != (1, 3, 480, 640)
    expected = rect.rect_to_frame_px(ransac.received[:80, :2])
    np.testing.assert_allclose(result.best.inlier_correspondences[:, :2], expected, atol=1e-3)
    np.testing.assert_array_equal(result.best.inlier_correspondences[:, 2:], ransac.received[:80, 2:])


def test_c3_disk_missing_weights_path_refused_at_construction() -> None:
    """No disk_weights_path -> EngineLoadError naming the config key, before any frame."""
    with pytest.raises(EngineLoadError, match=r"matcher\.disk_weights_path"):
        _disk([(1, 1.0)], config=MatcherConfig(strategy="disk_lightglue"))


def test_c3_preprocess_disk_pads_to_multiple_of_16_and_scales() -> None:
    """DISK input: long side = input_long_side_px, sides padded to multiples of 16, RGB in [0, 1]."""
    image = np.zeros((300, 500, 3), dtype=np.uint8)
    image[..., 2] = 255  # red in BGR
    tensor, (sx, sy) = preprocess_disk(image, 640)
    assert tensor.shape == (1, 3, 384, 640) and tensor.dtype == np.float32
    assert tensor[0, 0, :384, :].max() == 1.0 and tensor[0, 2].max() == 0.0  # R channel first
    assert sx == pytest.approx(640 / 500) and sy == pytest.approx(384 / 300)
    assert tensor[0, 0, 384 - 1, :].min() == 1.0  # 300 * 1.28 = 384: no padding rows here


def test_c3_registry_unknown_strategy_lists_valid_names() -> None:
    """An unknown strategy name raises StrategyNotLinkedError naming the valid strategies."""
    with pytest.raises(StrategyNotLinkedError, match="classical, disk_lightglue"):
        create_matcher("superglue", config=MatcherConfig())


def test_c3_registry_register_strategy_and_conflict() -> None:
    """register_strategy adds a name; registering another factory under it is refused."""

    def factory(
        config: MatcherConfig, ransac_filter: RansacFilter, health_window: RollingHealthWindow
    ) -> ClassicalMatcher:
        return ClassicalMatcher(ransac_filter, None, health_window, config)

    try:
        register_strategy("test_only", factory)
        assert "test_only" in available_strategies()
        matcher = create_matcher(
            "test_only",
            config=MatcherConfig(),
            ransac_filter=RansacFilter(),
            health_window=RollingHealthWindow(25),
            inference_runtime=FakeInferenceRuntime(),  # unused by this factory: filtered out
        )
        assert isinstance(matcher, ClassicalMatcher)
        with pytest.raises(ValueError, match="already registered"):
            register_strategy("test_only", lambda **_: matcher)
    finally:
        _STRATEGY_REGISTRY.pop("test_only", None)


def test_c3_registry_missing_dependency_is_named() -> None:
    """A factory dependency that was not given is named in the TypeError."""
    with pytest.raises(TypeError, match="health_window"):
        create_matcher("classical", config=MatcherConfig(), ransac_filter=RansacFilter())


def test_health_window_counts_consecutive_low_and_mean_over_60s() -> None:
    """consecutive_low_inlier resets on a good frame; mean_inliers_60s ages frames out after 60 s."""
    now = [0]
    window = RollingHealthWindow(25, clock=lambda: now[0])
    s = 1_000_000_000
    for t, inl in [(0, 100), (10, 10), (20, 0), (30, 20)]:
        window.update(t * s, best_inlier_count=inl, had_backbone_error=inl == 0)
    now[0] = 30 * s
    snap = window.snapshot()
    assert snap.consecutive_low_inlier == 3
    assert snap.mean_inliers_60s == pytest.approx(130 / 4)
    assert snap.frames_60s == 4 and snap.backbone_error_frames_60s == 1
    window.update(65 * s, best_inlier_count=50, had_backbone_error=False)
    now[0] = 65 * s
    snap = window.snapshot()
    assert snap.consecutive_low_inlier == 0
    assert snap.mean_inliers_60s == pytest.approx((10 + 0 + 20 + 50) / 4)  # t=0 aged out
    now[0] = 200 * s
    assert window.snapshot().mean_inliers_60s == 0.0


def test_health_window_rejects_time_going_backwards() -> None:
    """A non-monotonic timestamp is an error, not silently accepted."""
    window = RollingHealthWindow(25)
    window.update(10, best_inlier_count=1, had_backbone_error=False)
    with pytest.raises(ValueError, match="backwards"):
        window.update(5, best_inlier_count=1, had_backbone_error=False)


def test_c3_synthetic_chip_satisfies_tile_handle_protocol() -> None:
    """The test's chip double is a TilePixelsHandle (keeps the fakes honest)."""
    assert isinstance(SyntheticChip(0), TilePixelsHandle)


def test_c3_classical_unavailable_detector_is_a_clear_error() -> None:
    """A detector this OpenCV build lacks is refused at construction with its name, not at a frame."""
    import cv2

    if hasattr(cv2, "AKAZE_create"):
        pytest.skip("this OpenCV build has AKAZE")
    with pytest.raises(ValueError, match="akaze"):
        ClassicalMatcher(
            RansacFilter(), None, RollingHealthWindow(25), MatcherConfig(classical_detector="akaze")
        )


# --- integration: real ONNX Runtime + real LightGlue helper --------------------------------------------
class _OnnxChip:
    def __init__(self, pixels: np.ndarray, n: int) -> None:
        self._pixels = pixels
        self._tile_id = TileId.of(18, 10.0 + n * 1e-3, 20.0)

    @property
    def tile_id(self) -> TileId:
        return self._tile_id

    @property
    def gsd_m_px(self) -> float:
        return 0.3

    def pixels(self) -> np.ndarray:
        return self._pixels

    def chip_px_to_lonlat(self, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = np.asarray(px, dtype=np.float64).reshape(-1, 2)
        return 20.0 + p[:, 0] * 1e-6, self._tile_id.lat_deg - p[:, 1] * 1e-6

    def lonlat_to_chip_px(self, lon_deg: np.ndarray, lat_deg: np.ndarray) -> np.ndarray:
        raise NotImplementedError


def test_c3_disk_lightglue_real_onnx_runtime_end_to_end(tmp_path: Path) -> None:
    """Real C7 ORT + real LightGlue helper with test-built ONNX models: a shifted crop matches its chip."""
    pytest.importorskip("onnx")
    from gps_denied_onboard.components.c7_inference.onnx_runtime import OnnxInferenceRuntime
    from gps_denied_onboard.helpers.lightglue_runtime import LightGlueRuntime
    from onnx_builders import build_fake_extractor, build_fake_lightglue

    extractor = build_fake_extractor(tmp_path / "disk.onnx", dim=128, num_keypoints=512)
    matcher_model = build_fake_lightglue(tmp_path / "lightglue.onnx", dim=128, min_similarity=0.9)
    runtime = OnnxInferenceRuntime(intra_op_threads=1, providers=["CPUExecutionProvider"])
    lightglue = LightGlueRuntime(runtime, str(matcher_model))
    config = MatcherConfig(
        strategy="disk_lightglue",
        disk_weights_path=str(extractor),
        input_long_side_px=256,
        min_inliers_threshold=10,
    )
    matcher = create_matcher(
        "disk_lightglue",
        config=config,
        lightglue_runtime=lightglue,
        ransac_filter=RansacFilter(),
        inference_runtime=runtime,
        health_window=RollingHealthWindow(config.min_inliers_threshold),
    )
    assert isinstance(matcher, DiskLightGlueMatcher)
    rng = np.random.default_rng(0)
    world = (rng.integers(0, 255, (40, 40, 3), dtype=np.uint8)).repeat(8, 0).repeat(8, 1)  # 320x320 blocks
    world = np.ascontiguousarray(world)
    chip = world[:256, :256]
    query = np.ascontiguousarray(world[32:288, 48:304])  # chip px = query px + (48, 32)
    frame = NavCameraFrame(uuid.uuid4(), 0, 0, query, None, None, time.monotonic_ns())
    cands = [RerankCandidate(TileId.of(18, 10.0, 20.0), _OnnxChip(chip, 0), -1, 0.0)]
    result = matcher.match(
        frame, RerankResult(frame.frame_id, cands, 0), CameraCalibration.from_hfov(256, 256, 60)
    )
    corr = result.best.inlier_correspondences
    assert result.best.inlier_count >= 10
    shift = np.median(corr[:, 2:] - corr[:, :2], axis=0)
    np.testing.assert_allclose(shift, [48.0, 32.0], atol=1.5)
