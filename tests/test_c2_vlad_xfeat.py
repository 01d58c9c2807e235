"""C2 ``vlad_xfeat``: VLAD over the real exported XFeat extractor's descriptors, on real NAIP imagery.

Cross-date place recognition (map 2009, frames 2020) against the weights-free ``vlad``, the cache's record
of the extractor model and the refusal of another model (library and ``gdnav run``, exit 3), and the
start-up refusals of the VPR strategies (exit 3, one line). The XFeat extractor is the repository's
``models/`` export when its manifest verifies, else the session's registry export
(``registry_models_fixture``; skipped with the reason when the export extra is not installed).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import numpy_helper

from conftest import REPO_ROOT, shared_path
from daemon_harness import build_small_cache, daemon_command, free_tcp_port, free_udp_port
from gps_denied_onboard.bench.vpr import evaluate_recall, render_queries
from gps_denied_onboard.camera.types import CameraCalibration
from gps_denied_onboard.components.c2_vpr.learned_local import XFeatDescriber, find_xfeat_extractor
from gps_denied_onboard.components.c2_vpr.types import IndexUnavailableError
from gps_denied_onboard.components.c2_vpr.vlad import (
    VLAD_VOCABULARY_NAME,
    VladEncoder,
    VladError,
    VladParams,
    VladVocabulary,
    VladVpr,
)
from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.components.c7_inference.onnx_runtime import OnnxInferenceRuntime
from gps_denied_onboard.components.c10_cache_build.manifest import CacheManifest, Verification, sha256_file
from gps_denied_onboard.components.c10_cache_build.vpr_index import build_vlad_index
from gps_denied_onboard.helpers.model_manifest import ModelDirError
from registry_models_fixture import registry_models  # noqa: F401 - session fixture

NAIP = ("data", "naip_timeseries", "naip")
MAP_2009 = "m_4709963_se_14_1_20090818.tif"
FRAMES_2020 = "m_4709963_se_14_1_20200831.tif"
CALIB = CameraCalibration.from_hfov(640, 480, 70.0)
#: Small vocabularies, few training chips and no PCA (it needs > 256 samples) to keep the module short;
#: the benchmark's defaults (k=64, PCA 256, 600 chips) are in docs/benchmarks.md.
XFEAT_PARAMS = VladParams(
    descriptor="xfeat", n_clusters=32, pca_dim=0, train_samples=60, work_size_px=512, max_keypoints=512
)
ROOTSIFT_PARAMS = VladParams(n_clusters=32, pca_dim=0, train_samples=60)
#: An exported model's first download can take minutes on the shared 2-core machine.
EXPORT_TIMEOUT_S = 900


def _gdnav_run(cwd: Path, *overrides: str) -> subprocess.CompletedProcess[str]:
    """`gdnav run --config sitl.yaml` with ports and directories of its own plus ``overrides``."""
    cmd = daemon_command(free_udp_port(), free_tcp_port(), cwd / "fdr", *overrides)
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=cwd)


def _refusal_line(proc: subprocess.CompletedProcess[str], code: int) -> str:
    """Exit ``code``, no traceback, and the last stderr line is the one plain `gdnav:` refusal."""
    assert proc.returncode == code, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    plain = [ln for ln in proc.stderr.splitlines() if ln.strip() and not ln.startswith("{")]
    assert len(plain) == 1 and plain[0].startswith("gdnav: "), proc.stderr[-3000:]
    return plain[0]


@pytest.fixture(scope="module")
def xfeat_onnx(request: pytest.FixtureRequest) -> Path:
    """The XFeat extractor: ``models/`` when its manifest verifies, else the registry export."""
    try:
        return find_xfeat_extractor(REPO_ROOT / "models")
    except (ModelDirError, OSError):
        export: Callable[[str], Path] = request.getfixturevalue("registry_models")
        return find_xfeat_extractor(export("xfeat"))


@pytest.fixture(scope="module")
def naip_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The NAIP 2009 quarter-quad as a z16 cache of 128 px tiles (99 tiles, 3.3 m/px), no VPR index."""
    from gps_denied_onboard.components.c10_cache_build import build_cache_from_geotiff

    out = tmp_path_factory.mktemp("naip") / "cache"
    build_cache_from_geotiff(shared_path(*NAIP, MAP_2009), out, zoom=16, tile_size_px=128, progress=False)
    return out


