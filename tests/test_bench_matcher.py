"""``gdnav bench matcher`` on the real GeoVision ortho: result structure and inliers (no latency checks)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_path
from gps_denied_onboard.bench.matcher import (
    BenchmarkError,
    RasterChip,
    format_report,
    resolve_model_paths,
    run_matcher_benchmark,
)
from gps_denied_onboard.cli_bench import BENCH_COMMANDS, BenchCommand, register
from gps_denied_onboard.components.c6_tiles.types import TilePixelsHandle

pytestmark = pytest.mark.realdata

LATENCY_KEYS = ("frame_cold_ms", "frame_warm_ms", "candidate_cold_ms", "candidate_warm_ms", "query_ms")


@pytest.fixture(scope="module")
def geovision() -> Path:
    return shared_path("data", "geovision_india", "geovision_india_z18.tif")


@pytest.fixture(scope="module")
def classical_report(geovision: Path) -> dict:
    return run_matcher_benchmark(strategies=["classical"], map_path=geovision, n_frames=3, echo=None)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gdnav")
    register(parser.add_subparsers(dest="command", required=True))
    return parser


def test_bench_matcher_classical_result_structure(classical_report: dict) -> None:
    """Classical on 3 frames: every latency block has p50/p95 over the right sample counts."""
    r = classical_report["strategies"]["classical"]
    for key in LATENCY_KEYS:
        assert set(r[key]) >= {"p50", "p95", "mean", "n"}
        assert 0 < r[key]["p50"] <= r[key]["p95"]
    assert r["frame_cold_ms"]["n"] == 3 and r["frame_warm_ms"]["n"] == 3
    assert r["frame_cold_cpu_ms"]["p50"] > 0
    assert r["candidate_cold_ms"]["n"] == 9  # 3 frames x N=3
    assert r["ratio_to_classical"]["frame_cold_ms"] == {"p50": 1.0, "p95": 1.0}
    assert r["memory"]["python_heap_peak_cold_frame_mb"] > 0
    assert classical_report["memory"]["peak_rss_process_mb"] > 0
    assert classical_report["skipped"] == {}
    assert classical_report["setup"]["frame_size"] == [640, 480]
    assert classical_report["machine"]["cpu_count"] >= 1
    assert "met" in classical_report["targets"]["cpu_classical_frame_p95_le_250ms"]
    json.dumps(classical_report)  # JSON-serialisable as the CLI writes it


def test_bench_matcher_classical_finds_the_true_chip(classical_report: dict) -> None:
    """Same-source imagery: the true chip gets many inliers, the wrong ones few, and it ranks first."""
    inl = classical_report["strategies"]["classical"]["inliers"]
    assert inl["true_chip"]["p50"] > 0
    assert inl["true_chip"]["p50"] > 4 * max(inl["wrong_chip_max"]["p50"], 1)
    assert inl["true_chip_ranked_first"] >= 2 / 3
    assert inl["best"]["p50"] >= 80  # C3-IT-01 floor
    sol = classical_report["strategies"]["classical"]["solutions"]
    assert sol["frames"] == 3 and sol["solved"] == 3 and sol["wrong"] == 0
    assert sol["centre_error_m"]["p95"] < sol["wrong_beyond_m"] == pytest.approx(2.85, abs=0.2)
    per_frame = classical_report["strategies"]["classical"]["per_frame"]
    assert len(per_frame["true_chip_inliers"]) == len(per_frame["best_is_true_chip"]) == 3
    assert max(e for e in per_frame["centre_error_m"] if e is not None) <= sol["centre_error_max_m"]
    assert sum(e is not None for e in per_frame["centre_error_m"]) == sol["solved"]


def test_bench_matcher_table_lists_strategy_and_target(classical_report: dict) -> None:
    """The printed table names the strategy, the machine and the CPU target verdict."""
    text = format_report(classical_report)
    assert "classical" in text and classical_report["machine"]["cpu_model"] in text
    assert "target classical frame p95 <= 250 ms" in text


def test_bench_matcher_cross_date_pairs_render_the_frames_from_the_other_date() -> None:
    """--frames-from: the frames come from another date of the same ground and the chips from the map, so
    the same poses find fewer inliers across five years than on the map's own date."""
    naip = shared_path("data", "naip_timeseries", "naip")
    map_2009 = naip / "m_4709963_se_14_1_20090818.tif"
    kwargs = dict(strategies=["classical"], map_path=map_2009, n_frames=4, chip_size_px=320, alt_agl_m=1200.0)
    same = run_matcher_benchmark(**kwargs, echo=None)  # type: ignore[arg-type]
    across = run_matcher_benchmark(
        **kwargs,  # type: ignore[arg-type]
        frames_path=naip / "m_4709963_se_14_1_20200831.tif",
        echo=None,
    )
    assert across["setup"]["frames_from"].endswith("20200831.tif")
    assert same["setup"]["frames_from"] == same["setup"]["map"]
    inl_same = same["strategies"]["classical"]["inliers"]["true_chip"]["p50"]
    inl_across = across["strategies"]["classical"]["inliers"]["true_chip"]["p50"]
    assert inl_same >= 25 and inl_across < inl_same / 2
    sol = same["strategies"]["classical"]["solutions"]
    assert sol["solved"] >= 3 and sol["wrong"] == 0 and sol["centre_error_m"]["p95"] < 5.0
    text = format_report(across)
    assert "from m_4709963_se_14_1_20200831.tif" in text and "from m_4709963_se_14_1_20090818.tif" in text
    assert "classical: solved" in text


