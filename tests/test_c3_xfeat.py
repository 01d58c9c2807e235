"""C3 ``xfeat`` strategy through the real C7 ONNX Runtime with self-built XFeat-layout models.

The extractor models come from ``onnx_builders`` (LightGlue-ONNX extractor layout, C=1 grey or C=3,
D=64); the LightGlue model is the self-built mutual-NN matcher. The only double is a thin wrapper that
makes the real runtime raise on one chosen call (drop-and-continue).
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np
import pytest
from structlog.testing import capture_logs

pytest.importorskip("onnx")

from gps_denied_onboard.camera.types import CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c2_5_rerank.types import RerankCandidate, RerankResult
from gps_denied_onboard.components.c3_matcher import (
    CrossDomainMatcher,
    InsufficientInliersError,
    RollingHealthWindow,
)
from gps_denied_onboard.components.c3_matcher.xfeat import (
    XFeatMatcher,
    create,
    preprocess_xfeat,
    xfeat_input_size,
)
from gps_denied_onboard.components.c6_tiles.types import TileId
from gps_denied_onboard.components.c7_inference.onnx_runtime import OnnxInferenceRuntime
from gps_denied_onboard.components.c7_inference.protocol import EngineLoadError, InferenceError
from gps_denied_onboard.config import MatcherConfig
from gps_denied_onboard.constants import LogEvent
from gps_denied_onboard.helpers.lightglue_runtime import LightGlueRuntime
from gps_denied_onboard.helpers.ransac_filter import RansacFilter
from onnx_builders import build_fake_extractor, build_fake_lightglue

CALIB = CameraCalibration.from_hfov(256, 256, 60.0)


class ArrayChip:
    """TilePixelsHandle over an in-memory array (read-only view, fake geo mapping)."""

    def __init__(self, pixels: np.ndarray, n: int) -> None:
        self._pixels = np.ascontiguousarray(pixels)
        self._pixels.setflags(write=False)
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
        return np.column_stack(
            [(np.asarray(lon_deg) - 20.0) / 1e-6, (self._tile_id.lat_deg - np.asarray(lat_deg)) / 1e-6]
        )


class FlakyRuntime:
    """The real ONNX runtime, raising ``InferenceError`` on the listed calls of the XFeat engine."""

    def __init__(self, inner: OnnxInferenceRuntime, fail_on_calls: tuple[int, ...]) -> None:
        self._inner = inner
        self._fail = set(fail_on_calls)
        self.calls = 0

    def load_engine(self, path: str, signature: object = None) -> str:
        return self._inner.load_engine(path, signature)  # type: ignore[arg-type]

    def run(self, engine_id: str, inputs: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        if engine_id.startswith("xfeat"):  # LightGlue shares the runtime; count extractor calls only
            self.calls += 1
        if engine_id.startswith("xfeat") and self.calls in self._fail:
            raise InferenceError(f"engine '{engine_id}': CUDA error: an illegal memory access")
        return self._inner.run(engine_id, inputs)

    def provider(self, engine_id: str) -> str:
        return self._inner.provider(engine_id)

    def engine_info(self, engine_id: str) -> object:
        return self._inner.engine_info(engine_id)


def _world(seed: int = 0) -> np.ndarray:
    """A 320x320 BGR image of random 8x8 blocks (texture every patch of the fake extractor sees)."""
    rng = np.random.default_rng(seed)
    return np.ascontiguousarray(rng.integers(0, 255, (40, 40, 3), dtype=np.uint8).repeat(8, 0).repeat(8, 1))


def _runtime() -> OnnxInferenceRuntime:
    return OnnxInferenceRuntime(intra_op_threads=1, providers=["CPUExecutionProvider"])


def _config(xfeat_path: Path | str | None, **overrides: object) -> MatcherConfig:
    values: dict[str, object] = {
        "strategy": "xfeat",
        "xfeat_weights_path": None if xfeat_path is None else str(xfeat_path),
        "input_long_side_px": 256,
        "min_inliers_threshold": 10,
    }
    values.update(overrides)
    return MatcherConfig(**values)  # type: ignore[arg-type]


def _matcher(
    tmp_path: Path,
    *,
    channels: int = 1,
    runtime: object | None = None,
    lightglue_min_similarity: float = 0.9,
    num_keypoints: int = 512,
    **config_overrides: object,
) -> XFeatMatcher:
    extractor = build_fake_extractor(
        tmp_path / f"xfeat_c{channels}.onnx",
        channels=channels,
        dim=64,
        num_keypoints=num_keypoints,
        keypoint_dtype="float32",
    )
    rt = runtime if runtime is not None else _runtime()
    lg_model = build_fake_lightglue(
        tmp_path / "lighterglue.onnx", dim=64, min_similarity=lightglue_min_similarity
    )
    lightglue = LightGlueRuntime(rt, str(lg_model), descriptor_dim=64)  # type: ignore[arg-type]
    config = _config(extractor, **config_overrides)
    return create(
        config,
        lightglue,
        RansacFilter(),
        rt,  # type: ignore[arg-type]
        RollingHealthWindow(config.min_inliers_threshold),
    )


def _frame(image: np.ndarray) -> NavCameraFrame:
    return NavCameraFrame(uuid.uuid4(), 0, 0, image, None, None, time.monotonic_ns())


def _rerank(frame: NavCameraFrame, chips: list[np.ndarray]) -> RerankResult:
    cands = [
        RerankCandidate(ArrayChip(c, i).tile_id, ArrayChip(c, i), -1, 0.1 * i) for i, c in enumerate(chips)
    ]
    return RerankResult(frame.frame_id, cands, 0)


# --- tests -----------------------------------------------------------------------------------------------
def test_xfeat_real_onnx_shifted_crop_matches_its_chip(tmp_path: Path) -> None:
    """Grey C=1/D=64 model via real ORT + LightGlue model: a shifted crop matches its chip at the shift."""
    matcher = _matcher(tmp_path)
    assert isinstance(matcher, CrossDomainMatcher)
    assert matcher.input_channels == 1
    world = _world()
    chip = world[:256, :256]
    query = world[32:288, 48:304]  # chip px = query px + (48, 32)
    other = _world(seed=5)[:256, :256]
    frame = _frame(np.ascontiguousarray(query))
    result = matcher.match(frame, _rerank(frame, [other, chip]), CALIB)
    best = result.best
    assert result.matcher_label == "xfeat"
    assert best.tile_id == TileId.of(18, 10.001, 20.0)
    assert best.inlier_count >= 10
    assert best.inlier_correspondences.dtype == np.float32
    assert best.inlier_correspondences.shape == (best.inlier_count, 4)
    shift = np.median(best.inlier_correspondences[:, 2:] - best.inlier_correspondences[:, :2], axis=0)
    np.testing.assert_allclose(shift, [48.0, 32.0], atol=1.0)


def test_xfeat_features_have_documented_shapes_and_dynamic_counts(tmp_path: Path) -> None:
    """Keypoints (N, 2) float32 in image px and descriptors (N, 64) float32, N varying with image size."""
    matcher = _matcher(tmp_path, num_keypoints=8192, max_keypoints=8192, input_long_side_px=256)
    small = matcher.extract_tile(_world()[:32, :256])
    large = matcher.extract_tile(_world()[:256, :256])
    for feats, (w, h) in ((small, (256, 32)), (large, (256, 256))):
        assert feats.keypoints_px.dtype == np.float32 and feats.keypoints_px.shape == (feats.count, 2)
        assert feats.descriptors.dtype == np.float32 and feats.descriptors.shape == (feats.count, 64)
        assert feats.image_size == (w, h)
        assert (feats.keypoints_px >= -0.5).all()
        assert (feats.keypoints_px[:, 0] < w).all() and (feats.keypoints_px[:, 1] < h).all()
    assert 0 < small.count < large.count


def test_xfeat_max_keypoints_keeps_the_strongest(tmp_path: Path) -> None:
    """More model keypoints than ``max_keypoints`` are cut to that many."""
    matcher = _matcher(tmp_path, max_keypoints=100)
    assert matcher.extract_tile(_world()[:256, :256]).count == 100


def test_xfeat_zero_matches_drop_candidates_without_backbone_error(tmp_path: Path) -> None:
    """Unrelated images give no matches: InsufficientInliersError, and no backbone error is logged."""
    matcher = _matcher(tmp_path, lightglue_min_similarity=1.5)  # cosine never exceeds 1: M = 0
    frame = _frame(_world(seed=1)[:256, :256])
    with capture_logs() as logs, pytest.raises(InsufficientInliersError) as info:
        matcher.match(frame, _rerank(frame, [_world(seed=2)[:256, :256], _world(seed=3)[:256, :256]]), CALIB)
    assert info.value.best_inlier_count == 0 and info.value.candidates_dropped == 2
    assert not [e for e in logs if e["event"] == LogEvent.C3_BACKBONE_ERROR]
    assert matcher.health_snapshot().backbone_error_frames_60s == 0


def test_xfeat_runtime_error_on_a_chip_drops_it_and_continues(tmp_path: Path) -> None:
    """An InferenceError on the 2nd chip's forward drops that candidate; the true chip still wins."""
    runtime = FlakyRuntime(_runtime(), fail_on_calls=(3,))  # XFeat call 1 = query, 2 = chip 1, 3 = chip 2
    matcher = _matcher(tmp_path, runtime=runtime)
    world = _world()
    frame = _frame(np.ascontiguousarray(world[32:288, 48:304]))
    chips = [world[:256, :256], _world(seed=9)[:256, :256], world[:256, 32:288]]
    with capture_logs() as logs:
        result = matcher.match(frame, _rerank(frame, chips), CALIB)
    assert result.candidates_input == 3 and result.candidates_dropped >= 1
    errors = [e for e in logs if e["event"] == LogEvent.C3_BACKBONE_ERROR]
    assert len(errors) == 1
    assert errors[0]["phase"] == "xfeat_forward"
    assert errors[0]["tile_id"] == list(TileId.of(18, 10.001, 20.0))
    assert result.best.inlier_count >= 10
    assert matcher.health_snapshot().backbone_error_frames_60s == 1


