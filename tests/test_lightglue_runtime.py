"""LightGlueRuntime / FusedPipelineRuntime on real ONNX Runtime sessions of self-built models."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pytest
from structlog.testing import capture_logs

from gps_denied_onboard.components.c7_inference import (
    EngineLoadError,
    EngineSignature,
    InferenceError,
    OnnxInferenceRuntime,
)
from gps_denied_onboard.constants import LogEvent
from gps_denied_onboard.helpers.lightglue_runtime import (
    FusedPipelineRuntime,
    LightGlueRuntime,
    mutual_nearest_neighbours,
    normalize_keypoints,
)
from gps_denied_onboard.helpers.onnx_signatures import DISK_EXTRACTOR
from onnx_builders import (
    CENTRE_OFFSET_INT,
    STRIDE_PX,
    build_constant_matcher,
    build_fake_extractor,
    build_fake_lightglue,
    build_fused_pipeline,
)


class RecordingRuntime:
    """Real OnnxInferenceRuntime that also records every run's inputs and outputs."""

    def __init__(self) -> None:
        self.inner = OnnxInferenceRuntime(intra_op_threads=1)
        self.calls: list[tuple[dict[str, np.ndarray], dict[str, np.ndarray]]] = []

    def load_engine(self, path: str, signature: EngineSignature | None = None) -> str:
        return self.inner.load_engine(path, signature)

    def run(self, engine_id: str, inputs: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        out = self.inner.run(engine_id, inputs)
        self.calls.append((dict(inputs), out))
        return out

    def provider(self, engine_id: str) -> str:
        return self.inner.provider(engine_id)


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("lg_models")
    return {
        "lg": build_fake_lightglue(d / "lg.onnx", 128),
        "lg_echo": build_fake_lightglue(d / "lg_echo.onnx", 128, echo_inputs=True),
        "lg_even": build_fake_lightglue(d / "lg_even.onnx", 128, require_even_n0=True),
        "lg64": build_fake_lightglue(d / "lg64.onnx", 64),
        "bad_index": build_constant_matcher(d / "bad.onnx", np.array([[0, 1], [2, 7]]), np.array([0.9, 0.8])),
        "scored": build_constant_matcher(
            d / "scored.onnx", np.array([[0, 0], [1, 1], [2, 2]]), np.array([0.2, 0.6, 0.9])
        ),
        "extractor": build_fake_extractor(d / "disk.onnx", dim=128, num_keypoints=96),
        "fused": build_fused_pipeline(d / "fused.onnx", num_keypoints=96),
    }


@pytest.fixture
def runtime() -> RecordingRuntime:
    return RecordingRuntime()


def _unit_rows(n: int, dim: int, seed: int) -> np.ndarray:
    d = np.random.default_rng(seed).standard_normal((n, dim)).astype(np.float32)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _kpts(n: int, seed: int, w: int = 640, h: int = 480) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (rng.random((n, 2)) * [w, h]).astype(np.float32)


def _crop_pair(seed: int, dx: int, dy: int) -> tuple[np.ndarray, np.ndarray]:
    """Two (3, 96, 128) views of one random image, the second shifted by (dx, dy) px."""
    big = np.random.default_rng(seed).random((3, 96 + dy, 128 + dx), dtype=np.float32)
    return big[:, dy:, dx:][:, :96, :128].copy(), big[:, :96, :128].copy()


def test_normalize_keypoints_lightglue_formula_exact() -> None:
    """(k - size/2) / (max(size)/2) with size=(w, h): corners and centre of a 640x480 image."""
    k = np.array([[0, 0], [640, 480], [320, 240], [0, 480]], np.float32)
    expected = np.array([[-1, -0.75], [1, 0.75], [0, 0], [-1, 0.75]], np.float32)
    got = normalize_keypoints(k, (640, 480))
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, expected)


def test_normalize_keypoints_portrait_scales_by_height() -> None:
    """For h > w the longer side (h) sets the scale."""
    got = normalize_keypoints(np.array([[100, 400]], np.float32), (200, 400))
    np.testing.assert_allclose(got, [[0.0, 1.0]])


