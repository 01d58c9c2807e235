"""Precomputed tile features (``gdnav cache features``): built, verified, used, refused.

Real NAIP imagery (a map cache built from the 2009 GeoTIFF) and real ONNX Runtime throughout. The default
run uses the self-built XFeat-layout stand-in models (``onnx_builders``, D=64); the slow test runs the real
XFeat + LighterGlue exported from the registry packages (``registry_models_fixture``) on a 2020 frame.
The only double is a counting wrapper around the real runtime (how many extractor forward passes ran).
"""

from __future__ import annotations

import dataclasses
import fcntl
import math
import os
import pty
import struct
import subprocess
import sys
import termios
import time
import uuid
from collections.abc import Callable, Mapping
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("onnx")

from conftest import REPO_ROOT, shared_path
from gps_denied_onboard.camera.types import CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c2_5_rerank.types import RerankCandidate, RerankResult
from gps_denied_onboard.components.c3_matcher import RollingHealthWindow
from gps_denied_onboard.components.c3_matcher.base import MatchResult
from gps_denied_onboard.components.c3_matcher.tile_features import (
    PrecomputedTileFeatures,
    TileFeaturesRefused,
    file_names,
)
from gps_denied_onboard.components.c3_matcher.xfeat import XFeatMatcher, create
from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.components.c7_inference.onnx_runtime import OnnxInferenceRuntime
from gps_denied_onboard.components.c10_cache_build import build_cache
from gps_denied_onboard.components.c10_cache_build.manifest import CacheManifest, Verification
from gps_denied_onboard.components.c10_cache_build.tile_features import build_tile_features
from gps_denied_onboard.config import Config, MatcherConfig, load_config
from gps_denied_onboard.constants import FdrKind
from gps_denied_onboard.helpers.lightglue_runtime import LightGlueRuntime
from gps_denied_onboard.helpers.ransac_filter import RansacFilter
from gps_denied_onboard.runtime_root.compose import StartupError, open_tile_features
from onnx_builders import build_fake_extractor, build_fake_lightglue
from registry_models_fixture import registry_models  # noqa: F401 - session fixture
from test_c3_matcher_contract import FakeFdrClient

NAIP = ("data", "naip_timeseries", "naip")
NAIP_2009 = "m_4709963_se_14_1_20090818.tif"
NAIP_2020 = "m_4709963_se_14_1_20200831.tif"
CHIP_PX = 256


