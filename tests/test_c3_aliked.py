"""C3 ``aliked_lightglue`` strategy with the real exported ALIKED T16 ONNX model and ONNX Runtime.

Contract basics (protocol, shapes, determinism, drop-and-continue, tile cache), the NAIP cross-date
proof (ALIKED vs the classical strategy on the same warped trials) and the per-frame latency.
"""

from __future__ import annotations

import glob
import math
import time
import uuid
from pathlib import Path

import cv2
import numpy as np
import pytest

import aliked_fixture
from conftest import shared_path
from gps_denied_onboard.camera.types import CameraCalibration, NavCameraFrame
from gps_denied_onboard.cli_match import ImageChip
from gps_denied_onboard.components.c2_5_rerank.types import RerankCandidate, RerankResult
from gps_denied_onboard.components.c3_matcher import registry
from gps_denied_onboard.components.c3_matcher.aliked_lightglue import (
    ALIKED_MNN_MIN_SIMILARITY,
    AlikedLightGlueMatcher,
    letterbox,
)
from gps_denied_onboard.components.c3_matcher.classical import ClassicalMatcher
from gps_denied_onboard.components.c3_matcher.errors import InsufficientInliersError
from gps_denied_onboard.components.c3_matcher.health import RollingHealthWindow
from gps_denied_onboard.components.c3_matcher.protocol import CrossDomainMatcher
from gps_denied_onboard.components.c6_tiles.types import TileId
from gps_denied_onboard.components.c7_inference.onnx_runtime import OnnxInferenceRuntime
from gps_denied_onboard.components.c7_inference.protocol import EngineLoadError, InferenceError
from gps_denied_onboard.config import MatcherConfig
from gps_denied_onboard.constants import FdrKind
from gps_denied_onboard.helpers.lightglue_runtime import LightGlueRuntime
from gps_denied_onboard.helpers.ransac_filter import RansacFilter

#: The session-scoped export fixture, made visible to this module's tests.
aliked_t16_onnx = aliked_fixture.aliked_t16_onnx
EXPORT_HEIGHT, EXPORT_WIDTH = aliked_fixture.EXPORT_HEIGHT, aliked_fixture.EXPORT_WIDTH

NAIP_PAIRS = ((2009, 2014), (2009, 2020), (2012, 2018))
NAIP_TRIALS_PER_PAIR = 10
NAIP_FRAME_WH = (320, 240)
NAIP_CHIP_PX = 384
CORNER_TOLERANCE_PX = 10.0


class RecordingFdr:
    """FdrClient that keeps (kind, fields) records."""

    def __init__(self) -> None:
        self.records: list[tuple[str, dict[str, object]]] = []

    def record(self, kind: str, fields: object) -> None:
        self.records.append((kind, dict(fields)))  # type: ignore[call-overload]


class FailingRuntime:
    """The real runtime, raising ``InferenceError`` on the ``fail_on``-th ``run`` call (1-based)."""

    def __init__(self, inner: OnnxInferenceRuntime, fail_on: int) -> None:
        self._inner = inner
        self.fail_on = fail_on
        self.calls = 0

    def load_engine(self, path, signature=None):
        return self._inner.load_engine(path, signature)

    def run(self, engine_id, inputs):
        self.calls += 1
        if self.calls == self.fail_on:
            raise InferenceError(f"injected failure on call {self.calls}")
        return self._inner.run(engine_id, inputs)

    def provider(self, engine_id):
        return self._inner.provider(engine_id)

    def engine_info(self, engine_id):
        return self._inner.engine_info(engine_id)


def _config(model: Path, **overrides: object) -> MatcherConfig:
    settings: dict[str, object] = {"min_inliers_threshold": 12, **overrides}
    return MatcherConfig(
        strategy="aliked_lightglue",
        aliked_weights_path=str(model),
        **settings,  # type: ignore[arg-type]
    )