def test_normalize_keypoints_rejects_non_positive_size() -> None:
    """A zero-width image size is a ValueError."""
    with pytest.raises(ValueError, match="image_size"):
        normalize_keypoints(np.zeros((1, 2), np.float32), (0, 10))


def test_match_pair_model_receives_per_image_normalised_keypoints(runtime, models) -> None:
    """The matcher model gets each image's keypoints normalised by that image's own size, batched."""
    lg = LightGlueRuntime(runtime, str(models["lg_echo"]))
    k0 = np.array([[0, 0], [640, 480], [320, 240]], np.float32)
    k1 = np.array([[0, 0], [100, 200], [50, 100], [100, 0]], np.float32)
    lg.match_pair(
        k0, _unit_rows(3, 128, 0), k1, _unit_rows(4, 128, 1), image_size0=(640, 480), image_size1=(100, 200)
    )
    fed, out = runtime.calls[-1]
    assert fed["kpts0"].shape == (1, 3, 2) and fed["desc1"].shape == (1, 4, 128)
    np.testing.assert_array_equal(out["echo_kpts0"][0], [[-1, -0.75], [1, 0.75], [0, 0]])
    np.testing.assert_array_equal(out["echo_kpts1"][0], [[-0.5, -1], [0.5, 1], [0, 0], [0.5, -1]])


def test_match_pair_dynamic_counts_recovers_permutation(runtime, models) -> None:
    """N0=40, N1=25: image 1 holds a shuffled subset of image 0's descriptors; every pair is found."""
    lg = LightGlueRuntime(runtime, str(models["lg"]))
    d0 = _unit_rows(40, 128, 2)
    subset = np.random.default_rng(3).permutation(40)[:25]
    d1 = d0[subset]
    matches, scores = lg.match_pair(
        _kpts(40, 4), d0, _kpts(25, 5), d1, image_size0=(640, 480), image_size1=(640, 480)
    )
    assert matches.dtype == np.int64 and scores.dtype == np.float32
    assert matches.shape == (25, 2) and scores.shape == (25,)
    np.testing.assert_array_equal(matches[:, 0], subset[matches[:, 1]])
    np.testing.assert_allclose(scores, 1.0, atol=1e-5)


def test_match_pair_zero_keypoints_returns_empty_without_running(runtime, models) -> None:
    """Zero keypoints on either side: empty (0,2) int64 / (0,) float32, the model is not run."""
    lg = LightGlueRuntime(runtime, str(models["lg"]))
    for n0, n1 in ((0, 5), (5, 0), (0, 0)):
        matches, scores = lg.match_pair(
            _kpts(n0, 1),
            _unit_rows(n0, 128, 1),
            _kpts(n1, 2),
            _unit_rows(n1, 128, 2),
            image_size0=(640, 480),
            image_size1=(640, 480),
        )
        assert matches.shape == (0, 2) and matches.dtype == np.int64
        assert scores.shape == (0,) and scores.dtype == np.float32
    assert runtime.calls == []


def test_match_pair_zero_matches_returns_empty(runtime, models) -> None:
    """Descriptors that are all dissimilar give M=0 from the model, returned as empty arrays."""
    lg = LightGlueRuntime(runtime, str(models["lg"]))
    d0 = np.zeros((3, 128), np.float32)
    d0[np.arange(3), np.arange(3)] = 1.0
    d1 = np.zeros((4, 128), np.float32)
    d1[np.arange(4), 10 + np.arange(4)] = 1.0  # orthogonal to every row of d0
    matches, scores = lg.match_pair(
        _kpts(3, 1), d0, _kpts(4, 2), d1, image_size0=(64, 64), image_size1=(64, 64)
    )
    assert len(runtime.calls) == 1
    assert matches.shape == (0, 2) and matches.dtype == np.int64
    assert scores.shape == (0,) and scores.dtype == np.float32


