"""C13 frame images, low-disk policy and health; the start record's input hashes; the daemon's JPEG hook."""

from __future__ import annotations

import asyncio
import errno
import hashlib
import json
import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from gps_denied_onboard.components.c13_fdr import FdrReader, FlightDataRecorder, list_images, list_segments
from gps_denied_onboard.components.c13_fdr import recorder as recorder_mod
from gps_denied_onboard.components.c13_fdr.provenance import run_inputs
from gps_denied_onboard.constants import FdrHealthState, FdrKind

KIB = 1 << 10


class _Disk:
    """A file system of ``capacity`` bytes holding only the FDR directory: free = capacity - its files."""

    def __init__(self, root: Path, capacity: int) -> None:
        self.root = root
        self.capacity = capacity

    def used(self) -> int:
        return sum(p.stat().st_size for p in self.root.rglob("*") if p.is_file())

    def __call__(self, _path: Path) -> int:
        return max(0, self.capacity - self.used())


def _recorder(d: Path, disk: _Disk | None = None, **kw: int) -> FlightDataRecorder:
    opts: dict = {"images_max_bytes": 256 * KIB, "min_free_bytes": 256 * KIB, "free_check_interval_s": 0.0}
    opts.update(kw)
    if disk is not None:
        opts["free_bytes"] = disk
    return FlightDataRecorder(d, 64 * KIB, 16 * KIB, **opts)


def _jpeg(n: int) -> bytes:
    return b"\xff\xd8" + bytes(n - 4) + b"\xff\xd9"


def test_fdr_frame_image_file_and_record(tmp_path: Path) -> None:
    """An image lands in images/ under the run's start time and frame seq, with a record naming it."""
    with _recorder(tmp_path) as fdr:
        path = fdr.record_frame_image(42, 1_717_000_000_123_456, _jpeg(3 * KIB))
    assert path is not None and path.parent == tmp_path / "images"
    assert path.name.startswith(f"img-{fdr._start_tag}-000001-") and path.name.endswith("-42.jpg")
    assert path.read_bytes() == _jpeg(3 * KIB)
    (rec,) = FdrReader(tmp_path).records(FdrKind.FRAME_IMAGE)
    assert rec["frame_seq"] == 42 and rec["exposure_time_unix_usec"] == 1_717_000_000_123_456
    assert rec["file"] == f"images/{path.name}" and rec["bytes"] == 3 * KIB
    assert (tmp_path / rec["file"]).is_file()
    closed = next(FdrReader(tmp_path).records(FdrKind.FDR_CLOSED))
    assert closed["images_written"] == 1 and closed["images_dropped"] == 0


def test_fdr_images_budget_deletes_oldest_images_only(tmp_path: Path) -> None:
    """Over the images budget the oldest images go; record segments are untouched by it."""
    fdr = _recorder(tmp_path, images_max_bytes=64 * KIB)
    for seq in range(10):
        assert fdr.record_frame_image(seq, seq, _jpeg(20 * KIB)) is not None
    kept = list_images(tmp_path)
    assert [int(p.stem.rsplit("-", 1)[1]) for p in kept] == [7, 8, 9]
    assert fdr.images_deleted == 7 and fdr.segments_deleted == 0
    assert sum(p.stat().st_size for p in kept) <= 64 * KIB
    recs = list(FdrReader(tmp_path).records(FdrKind.FRAME_IMAGE))
    assert [r["frame_seq"] for r in recs] == list(range(10))  # every record kept, its file maybe gone
    fdr.close()


def test_fdr_low_disk_deletes_images_before_any_segment(tmp_path: Path) -> None:
    """Low free space: images are deleted (oldest first) and no longer written; records go on, and no
    record segment is deleted for it."""
    disk = _Disk(tmp_path, capacity=10 << 20)
    fdr = _recorder(tmp_path, disk, images_max_bytes=1 << 20, min_free_bytes=256 * KIB)
    for seq in range(8):
        fdr.record_frame_image(seq, seq, _jpeg(32 * KIB))
    for i in range(200):
        fdr.record(FdrKind.FRAME, {"i": i, "pad": "x" * 100})
    segments_before = list_segments(tmp_path)
    assert len(list_images(tmp_path)) == 8 and fdr.health().state is FdrHealthState.OK

    disk.capacity = disk.used() + 200 * KIB  # 200 KiB free: below min_free_bytes, above the records' floor
    assert fdr.record_frame_image(8, 8, _jpeg(32 * KIB)) is None
    assert fdr.images_dropped == 1
    remaining = list_images(tmp_path)
    assert len(remaining) < 8 and [int(p.stem.rsplit("-", 1)[1]) for p in remaining] == list(
        range(8 - len(remaining), 8)
    )  # the oldest went first
    assert disk(tmp_path) >= 256 * KIB  # reclaimed back to the threshold, no further
    assert len(remaining) == 6
    fdr.record(FdrKind.FRAME, {"after": True})
    assert set(segments_before) <= set(list_segments(tmp_path)) and fdr.segments_deleted == 0
    assert fdr.records_dropped == 0
    assert any(r.get("after") for r in FdrReader(tmp_path).records(FdrKind.FRAME))
    fdr.close()