def test_bench_matcher_frames_from_other_ground_raises(geovision: Path) -> None:
    """Frames from an image of other ground: refused, naming both files, before anything runs."""
    naip_2020 = shared_path("data", "naip_timeseries", "naip", "m_4709963_se_14_1_20200831.tif")
    with pytest.raises(BenchmarkError, match="too little common ground") as info:
        run_matcher_benchmark(strategies=["classical"], map_path=geovision, frames_path=naip_2020, echo=None)
    assert "geovision_india_z18.tif" in str(info.value) and "20200831.tif" in str(info.value)


def test_bench_matcher_learned_strategy_with_self_built_models(geovision: Path, tmp_path: Path) -> None:
    """disk_lightglue with self-built ONNX models runs beside classical and gets a ratio to it."""
    pytest.importorskip("onnx")
    from onnx_builders import build_fake_extractor, build_fake_lightglue

    disk = build_fake_extractor(tmp_path / "disk.onnx", dim=128, num_keypoints=256)
    lightglue = build_fake_lightglue(tmp_path / "lightglue.onnx", dim=128, min_similarity=0.9)
    report = run_matcher_benchmark(
        map_path=geovision,
        model_paths={"disk": disk, "lightglue": lightglue},
        n_frames=1,
        intra_op_threads=1,
        echo=None,
    )
    assert list(report["strategies"]) == ["classical", "disk_lightglue"]
    learned = report["strategies"]["disk_lightglue"]
    assert learned["lightglue_mode"] == "lightglue"
    assert learned["candidate_cold_ms"]["n"] == 3
    assert learned["ratio_to_classical"]["frame_cold_ms"]["p95"] > 0


def test_bench_matcher_times_precomputed_tile_features_from_a_cache(geovision: Path, tmp_path: Path) -> None:
    """--cache: candidates are the cache's chips, and a strategy whose precomputed tile features the cache
    holds is timed with them beside the cold frame, with the same best inliers as live extraction."""
    pytest.importorskip("onnx")
    from gps_denied_onboard.components.c3_matcher.health import RollingHealthWindow
    from gps_denied_onboard.components.c3_matcher.registry import create_matcher
    from gps_denied_onboard.components.c7_inference.onnx_runtime import OnnxInferenceRuntime
    from gps_denied_onboard.components.c10_cache_build import build_cache
    from gps_denied_onboard.components.c10_cache_build.tile_features import build_tile_features
    from gps_denied_onboard.config import MatcherConfig
    from gps_denied_onboard.helpers.lightglue_runtime import LightGlueRuntime
    from gps_denied_onboard.helpers.ransac_filter import RansacFilter
    from onnx_builders import build_fake_extractor, build_fake_lightglue

    xfeat = build_fake_extractor(
        tmp_path / "xfeat.onnx", channels=1, dim=64, num_keypoints=256, keypoint_dtype="float32"
    )
    lightglue = build_fake_lightglue(tmp_path / "lighterglue.onnx", dim=64, min_similarity=0.9)
    cache = tmp_path / "cache"
    build_cache(geovision, cache, progress=False)
    runtime = OnnxInferenceRuntime(intra_op_threads=1, providers=["CPUExecutionProvider"])
    config = MatcherConfig(
        strategy="xfeat",
        xfeat_weights_path=str(xfeat),
        lightglue_weights_path=str(lightglue),
        chip_size_px=256,
    )
    matcher = create_matcher(
        "xfeat",
        config=config,
        inference_runtime=runtime,
        lightglue_runtime=LightGlueRuntime(runtime, str(lightglue), descriptor_dim=64),
        ransac_filter=RansacFilter(),
        health_window=RollingHealthWindow(25),
    )
    build_tile_features(cache, matcher, progress=False)  # type: ignore[arg-type]
    report = run_matcher_benchmark(
        map_path=geovision,
        model_paths={"xfeat": xfeat, "lightglue": lightglue},
        n_frames=2,
        chip_size_px=256,
        intra_op_threads=1,
        cache_dir=cache,
        echo=None,
    )
    learned = report["strategies"]["xfeat"]
    assert learned["frame_precomputed_ms"]["n"] == 2 and learned["frame_cold_ms"]["n"] == 2
    assert learned["precomputed_same_best_inliers"] == 1.0
    assert report["strategies"]["classical"]["frame_precomputed_ms"] == {}
    assert report["tile_features"]["xfeat"]["tiles"] == 136
    assert "frame pre" in format_report(report)