def test_match_pair_out_of_range_index_raises_inference_error(runtime, models) -> None:
    """A model returning kpts1 index 7 for N1=5 is rejected with the offending pair named."""
    lg = LightGlueRuntime(runtime, str(models["bad_index"]))
    with pytest.raises(InferenceError, match=r"1 match indices out of range \(N0=5, N1=5\), first \[2, 7\]"):
        lg.match_pair(
            _kpts(5, 1),
            _unit_rows(5, 128, 1),
            _kpts(5, 2),
            _unit_rows(5, 128, 2),
            image_size0=(64, 64),
            image_size1=(64, 64),
        )


def test_match_pair_min_score_filters(runtime, models) -> None:
    """Matches scored below min_score are dropped."""
    lg = LightGlueRuntime(runtime, str(models["scored"]), min_score=0.5)
    matches, scores = lg.match_pair(
        _kpts(3, 1),
        _unit_rows(3, 128, 1),
        _kpts(3, 2),
        _unit_rows(3, 128, 2),
        image_size0=(64, 64),
        image_size1=(64, 64),
    )
    np.testing.assert_array_equal(matches, [[1, 1], [2, 2]])
    np.testing.assert_allclose(scores, [0.6, 0.9])


def test_match_pair_model_failure_raises_inference_error(runtime, models) -> None:
    """A forward pass that fails in ORT (odd N0 here) surfaces as InferenceError."""
    lg = LightGlueRuntime(runtime, str(models["lg_even"]))
    ok, _ = lg.match_pair(
        _kpts(4, 1),
        _unit_rows(4, 128, 1),
        _kpts(4, 2),
        _unit_rows(4, 128, 1),
        image_size0=(64, 64),
        image_size1=(64, 64),
    )
    assert ok.shape == (4, 2)
    with pytest.raises(InferenceError) as err:
        lg.match_pair(
            _kpts(5, 1),
            _unit_rows(5, 128, 1),
            _kpts(4, 2),
            _unit_rows(4, 128, 1),
            image_size0=(64, 64),
            image_size1=(64, 64),
        )
    assert err.value.__cause__ is not None


def test_match_pair_descriptor_size_mismatch_raises_value_error(runtime, models) -> None:
    """D0 != D1 is a caller error."""
    lg = LightGlueRuntime(runtime, str(models["lg"]))
    with pytest.raises(ValueError, match="descriptor sizes differ"):
        lg.match_pair(
            _kpts(3, 1),
            _unit_rows(3, 128, 1),
            _kpts(3, 2),
            _unit_rows(3, 64, 2),
            image_size0=(64, 64),
            image_size1=(64, 64),
        )


def test_match_pair_keypoint_descriptor_count_mismatch_raises_value_error(runtime, models) -> None:
    """N keypoints with a different number of descriptor rows is a caller error."""
    lg = LightGlueRuntime(runtime, str(models["lg"]))
    with pytest.raises(ValueError, match=r"image 1: descriptors must be \(N=3, D\)"):
        lg.match_pair(
            _kpts(3, 1),
            _unit_rows(3, 128, 1),
            _kpts(3, 2),
            _unit_rows(4, 128, 2),
            image_size0=(64, 64),
            image_size1=(64, 64),
        )


def test_lightglue_runtime_wrong_model_refused_at_construction(runtime, models) -> None:
    """An extractor configured as the matcher fails at start-up with EngineLoadError."""
    with pytest.raises(EngineLoadError, match="input 'kpts0': missing"):
        LightGlueRuntime(runtime, str(models["extractor"]))


def test_lightglue_runtime_descriptor_dim_pinned(runtime, models) -> None:
    """descriptor_dim=128 refuses a 64-d matcher at load time."""
    with pytest.raises(EngineLoadError, match="input 'desc0': dim 2 expected 128, model has 64"):
        LightGlueRuntime(runtime, str(models["lg64"]), descriptor_dim=128)


def test_lightglue_runtime_unknown_fallback_lists_valid() -> None:
    """An unknown fallback name is rejected with the valid ones listed."""
    with pytest.raises(ValueError, match="valid: mutual_nn, none"):
        LightGlueRuntime(RecordingRuntime(), None, fallback="ratio")