def test_fdr_records_below_floor_reclaim_images_first(tmp_path: Path) -> None:
    """A record that finds the disk below the records' floor deletes images to make room and is written:
    no record is dropped and no segment deleted while an image is left to delete."""
    disk = _Disk(tmp_path, capacity=10 << 20)
    fdr = _recorder(tmp_path, disk, images_max_bytes=1 << 20, min_free_bytes=256 * KIB)
    for seq in range(8):
        fdr.record_frame_image(seq, seq, _jpeg(32 * KIB))
    segments_before = list_segments(tmp_path)
    disk.capacity = disk.used() + 8 * KIB  # below the 64 KiB floor
    fdr.record(FdrKind.FRAME, {"kept": True})
    assert fdr.records_dropped == 0 and fdr.segments_deleted == 0
    assert list_segments(tmp_path) == segments_before
    assert fdr.images_deleted == 8 - len(list_images(tmp_path)) >= 1  # until above the threshold
    assert disk(tmp_path) >= 256 * KIB - 1 * KIB  # (less the record just written)
    assert any(r.get("kept") for r in FdrReader(tmp_path).records(FdrKind.FRAME))
    fdr.close()


def test_fdr_health_goes_degraded_then_failing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """ok -> degraded (below min_free_bytes, images dropped) -> failing (below the records' floor: records
    dropped and counted, never raised) -> ok again once space is back and the hold has passed."""
    monkeypatch.setattr(recorder_mod, "HEALTH_HOLD_S", 0.0)
    disk = _Disk(tmp_path, capacity=10 << 20)
    fdr = _recorder(tmp_path, disk, min_free_bytes=256 * KIB)
    fdr.record(FdrKind.FRAME, {"i": 0})
    assert fdr.health().state is FdrHealthState.OK

    disk.capacity = disk.used() + 128 * KIB  # under min_free_bytes, over its quarter
    assert fdr.record_frame_image(1, 1, _jpeg(8 * KIB)) is None
    fdr.record(FdrKind.FRAME, {"i": 1})
    h = fdr.health()
    assert h.state is FdrHealthState.DEGRADED and h.images_dropped == 1 and h.records_dropped == 0
    assert h.free_bytes is not None and h.free_bytes < 256 * KIB

    disk.capacity = disk.used() + 16 * KIB  # under the records' floor (64 KiB)
    written = fdr.records_written
    for i in range(5):
        fdr.record(FdrKind.FRAME, {"i": 2 + i})  # never raises
    h = fdr.health()
    assert h.state is FdrHealthState.FAILING and h.records_dropped == 5 and h.write_errors >= 5
    assert fdr.records_written == written

    disk.capacity = 10 << 20
    fdr.record(FdrKind.FRAME, {"i": 99})
    assert fdr.health().state is FdrHealthState.OK
    fdr.close()
    assert [r["i"] for r in FdrReader(tmp_path).records(FdrKind.FRAME)] == [0, 1, 99]


