"""C2 appearance VPR on real imagery: VLAD cache build (manifest, idempotence), query normalisation,
retrieval (corpus-wide / prior-gated, logging), recall floors on geovision, and the generic ONNX backbone
through the real ONNX Runtime."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import uuid
from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper
from structlog.testing import capture_logs

from gps_denied_onboard.bench.vpr import evaluate_recall, render_queries
from gps_denied_onboard.camera.types import Attitude, CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c2_vpr.onnx_global import OnnxGlobalEncoder, OnnxGlobalVpr
from gps_denied_onboard.components.c2_vpr.protocol import SearchRegion, VprStrategy
from gps_denied_onboard.components.c2_vpr.query_norm import QueryNormaliser
from gps_denied_onboard.components.c2_vpr.retrieval import VPR_DESCRIPTORS_NAME, VPR_INDEX_NAME, VPR_META_NAME
from gps_denied_onboard.components.c2_vpr.types import IndexUnavailableError, VprBackboneError, VprQuery
from gps_denied_onboard.components.c2_vpr.vlad import (
    VLAD_VOCABULARY_NAME,
    VladParams,
    VladVpr,
    local_descriptors,
)
from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.components.c7_inference.onnx_runtime import OnnxInferenceRuntime
from gps_denied_onboard.components.c7_inference.protocol import EngineLoadError
from gps_denied_onboard.components.c10_cache_build.manifest import CacheManifest, Verification, sha256_file
from gps_denied_onboard.components.c10_cache_build.vpr_index import build_encoder_index, build_vlad_index
from gps_denied_onboard.constants import LogEvent

pytestmark = pytest.mark.realdata

SHARED_DATA = (
    Path(os.environ.get("GDNAV_SHARED_DIR", Path(__file__).resolve().parents[1].parent / "shared")) / "data"
)


def shared_path(*parts: str) -> Path:
    """A file under the shared data directory, or skip with the reason."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"shared data not available: {path}")
    return path


GEOVISION = ("geovision_india", "geovision_india_z18.tif")
#: Fewer training chips than the default (600) and no PCA (it needs > 256 samples) to keep the module fast.
PARAMS = VladParams(n_clusters=64, pca_dim=0, train_samples=120)
CALIB = CameraCalibration.from_hfov(640, 480, 70.0)