def test_lightglue_runtime_no_model_and_no_fallback_rejected() -> None:
    """fallback='none' without a model is a configuration error."""
    with pytest.raises(ValueError, match="fallback='none'"):
        LightGlueRuntime(RecordingRuntime(), None, fallback="none")


def test_mnn_fallback_matches_noisy_subset_and_logs_mode(runtime) -> None:
    """Without a model, mutual NN on cosine recovers a noisy shuffled subset; no engine is run."""
    with capture_logs() as logs:
        lg = LightGlueRuntime(runtime, None, mnn_min_similarity=0.8)
    assert lg.mode == "mutual_nn" and lg.engine_id is None
    assert any(e["event"] == LogEvent.LIGHTGLUE_READY and e["mode"] == "mutual_nn" for e in logs)
    d0 = _unit_rows(50, 64, 7)
    perm = np.random.default_rng(8).permutation(50)[:30]
    d1 = d0[perm] * 3.0 + np.random.default_rng(9).normal(0, 0.01, (30, 64)).astype(np.float32)
    matches, scores = lg.match_pair(
        _kpts(50, 1), d0, _kpts(30, 2), d1, image_size0=(64, 64), image_size1=(64, 64)
    )
    assert matches.shape == (30, 2)
    np.testing.assert_array_equal(matches[:, 0], perm[matches[:, 1]])
    assert np.all(np.diff(matches[:, 0]) > 0)  # sorted by idx0: deterministic order
    assert np.all(scores > 0.99)
    assert runtime.calls == []


def test_mnn_threshold_and_mutuality() -> None:
    """Non-mutual best pairs and pairs below the cosine threshold are both dropped."""
    d0 = np.array([[1, 0], [0.9, 0.1], [0, 1]], np.float32)
    d1 = np.array([[1, 0], [0.6, 0.8]], np.float32)
    matches, scores = mutual_nearest_neighbours(d0, d1, min_similarity=0.75)
    # row 1's best is d1[0], but d1[0]'s best is row 0; row 2 -> d1[1] is mutual with cosine 0.8.
    np.testing.assert_array_equal(matches, [[0, 0], [2, 1]])
    np.testing.assert_allclose(scores, [1.0, 0.8], atol=1e-6)
    strict, _ = mutual_nearest_neighbours(d0, d1, min_similarity=0.9)
    np.testing.assert_array_equal(strict, [[0, 0]])


def _mnn_reference(d0: np.ndarray, d1: np.ndarray, min_similarity: float) -> np.ndarray:
    """Mutual nearest neighbours spelt out: argmax down each column (first row on ties) and along rows."""
    n0 = d0 / np.maximum(np.linalg.norm(d0, axis=1, keepdims=True), np.float32(1e-12))
    n1 = d1 / np.maximum(np.linalg.norm(d1, axis=1, keepdims=True), np.float32(1e-12))
    sim = n0.astype(np.float32) @ n1.astype(np.float32).T
    nn01, nn10 = np.argmax(sim, axis=1), np.argmax(sim, axis=0)
    rows = [i for i in range(len(d0)) if nn10[nn01[i]] == i and sim[i, nn01[i]] >= min_similarity]
    return np.array([[i, nn01[i]] for i in rows], dtype=np.int64).reshape(-1, 2)


