"""C10 cache build in shards (``c10_cache_build/shards.py``): the same bytes on a local Dask cluster of two
workers as in one process, a resumed build, a worker lost mid-shard, and the dry run. Real GeoTIFFs, real
reprojection, a real ``distributed.LocalCluster``."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from gps_denied_onboard import cli
from gps_denied_onboard.components.c10_cache_build import (
    CacheManifest,
    CacheManifestError,
    geotiff,
    map_fields,
)
from gps_denied_onboard.components.c10_cache_build.geotiff import WarpJob, build_cache_from_geotiff
from gps_denied_onboard.components.c10_cache_build.manifest import Verification
from gps_denied_onboard.components.c10_cache_build.shards import (
    JOURNAL_DIR_NAME,
    EngineSpec,
    Shard,
    ShardJournal,
    ShardOutput,
)

#: A fixed creation stamp (2026-01-01), so that whole caches compare byte for byte.
EPOCH_S = "1767225600"
#: Four 256 px tiles a shard: the small test map is cut in about a dozen shards.
SHARD_PX = 4 * 256 * 256
#: Where ``_dying_warp`` leaves its mark (it runs in a Dask worker: the path comes in the environment).
DEATH_MARK_ENV = "GDNAV_TEST_DEATH_MARK"
#: The real worker function, taken before any test replaces it.
REAL_WARP = geotiff.warp_shard


def _source(path: Path, *, width_px: int = 1200, height_px: int = 900) -> Path:
    """A textured 3-band UTM 33N GeoTIFF at 1 m/px near Vienna: fields, roads, noise, a nodata corner."""
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[0:height_px, 0:width_px]
    base = 100 + 40 * np.sin(xx / 37.0) * np.cos(yy / 23.0) + rng.normal(0, 12, (height_px, width_px))
    base[(xx + 2 * yy) % 151 < 6] = 220
    data = np.clip(np.stack([base, base * 0.9 + 10, base * 0.8 + 20]), 1, 255).astype(np.uint8)
    data[:, : height_px // 5, : width_px // 5] = 0
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=width_px,
        height=height_px,
        count=3,
        dtype="uint8",
        crs="EPSG:32633",
        transform=from_origin(600_000.0, 5_340_000.0, 1.0, 1.0),
        nodata=0,
    ) as dst:
        dst.write(data)
    return path


def _files(cache_dir: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(cache_dir.iterdir()) if p.is_file()}


def _assert_same_cache(a: Path, b: Path) -> None:
    fa, fb = _files(a), _files(b)
    assert sorted(fa) == sorted(fb)
    for name in fa:
        assert fa[name] == fb[name], f"{name} differs"


@dataclass
class _RunSpy:
    """What ``run_shards`` was asked and did, and the engines the fields' bands ran on, seen from the
    build."""

    calls: list[dict[str, Any]]
    field_engines: list[tuple[str, int]]


@pytest.fixture
def run_spy(monkeypatch: pytest.MonkeyPatch) -> _RunSpy:
    spy = _RunSpy(calls=[], field_engines=[])
    real = geotiff.run_shards
    real_ordered = map_fields.run_ordered

    def spying_ordered(engine, work, items):  # type: ignore[no-untyped-def]
        spy.field_engines.append((engine.name, engine.workers))
        return real_ordered(engine, work, items)

    monkeypatch.setattr(map_fields, "run_ordered", spying_ordered)

    def spying(journal, shards, work, engine, **kwargs):  # type: ignore[no-untyped-def]
        run = real(journal, shards, work, engine, **kwargs)
        spy.calls.append(
            {"engine": engine.name, "workers": engine.workers, "shards": len(shards), "ran": run.ran}
        )
        return run

    monkeypatch.setattr(geotiff, "run_shards", spying)
    return spy


@pytest.fixture
def small_shards(monkeypatch: pytest.MonkeyPatch) -> None:
    """Shards of four tiles, and a fixed creation stamp."""
    monkeypatch.setattr(geotiff, "_BLOCK_TARGET_PX", SHARD_PX)
    monkeypatch.setenv("SOURCE_DATE_EPOCH", EPOCH_S)


def test_cache_build_two_dask_workers_is_byte_identical_to_one_process(
    tmp_path: Path, small_shards: None, run_spy: _RunSpy
) -> None:
    """``gdnav cache build --workers 2`` (a local Dask cluster: the mosaic's shards and the fields' bands)
    writes the same files, byte for byte and the manifest included, as the default single-process build."""
    src = _source(tmp_path / "src.tif")
    one, two = tmp_path / "one", tmp_path / "two"
    assert cli.main(["cache", "build", "--source", str(src), "--out", str(one), "--quiet"]) == 0
    assert (
        cli.main(["cache", "build", "--source", str(src), "--out", str(two), "--quiet", "--workers", "2"])
        == 0
    )
    assert [(c["engine"], c["workers"]) for c in run_spy.calls] == [("serial", 1), ("dask", 2)]
    assert run_spy.field_engines == [("serial", 1), ("dask", 2)]
    assert run_spy.calls[0]["shards"] >= 8 and run_spy.calls[1]["ran"] == run_spy.calls[1]["shards"]
    _assert_same_cache(one, two)
    manifest = CacheManifest.load(two)
    assert manifest.map_fields is not None and manifest.created_utc == "2026-01-01T00:00:00Z"
    manifest.verify_artifacts(two, Verification.FULL)
    assert not (two / JOURNAL_DIR_NAME).exists()


class _Killed(BaseException):
    """Stands for a SIGKILL between a shard's pixels and its record."""