@pytest.fixture(scope="module")
def vlad_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The geovision ortho as a z19 cache (136 tiles) with VLAD descriptors and HNSW index."""
    from gps_denied_onboard.components.c10_cache_build import build_cache_from_geotiff

    src = shared_path(*GEOVISION)
    out = tmp_path_factory.mktemp("geo") / "cache"
    build_cache_from_geotiff(src, out, progress=False)
    build_vlad_index(out, PARAMS, progress=False)
    return out


@pytest.fixture(scope="module")
def store(vlad_cache: Path) -> TileStore:
    return TileStore.open(vlad_cache)


@pytest.fixture(scope="module")
def vpr(store: TileStore) -> VladVpr:
    return VladVpr.from_cache(store, top1_distance_warn=1.0)


@pytest.fixture(scope="module")
def queries(store: TileStore) -> list:
    return render_queries(shared_path(*GEOVISION), store, CALIB, n=24, alt_range_m=(100.0, 150.0), seed=3)


def _frame(image: np.ndarray, attitude: Attitude | None, alt: float | None) -> NavCameraFrame:
    return NavCameraFrame(uuid.uuid4(), 0, 0, image, attitude, alt, 0)


# --- C10: artifacts and manifest --------------------------------------------------------------------
def test_build_vlad_index_records_backbone_and_hashes(vlad_cache: Path) -> None:
    """The manifest names backbone 'vlad', the vocabulary's sha256, and every VPR artifact's hash."""
    manifest = CacheManifest.load(vlad_cache)
    assert manifest.vpr.backbone == "vlad"
    assert manifest.vpr.model_sha256 == sha256_file(vlad_cache / VLAD_VOCABULARY_NAME)
    for name in (VPR_INDEX_NAME, VPR_DESCRIPTORS_NAME, VPR_META_NAME, VLAD_VOCABULARY_NAME):
        assert manifest.artifacts[name].sha256 == sha256_file(vlad_cache / name)
    manifest.verify_artifacts(vlad_cache, Verification.FULL)
    desc = np.load(vlad_cache / VPR_DESCRIPTORS_NAME)
    assert desc.shape == (manifest.tile_count, PARAMS.vlad_dim) and desc.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(desc, axis=1), 1.0, atol=1e-4)


def test_build_vlad_index_rerun_is_idempotent(vlad_cache: Path) -> None:
    """Re-running with the same parameters recomputes nothing and leaves the files untouched."""
    before = {p.name: p.stat().st_mtime_ns for p in vlad_cache.iterdir()}
    with capture_logs() as logs:
        manifest = build_vlad_index(vlad_cache, PARAMS, progress=False)
    assert manifest == CacheManifest.load(vlad_cache)
    assert {p.name: p.stat().st_mtime_ns for p in vlad_cache.iterdir()} == before
    assert any(e["event"] == LogEvent.VPR_INDEX_UP_TO_DATE for e in logs)


@pytest.mark.slow
def test_build_vlad_index_after_interrupted_run_rebuilds_with_pca(vlad_cache: Path, tmp_path: Path) -> None:
    """A cache whose index file was replaced mid-build is rebuilt cleanly (here with PCA to 32 dims)."""
    cache = tmp_path / "cache"
    shutil.copytree(vlad_cache, cache)
    (cache / VPR_INDEX_NAME).write_bytes(b"partial")
    with pytest.raises(Exception, match=r"vpr_index\.faiss"):
        TileStore.open(cache)
    params = dataclasses.replace(PARAMS, train_samples=60, pca_dim=32)
    manifest = build_vlad_index(cache, params, progress=False)
    assert manifest.vpr.backbone == "vlad"
    store = TileStore.open(cache)  # verifies every hash, the new index included
    # The rebuild used PCA-whitening: 32-dim unit descriptors.
    assert VladVpr.from_cache(store, top1_distance_warn=1.0).descriptor_dim() == 32
    assert np.load(cache / VPR_DESCRIPTORS_NAME).shape == (len(store), 32)


def test_from_cache_without_descriptors_raises_index_unavailable(vlad_cache: Path, tmp_path: Path) -> None:
    """A cache built without VPR (backbone geo_prior) is refused by the vlad strategy."""
    cache = tmp_path / "cache"
    shutil.copytree(vlad_cache, cache)
    manifest = CacheManifest.load(cache)
    base = {k: v for k, v in manifest.artifacts.items() if not k.startswith("vpr_")}
    dataclasses.replace(
        manifest, vpr=dataclasses.replace(manifest.vpr, backbone="geo_prior"), artifacts=base
    ).save(cache)
    with pytest.raises(IndexUnavailableError, match="geo_prior"):
        VladVpr.from_cache(TileStore.open(cache), top1_distance_warn=1.0)


# --- query normalisation ----------------------------------------------------------------------------
def test_query_norm_removes_heading(store: TileStore) -> None:
    """The same place seen with headings 0 and 137 deg normalises to nearly the same north-up image."""
    from gps_denied_onboard.sitl.render import MapRenderer

    renderer = MapRenderer(shared_path(*GEOVISION))
    lon, lat = store.center_lonlat
    norm = QueryNormaliser(gsd_m_px=store.gsd_m_px, chip_size_px=512, backbone="vlad")
    imgs = []
    for yaw_deg in (0.0, 137.0):
        att = Attitude(0.0, 0.0, math.radians(yaw_deg))
        imgs.append(
            norm.normalise(_frame(renderer.render(CALIB, lat, lon, 120.0, att), att, 120.0), CALIB).image
        )
    both = imgs[0].any(axis=2) & imgs[1].any(axis=2)
    assert both.mean() > 0.4
    a = imgs[0][both].astype(np.float64).ravel()
    b = imgs[1][both].astype(np.float64).ravel()
    assert np.corrcoef(a, b)[0, 1] > 0.9
    assert imgs[0].shape == (512, 512, 3)


def test_embed_query_without_attitude_raises_backbone_error(vpr: VladVpr) -> None:
    """No north-up query without heading: a frame lacking attitude raises VprBackboneError and logs ERROR."""
    frame = _frame(np.full((480, 640, 3), 90, np.uint8), None, 120.0)
    with capture_logs() as logs, pytest.raises(VprBackboneError, match="attitude"):
        vpr.embed_query(frame, CALIB)
    assert [e["log_level"] for e in logs if e["event"] == LogEvent.VPR_ERROR] == ["error"]


def test_embed_query_returns_unit_vector_of_descriptor_dim(vpr: VladVpr, queries: list) -> None:
    """embed_query gives a (D,) float32 unit vector with the frame's id."""
    q = vpr.embed_query(queries[0].frame, CALIB)
    assert isinstance(vpr, VprStrategy)
    assert q.embedding.shape == (vpr.descriptor_dim(),) and q.embedding.dtype == np.float32
    assert np.linalg.norm(q.embedding) == pytest.approx(1.0, abs=1e-4)
    assert q.frame_id == queries[0].frame.frame_id