class CountingRuntime:
    """The real ONNX runtime, counting the forward passes of the extractor engine."""

    def __init__(self, inner: OnnxInferenceRuntime) -> None:
        self._inner = inner
        self.extractor_calls = 0

    def load_engine(self, path: str, signature: object = None) -> str:
        return self._inner.load_engine(path, signature)  # type: ignore[arg-type]

    def run(self, engine_id: str, inputs: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        if engine_id.startswith("xfeat"):  # LightGlue shares the runtime: count the extractor only
            self.extractor_calls += 1
        return self._inner.run(engine_id, inputs)

    def provider(self, engine_id: str) -> str:
        return self._inner.provider(engine_id)

    def engine_info(self, engine_id: str) -> object:
        return self._inner.engine_info(engine_id)


@pytest.fixture(scope="module")
def naip_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A map cache of the NAIP 2009 GeoTIFF (28 tiles at zoom 15), built once for the module."""
    out = tmp_path_factory.mktemp("naip2009") / "cache"
    build_cache(shared_path(*NAIP, NAIP_2009), out, progress=False)
    return out


@pytest.fixture()
def cache(naip_cache: Path, tmp_path: Path) -> Path:
    """A private copy of the module's cache (tests add and damage feature sets)."""
    out = tmp_path / "cache"
    out.mkdir()
    for f in naip_cache.iterdir():
        (out / f.name).write_bytes(f.read_bytes())
    return out


@pytest.fixture(scope="module")
def stand_in_models(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("models")
    return {
        "a": build_fake_extractor(
            d / "xfeat_a.onnx", channels=1, dim=64, num_keypoints=256, keypoint_dtype="float32"
        ),
        "b": build_fake_extractor(
            d / "xfeat_b.onnx", channels=1, dim=64, num_keypoints=256, keypoint_dtype="float32", seed=8
        ),
        "lightglue": build_fake_lightglue(d / "lighterglue.onnx", dim=64, min_similarity=0.9),
    }


def _matcher_config(model: Path, lightglue: Path, **overrides: object) -> MatcherConfig:
    values: dict[str, object] = {
        "strategy": "xfeat",
        "xfeat_weights_path": str(model),
        "lightglue_weights_path": str(lightglue),
        "chip_size_px": CHIP_PX,
        "input_long_side_px": CHIP_PX,
        "min_inliers_threshold": 10,
    }
    values.update(overrides)
    return MatcherConfig(**values)  # type: ignore[arg-type]


def _xfeat(
    config: MatcherConfig, tile_features: PrecomputedTileFeatures | None = None
) -> tuple[XFeatMatcher, CountingRuntime]:
    runtime = CountingRuntime(OnnxInferenceRuntime(intra_op_threads=1, providers=["CPUExecutionProvider"]))
    lightglue = LightGlueRuntime(runtime, config.lightglue_weights_path, descriptor_dim=64)  # type: ignore[arg-type]
    matcher = create(
        config,
        lightglue,
        RansacFilter(),
        runtime,  # type: ignore[arg-type]
        RollingHealthWindow(config.min_inliers_threshold),
        tile_features=tile_features,
    )
    return matcher, runtime


def _daemon_config(cache: Path, matcher: MatcherConfig, **cache_overrides: object) -> Config:
    base = load_config(REPO_ROOT / "config" / "sitl.yaml", ())
    return dataclasses.replace(
        base,
        cache=dataclasses.replace(base.cache, dir=str(cache), **cache_overrides),  # type: ignore[arg-type]
        matcher=matcher,
    )


def _crop_frame(store: TileStore, tile_index: int, dx: int, dy: int) -> tuple[NavCameraFrame, RerankResult]:
    """A nadir frame cut from the map itself, (dx, dy) px off the chip of tile ``tile_index`` (multiples of
    4 px keep the stand-in extractor's grid), with that chip and the two next tiles' as candidates."""
    tile = store.tile_ids[tile_index]
    chip = store.chip(tile, CHIP_PX)
    col0 = chip.origin_px[0] - store.manifest.tile_range.x0 * store.tile_size_px
    row0 = chip.origin_px[1] - store.manifest.tile_range.y0 * store.tile_size_px
    image = np.ascontiguousarray(
        store.mosaic[row0 + dy : row0 + dy + CHIP_PX, col0 + dx : col0 + dx + CHIP_PX]
    )
    frame = NavCameraFrame(uuid.uuid4(), 0, 0, image, None, None, time.monotonic_ns())
    cands = [
        RerankCandidate(t, store.chip(t, CHIP_PX), -1, float(i))
        for i, t in enumerate(store.tile_ids[tile_index : tile_index + 3])
    ]
    return frame, RerankResult(frame.frame_id, cands, 0)


def _same_result(a: MatchResult, b: MatchResult) -> None:
    assert [c.tile_id for c in a.per_candidate] == [c.tile_id for c in b.per_candidate]
    for ca, cb in zip(a.per_candidate, b.per_candidate, strict=True):
        assert ca.inlier_count == cb.inlier_count
        np.testing.assert_array_equal(ca.inlier_correspondences, cb.inlier_correspondences)
        assert ca.per_candidate_residual_px == cb.per_candidate_residual_px


# --- default run: stand-in models, real ORT, real NAIP ------------------------------------------------------
def test_tile_features_built_then_used_instead_of_extracting(
    cache: Path, stand_in_models: dict[str, Path]
) -> None:
    """Every tile's precomputed features equal a live extraction, the candidate loop gives the same result
    with them as live, and with them the extractor runs once per frame (the query) instead of 1 + N."""
    config = _matcher_config(stand_in_models["a"], stand_in_models["lightglue"])
    live, live_rt = _xfeat(config)
    build = build_tile_features(cache, live, progress=False)
    assert build.built and build.manifest.tile_features["xfeat"].tile_count == 28
    assert live_rt.extractor_calls == 28  # one forward pass per tile, at build time
    for name in file_names("xfeat"):
        assert np.load(cache / name, mmap_mode="r") is not None

    store = TileStore.open(cache)
    fdr = FakeFdrClient()
    feats = open_tile_features(_daemon_config(cache, config), store, fdr)  # type: ignore[arg-type]
    assert feats is not None
    assert fdr.of(FdrKind.TILE_FEATURES)[0]["used"] is True
    for tile in store.tile_ids:
        chip = store.chip(tile, CHIP_PX)
        got = feats.lookup(chip, chip.size_px)
        want = live.extract_tile(chip.pixels())
        assert got is not None and got.count > 0
        np.testing.assert_array_equal(got.keypoints_px, want.keypoints_px)
        np.testing.assert_array_equal(got.descriptors, want.descriptors)
        assert got.image_size == want.image_size
    # A chip cut elsewhere around the same tile is not the chip the features were made from.
    other = store.chip(store.tile_ids[10], CHIP_PX + 64)
    assert feats.lookup(other, other.size_px) is None

    pre, pre_rt = _xfeat(config, tile_features=feats)
    live2, live2_rt = _xfeat(config)
    frame, rerank = _crop_frame(store, 10, 48, 32)
    result_pre = pre.match(frame, rerank, CameraCalibration.from_hfov(CHIP_PX, CHIP_PX, 60.0))
    result_live = live2.match(frame, rerank, CameraCalibration.from_hfov(CHIP_PX, CHIP_PX, 60.0))
    assert result_pre.best.tile_id == store.tile_ids[10] and result_pre.best.inlier_count >= 25
    _same_result(result_pre, result_live)
    assert pre_rt.extractor_calls == 1  # the query only
    assert live2_rt.extractor_calls == 1 + len(rerank.candidates)
    assert feats.hits == 28 + 3


def test_tile_features_of_another_model_are_refused_and_rebuilt(
    cache: Path, stand_in_models: dict[str, Path]
) -> None:
    """A set made with model A is refused for model B (logged, recorded, live extraction; exit 3 with
    require), never handed to B's matcher; `cache features` with B replaces it."""
    config_a = _matcher_config(stand_in_models["a"], stand_in_models["lightglue"])
    config_b = _matcher_config(stand_in_models["b"], stand_in_models["lightglue"])
    matcher_a, _ = _xfeat(config_a)
    build_tile_features(cache, matcher_a, progress=False)
    store = TileStore.open(cache)

    fdr = FakeFdrClient()
    assert open_tile_features(_daemon_config(cache, config_b), store, fdr) is None  # type: ignore[arg-type]
    (record,) = fdr.of(FdrKind.TILE_FEATURES)
    assert record["used"] is False and "model_sha256" in str(record["reason"])
    with pytest.raises(StartupError, match="model_sha256"):
        open_tile_features(
            _daemon_config(cache, dataclasses.replace(config_b, tile_features="require")),
            store,
            FakeFdrClient(),  # type: ignore[arg-type]
        )
    # The same set is refused for A too when its keypoint cap differs (the features depend on it).
    with pytest.raises(TileFeaturesRefused, match="max_keypoints"):
        PrecomputedTileFeatures.open(
            store, _xfeat(dataclasses.replace(config_a, max_keypoints=100))[0].extractor_identity
        )
    feats_a = open_tile_features(_daemon_config(cache, config_a), store, FakeFdrClient())  # type: ignore[arg-type]
    assert feats_a is not None
    with pytest.raises(ValueError, match="precomputed tile features made by"):
        _xfeat(config_b, tile_features=feats_a)

    matcher_b, _ = _xfeat(config_b)
    rebuilt = build_tile_features(cache, matcher_b, progress=False)
    assert rebuilt.built
    assert rebuilt.manifest.tile_features["xfeat"].identity == matcher_b.extractor_identity.to_json()
    store = TileStore.open(cache)
    assert open_tile_features(_daemon_config(cache, config_b), store, FakeFdrClient()) is not None  # type: ignore[arg-type]
    assert not build_tile_features(cache, matcher_b, progress=False).built  # now up to date


def test_tampered_tile_features_refused_at_open_and_on_read(
    cache: Path, stand_in_models: dict[str, Path]
) -> None:
    """A changed byte in the descriptors: refused at open by the full check (the cache itself still
    opens); the light check (no sha256 of the descriptors) opens it and the tile's CRC-32 refuses it on
    read, once, and it is extracted live."""
    config = _matcher_config(stand_in_models["a"], stand_in_models["lightglue"])
    matcher, _ = _xfeat(config)
    build_tile_features(cache, matcher, progress=False)
    store = TileStore.open(cache)
    identity = matcher.extractor_identity
    table = np.load(cache / file_names("xfeat")[2])
    row = 10
    desc_path = cache / file_names("xfeat")[1]
    header = desc_path.stat().st_size - np.load(desc_path, mmap_mode="r").nbytes
    pos = header + int(table["offset"][row]) * 64 * 4 + 17
    data = bytearray(desc_path.read_bytes())
    data[pos] ^= 0x40
    desc_path.write_bytes(bytes(data))

    with pytest.raises(TileFeaturesRefused, match="sha256 mismatch"):
        PrecomputedTileFeatures.open(store, identity, Verification.FULL)
    fdr = FakeFdrClient()
    assert open_tile_features(_daemon_config(cache, config), TileStore.open(cache), fdr) is None  # type: ignore[arg-type]
    assert "sha256 mismatch" in str(fdr.of(FdrKind.TILE_FEATURES)[0]["reason"])

    feats = PrecomputedTileFeatures.open(store, identity, Verification.LIGHT)
    seen: list[dict[str, object]] = []
    feats.on_corrupt = seen.append
    bad = store.chip(store.tile_ids[row], CHIP_PX)
    good = store.chip(store.tile_ids[row + 1], CHIP_PX)
    assert feats.lookup(bad, bad.size_px) is None
    assert feats.lookup(bad, bad.size_px) is None
    assert feats.lookup(good, good.size_px) is not None
    assert len(seen) == 1 and seen[0]["tile_id"] == list(store.tile_ids[row])

    pre, rt = _xfeat(config, tile_features=feats)
    frame, rerank = _crop_frame(store, row, 48, 32)
    result = pre.match(frame, rerank, CameraCalibration.from_hfov(CHIP_PX, CHIP_PX, 60.0))
    assert result.best.tile_id == store.tile_ids[row]
    assert rt.extractor_calls == 2  # the query + the damaged tile, extracted live

    # A truncated file is refused by the light check too.
    desc_path.write_bytes(bytes(data[:-64]))
    with pytest.raises(TileFeaturesRefused, match="bytes"):
        PrecomputedTileFeatures.open(store, identity, Verification.LIGHT)


def test_old_manifest_without_tile_features_still_loads(cache: Path) -> None:
    """A manifest written before tile features existed (no key, and no hash of its content, which came
    later) loads with none."""
    import json

    path = cache / "manifest.json"
    payload = json.loads(path.read_text())
    payload.pop("tile_features", None)
    payload.pop("content_sha256", None)
    path.write_text(json.dumps(payload))
    assert CacheManifest.load(cache).tile_features == {}


def _cli(args: list[str], *, tty: bool) -> tuple[int, str, str]:
    """Run gdnav; stderr on a pseudo-terminal when ``tty`` (tqdm draws only on a terminal)."""
    cmd = [sys.executable, "-m", "gps_denied_onboard.cli", *args]
    if not tty:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
        return proc.returncode, proc.stdout, proc.stderr
    master, slave = pty.openpty()
    # A terminal 120 columns wide (a fresh pty reports 0, and tqdm then draws an empty line).
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
    proc2 = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=slave, text=True)
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 4096)
        except OSError:
            break
        if not data:
            break
        chunks.append(data)
    out, _ = proc2.communicate(timeout=120)
    os.close(master)
    return proc2.returncode, out, b"".join(chunks).decode("utf-8", "replace")


