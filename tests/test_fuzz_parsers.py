"""Fuzz the parsers of files that come from outside the process (FDR segments, the cache manifest, the
camera stream's frame header, profiles, calibration files, replay truth): whatever the bytes, each returns
a value or raises its own refusal, never anything else. Bounded to a few seconds (derandomised, no example
database), so it runs in every CI run."""

from __future__ import annotations

import contextlib
import json
import math
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gps_denied_onboard.camera.stream import FrameStreamError, _parse_header
from gps_denied_onboard.camera.types import CalibrationError, CameraCalibration
from gps_denied_onboard.cli_fdr import boresight, format_boresight, format_summary, summarise
from gps_denied_onboard.cli_replay import load_truth
from gps_denied_onboard.components.c5_estimator.prior import read_previous_run
from gps_denied_onboard.components.c10_cache_build.manifest import CacheManifest, CacheManifestError
from gps_denied_onboard.components.c13_fdr import read_records_newest_first
from gps_denied_onboard.components.c13_fdr.reader import FdrReader, FdrReadError, scan
from gps_denied_onboard.components.c13_fdr.recorder import parse_line
from gps_denied_onboard.config import ConfigError, load_config
from gps_denied_onboard.replay.inputs import ReplayInputError

FUZZ = settings(
    max_examples=60,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)

#: JSON values, nested a few levels, with the numbers that break conversions (huge ints, +-inf, NaN).
_SCALARS = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(10**400), max_value=10**400)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=12)
)
JSON_VALUES = st.recursive(
    _SCALARS,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)
#: Keys the parsers look up, so that the values land where they are read.
_KEYS = st.sampled_from(
    [
        "t_unix_s", "kind", "seq", "fix_type", "lat_deg", "lon_deg", "horiz_sigma_m", "time_unix_usec",
        "frame_seq", "provenance", "inliers", "pid", "previous_torn_lines", "config", "camera",
        "ground_tilt_check", "attitude_check", "tilt_off_deg", "format_version", "zoom", "tile_range",
        "bbox_lonlat", "mosaic_shape", "tile_count", "source", "vpr", "artifacts", "tile_features",
        "per_frame", "exposure_time_unix_usec", "true_lat_deg", "true_lon_deg", "width_px", "height_px",
        "encoding", "profile", "cache", "matcher", "strategy", "init",
    ]
)
_KINDS = st.sampled_from(
    ["mavlink.estimate", "pipeline.fix", "pipeline.frame", "fdr.opened", "fdr.closed", "daemon.config"]
)
RECORDS = st.fixed_dictionaries({"kind": _KINDS}, optional={"t_unix_s": JSON_VALUES}).flatmap(
    lambda head: st.dictionaries(_KEYS, JSON_VALUES, max_size=6).map(lambda rest: {**rest, **head})
)


def _dumps(value: Any) -> bytes:
    return json.dumps(value, allow_nan=True).encode()


#: One line: raw bytes, a JSON value, a record, or brackets nested past the decoder.
LINES = (
    st.binary(max_size=80)
    | JSON_VALUES.map(_dumps)
    | RECORDS.map(_dumps)
    | st.integers(min_value=1, max_value=30_000).map(lambda n: b"[" * n + b"]" * n)
    | st.integers(min_value=1, max_value=30_000).map(lambda n: b'{"kind":"x","a":' + b"[" * n)
)


@FUZZ
@given(line=LINES)
def test_fuzz_fdr_parse_line(line: bytes) -> None:
    """A record (an object with a kind) or None."""
    rec = parse_line(line)
    assert rec is None or (isinstance(rec, dict) and "kind" in rec)


@FUZZ
@given(lines=st.lists(LINES, max_size=6))
def test_fuzz_fdr_readers(tmp_path_factory: pytest.TempPathFactory, lines: list[bytes]) -> None:
    """The start-up read, every FdrReader accessor and the preflight scan read any segment."""
    d = tmp_path_factory.mktemp("fdr")
    segment = d / "fdr-20260101T000000.000Z-000001.jsonl"
    segment.write_bytes(b"\n".join(x.replace(b"\n", b" ") for x in lines))
    previous = read_previous_run(read_records_newest_first(d))
    if previous.last_3d is not None:
        assert math.isfinite(previous.last_3d.lat_deg) and math.isfinite(previous.last_3d.horiz_sigma_m)
    reader = FdrReader(d)
    reader.runs()
    for accessor in (
        reader.estimates,
        reader.fixes,
        reader.provenance_changes,
        reader.frame_errors,
        reader.frame_refusals,
    ):
        list(accessor())
    found = scan(d)
    assert found.records + found.torn_lines + found.corrupt_lines <= len(lines)
    with contextlib.suppress(FdrReadError):  # no record at all
        summary = summarise(reader)
        format_summary(summary)
        json.dumps(summary, allow_nan=True)
    with contextlib.suppress(FdrReadError):
        format_boresight(boresight(d, None, 1.0))