@pytest.fixture(scope="module")
def xfeat_cache(naip_cache: Path, xfeat_onnx: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    cache = tmp_path_factory.mktemp("naip_xfeat") / "cache"
    shutil.copytree(naip_cache, cache)
    describer = XFeatDescriber(OnnxInferenceRuntime(intra_op_threads=2), xfeat_onnx)
    build_vlad_index(cache, XFEAT_PARAMS, describer=describer, progress=False)
    return cache


def _other_model(src: Path, dst: Path) -> Path:
    """A different XFeat model: the same graph with its largest weight tensor scaled by 1.05."""
    model = onnx.load(str(src))
    init = max(model.graph.initializer, key=lambda t: int(np.prod(t.dims)))
    init.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(init) * np.float32(1.05), init.name))
    onnx.save(model, str(dst))
    return dst


@pytest.mark.slow
@pytest.mark.realdata
@pytest.mark.timeout(EXPORT_TIMEOUT_S)
def test_vlad_xfeat_ranks_cross_date_frames_better_than_rootsift(
    naip_cache: Path, xfeat_cache: Path, xfeat_onnx: Path, tmp_path: Path
) -> None:
    """Map 2009, frames 2020: VLAD over XFeat finds the true tile in its top 10 for most frames, and
    clearly more often than the weights-free dense-RootSIFT VLAD on the same frames."""
    rootsift_cache = tmp_path / "cache"
    shutil.copytree(naip_cache, rootsift_cache)
    build_vlad_index(rootsift_cache, ROOTSIFT_PARAMS, progress=False)
    rootsift_store = TileStore.open(rootsift_cache)
    queries = render_queries(
        shared_path(*NAIP, FRAMES_2020), rootsift_store, CALIB, n=20, alt_range_m=(1500.0, 2000.0), seed=5
    )
    xfeat_store = TileStore.open(xfeat_cache)
    describer = XFeatDescriber(OnnxInferenceRuntime(intra_op_threads=2), xfeat_onnx)
    learned = VladVpr.from_cache(xfeat_store, top1_distance_warn=2.0, describer=describer)
    xfeat = evaluate_recall(xfeat_store, learned, CALIB, queries)
    weights_free = VladVpr.from_cache(rootsift_store, top1_distance_warn=2.0)
    rootsift = evaluate_recall(rootsift_store, weights_free, CALIB, queries)
    print("vlad_xfeat", xfeat["recall_corpus"], "vlad", rootsift["recall_corpus"])
    assert learned.label == "vlad_xfeat" and learned.descriptor_dim() == 32 * 64
    assert xfeat["queries"] == rootsift["queries"] >= 15
    assert xfeat["recall_corpus"]["@10"] >= 0.8
    assert xfeat["recall_corpus"]["@5"] >= rootsift["recall_corpus"]["@5"] + 0.2
    assert xfeat["recall_corpus"]["@10"] >= rootsift["recall_corpus"]["@10"] + 0.2


@pytest.mark.slow
@pytest.mark.realdata
@pytest.mark.timeout(EXPORT_TIMEOUT_S)
def test_vlad_xfeat_cache_records_the_model_and_refuses_another(
    xfeat_cache: Path, xfeat_onnx: Path, tmp_path: Path
) -> None:
    """The manifest records backbone vlad_xfeat and the extractor's sha256; the strategy with another
    XFeat model, or the weights-free vlad, refuses the cache instead of mixing descriptors."""
    manifest = CacheManifest.load(xfeat_cache)
    assert (manifest.vpr.backbone, manifest.vpr.model_sha256) == ("vlad_xfeat", sha256_file(xfeat_onnx))
    manifest.verify_artifacts(xfeat_cache, Verification.FULL)
    meta = json.loads((xfeat_cache / "vpr_meta.json").read_text())
    assert meta["model_sha256"] == sha256_file(xfeat_onnx) and meta["params"]["descriptor"] == "xfeat"
    store = TileStore.open(xfeat_cache)
    runtime = OnnxInferenceRuntime(intra_op_threads=2)
    VladVpr.from_cache(store, top1_distance_warn=2.0, describer=XFeatDescriber(runtime, xfeat_onnx))
    other = XFeatDescriber(runtime, _other_model(xfeat_onnx, tmp_path / "xfeat-other.onnx"))
    assert other.model_sha256 != sha256_file(xfeat_onnx)
    with pytest.raises(IndexUnavailableError, match="another 'vlad_xfeat' model"):
        VladVpr.from_cache(store, top1_distance_warn=2.0, describer=other)
    with pytest.raises(IndexUnavailableError, match="backbone 'vlad_xfeat', this strategy is 'vlad'"):
        VladVpr.from_cache(store, top1_distance_warn=2.0)