def test_cli_cache_features_progress_quiet_and_refusals(
    cache: Path, stand_in_models: dict[str, Path]
) -> None:
    """`gdnav cache features` draws a progress bar on a terminal and none with --quiet, says when the set
    is up to date, and refuses a damaged cache with exit 3 and one line."""
    sets = [
        "--set", "matcher.strategy=xfeat",
        "--set", f"matcher.xfeat_weights_path={stand_in_models['a']}",
        "--set", f"matcher.lightglue_weights_path={stand_in_models['lightglue']}",
        "--set", f"matcher.chip_size_px={CHIP_PX}",
        "--set", f"matcher.input_long_side_px={CHIP_PX}",
    ]  # fmt: skip
    base = ["cache", "features", "--config", str(REPO_ROOT / "config" / "sitl.yaml"), "--cache", str(cache)]
    code, out, err = _cli([*base, *sets], tty=True)
    assert code == 0, err
    assert "tile features xfeat" in err and "28/28" in err  # tqdm's bar
    assert "xfeat tile features built: 28 tiles" in out
    code, out, err = _cli([*base, *sets, "--force", "--quiet"], tty=True)
    assert code == 0, err
    assert "28/28" not in err and "xfeat tile features built" in out
    code, out, _ = _cli([*base, *sets, "--quiet"], tty=False)
    assert code == 0 and "up to date" in out

    mosaic = cache / CacheManifest.load(cache).mosaic_name
    raw = bytearray(mosaic.read_bytes())
    raw[-1] ^= 0xFF
    mosaic.write_bytes(bytes(raw))
    code, _, err = _cli([*base, *sets, "--quiet"], tty=False)
    assert code == 3
    assert "does not verify" in err and "Traceback" not in err
    code, _, err = _cli([*base, *sets[2:], "--set", "matcher.strategy=classical"], tty=False)
    assert code == 2 and "no precomputable tile features" in err