def _matcher(model: Path, runtime=None, fdr=None, **overrides: object) -> AlikedLightGlueMatcher:
    rt = runtime or OnnxInferenceRuntime(intra_op_threads=1, providers=["CPUExecutionProvider"])
    config = _config(model, **overrides)
    matcher = registry.create_matcher(
        "aliked_lightglue",
        config=config,
        inference_runtime=rt,
        lightglue_runtime=LightGlueRuntime(rt, None, mnn_min_similarity=ALIKED_MNN_MIN_SIMILARITY),
        ransac_filter=RansacFilter(),
        health_window=RollingHealthWindow(config.min_inliers_threshold),
        fdr_client=fdr,
    )
    assert isinstance(matcher, AlikedLightGlueMatcher)
    return matcher


class OffsetChip(ImageChip):
    """ImageChip with its own tile id (several distinct candidates in one frame)."""

    def __init__(self, image: np.ndarray, tile_no: int) -> None:
        super().__init__(image)
        self._tile_id = TileId.of(18, 17.0 + tile_no * 1e-3, 78.0)
        self._no = tile_no

    def chip_px_to_lonlat(self, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lon, lat = super().chip_px_to_lonlat(px)
        return lon + self._no, lat


def _frame(image: np.ndarray) -> NavCameraFrame:
    return NavCameraFrame(uuid.uuid4(), 0, 0, image, None, None, time.monotonic_ns())


def _rerank(frame: NavCameraFrame, chips: list[ImageChip]) -> RerankResult:
    return RerankResult(frame.frame_id, [RerankCandidate(c.tile_id, c, -1, 0.0) for c in chips], 0)


@pytest.fixture(scope="module")
def geovision_patch() -> np.ndarray:
    image = cv2.imread(str(shared_path("data", "geovision_india", "sat_patch_0000.png")), cv2.IMREAD_COLOR)
    if image is None:
        pytest.skip("geovision patch unreadable")
    return image


def _same_source_case(patch: np.ndarray) -> tuple[np.ndarray, list[ImageChip]]:
    """Query = a 480x640 crop; chips: the true overlapping crop (shifted (37, 23) px) + 2 others."""
    query = np.ascontiguousarray(patch[100:580, 100:740])
    true_chip = np.ascontiguousarray(patch[123:635, 137:649])
    other = np.ascontiguousarray(np.rot90(patch[0:512, 0:512], 2))
    third = np.ascontiguousarray(cv2.flip(patch[-512:, -512:], 1))
    return query, [OffsetChip(true_chip, 0), OffsetChip(other, 1), OffsetChip(third, 2)]


# ------------------------------------------------------------------------------------------ contract


def test_aliked_matcher_satisfies_protocol_with_model_input_size(aliked_t16_onnx: Path) -> None:
    """The registry builds a CrossDomainMatcher that reads the fixed input size from the model."""
    matcher = _matcher(aliked_t16_onnx)
    assert isinstance(matcher, CrossDomainMatcher)
    assert matcher.label == "aliked_lightglue"
    assert matcher.input_hw == (EXPORT_HEIGHT, EXPORT_WIDTH)
    assert "aliked_lightglue" in registry.available_strategies()


def test_aliked_matcher_missing_model_raises_engine_load_error(tmp_path: Path) -> None:
    """A missing model file is refused at build time, naming the file."""
    missing = tmp_path / "nope.onnx"
    with pytest.raises(EngineLoadError, match=r"nope\.onnx"):
        _matcher(missing)


def test_aliked_matcher_unset_model_path_raises_engine_load_error() -> None:
    """No aliked_weights_path configured is a start-up refusal naming the setting."""
    rt = OnnxInferenceRuntime(intra_op_threads=1)
    with pytest.raises(EngineLoadError, match="aliked_weights_path"):
        AlikedLightGlueMatcher(
            rt, LightGlueRuntime(rt, None), RansacFilter(), None, RollingHealthWindow(12), MatcherConfig()
        )


def test_aliked_matcher_wrong_model_signature_raises(tmp_path: Path) -> None:
    """A model file with another layout (a LightGlue-style graph) is refused with the file named."""
    from onnx_builders import build_fake_lightglue  # type: ignore[import-not-found]

    path = build_fake_lightglue(tmp_path / "lightglue.onnx")
    with pytest.raises(EngineLoadError, match=r"lightglue\.onnx"):
        _matcher(path)


def test_letterbox_maps_keypoints_back_to_original_pixels() -> None:
    """A 240x320 image letterboxed to 384x512 is scaled 1.6 with the padding at bottom/right."""
    image = np.full((240, 320, 3), 200, np.uint8)
    box = letterbox(image, (384, 512))
    assert box.tensor.shape == (1, 3, 384, 512) and box.tensor.dtype == np.float32
    assert box.scale == pytest.approx(1.6) and box.content_wh == (512, 384)
    square = letterbox(np.full((512, 512, 3), 10, np.uint8), (384, 512))
    assert square.content_wh == (384, 384) and float(square.tensor[0, :, :, 400:].max()) == 0.0


def test_aliked_matcher_shape_and_determinism(aliked_t16_onnx: Path, geovision_patch: np.ndarray) -> None:
    """Inliers are (I, 4) float32 nav-frame/chip px; the true chip wins; 3 calls give identical results."""
    matcher = _matcher(aliked_t16_onnx)
    query, chips = _same_source_case(geovision_patch)
    results = []
    for _ in range(3):
        frame = _frame(query)
        results.append(matcher.match(frame, _rerank(frame, chips), CameraCalibration.from_hfov(640, 480, 70)))
    best = results[0].best
    assert best.tile_id == chips[0].tile_id
    assert best.inlier_correspondences.shape == (best.inlier_count, 4)
    assert best.inlier_correspondences.dtype == np.float32
    assert best.inlier_count >= 100
    # Query px p is at p - (37, 23) in the true chip.
    shift = best.inlier_correspondences[:, :2] - best.inlier_correspondences[:, 2:]
    assert np.abs(np.median(shift, axis=0) - [37.0, 23.0]).max() < 0.5
    for other in results[1:]:
        assert [(c.tile_id, c.inlier_count, c.per_candidate_residual_px) for c in other.per_candidate] == [
            (c.tile_id, c.inlier_count, c.per_candidate_residual_px) for c in results[0].per_candidate
        ]
        np.testing.assert_array_equal(other.best.inlier_correspondences, best.inlier_correspondences)


def test_aliked_matcher_drops_candidate_when_runtime_raises(
    aliked_t16_onnx: Path, geovision_patch: np.ndarray
) -> None:
    """A forward failure on the 2nd chip drops only that candidate, with an FDR backbone record."""
    inner = OnnxInferenceRuntime(intra_op_threads=1, providers=["CPUExecutionProvider"])
    runtime = FailingRuntime(inner, fail_on=10**9)
    fdr = RecordingFdr()
    matcher = _matcher(aliked_t16_onnx, runtime=runtime, fdr=fdr, min_inliers_threshold=4)
    runtime.calls, runtime.fail_on = 0, 3  # run #1 = query, #2 = chip 1, #3 = chip 2
    query, chips = _same_source_case(geovision_patch)
    frame = _frame(query)
    result = matcher.match(frame, _rerank(frame, chips), CameraCalibration.from_hfov(640, 480, 70))
    assert result.candidates_dropped >= 1
    assert chips[1].tile_id not in [c.tile_id for c in result.per_candidate]
    assert result.best.tile_id == chips[0].tile_id
    errors = [f for k, f in fdr.records if k == FdrKind.MATCHER_BACKBONE_ERROR]
    assert len(errors) == 1
    assert errors[0]["phase"] == "aliked_forward" and errors[0]["tile_id"] == list(chips[1].tile_id)
    assert [k for k, _ in fdr.records].count(FdrKind.MATCHER_FRAME_DONE) == 1
    assert matcher.health_snapshot().consecutive_low_inlier == 0


def test_aliked_matcher_query_failure_fails_frame(aliked_t16_onnx: Path, geovision_patch: np.ndarray) -> None:
    """A failure of the query forward pass fails the frame with InsufficientInliersError."""
    inner = OnnxInferenceRuntime(intra_op_threads=1, providers=["CPUExecutionProvider"])
    runtime = FailingRuntime(inner, fail_on=10**9)
    matcher = _matcher(aliked_t16_onnx, runtime=runtime)
    runtime.calls, runtime.fail_on = 0, 1
    query, chips = _same_source_case(geovision_patch)
    frame = _frame(query)
    with pytest.raises(InsufficientInliersError):
        matcher.match(frame, _rerank(frame, chips), CameraCalibration.from_hfov(640, 480, 70))


def test_aliked_matcher_caches_tile_features(aliked_t16_onnx: Path, geovision_patch: np.ndarray) -> None:
    """The second frame against the same chips costs one forward pass (the query)."""
    inner = OnnxInferenceRuntime(intra_op_threads=1, providers=["CPUExecutionProvider"])
    runtime = FailingRuntime(inner, fail_on=-1)
    matcher = _matcher(aliked_t16_onnx, runtime=runtime)
    query, chips = _same_source_case(geovision_patch)
    calib = CameraCalibration.from_hfov(640, 480, 70)
    for _ in range(2):
        frame = _frame(query)
        matcher.match(frame, _rerank(frame, chips), calib)
    assert runtime.calls == 1 + 3 + 1
    assert matcher.tile_cache.hits == 3


# ------------------------------------------------------------------------------- NAIP cross-date proof


def _naip(year: int) -> np.ndarray:
    rasterio = pytest.importorskip("rasterio")
    found = sorted(glob.glob(str(shared_path("data", "naip_timeseries", "naip") / f"*_{year}*.tif")))
    if not found:
        pytest.skip(f"NAIP {year} not available")
    with rasterio.open(found[0]) as ds:
        rgb = ds.read([1, 2, 3])
    return np.ascontiguousarray(cv2.cvtColor(rgb.transpose(1, 2, 0), cv2.COLOR_RGB2BGR))


def _random_homography(rng: np.random.Generator, centre: tuple[float, float]) -> np.ndarray:
    """Frame px -> raster px: +-10 deg rotation, +-10 % scale, mild perspective, about ``centre``."""
    fw, fh = NAIP_FRAME_WH
    theta = math.radians(rng.uniform(-10, 10))
    s = rng.uniform(0.9, 1.1)
    c, si = math.cos(theta), math.sin(theta)
    to_centre = np.array([[1, 0, -fw / 2], [0, 1, -fh / 2], [0, 0, 1]], dtype=np.float64)
    rot_scale = np.array([[s * c, -s * si, 0], [s * si, s * c, 0], [0, 0, 1]])
    persp = np.array([[1, 0, 0], [0, 1, 0], [rng.uniform(-1e-4, 1e-4), rng.uniform(-1e-4, 1e-4), 1]])
    to_raster = np.array([[1, 0, centre[0]], [0, 1, centre[1]], [0, 0, 1]])
    return to_raster @ rot_scale @ persp @ to_centre


def _corner_errors(
    matcher: object, query: np.ndarray, chip: ImageChip, origin, h_true
) -> tuple[float, float, int]:
    """(corner error of the 4-dof fit, of the 8-dof fit, inliers); inf when no match."""
    frame = _frame(query)
    try:
        result = matcher.match(frame, _rerank(frame, [chip]), CameraCalibration.from_hfov(*NAIP_FRAME_WH, 70))  # type: ignore[attr-defined]
    except InsufficientInliersError as exc:
        return math.inf, math.inf, exc.best_inlier_count
    corr = result.best.inlier_correspondences
    fw, fh = NAIP_FRAME_WH
    corners = np.array([[[0, 0]], [[fw, 0]], [[fw, fh]], [[0, fh]]], dtype=np.float64)
    truth = cv2.perspectiveTransform(corners, h_true).reshape(-1, 2)
    sim, _ = cv2.estimateAffinePartial2D(
        np.ascontiguousarray(corr[:, :2]), np.ascontiguousarray(corr[:, 2:]), method=cv2.LMEDS
    )
    errors = []
    for est in (
        None if sim is None else cv2.transform(corners, sim).reshape(-1, 2),
        cv2.perspectiveTransform(corners, RansacFilter().filter(corr, 3.0).homography).reshape(-1, 2),
    ):
        errors.append(math.inf if est is None else float(np.linalg.norm(est + origin - truth, axis=1).max()))
    return errors[0], errors[1], result.best.inlier_count


@pytest.mark.realdata
def test_aliked_naip_cross_date_beats_classical(aliked_t16_onnx: Path) -> None:
    """NAIP frames of one year vs chips of another: ALIKED recovers the warp (< 10 px) in >= 90 %."""
    aliked = _matcher(aliked_t16_onnx)
    classical_cfg = MatcherConfig(min_inliers_threshold=12)
    classical = ClassicalMatcher(RansacFilter(), None, RollingHealthWindow(12), classical_cfg)
    fw, fh = NAIP_FRAME_WH
    rows = []
    for year_map, year_frame in NAIP_PAIRS:
        map_img, frame_src = _naip(year_map), _naip(year_frame)
        h = min(map_img.shape[0], frame_src.shape[0])
        w = min(map_img.shape[1], frame_src.shape[1])
        map_img, frame_src = map_img[:h, :w], frame_src[:h, :w]
        rng = np.random.default_rng(year_map * year_frame)
        for _ in range(NAIP_TRIALS_PER_PAIR):
            margin = NAIP_CHIP_PX // 2 + 45
            cx, cy = rng.uniform(margin, w - margin), rng.uniform(margin, h - margin)
            h_true = _random_homography(rng, (cx, cy))
            query = cv2.warpPerspective(
                frame_src, h_true, (fw, fh), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
            )
            jx, jy = rng.uniform(-40, 40, 2)
            x0 = int(np.clip(cx + jx - NAIP_CHIP_PX / 2, 0, w - NAIP_CHIP_PX))
            y0 = int(np.clip(cy + jy - NAIP_CHIP_PX / 2, 0, h - NAIP_CHIP_PX))
            chip = ImageChip(
                np.ascontiguousarray(map_img[y0 : y0 + NAIP_CHIP_PX, x0 : x0 + NAIP_CHIP_PX]), 5.0, (x0, y0)
            )
            origin = np.array([x0, y0], dtype=np.float64)
            rows.append(
                (
                    (year_map, year_frame),
                    _corner_errors(aliked, query, chip, origin, h_true),
                    _corner_errors(classical, query, chip, origin, h_true),
                )
            )
    n = len(rows)
    aliked_ok = sum(r[1][0] < CORNER_TOLERANCE_PX for r in rows) / n
    aliked_h8_ok = sum(r[1][1] < CORNER_TOLERANCE_PX for r in rows) / n
    classical_ok = sum(r[2][0] < CORNER_TOLERANCE_PX for r in rows) / n
    for pair in NAIP_PAIRS:
        sel = [r for r in rows if r[0] == pair]
        print(
            f"\nNAIP map {pair[0]} / frame {pair[1]}: aliked (inliers, corner px) "
            f"{[(r[1][2], round(r[1][0], 1)) for r in sel]}; classical inliers {[r[2][2] for r in sel]}"
        )
    print(
        f"\nNAIP cross-date, {n} trials: aliked_lightglue success {aliked_ok:.2f} (4-dof fit of its inliers; "
        f"8-dof homography {aliked_h8_ok:.2f}); classical success {classical_ok:.2f}"
    )
    assert n >= 20
    assert aliked_ok >= 0.9


# ------------------------------------------------------------------------------------------- latency


@pytest.mark.slow
@pytest.mark.realdata
def test_aliked_matcher_frame_latency_warm_tiles(aliked_t16_onnx: Path, geovision_patch: np.ndarray) -> None:
    """Steady state: one 640x480 extraction + 3 matches against cached chips; report p50/p95."""
    import os

    matcher = _matcher(aliked_t16_onnx)
    query, chips = _same_source_case(geovision_patch)
    calib = CameraCalibration.from_hfov(640, 480, 70)
    frame = _frame(query)
    matcher.match(frame, _rerank(frame, chips), calib)  # fills the tile cache
    times = []
    for _ in range(15):
        frame = _frame(query)
        t0 = time.perf_counter()
        matcher.match(frame, _rerank(frame, chips), calib)
        times.append((time.perf_counter() - t0) * 1e3)
    p50, p95 = np.percentile(times, 50), np.percentile(times, 95)
    print(
        f"\naliked_lightglue {EXPORT_HEIGHT}x{EXPORT_WIDTH} warm frame ms p50 {p50:.0f} p95 {p95:.0f}; "
        f"load {os.getloadavg()}"
    )
    assert p50 < 2000.0