_GOOD_MANIFEST: dict[str, Any] = {
    "format_version": 1,
    "created_utc": "2026-01-01T00:00:00Z",
    "source": {"kind": "geotiff", "path": "m.tif", "sha256": "0" * 64, "crs": "EPSG:4326"},
    "zoom": 18,
    "tile_size_px": 256,
    "tile_range": {"x0": 0, "y0": 0, "x1": 1, "y1": 1},
    "bbox_lonlat": [8.0, 47.0, 8.1, 47.1],
    "mosaic_shape": [512, 512, 3],
    "tile_count": 4,
    "min_tile_valid_fraction": 0.5,
    "resampling": "area",
    "vpr": {"backbone": "none", "model_sha256": None},
    "artifacts": {"tiles.json": {"sha256": "0" * 64, "bytes": 10}},
    "tile_features": {},
}


@FUZZ
@given(
    data=st.binary(max_size=200)
    | JSON_VALUES.map(_dumps)
    | st.dictionaries(_KEYS, JSON_VALUES, max_size=4).map(lambda d: _dumps({**_GOOD_MANIFEST, **d}))
    | st.integers(min_value=1, max_value=30_000).map(lambda n: b'{"format_version":1,"x":' + b"[" * n)
)
def test_fuzz_cache_manifest(tmp_path_factory: pytest.TempPathFactory, data: bytes) -> None:
    """A manifest or CacheManifestError."""
    d = tmp_path_factory.mktemp("cache")
    (d / "manifest.json").write_bytes(data)
    with contextlib.suppress(CacheManifestError):
        CacheManifest.load(d)


@FUZZ
@given(
    raw=st.binary(max_size=200)
    | JSON_VALUES.map(_dumps)
    | st.dictionaries(_KEYS, JSON_VALUES, max_size=6).map(_dumps)
    | st.sampled_from([1200, 2048]).map(lambda n: b"[" * n + b"]" * n)
)
def test_fuzz_camera_frame_header(raw: bytes) -> None:
    """A header of non-negative integers and a known encoding, or FrameStreamError."""
    try:
        header = _parse_header(raw)
    except FrameStreamError:
        return
    assert all(isinstance(header[k], int) and header[k] >= 0 for k in ("seq", "width_px", "height_px"))


_YAML_TEXT = (
    st.text(max_size=200)
    | st.dictionaries(_KEYS, JSON_VALUES, max_size=5).map(lambda d: json.dumps(d, allow_nan=True))
    | st.dictionaries(
        st.sampled_from(["cache", "matcher", "init", "fdr", "camera", "vpr"]),
        st.dictionaries(st.text(max_size=12), JSON_VALUES, max_size=3),
        max_size=3,
    ).map(lambda d: json.dumps(d, allow_nan=True))
    | st.integers(min_value=1, max_value=5000).map(lambda n: "a: " + "[" * n + "]" * n)
)


@FUZZ
@given(text=_YAML_TEXT)
def test_fuzz_profile(tmp_path_factory: pytest.TempPathFactory, text: str) -> None:
    """A Config or ConfigError."""
    p = tmp_path_factory.mktemp("cfg") / "p.yaml"
    p.write_text(text, encoding="utf-8", errors="surrogatepass")
    with contextlib.suppress(ConfigError):
        load_config(p)


_CALIBRATION = (
    "%YAML:1.0\n---\n"
    "image_width: {w}\nimage_height: {h}\n"
    "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ {k} ]\n"
    "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: {nd}\n   dt: d\n   data: [ {d} ]\n"
)
_NUMBERS = st.sampled_from(["0", "-1", "1e308", "1e999", ".nan", ".inf", "-.inf", "640", "x", ""])


@FUZZ
@given(
    text=st.text(max_size=120).map(lambda t: "%YAML:1.0\n---\n" + t)
    | st.builds(
        lambda w, h, k, nd, d: _CALIBRATION.format(w=w, h=h, k=", ".join(k), nd=nd, d=", ".join(d)),
        _NUMBERS,
        _NUMBERS,
        st.lists(_NUMBERS, min_size=0, max_size=10),
        st.integers(min_value=0, max_value=6),
        st.lists(_NUMBERS, min_size=0, max_size=6),
    )
)
def test_fuzz_calibration_file(tmp_path_factory: pytest.TempPathFactory, text: str) -> None:
    """A usable camera model (positive size, finite positive focal lengths) or CalibrationError."""
    p = tmp_path_factory.mktemp("cal") / "calib.yaml"
    p.write_text(text, encoding="utf-8", errors="surrogatepass")
    try:
        cal = CameraCalibration.from_opencv_yaml(p)
    except CalibrationError:
        return
    assert cal.width_px > 0 and cal.height_px > 0 and cal.fx_px > 0 and math.isfinite(cal.fx_px)