# --- slow: the real XFeat + LighterGlue on a real cross-date frame -----------------------------------------
@pytest.mark.slow
@pytest.mark.realdata
@pytest.mark.timeout(900)
def test_real_xfeat_precomputed_equals_live_on_a_2020_frame(
    registry_models: Callable[[str], Path],  # noqa: F811
    tmp_path: Path,
) -> None:
    """Real XFeat + LighterGlue, 2009 map cache, a rotated 2020 frame: the result with precomputed tile
    features is exactly the live one, and the extractor ran once (the query) instead of 1 + N."""
    from gps_denied_onboard.helpers.model_manifest import verify_model_dir
    from gps_denied_onboard.models.learned_export import family_models

    model_dir = registry_models("xfeat")
    extractor, lighterglue = family_models(verify_model_dir(model_dir), "xfeat")  # type: ignore[misc]
    cache = tmp_path / "c2009"
    build_cache(shared_path(*NAIP, NAIP_2009), cache, progress=False)
    frames = tmp_path / "c2020"
    build_cache(shared_path(*NAIP, NAIP_2020), frames, progress=False, zoom=CacheManifest.load(cache).zoom)
    config = MatcherConfig(
        strategy="xfeat",
        xfeat_weights_path=str(model_dir / extractor.file),
        lightglue_weights_path=str(model_dir / lighterglue.file),
        min_inliers_threshold=25,
    )
    live, live_rt = _xfeat(config)
    t0 = time.perf_counter()
    build_tile_features(cache, live, progress=False)
    build_s = time.perf_counter() - t0
    store = TileStore.open(cache)
    feats = open_tile_features(_daemon_config(cache, config), store, FakeFdrClient())  # type: ignore[arg-type]
    assert feats is not None
    pre, pre_rt = _xfeat(config, tile_features=feats)

    src = TileStore.open(frames)
    assert src.manifest.tile_range == store.manifest.tile_range
    frame, rerank, calib, _h = rotated_frame_over_tile(store, src, config.chip_size_px)
    tile = store.tile_ids[10]
    t0 = time.perf_counter()
    result_pre = pre.match(frame, rerank, calib)
    pre_ms = (time.perf_counter() - t0) * 1e3
    t0 = time.perf_counter()
    result_live = live.match(frame, rerank, calib)
    live_ms = (time.perf_counter() - t0) * 1e3
    print(
        f"xfeat NAIP 2020 -> 2009 cache: {result_pre.best.inlier_count} inliers; frame {pre_ms:.0f} ms with "
        f"precomputed tile features vs {live_ms:.0f} ms live; {len(store)} tiles built in {build_s:.1f} s"
    )
    assert result_pre.best.tile_id == tile and result_pre.best.inlier_count >= 25
    _same_result(result_pre, result_live)
    assert pre_rt.extractor_calls == 1
    assert live_rt.extractor_calls == len(store) + 1 + len(rerank.candidates)  # build + query + N