# --- retrieval --------------------------------------------------------------------------------------
def test_retrieve_gated_returns_only_tiles_in_region(vpr: VladVpr, store: TileStore, queries: list) -> None:
    """With a region, every candidate's centre lies within the radius; distances ascend."""
    q = queries[1]
    query = vpr.embed_query(q.frame, CALIB)
    region = SearchRegion(q.centre_lat_deg, q.centre_lon_deg, 150.0)
    result = vpr.retrieve_topk(query, 10, region=region)
    inside = {t for t, _ in store.tiles_near(q.centre_lat_deg, q.centre_lon_deg, 150.0)}
    assert result.candidates and {c.tile_id for c in result.candidates} <= inside
    d = [c.descriptor_distance for c in result.candidates]
    assert d == sorted(d)
    assert result.backbone_label == "vlad"


def test_retrieve_corpus_wide_returns_k_ranked(vpr: VladVpr, queries: list) -> None:
    """Corpus-wide retrieval returns k candidates ranked by distance, all with the descriptor dim."""
    result = vpr.retrieve_topk(vpr.embed_query(queries[2].frame, CALIB), 10)
    assert len(result.candidates) == 10
    assert all(c.descriptor_dim == vpr.descriptor_dim() for c in result.candidates)
    d = [c.descriptor_distance for c in result.candidates]
    assert d == sorted(d) and 0.0 <= d[0] <= 2.0


def test_retrieve_logs_debug_topk_and_warns_on_far_top1(store: TileStore, queries: list) -> None:
    """DEBUG top-k distances every call; WARN when the top-1 distance is above the threshold."""
    strict = VladVpr.from_cache(store, top1_distance_warn=1e-3)
    query = strict.embed_query(queries[0].frame, CALIB)
    with capture_logs() as logs:
        strict.retrieve_topk(query, 5)
    events = {e["event"]: e for e in logs}
    assert len(events[LogEvent.VPR_TOPK]["topk_distances"]) == 5
    assert events[LogEvent.VPR_FAR_TOP1]["log_level"] == "warning"


def test_retrieve_wrong_embedding_dim_raises_index_unavailable(vpr: VladVpr) -> None:
    """A query embedding that does not fit the index raises IndexUnavailableError."""
    with pytest.raises(IndexUnavailableError, match="index dimension"):
        vpr.retrieve_topk(VprQuery(uuid.uuid4(), np.ones(7, np.float32), 0), 5)


def test_ready_logged_with_backbone_dim_and_corpus_size(store: TileStore) -> None:
    """Building the strategy logs INFO c2.vpr.ready with backbone, dim and corpus size."""
    with capture_logs() as logs:
        v = VladVpr.from_cache(store, top1_distance_warn=1.0)
    ready = next(e for e in logs if e["event"] == LogEvent.VPR_READY)
    assert (ready["backbone"], ready["dim"], ready["corpus_size"]) == ("vlad", v.descriptor_dim(), len(store))


def test_recall_floors_on_geovision(vpr: VladVpr, store: TileStore, queries: list) -> None:
    """Rendered frames (100-150 m AGL, any heading) retrieve a true tile: floors below what is measured."""
    r = evaluate_recall(store, vpr, CALIB, queries, chip_size_px=PARAMS.chip_size_px)
    assert r["queries"] >= 20
    # Measured with these parameters: corpus @1 0.83, @10 1.0; gated @5 1.0 (24 frames).
    assert r["recall_corpus"]["@1"] >= 0.6
    assert r["recall_corpus"]["@10"] >= 0.85
    assert r["recall_gated"]["@5"] >= 0.9