def test_bench_matcher_missing_model_file_is_skipped_with_reason(geovision: Path, tmp_path: Path) -> None:
    """A model path that does not exist: classical still runs, the strategy is skipped with the path."""
    missing = tmp_path / "nope.onnx"
    report = run_matcher_benchmark(
        strategies=["disk_lightglue", "no_such_strategy"],
        map_path=geovision,
        model_paths={"disk": missing},
        n_frames=1,
        echo=None,
    )
    assert list(report["strategies"]) == ["classical"]
    assert str(missing) in report["skipped"]["disk_lightglue"]
    assert "not registered" in report["skipped"]["no_such_strategy"]


def test_bench_matcher_cli_writes_json(
    geovision: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """``bench matcher --frames 1 --json OUT`` prints the table, writes the figures, exits 0."""
    out = tmp_path / "bench" / "matcher.json"
    args = _parser().parse_args(
        ["bench", "matcher", "--frames", "1", "--map", str(geovision), "--json", str(out)]
    )
    assert args.func(args) == 0
    assert "classical" in capsys.readouterr().out
    assert json.loads(out.read_text())["strategies"]["classical"]["frame_cold_ms"]["n"] == 1


def test_bench_matcher_cli_missing_model_exits_3(geovision: Path, tmp_path: Path) -> None:
    """An explicitly given model that cannot be loaded makes the command exit 3 (resource refused)."""
    args = _parser().parse_args(
        [
            "bench",
            "matcher",
            "--frames",
            "1",
            "--map",
            str(geovision),
            "--xfeat-model",
            str(tmp_path / "x.onnx"),
        ]
    )
    assert args.func(args) == 3


def test_bench_matcher_unusable_map_raises(tmp_path: Path) -> None:
    """A map file that does not exist is a BenchmarkError naming it."""
    with pytest.raises(BenchmarkError, match=r"nope\.tif"):
        run_matcher_benchmark(map_path=tmp_path / "nope.tif", n_frames=1, echo=None)


def test_bench_register_takes_a_list_of_subcommands() -> None:
    """``register`` adds every given BenchCommand; duplicates are refused."""
    ran: list[str] = []

    def add_arguments(p: argparse.ArgumentParser) -> None:
        p.add_argument("--x", type=int)

    def run(args: argparse.Namespace) -> int:
        ran.append("extra")
        return 0

    extra = BenchCommand("extra", "h", "d", add_arguments, run)
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="command"), [*BENCH_COMMANDS, extra])
    args = parser.parse_args(["bench", "extra", "--x", "2"])
    assert args.func(args) == 0 and ran == ["extra"] and args.x == 2
    with pytest.raises(ValueError, match="duplicate"):
        register(argparse.ArgumentParser().add_subparsers(), [extra, extra])


def test_bench_raster_chip_is_a_tile_handle_and_round_trips() -> None:
    """RasterChip satisfies TilePixelsHandle; lon/lat <-> chip px round-trips; pixels are read-only."""
    raster = np.zeros((100, 120, 3), dtype=np.uint8)
    affine = np.array([[1e-5, 0.0, 78.0], [0.0, -1e-5, 17.0], [0.0, 0.0, 1.0]])
    chip = RasterChip(raster, 10, 20, 64, 0.3, affine)
    assert isinstance(chip, TilePixelsHandle)
    assert chip.pixels().shape == (64, 64, 3) and not chip.pixels().flags.writeable
    px = np.array([[0.0, 0.0], [63.0, 10.5]])
    lon, lat = chip.chip_px_to_lonlat(px)
    np.testing.assert_allclose(chip.lonlat_to_chip_px(lon, lat), px, atol=1e-6)
    with pytest.raises(BenchmarkError):
        RasterChip(raster, 100, 0, 64, 0.3, affine)