def test_cache_build_interrupted_resumes_without_redoing_finished_shards(
    tmp_path: Path, small_shards: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A build killed after its fourth shard's pixels were written but before it was recorded is not a
    cache; run again, it redoes that shard and the ones never started, none of the three recorded, and
    ends byte-identical to an uninterrupted build."""
    src = _source(tmp_path / "src.tif")
    clean, out = tmp_path / "clean", tmp_path / "resumed"
    build_cache_from_geotiff(src, clean, progress=False)

    real_record = ShardJournal.record
    recorded: list[int] = []

    def record_then_die(self: ShardJournal, index: int, fractions: np.ndarray) -> None:
        if len(recorded) == 3:
            raise _Killed
        real_record(self, index, fractions)
        recorded.append(index)

    monkeypatch.setattr(ShardJournal, "record", record_then_die)
    with pytest.raises(_Killed):
        build_cache_from_geotiff(src, out, progress=False)
    monkeypatch.setattr(ShardJournal, "record", real_record)
    with pytest.raises(CacheManifestError):
        CacheManifest.load(out)
    assert len(list((out / JOURNAL_DIR_NAME).glob("shard_*.npy"))) == 3

    warped: list[int] = []

    def counting_warp(job: WarpJob, shard: Shard) -> ShardOutput:
        warped.append(shard.index)
        return REAL_WARP(job, shard)

    monkeypatch.setattr(geotiff, "warp_shard", counting_warp)
    build_cache_from_geotiff(src, out, progress=False)
    n_shards = len(geotiff._blocks(CacheManifest.load(clean).tile_range, 256))
    assert sorted(warped) == sorted(set(range(n_shards)) - set(recorded))
    assert recorded[-1] + 1 in warped  # the shard killed between its pixels and its record
    _assert_same_cache(clean, out)
    assert not (out / JOURNAL_DIR_NAME).exists()


def test_cache_build_other_parameters_do_not_resume_a_journal(
    tmp_path: Path, small_shards: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A journal left by a build of another zoom is discarded, not mixed into this one."""
    src = _source(tmp_path / "src.tif")
    out = tmp_path / "cache"

    def die(self: ShardJournal, index: int, fractions: np.ndarray) -> None:
        raise _Killed

    real_record = ShardJournal.record
    monkeypatch.setattr(ShardJournal, "record", die)
    with pytest.raises(_Killed):
        build_cache_from_geotiff(src, out, zoom=16, progress=False)
    monkeypatch.setattr(ShardJournal, "record", real_record)
    build_cache_from_geotiff(src, out, zoom=17, progress=False)
    build_cache_from_geotiff(src, tmp_path / "clean", zoom=17, progress=False)
    _assert_same_cache(tmp_path / "clean", out)


def _dying_warp(job: WarpJob, shard: Shard) -> ShardOutput:
    """The real warp, except that the first worker to reach shard 2 dies in it (once per mark)."""
    mark = Path(os.environ[DEATH_MARK_ENV])
    if shard.index == 2 and not mark.exists():
        mark.touch()
        os._exit(1)
    return REAL_WARP(job, shard)


@pytest.mark.slow
def test_cache_build_worker_lost_mid_shard_is_redone_elsewhere(
    tmp_path: Path, small_shards: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A Dask worker that dies inside a shard leaves nothing torn: the shard runs again and the cache is
    the same bytes as a single-process build."""
    src = _source(tmp_path / "src.tif")
    build_cache_from_geotiff(src, tmp_path / "one", progress=False)
    mark = tmp_path / "worker_died"
    monkeypatch.setenv(DEATH_MARK_ENV, str(mark))
    # The build hands the workers partial(_dying_warp, job): they import it from this module.
    monkeypatch.setattr(geotiff, "warp_shard", _dying_warp)
    build_cache_from_geotiff(src, tmp_path / "two", progress=False, engine=EngineSpec(workers=2))
    assert mark.exists(), "no worker died: the test did not test anything"
    _assert_same_cache(tmp_path / "one", tmp_path / "two")


def test_cache_build_dry_run_states_exact_sizes_and_builds_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--dry-run`` prints the tile count and each artifact's size (the .npy sizes exact, as a real build
    then writes them) and a time per stage, and writes nothing."""
    src = _source(tmp_path / "src.tif")
    out = tmp_path / "cache"
    assert cli.main(["cache", "build", "--source", str(src), "--out", str(out), "--dry-run"]) == 0
    printed = capsys.readouterr().out
    assert not out.exists()
    assert cli.main(["cache", "build", "--source", str(src), "--out", str(out), "--quiet"]) == 0
    capsys.readouterr()
    manifest = CacheManifest.load(out)
    tr = manifest.tile_range
    assert f"{tr.n_cols} x {tr.n_rows} = {tr.n_rows * tr.n_cols} tiles" in printed
    from gps_denied_onboard.components.c10_cache_build.dry_run import estimate_geotiff_build

    estimate = estimate_geotiff_build(src)
    for name, size in estimate.artifacts.items():
        if name.endswith(".npy"):
            assert size == (out / name).stat().st_size, name
    assert estimate.artifacts["tiles.json"] >= (out / "tiles.json").stat().st_size
    stages = {s.name for s in estimate.stages}
    assert {"mosaic (read, warp, write)", "orientation fields", "calibration"} <= stages
    assert all(s.seconds >= 0 for s in estimate.stages)
    for stage in estimate.stages:
        assert stage.name in printed


def test_cache_build_rejects_zero_workers(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--workers 0`` is a usage error (exit 2) naming the value."""
    src = _source(tmp_path / "src.tif", width_px=300, height_px=300)
    code = cli.main(["cache", "build", "--source", str(src), "--out", str(tmp_path / "c"), "--workers", "0"])
    assert code == 2
    assert "workers 0" in capsys.readouterr().err


def test_the_daemon_and_the_default_build_never_import_dask() -> None:
    """Dask is the build's cluster engine only: the daemon's modules, the CLI and the single-process build
    path import neither ``dask`` nor ``distributed``."""
    code = (
        "import sys\n"
        "import gps_denied_onboard.cli, gps_denied_onboard.runtime_root, gps_denied_onboard.daemon.service\n"
        "import gps_denied_onboard.components.c10_cache_build.geotiff\n"
        "import gps_denied_onboard.components.c10_cache_build.dry_run\n"
        "from gps_denied_onboard.components.c10_cache_build.shards import EngineSpec, open_engine\n"
        "with open_engine(EngineSpec()) as engine: pass\n"
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'dask', 'distributed'}))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    assert out.stdout.strip() == "[]", out.stdout


@pytest.mark.slow
def test_cache_build_killed_process_resumes_byte_identical(tmp_path: Path) -> None:
    """A real ``gdnav cache build`` killed with SIGKILL once two shards are recorded, run again with the
    same arguments, says it resumed, and ends byte-identical to a build never killed."""
    src = _source(tmp_path / "src.tif", width_px=4000, height_px=3000)
    out, clean = tmp_path / "killed", tmp_path / "clean"
    env = {**os.environ, "SOURCE_DATE_EPOCH": EPOCH_S}

    def build(dest: Path) -> list[str]:
        return [sys.executable, "-m", "gps_denied_onboard.cli", "cache", "build", "--source", str(src),
                "--out", str(dest), "--quiet", "--no-fields"]  # fmt: skip

    proc = subprocess.Popen(build(out), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    journal = out / JOURNAL_DIR_NAME
    try:
        deadline = time.monotonic() + 120
        while len(list(journal.glob("shard_*.npy"))) < 2:
            assert proc.poll() is None, "the build ended before it could be killed: make the source larger"
            assert time.monotonic() < deadline
            time.sleep(0.02)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    assert not (out / "manifest.json").exists()
    recorded = len(list(journal.glob("shard_*.npy")))
    again = subprocess.run(build(out), env=env, capture_output=True, text=True, timeout=300, check=True)
    assert f"shards_done={recorded}" in again.stdout + again.stderr
    subprocess.run(build(clean), env=env, capture_output=True, timeout=300, check=True)
    _assert_same_cache(clean, out)


@pytest.mark.slow
def test_cache_build_on_a_running_cluster_address_is_byte_identical(
    tmp_path: Path, small_shards: None, run_spy: _RunSpy
) -> None:
    """``--address`` builds on a Dask scheduler already running (a local one here), with the same bytes
    as the default build."""
    from distributed import LocalCluster

    src = _source(tmp_path / "src.tif")
    one, remote = tmp_path / "one", tmp_path / "remote"
    base = ["cache", "build", "--source", str(src), "--quiet", "--no-fields"]
    assert cli.main([*base, "--out", str(one)]) == 0
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        assert cli.main([*base, "--out", str(remote), "--address", cluster.scheduler_address]) == 0
    assert [(c["engine"], c["workers"]) for c in run_spy.calls] == [("serial", 1), ("dask", 1)]
    _assert_same_cache(one, remote)


@pytest.mark.slow
def test_vlad_descriptors_on_two_workers_are_byte_identical(
    tmp_path: Path, small_shards: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``gdnav cache vpr`` with its tiles described in shards on two Dask workers writes the same
    descriptors, index, metadata, vocabulary and manifest as in one process."""
    from gps_denied_onboard.components.c2_vpr.vlad import VladParams
    from gps_denied_onboard.components.c10_cache_build import vpr_index

    engines: list[str] = []
    real_ordered = vpr_index.run_ordered

    def spying_ordered(engine, work, items):  # type: ignore[no-untyped-def]
        engines.append(engine.name)
        return real_ordered(engine, work, items)

    monkeypatch.setattr(vpr_index, "run_ordered", spying_ordered)
    src = _source(tmp_path / "src.tif")
    one, two = tmp_path / "one", tmp_path / "two"
    build_cache_from_geotiff(src, one, progress=False)
    build_cache_from_geotiff(src, two, progress=False)
    params = VladParams(n_clusters=16, pca_dim=0, train_samples=60)
    vpr_index.build_vlad_index(one, params, progress=False)
    vpr_index.build_vlad_index(two, params, progress=False, engine=EngineSpec(workers=2))
    assert engines == ["dask"]
    assert (two / "vpr_descriptors.npy").is_file()
    _assert_same_cache(one, two)