@pytest.mark.slow
@pytest.mark.realdata
@pytest.mark.timeout(EXPORT_TIMEOUT_S)
def test_cli_run_with_another_xfeat_model_than_the_cache_exits_3(
    xfeat_cache: Path, xfeat_onnx: Path, tmp_path: Path
) -> None:
    """`gdnav run` with vpr.strategy vlad_xfeat and a model the cache was not built with: exit 3, one line
    naming the strategy and the mismatch (never a start on mixed descriptors)."""
    other = _other_model(xfeat_onnx, tmp_path / "xfeat-other.onnx")
    line = _refusal_line(
        _gdnav_run(
            tmp_path,
            f"cache.dir={xfeat_cache}",
            "vpr.strategy=vlad_xfeat",
            f"vpr.xfeat_weights_path={other}",
        ),
        3,
    )
    assert "vpr.strategy" in line and "another 'vlad_xfeat' model" in line, line


@pytest.mark.slow
@pytest.mark.realdata
@pytest.mark.timeout(EXPORT_TIMEOUT_S)
def test_compose_builds_vlad_xfeat_from_the_matcher_model_dir(xfeat_cache: Path, xfeat_onnx: Path) -> None:
    """The composition root takes the XFeat extractor from matcher.model_dir (manifest verified) when
    vpr.xfeat_weights_path is null, and the strategy it builds retrieves a real cross-date frame."""
    from gps_denied_onboard.config import load_config
    from gps_denied_onboard.runtime_root.compose import create_vpr, open_tile_store

    config = load_config(
        None,
        [f"cache.dir={xfeat_cache}", "vpr.strategy=vlad_xfeat", f"matcher.model_dir={xfeat_onnx.parent}"],
    )
    tiles = open_tile_store(config, Verification.FULL)
    vpr = create_vpr(tiles, config)
    assert isinstance(vpr, VladVpr) and vpr.label == "vlad_xfeat"
    (query,) = render_queries(
        shared_path(*NAIP, FRAMES_2020), tiles, CALIB, n=1, alt_range_m=(1500.0, 2000.0), seed=11
    )
    result = vpr.retrieve_topk(vpr.embed_query(query.frame, CALIB), 10)
    assert result.backbone_label == "vlad_xfeat" and len(result.candidates) == 10


# --- fast: no model needed --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A procedural-map cache without any VPR index (geo_prior only)."""
    return build_small_cache(tmp_path_factory.mktemp("small"))[1]


def test_cli_run_vlad_on_a_cache_without_its_index_exits_3(small_cache: Path, tmp_path: Path) -> None:
    """vpr.strategy vlad on a cache without its VLAD index: exit 3 and one line naming the fix."""
    line = _refusal_line(_gdnav_run(tmp_path, f"cache.dir={small_cache}", "vpr.strategy=vlad"), 3)
    assert "vpr.strategy" in line and "gdnav cache vpr" in line, line


def test_cli_run_vlad_xfeat_without_a_model_exits_3(small_cache: Path, tmp_path: Path) -> None:
    """vlad_xfeat with neither vpr.xfeat_weights_path nor a usable matcher.model_dir: exit 3, one line."""
    line = _refusal_line(
        _gdnav_run(
            tmp_path, f"cache.dir={small_cache}", "vpr.strategy=vlad_xfeat", f"matcher.model_dir={tmp_path}"
        ),
        3,
    )
    assert "matcher.model_dir" in line, line
    missing = tmp_path / "nope.onnx"
    line = _refusal_line(
        _gdnav_run(
            tmp_path,
            f"cache.dir={small_cache}",
            "vpr.strategy=vlad_xfeat",
            f"vpr.xfeat_weights_path={missing}",
        ),
        3,
    )
    assert "vpr.xfeat_weights_path" in line and str(missing) in line, line