def test_bench_resolve_model_paths_from_dir(tmp_path: Path) -> None:
    """Explicit paths win; the rest come from ``{key}*.onnx`` in the model dir; unknown keys are refused."""
    for name in ("aliked-t16.onnx", "disk_lightglue.onnx", "lightglue_disk.onnx", "xfeat.onnx"):
        (tmp_path / name).write_bytes(b"")
    got = resolve_model_paths({"xfeat": "/elsewhere/x.onnx"}, tmp_path)
    assert got == {
        "xfeat": Path("/elsewhere/x.onnx"),
        "aliked": tmp_path / "aliked-t16.onnx",
        "lightglue": tmp_path / "lightglue_disk.onnx",
    }
    with pytest.raises(BenchmarkError, match="unknown model key"):
        resolve_model_paths({"superpoint": "a.onnx"}, None)


def test_bench_resolve_model_paths_pairs_each_extractor_with_its_lightglue(tmp_path: Path) -> None:
    """A directory from ``gdnav models export`` gives each learned strategy its own LightGlue."""
    from gps_denied_onboard.helpers.model_manifest import ModelEntry, ModelSource, write_manifest
    from gps_denied_onboard.models.learned_export import family_spec

    for family in ("disk", "xfeat"):
        spec = family_spec(family)
        for role, file, sig in (
            ("extractor", spec.extractor_file, spec.extractor_signature),
            ("matcher", spec.matcher_file, spec.matcher_signature),
        ):
            (tmp_path / file).write_bytes(b"x")
            source = ModelSource(name=f"{family}-{role}", sha256="0" * 64, licence="Apache-2.0", url="u")
            write_manifest(
                tmp_path, ModelEntry(file, "0" * 64, source, sig, {"family": family, "role": role})
            )
    got = resolve_model_paths(None, tmp_path)
    assert got["disk"] == tmp_path / family_spec("disk").extractor_file
    assert got["disk_lightglue"] == tmp_path / "disk_lightglue.onnx"
    assert got["xfeat_lightglue"] == tmp_path / "xfeat_lighterglue.onnx"
    assert "aliked" not in got and "aliked_lightglue" not in got


def test_bench_matcher_footprint_first_chip_is_cut_around_the_frame(geovision: Path, tmp_path: Path) -> None:
    """--first-chip footprint: the true chip is centred within the prior error the daemon allows of the
    frame's centre (the nearest tile's is not, in general), and the wrong chips are the same as with the
    nearest tile's, so the two runs differ only in the true chip."""
    from gps_denied_onboard.bench.matcher import render_bench_frames, with_cache_candidates
    from gps_denied_onboard.camera.types import CameraCalibration
    from gps_denied_onboard.components.c2_5_rerank.footprint import FOOTPRINT_CHIP_MAX_OFFSET_FRAC
    from gps_denied_onboard.components.c6_tiles.store import TileStore
    from gps_denied_onboard.components.c10_cache_build import build_cache
    from gps_denied_onboard.geo import haversine_m

    cache = tmp_path / "cache"
    build_cache(geovision, cache, progress=False)
    store = TileStore.open(cache)
    calib = CameraCalibration.from_hfov(640, 480, 70.0)
    frames = render_bench_frames(
        geovision, calib, n_frames=6, n_candidates=1, chip_size_px=256, alt_agl_m=120.0, seed=3
    )
    kwargs = dict(n_candidates=3, chip_size_px=256, seed=3)
    nearest = with_cache_candidates(frames, store, **kwargs)  # type: ignore[arg-type]
    around = with_cache_candidates(frames, store, **kwargs, first_chip="footprint")  # type: ignore[arg-type]
    allowed_m = FOOTPRINT_CHIP_MAX_OFFSET_FRAC * 256 * store.gsd_m_px * np.sqrt(2.0) + 2 * store.gsd_m_px
    offsets_m = {"nearest": [], "footprint": []}
    for bf, n, a in zip(frames, nearest, around, strict=True):
        lon, lat = bf.centre_lonlat
        assert [c.origin_px for c in n.candidates[1:]] == [c.origin_px for c in a.candidates[1:]]  # type: ignore[attr-defined]
        for name, chip in (("nearest", n.candidates[0]), ("footprint", a.candidates[0])):
            c_lon, c_lat = chip.chip_px_to_lonlat(np.array([127.5, 127.5]))
            offsets_m[name].append(haversine_m(lat, lon, float(c_lat), float(c_lon)))
    assert max(offsets_m["footprint"]) <= allowed_m
    assert max(offsets_m["nearest"]) > allowed_m
    with pytest.raises(BenchmarkError, match="first_chip must be one of nearest_tile, footprint"):
        with_cache_candidates(frames, store, **kwargs, first_chip="centre")  # type: ignore[arg-type]
    with pytest.raises(BenchmarkError, match="needs a map cache"):
        run_matcher_benchmark(map_path=geovision, n_frames=1, first_chip="footprint", echo=None)