@FUZZ
@given(
    data=st.binary(max_size=120)
    | JSON_VALUES.map(_dumps)
    | st.lists(st.dictionaries(_KEYS, JSON_VALUES, max_size=4), max_size=3).map(
        lambda rows: _dumps({"per_frame": rows})
    )
    | st.integers(min_value=1000, max_value=30_000).map(lambda n: b'{"per_frame":' + b"[" * n + b"]" * n)
)
def test_fuzz_replay_truth(tmp_path_factory: pytest.TempPathFactory, data: bytes) -> None:
    """Truth samples or ReplayInputError."""
    p: Path = tmp_path_factory.mktemp("truth") / "truth.json"
    p.write_bytes(data)
    with contextlib.suppress(ReplayInputError):
        load_truth(p)


_CSV_CELLS = st.sampled_from(
    ["a.png", "47.0", "8.5", "100", "1", "1e999", "nan", "-inf", "", "x", '"', "9" * 400]
)
_CSV_ROWS = st.lists(st.lists(_CSV_CELLS, max_size=7).map(",".join), max_size=4)


@FUZZ
@given(
    rows=_CSV_ROWS,
    big=st.sampled_from(["", '"' + "x" * 140_000 + '"']),
)
def test_fuzz_replay_csv(tmp_path_factory: pytest.TempPathFactory, rows: list[str], big: str) -> None:
    """The photo CSV and the truth CSV give frames and samples, or ReplayInputError."""
    import cv2
    import numpy as np

    from gps_denied_onboard.replay.inputs import from_csv

    d = tmp_path_factory.mktemp("csv")
    (d / "img").mkdir()
    cv2.imwrite(str(d / "img" / "a.png"), np.zeros((8, 8, 3), np.uint8))
    pose, truth = d / "pose.csv", d / "truth.csv"
    pose.write_text("\n".join(["file,lat,lon,alt_agl_m,time_unix_s,roll_deg,pitch_deg", *rows, big]))
    truth.write_text("\n".join(["time_unix_s,lat,lon", *rows, big]))
    with contextlib.suppress(ReplayInputError):
        from_csv(d / "img", pose, ground_alt_amsl_m=None, prior_sigma_m=30.0)
    with contextlib.suppress(ReplayInputError):
        load_truth(truth)


_REPLAY_KINDS = st.sampled_from(
    [
        "fdr.opened",
        "daemon.config",
        "estimator.prior",
        "pipeline.frame",
        "pipeline.frame_image",
        "estimator.input",
    ]
)
_REPLAY_KEYS = st.sampled_from(
    [
        "frame_seq", "attitude_rad", "exposure_time_unix_usec", "alt_agl_m", "file", "config", "lat_deg",
        "lon_deg", "sigma_m", "horiz_sigma_m", "unit", "n", "time_unix_usec", "seq", "t_unix_s",
    ]
)
_REPLAY_RECORDS = st.tuples(_REPLAY_KINDS, st.dictionaries(_REPLAY_KEYS, JSON_VALUES, max_size=6)).map(
    lambda kv: {**kv[1], "kind": kv[0]}
)


@FUZZ
@given(records=st.lists(_REPLAY_RECORDS, max_size=8))
def test_fuzz_replay_fdr(tmp_path_factory: pytest.TempPathFactory, records: list[dict[str, Any]]) -> None:
    """`replay --fdr`'s reader gives a replay input or ReplayInputError, whatever the records hold."""
    from gps_denied_onboard.replay.inputs import from_fdr

    d = tmp_path_factory.mktemp("fdr")
    (d / "images").mkdir()
    (d / "images" / "x.png").write_bytes(b"not a png")
    first = {"kind": "pipeline.frame", "attitude_rad": [0, 0, 0], "exposure_time_unix_usec": 1}
    first["frame_seq"] = 0  # a frame with its image: the reader goes past its first refusals
    image = {"kind": "pipeline.frame_image", "exposure_time_unix_usec": 1, "file": "images/x.png"}
    lines = [_dumps(r) for r in [first, image, *records]]
    (d / "fdr-20260101T000000.000Z-000001.jsonl").write_bytes(b"\n".join(lines))
    with contextlib.suppress(ReplayInputError):
        from_fdr(d)