def test_composition_root_wires_the_verified_set_into_the_matcher(
    cache: Path, stand_in_models: dict[str, Path]
) -> None:
    """The matcher the composition root builds (here for a replay) holds the cache's set when it was
    made by its extractor, and none (live extraction) when the set is of another model."""
    from gps_denied_onboard.runtime_root.compose import compose_replay

    config_a = _matcher_config(stand_in_models["a"], stand_in_models["lightglue"])
    build_tile_features(cache, _xfeat(config_a)[0], progress=False)
    for matcher_config, expect_used in (
        (config_a, True),
        (dataclasses.replace(config_a, max_keypoints=64), False),
    ):
        fdr = FakeFdrClient()
        root = compose_replay(
            _daemon_config(cache, matcher_config),
            fdr=fdr,  # type: ignore[arg-type]
            clock_unix_usec=lambda: 0,
        )
        matcher = root.pipeline.ladder.rungs[0].matcher  # type: ignore[union-attr]
        assert (matcher.tile_features is not None) is expect_used
        assert fdr.of(FdrKind.TILE_FEATURES)[0]["used"] is expect_used


def rotated_frame_over_tile(
    store: TileStore, src: TileStore, chip_size_px: int, index: int = 10
) -> tuple[NavCameraFrame, RerankResult, CameraCalibration, np.ndarray]:
    """A frame of ``src``'s imagery (another date on the same Web-Mercator grid), rotated 8 deg and scaled
    1.05, centred on tile ``index``'s chip of ``store``; the three nearest tiles as candidates; its
    calibration; and the frame -> mosaic homography (3, 3)."""
    tile = store.tile_ids[index]
    chip = store.chip(tile, chip_size_px)
    cx = chip.origin_px[0] - store.manifest.tile_range.x0 * store.tile_size_px + 256.0
    cy = chip.origin_px[1] - store.manifest.tile_range.y0 * store.tile_size_px + 256.0
    fw, fh, theta, s = 480, 360, math.radians(8.0), 1.05
    c, si = math.cos(theta), math.sin(theta)
    frame_to_mosaic = (
        np.array([[1, 0, cx], [0, 1, cy], [0, 0, 1]])
        @ np.array([[s * c, -s * si, 0], [s * si, s * c, 0], [0, 0, 1]])
        @ np.array([[1, 0, -fw / 2], [0, 1, -fh / 2], [0, 0, 1]])
    )
    image = cv2.warpPerspective(
        np.asarray(src.mosaic), frame_to_mosaic, (fw, fh), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    )
    frame = NavCameraFrame(uuid.uuid4(), 0, 0, image, None, None, time.monotonic_ns())
    near = [t for t, _ in store.tiles_near(tile.lat_deg, tile.lon_deg, 1e5, k=3)]
    rerank = RerankResult(
        frame.frame_id, [RerankCandidate(t, store.chip(t, chip_size_px), -1, 0.0) for t in near], 0
    )
    return frame, rerank, CameraCalibration.from_hfov(fw, fh, 70.0), frame_to_mosaic