def test_xfeat_query_runtime_error_fails_the_frame(tmp_path: Path) -> None:
    """An InferenceError on the query forward fails the frame (phase xfeat_forward_query)."""
    runtime = FlakyRuntime(_runtime(), fail_on_calls=(1,))
    matcher = _matcher(tmp_path, runtime=runtime)
    frame = _frame(_world()[:256, :256])
    with capture_logs() as logs, pytest.raises(InsufficientInliersError):
        matcher.match(frame, _rerank(frame, [_world()[:256, :256]]), CALIB)
    phases = [e["phase"] for e in logs if e["event"] == LogEvent.C3_BACKBONE_ERROR]
    assert phases == ["xfeat_forward_query"]


def test_xfeat_colour_model_is_fed_rgb(tmp_path: Path) -> None:
    """A C=3/D=64 export loads, is read as C=3, and extracts features."""
    matcher = _matcher(tmp_path, channels=3)
    assert matcher.input_channels == 3
    assert matcher.extract_query(_world()[:256, :256]).count > 0


def test_xfeat_c3_d128_model_refused_naming_the_mismatch(tmp_path: Path) -> None:
    """A C=3/D=128 extractor (DISK-like) is refused at load with EngineLoadError naming descriptors D."""
    path = build_fake_extractor(tmp_path / "disk_like.onnx", channels=3, dim=128, keypoint_dtype="float32")
    rt = _runtime()
    with pytest.raises(EngineLoadError) as info:
        XFeatMatcher(
            rt, LightGlueRuntime(rt, None), RansacFilter(), None, RollingHealthWindow(10), _config(path)
        )
    message = str(info.value)
    assert info.value.path == str(path)
    assert "descriptors" in message and "64" in message and "128" in message