def test_config_xfeat_weights_path_without_vlad_xfeat_is_refused(tmp_path: Path) -> None:
    """vpr.xfeat_weights_path with another strategy is a configuration error (exit 2) naming the key."""
    proc = _gdnav_run(tmp_path, "vpr.strategy=vlad", f"vpr.xfeat_weights_path={tmp_path / 'x.onnx'}")
    assert proc.returncode == 2 and "vpr.xfeat_weights_path" in proc.stderr, proc.stderr[-2000:]


def test_vlad_encoder_refuses_a_describer_of_other_descriptors() -> None:
    """A vocabulary learned on RootSIFT cannot be fed XFeat descriptors (nor the reverse)."""
    rng = np.random.default_rng(0)
    vocab = VladVocabulary(
        XFEAT_PARAMS,
        rng.standard_normal((32, 64)).astype(np.float32),
        np.empty(0, np.float32),
        np.empty((0, 0), np.float32),
    )
    with pytest.raises(VladError, match="learned on 'xfeat' descriptors, the describer gives 'rootsift'"):
        VladEncoder(vocab)


def test_vlad_vocabulary_of_xfeat_round_trips_and_checks_its_shape(tmp_path: Path) -> None:
    """An XFeat vocabulary (k x 64) saves and loads; one whose words are not 64-d is refused."""
    rng = np.random.default_rng(0)
    empty = (np.empty(0, np.float32), np.empty((0, 0), np.float32))
    VladVocabulary(XFEAT_PARAMS, rng.standard_normal((32, 64)).astype(np.float32), *empty).save(
        tmp_path / VLAD_VOCABULARY_NAME
    )
    loaded = VladVocabulary.load(tmp_path / VLAD_VOCABULARY_NAME)
    assert loaded.params == XFEAT_PARAMS and loaded.dim == 32 * 64
    VladVocabulary(XFEAT_PARAMS, rng.standard_normal((32, 128)).astype(np.float32), *empty).save(
        tmp_path / "bad.npz"
    )
    with pytest.raises(VladError, match=r"centroids have shape \(32, 128\)"):
        VladVocabulary.load(tmp_path / "bad.npz")


def test_cli_bench_vpr_refuses_unknown_strategy_and_missing_model(tmp_path: Path) -> None:
    """`gdnav bench vpr`: an unknown --strategy is exit 2; vlad_xfeat without an XFeat export is exit 3,
    both before any cache is built."""
    base = [sys.executable, "-m", "gps_denied_onboard.cli", "bench", "vpr", "--map", str(tmp_path / "m.tif")]
    proc = subprocess.run([*base, "--strategy", "vlad,netvlad"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "netvlad" in proc.stderr and "vlad_xfeat" in proc.stderr, proc.stderr
    proc = subprocess.run(
        [*base, "--strategy", "vlad_xfeat", "--model-dir", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 3 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert str(tmp_path) in proc.stderr, proc.stderr


def test_cli_cache_vpr_xfeat_without_a_model_exits_3(small_cache: Path, tmp_path: Path) -> None:
    """`gdnav cache vpr --descriptor xfeat` with a model directory holding no export: exit 3 naming it;
    --xfeat without --descriptor xfeat: exit 2. The cache is left without a VPR index."""
    base = [sys.executable, "-m", "gps_denied_onboard.cli", "cache", "vpr", "--cache", str(small_cache)]
    proc = subprocess.run(
        [*base, "--descriptor", "xfeat", "--model-dir", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 3 and str(tmp_path) in proc.stderr, proc.stderr[-2000:]
    proc = subprocess.run(
        [*base, "--xfeat", str(tmp_path / "x.onnx")], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 2 and "--descriptor xfeat" in proc.stderr, proc.stderr[-2000:]
    assert CacheManifest.load(small_cache).vpr.backbone == "geo_prior"