def test_mnn_tie_goes_to_the_lower_row() -> None:
    """A column whose maximum two rows reach (duplicated descriptors) is matched to the first of them."""
    d0 = np.array([[0.8, 0.6], [1, 0], [1, 0]], np.float32)
    d1 = np.array([[1, 0], [0, 1]], np.float32)
    matches, _ = mutual_nearest_neighbours(d0, d1, min_similarity=0.5)
    np.testing.assert_array_equal(matches, [[1, 0]])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mnn_equals_the_spelt_out_rule_with_and_without_ties(seed: int) -> None:
    """On XFeat-sized random sets, with duplicated rows and columns, MNN is the spelt-out rule exactly."""
    rng = np.random.default_rng(seed)
    d0 = rng.standard_normal((512, 64)).astype(np.float32)
    d1 = rng.standard_normal((600, 64)).astype(np.float32)
    d1[:100] = d0[:100] + 0.05 * rng.standard_normal((100, 64)).astype(np.float32)
    for a, b in ((d0, d1), (d0.copy(), d1.copy())):
        matches, _ = mutual_nearest_neighbours(a, b, min_similarity=0.0)
        np.testing.assert_array_equal(matches, _mnn_reference(a, b, 0.0))
    d0[7] = d0[3]  # a tie down a column
    d1[11] = d1[5]  # a tie along a row
    matches, _ = mutual_nearest_neighbours(d0, d1, min_similarity=0.0)
    np.testing.assert_array_equal(matches, _mnn_reference(d0, d1, 0.0))
    assert len(matches) >= 90


def test_extractor_and_matcher_recover_image_shift(runtime, models) -> None:
    """End to end on real sessions: extractor on two shifted views + matcher -> matches agree on the shift."""
    extractor = runtime.load_engine(str(models["extractor"]), DISK_EXTRACTOR)
    lg = LightGlueRuntime(runtime, str(models["lg"]), descriptor_dim=128)
    img0, img1 = _crop_pair(seed=11, dx=12, dy=8)
    f0 = runtime.run(extractor, {"image": img0[None]})
    f1 = runtime.run(extractor, {"image": img1[None]})
    k0 = f0["keypoints"][0].astype(np.float32)
    k1 = f1["keypoints"][0].astype(np.float32)
    matches, _ = lg.match_pair(
        k0, f0["descriptors"][0], k1, f1["descriptors"][0], image_size0=(128, 96), image_size1=(128, 96)
    )
    shift = k1[matches[:, 1]] - k0[matches[:, 0]]
    agree = np.all(shift == [12, 8], axis=1)
    assert len(matches) >= 30
    assert agree.mean() > 0.9


def test_fused_pipeline_matches_shifted_pair(runtime, models) -> None:
    """Fused layout: keypoints in px, matches (M,2) int64 consistent with the known shift."""
    fused = FusedPipelineRuntime(runtime, str(models["fused"]))
    img0, img1 = _crop_pair(seed=12, dx=8, dy=4)
    result = fused.match_images(img0, img1)
    fed, out = runtime.calls[-1]
    assert fed["images"].shape == (2, 3, 96, 128)
    assert out["matches"].shape[1] == 3
    assert result.kpts0.dtype == np.float32 and result.kpts0.shape == (96, 2)
    assert result.matches.dtype == np.int64 and result.scores.dtype == np.float32
    assert result.matches.shape == (result.scores.shape[0], 2)
    shift = result.kpts1[result.matches[:, 1]] - result.kpts0[result.matches[:, 0]]
    assert len(result.matches) >= 30
    assert np.all(shift == [8, 4], axis=1).mean() > 0.9
    assert np.all((result.kpts0 - CENTRE_OFFSET_INT) % STRIDE_PX == 0)


def test_fused_pipeline_rejects_mismatched_images(runtime, models) -> None:
    """Two images of different shapes cannot be stacked."""
    fused = FusedPipelineRuntime(runtime, str(models["fused"]))
    with pytest.raises(ValueError, match="one shape"):
        fused.match_images(np.zeros((3, 64, 64), np.float32), np.zeros((3, 64, 72), np.float32))


def test_fused_pipeline_model_failure_raises_inference_error(runtime, models) -> None:
    """Images smaller than the patch make the model fail; surfaced as InferenceError."""
    fused = FusedPipelineRuntime(runtime, str(models["fused"]))
    with pytest.raises(InferenceError):
        fused.match_images(np.zeros((3, 4, 4), np.float32), np.zeros((3, 4, 4), np.float32))


def test_fused_pipeline_refuses_separate_extractor(runtime, models) -> None:
    """A separate extractor is not a fused pipeline: refused at construction."""
    with pytest.raises(EngineLoadError, match="input 'images': missing"):
        FusedPipelineRuntime(runtime, str(models["extractor"]))