def test_xfeat_two_channel_model_refused(tmp_path: Path) -> None:
    """A fixed C=2 input (neither grey nor RGB) is refused at load."""
    path = build_fake_extractor(tmp_path / "c2.onnx", channels=2, dim=64, keypoint_dtype="float32")
    rt = _runtime()
    with pytest.raises(EngineLoadError, match="C=2"):
        XFeatMatcher(
            rt, LightGlueRuntime(rt, None), RansacFilter(), None, RollingHealthWindow(10), _config(path)
        )


def test_xfeat_lightglue_model_for_128d_descriptors_refused(tmp_path: Path) -> None:
    """A LightGlue model built for 128-D descriptors is refused when the xfeat strategy is built."""
    extractor = build_fake_extractor(tmp_path / "x.onnx", channels=1, dim=64, keypoint_dtype="float32")
    rt = _runtime()
    lightglue = LightGlueRuntime(rt, str(build_fake_lightglue(tmp_path / "lg128.onnx", dim=128)))
    with pytest.raises(EngineLoadError, match="128-D"):
        create(_config(extractor), lightglue, RansacFilter(), rt, RollingHealthWindow(10))


def test_xfeat_missing_weights_path_refused() -> None:
    """No ``matcher.xfeat_weights_path`` -> EngineLoadError naming the config key."""
    rt = _runtime()
    with pytest.raises(EngineLoadError, match=r"matcher\.xfeat_weights_path"):
        create(_config(None), LightGlueRuntime(rt, None), RansacFilter(), rt, RollingHealthWindow(10))