# --- generic ONNX backbone --------------------------------------------------------------------------
def _gap_projection_model(path: Path, dim: int, seed: int, *, out_name: str = "descriptor") -> np.ndarray:
    """ONNX: input (1,3,H,W) -> GlobalAveragePool -> Flatten -> MatMul W (3, dim) -> (1, dim). Returns W."""
    w = np.random.default_rng(seed).standard_normal((3, dim)).astype(np.float32)
    nodes = [
        helper.make_node("GlobalAveragePool", ["input"], ["gap"]),
        helper.make_node("Flatten", ["gap"], ["flat"], axis=1),
        helper.make_node("MatMul", ["flat", "W"], [out_name]),
    ]
    graph = helper.make_graph(
        nodes,
        "gap_projection",
        [helper.make_tensor_value_info("input", TensorProto.FLOAT, [1, 3, "H", "W"])],
        [helper.make_tensor_value_info(out_name, TensorProto.FLOAT, [1, dim])],
        [numpy_helper.from_array(w, "W")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, path)
    return w


def test_onnx_encoder_matches_numpy_reference(tmp_path: Path) -> None:
    """The real ONNX Runtime output equals the normalised projection of the channel means."""
    w = _gap_projection_model(tmp_path / "g.onnx", 16, seed=1)
    enc = OnnxGlobalEncoder(
        OnnxInferenceRuntime(intra_op_threads=1),
        tmp_path / "g.onnx",
        input_size=(64, 64),
        output_name="descriptor",
        dim=16,
        label="gap16",
    )
    img = np.zeros((100, 120, 3), np.uint8)
    img[..., 0], img[..., 1], img[..., 2] = 30, 140, 220  # B, G, R
    x = enc.preprocess(img)
    assert x.shape == (1, 3, 64, 64) and x.dtype == np.float32
    expected = x.mean(axis=(2, 3)) @ w
    expected = expected[0] / np.linalg.norm(expected)
    np.testing.assert_allclose(enc.embed_image(img), expected, atol=1e-5)
    assert enc.model_sha256 == sha256_file(tmp_path / "g.onnx")


def test_onnx_encoder_mismatched_model_raises_engine_load_error(tmp_path: Path) -> None:
    """A model whose output dim or name differs from the configured one is refused at load time."""
    _gap_projection_model(tmp_path / "g.onnx", 16, seed=1)
    runtime = OnnxInferenceRuntime(intra_op_threads=1)
    with pytest.raises(EngineLoadError, match="dim 1 expected 32"):
        OnnxGlobalEncoder(
            runtime, tmp_path / "g.onnx", input_size=(64, 64), output_name="descriptor", dim=32, label="x"
        )
    with pytest.raises(EngineLoadError, match="'embedding': missing"):
        OnnxGlobalEncoder(
            runtime, tmp_path / "g.onnx", input_size=(64, 64), output_name="embedding", dim=16, label="x"
        )
    with pytest.raises(EngineLoadError, match="not found"):
        OnnxGlobalEncoder(
            runtime,
            tmp_path / "missing.onnx",
            input_size=(64, 64),
            output_name="descriptor",
            dim=16,
            label="x",
        )


def test_onnx_index_build_records_model_and_refuses_other_backbones(vlad_cache: Path, tmp_path: Path) -> None:
    """C10 records label + model sha256; the daemon refuses the cache with another model or backbone."""
    cache = tmp_path / "cache"
    shutil.copytree(vlad_cache, cache)
    runtime = OnnxInferenceRuntime(intra_op_threads=1)
    _gap_projection_model(tmp_path / "a.onnx", 16, seed=1)
    _gap_projection_model(tmp_path / "b.onnx", 16, seed=2)
    kw = {"input_size": (64, 64), "output_name": "descriptor", "dim": 16, "label": "gap16"}
    enc_a = OnnxGlobalEncoder(runtime, tmp_path / "a.onnx", **kw)
    manifest = build_encoder_index(cache, enc_a, chip_size_px=256, progress=False)
    assert (manifest.vpr.backbone, manifest.vpr.model_sha256) == ("gap16", sha256_file(tmp_path / "a.onnx"))
    assert VLAD_VOCABULARY_NAME not in manifest.artifacts
    assert json.loads((cache / VPR_META_NAME).read_text())["chip_size_px"] == 256
    store = TileStore.open(cache)
    strategy = OnnxGlobalVpr.from_cache(store, enc_a, top1_distance_warn=1.0)
    assert strategy.descriptor_dim() == 16 and strategy.normaliser.chip_size_px == 256
    enc_b = OnnxGlobalEncoder(runtime, tmp_path / "b.onnx", **kw)
    with pytest.raises(IndexUnavailableError, match="another 'gap16' model"):
        OnnxGlobalVpr.from_cache(store, enc_b, top1_distance_warn=1.0)
    with pytest.raises(IndexUnavailableError, match="backbone 'gap16'"):
        VladVpr.from_cache(store, top1_distance_warn=1.0)


def test_rootsift_is_finite_on_flat_areas_with_edges() -> None:
    """Flat areas crossed by sharp edges (the procedural demo map has them): the box filter's float sums
    leave -1e-17 where the gradient is zero, and RootSIFT's square root made NaN of it, which failed the
    vocabulary's SVD and the whole index build."""
    rng = np.random.default_rng(0)
    img = np.full((512, 512, 3), 120, np.uint8)
    for _ in range(12):
        colour = tuple(int(v) for v in rng.integers(20, 250, 3))
        x, y = (int(v) for v in rng.integers(0, 512, 2))
        w, h = (int(v) for v in rng.integers(20, 200, 2))
        cv2.rectangle(img, (x, y), (x + w, y + h), colour, -1)
        p0, p1 = (tuple(int(v) for v in rng.integers(0, 512, 2)) for _ in range(2))
        cv2.line(img, p0, p1, colour, int(rng.integers(1, 4)))
    desc = local_descriptors(img, VladParams())
    assert desc.shape[0] > 100
    assert np.isfinite(desc).all() and (desc >= 0).all()