def test_fdr_enospc_is_counted_and_never_raises(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """os.write failing with ENOSPC drops records and images (counted, health failing), never raises;
    the recorder writes again once the disk has room, and the file stays readable."""
    fdr = _recorder(tmp_path)
    fdr.record(FdrKind.FRAME, {"i": 0})
    real_write = os.write

    def full(_fd: int, _data: object) -> int:
        raise OSError(errno.ENOSPC, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr(os, "write", full)
        for i in range(3):
            fdr.record(FdrKind.FRAME, {"i": 1 + i})
        assert fdr.record_frame_image(7, 7, _jpeg(4 * KIB)) is None
    assert os.write is real_write
    h = fdr.health()
    assert h.state is FdrHealthState.FAILING
    assert h.records_dropped == 3 and h.images_dropped == 1 and h.write_errors == 4
    assert list_images(tmp_path) == [] and not list((tmp_path / "images").glob("*.part"))
    fdr.record(FdrKind.FRAME, {"i": 9})
    fdr.close()
    assert [r["i"] for r in FdrReader(tmp_path).records(FdrKind.FRAME)] == [0, 9]
    closed = next(FdrReader(tmp_path).records(FdrKind.FDR_CLOSED))
    assert closed["records_dropped"] == 3 and closed["images_dropped"] == 1


def test_fdr_reopen_counts_earlier_images_and_reclaims_partial(tmp_path: Path) -> None:
    """A new run counts the earlier run's images against the budget and deletes a leftover .part."""
    with _recorder(tmp_path, images_max_bytes=64 * KIB) as first:
        first.record_frame_image(1, 1, _jpeg(30 * KIB))
        first.record_frame_image(2, 2, _jpeg(30 * KIB))
    (tmp_path / "images" / "img-x.jpg.part").write_bytes(b"torn")
    with _recorder(tmp_path, images_max_bytes=64 * KIB) as second:
        second.record_frame_image(3, 3, _jpeg(30 * KIB))
    names = [p.name for p in list_images(tmp_path)]
    assert len(names) == 2 and names[-1].endswith("-3.jpg") and names[0].endswith("-2.jpg")
    assert not (tmp_path / "images" / "img-x.jpg.part").exists()


def test_fdr_record_frame_jpeg_encodes_a_real_image(tmp_path: Path) -> None:
    """record_frame_jpeg encodes with OpenCV at the given quality; a bad array is dropped, not raised."""
    import cv2

    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, (120, 160, 3), dtype=np.uint8)
    with _recorder(tmp_path) as fdr:
        hi = fdr.record_frame_jpeg(1, 1, image, 95)
        lo = fdr.record_frame_jpeg(2, 2, image, 10)
        assert fdr.record_frame_jpeg(3, 3, np.zeros((0, 0, 3), np.uint8), 80) is None
    assert hi is not None and lo is not None and lo.stat().st_size < hi.stat().st_size
    decoded = cv2.imdecode(np.frombuffer(hi.read_bytes(), np.uint8), cv2.IMREAD_COLOR)
    assert decoded.shape == image.shape
    assert fdr.images_dropped == 1 and fdr.images_written == 2


async def _stop_workers(daemon: object) -> None:
    await asyncio.gather(daemon._track_thread.stop(1.0), daemon._fix_thread.stop(1.0))  # type: ignore[attr-defined]


def test_daemon_track_stores_every_nth_frame(tmp_path: Path) -> None:
    """NavDaemon._track stores frames whose seq is a multiple of fdr.frame_jpeg_every_n, each with its
    pipeline.frame_image record; none when it is 0."""
    from gps_denied_onboard.camera.sources import RawFrame
    from gps_denied_onboard.camera.types import CameraCalibration
    from gps_denied_onboard.clock import DaemonClock
    from gps_denied_onboard.config import load_config
    from gps_denied_onboard.daemon.service import NavDaemon

    class _Pipeline:
        def track(self, frame: object, prior: object) -> str:
            return "tracked"

    image = np.full((48, 64, 3), 128, np.uint8)
    for every_n, expected in ((3, [0, 3, 6, 9]), (0, [])):
        d = tmp_path / f"n{every_n}"
        config = load_config(None, [f"fdr.frame_jpeg_every_n={every_n}", "fdr.frame_jpeg_quality=70"])
        fdr = _recorder(d)
        root = SimpleNamespace(
            config=config,
            time_axis=None,
            clock=DaemonClock(),
            calibration=CameraCalibration(64, 48, 50.0, 50.0, 32.0, 24.0),
            pipeline=_Pipeline(),
            fdr=fdr,
        )
        daemon = NavDaemon(root)  # type: ignore[arg-type]
        try:
            for seq in range(11):
                t_us = 1_000_000 * seq
                result = daemon._track(RawFrame(seq, t_us, image), t_us, 0, None, None, None)
                assert result is not None and result[1] == "tracked"
        finally:
            asyncio.run(_stop_workers(daemon))
            fdr.close()
        recs = list(FdrReader(d).records(FdrKind.FRAME_IMAGE))
        assert [r["frame_seq"] for r in recs] == expected
        assert [r["exposure_time_unix_usec"] for r in recs] == [1_000_000 * s for s in expected]
        assert all((d / r["file"]).read_bytes()[:2] == b"\xff\xd8" for r in recs)


def test_run_inputs_hash_real_files(tmp_path: Path) -> None:
    """The start record pins the config file, the cache manifest (and its file count) and each model
    file: from the model manifest where it lists the file, computed otherwise."""
    from gps_denied_onboard.components.c7_inference.protocol import EngineSignature
    from gps_denied_onboard.helpers.model_manifest import ModelEntry, ModelSource, write_manifest

    cfg = tmp_path / "profile.yaml"
    cfg.write_text("fdr:\n  max_bytes: 1048576\n")
    cache = tmp_path / "cache"
    cache.mkdir()
    manifest = {"format_version": 1, "artifacts": {"mosaic_z18.npy": {}, "tiles.json": {}, "x.npy": {}}}
    (cache / "manifest.json").write_text(json.dumps(manifest))
    models = tmp_path / "models"
    models.mkdir()
    onnx = models / "aliked.onnx"
    onnx.write_bytes(b"aliked-weights")
    write_manifest(
        models,
        ModelEntry(
            "aliked.onnx",
            hashlib.sha256(b"aliked-weights").hexdigest(),
            ModelSource("aliked-n16", "0" * 64, "BSD-3-Clause", "https://example.invalid"),
            EngineSignature("aliked", (), ()),
        ),
    )
    lightglue = tmp_path / "lightglue.onnx"
    lightglue.write_bytes(b"lightglue-weights")

    out = run_inputs(
        cfg,
        overrides=["matcher.strategy=aliked_lightglue"],
        cache_dir=cache,
        model_dir=models,
        model_files=[onnx, None, lightglue],
    )
    sha = lambda p: hashlib.sha256(p.read_bytes()).hexdigest()  # noqa: E731
    assert out["config_sha256"] == sha(cfg) and out["config_file"] == str(cfg)
    assert out["config_overrides"] == ["matcher.strategy=aliked_lightglue"]
    assert out["cache_manifest_sha256"] == sha(cache / "manifest.json") and out["cache_manifest_files"] == 3
    assert out["model_manifest_sha256"] == sha(models / "manifest.json")
    assert out["models"] == [
        {"file": str(onnx), "sha256": sha(onnx), "from": "manifest"},
        {"file": str(lightglue), "sha256": sha(lightglue), "from": "computed"},
    ]
    assert out["input_errors"] == []

    with _recorder(tmp_path / "fdr") as fdr:
        fdr.record(FdrKind.CONFIG, {"version": "t", "config": {}, **out})
    rec = next(FdrReader(tmp_path / "fdr").records(FdrKind.CONFIG))
    assert rec["config_sha256"] == sha(cfg) and rec["models"][1]["sha256"] == sha(lightglue)


def test_run_inputs_never_raises_on_missing_files(tmp_path: Path) -> None:
    """Unreadable inputs give null hashes and input_errors; nothing raises (the start is already accepted)."""
    out = run_inputs(None, cache_dir=tmp_path / "nocache", model_files=[tmp_path / "missing.onnx"])
    assert out["config_file"] is None and out["config_sha256"] is None
    assert out["cache_manifest_sha256"] is None and out["cache_manifest_files"] is None
    assert out["models"] == [{"file": str(tmp_path / "missing.onnx"), "sha256": None, "from": "computed"}]
    assert len(out["input_errors"]) == 2


class _Clock:
    def __init__(self, t: float) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


@pytest.mark.parametrize("earlier", [1_700_000_000.0, 1_800_000_000.0], ids=["clock-behind", "same-ms"])
def test_fdr_names_keep_recording_order_when_the_clock_reads_earlier(tmp_path: Path, earlier: float) -> None:
    """A restart on a clock that reads earlier than the last run (no RTC), or within its millisecond, goes
    on under the last run's tag, so segments and images still sort oldest first and the image budget
    deletes the oldest."""
    later = 1_800_000_000.0
    opts = {"images_max_bytes": 64 * KIB, "min_free_bytes": 0, "free_check_interval_s": 0.0}
    with FlightDataRecorder(tmp_path, 1 << 20, 1 << 16, clock=_Clock(later), **opts) as first:
        first.record_frame_image(1, 1, _jpeg(30 * KIB))
        for _ in range(2):  # the second cannot fit the 64 KiB segment: a second one opens
            first.record(FdrKind.FRAME, {"run": 0, "pad": "x" * 40 * KIB})
        first.record(FdrKind.FRAME, {"run": 1})  # in the run's second segment
    first_segments = list_segments(tmp_path)
    assert len(first_segments) == 2
    first_segments[0].unlink()  # as the size budget deletes the oldest
    with FlightDataRecorder(tmp_path, 1 << 20, 1 << 16, clock=_Clock(earlier), **opts) as second:
        second.record_frame_image(2, 2, _jpeg(30 * KIB))
        second.record_frame_image(3, 3, _jpeg(30 * KIB))
        second.record(FdrKind.FRAME, {"run": 2})
    images = [p.name.split("-") for p in list_images(tmp_path)]
    assert [parts[-1] for parts in images] == ["2.jpg", "3.jpg"]
    assert [int(parts[2]) for parts in images] == [2, 3]  # numbered after the first run's image
    assert [r["run"] for r in FdrReader(tmp_path).records(FdrKind.FRAME)] == [0, 1, 2]  # 1st pad: deleted
    segs = list_segments(tmp_path)
    assert segs[0] == first_segments[1] and len({s.name.split("-")[1] for s in segs}) == 1
    assert [int(s.stem.split("-")[-1]) for s in segs] == [2, 3]  # numbered after, not in the gap
    assert next(FdrReader(tmp_path).records(FdrKind.FDR_OPENED))["t_unix_s"] == earlier  # the clock as read