def test_xfeat_mutual_nn_fallback_without_lightglue_model(tmp_path: Path) -> None:
    """Without a LightGlue model the helper's mutual-NN fallback still matches the shifted crop."""
    extractor = build_fake_extractor(
        tmp_path / "x.onnx", channels=1, dim=64, num_keypoints=512, keypoint_dtype="float32"
    )
    rt = _runtime()
    config = _config(extractor)
    matcher = create(config, LightGlueRuntime(rt, None), RansacFilter(), rt, RollingHealthWindow(10))
    world = _world()
    frame = _frame(np.ascontiguousarray(world[32:288, 48:304]))
    result = matcher.match(frame, _rerank(frame, [world[:256, :256]]), CALIB)
    assert result.best.inlier_count >= 10


def test_xfeat_preprocess_resizes_to_multiples_of_32() -> None:
    """640x480 stays; 500x300 at long side 640 becomes 640x384; grey tensor float32 in [0, 1]."""
    assert xfeat_input_size(640, 480, 640) == (640, 480)
    assert xfeat_input_size(500, 300, 640) == (640, 384)
    image = np.full((300, 500, 3), 255, dtype=np.uint8)
    tensor, (sx, sy) = preprocess_xfeat(image, 640, 1)
    assert tensor.shape == (1, 1, 384, 640) and tensor.dtype == np.float32
    assert float(tensor.min()) == pytest.approx(1.0) and float(tensor.max()) == pytest.approx(1.0)
    assert (sx, sy) == pytest.approx((640 / 500, 384 / 300))
    rgb, _ = preprocess_xfeat(image, 640, 3)
    assert rgb.shape == (1, 3, 384, 640)
    with pytest.raises(ValueError, match="channels"):
        preprocess_xfeat(image, 640, 2)


@pytest.mark.parametrize("size", [(480, 640), (512, 512), (300, 500)])
def test_xfeat_preprocess_is_the_plain_formula_bit_for_bit(size: tuple[int, int]) -> None:
    """The tensor is exactly cvtColor -> float32 -> x float32(1/255), NCHW and C-contiguous, RGB and grey."""
    image = np.random.default_rng(3).integers(0, 256, (*size, 3), dtype=np.uint8)
    w, h = xfeat_input_size(size[1], size[0], 640)
    interp = cv2.INTER_AREA if w * h < size[0] * size[1] else cv2.INTER_LINEAR
    resized = image if (w, h) == (size[1], size[0]) else cv2.resize(image, (w, h), interpolation=interp)
    rgb = cv2.cvtColor(resized, cv2.COLOR_BGR2RGB).transpose(2, 0, 1)[None].astype(np.float32)
    grey = cv2.cvtColor(resized, cv2.COLOR_BGR2GRAY)[None, None].astype(np.float32)
    for channels, plain in ((3, rgb), (1, grey)):
        tensor, _ = preprocess_xfeat(image, 640, channels)
        assert tensor.flags.c_contiguous and tensor.dtype == np.float32
        np.testing.assert_array_equal(tensor, plain * np.float32(1.0 / 255.0))
