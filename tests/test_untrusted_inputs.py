"""Hostile or broken files the daemon and its tools read (FDR segments, cache manifests, replay frames,
configuration) give one plain line and an exit code, or a skipped and counted record: never a traceback.
The commands run as real `gdnav` processes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from gps_denied_onboard.components.c5_estimator.prior import read_previous_run
from gps_denied_onboard.components.c13_fdr import FlightDataRecorder, read_records, read_records_newest_first
from gps_denied_onboard.components.c13_fdr.reader import FdrReader, scan
from gps_denied_onboard.components.c13_fdr.recorder import MAX_RECORD_BYTES, parse_line

NOW_USEC = 1_717_000_000_000_000
#: One FDR line nested far past what CPython's JSON decoder follows (it raised RecursionError).
NESTED_LINE = (
    b'{"t_unix_s":1717000000.5,"kind":"mavlink.estimate","x":' + b"[" * 100_000 + b"]" * 100_000 + b"}\n"
)


def _gdnav(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gps_denied_onboard.cli", *args],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=cwd,
    )


def _one_line(proc: subprocess.CompletedProcess[str], code: int) -> str:
    """Exit ``code``, no traceback, and the last stderr line a plain ``gdnav:`` line; returns it."""
    assert proc.returncode == code, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    line = proc.stderr.strip().splitlines()[-1]
    assert line.startswith("gdnav: "), proc.stderr[-3000:]
    return line


def _fdr_with(tmp_path: Path, *hostile: bytes) -> Path:
    """A real recorder's segment with three 3D estimates, then ``hostile`` lines appended to it."""
    d = tmp_path / "fdr"
    with FlightDataRecorder(d, max_bytes=1 << 20, segment_bytes=1 << 16) as fdr:
        for k in range(3):
            fdr.record(
                "mavlink.estimate",
                {
                    "time_unix_usec": NOW_USEC + k,
                    "fix_type": 3,
                    "lat_deg": 47.0 + k,
                    "lon_deg": 8.0,
                    "horiz_sigma_m": 2.0,
                },
            )
    seg = sorted(d.glob("fdr-*.jsonl"))[-1]
    with seg.open("ab") as fh:
        for line in hostile:
            fh.write(line)
    return d


# --- FDR lines --------------------------------------------------------------------------------------


def test_fdr_nested_line_is_skipped_by_the_startup_read(tmp_path: Path) -> None:
    """A deeply nested line (RecursionError in the decoder: `gdnav run` crashed at every start) is
    skipped, and the resume state behind it is still found."""
    d = _fdr_with(tmp_path, NESTED_LINE)
    previous = read_previous_run(read_records_newest_first(d))
    assert previous.last_3d is not None and previous.last_3d.lat_deg == 49.0


def test_fdr_infinite_time_record_is_skipped_by_the_startup_read(tmp_path: Path) -> None:
    """A 3D estimate whose time_unix_usec is Infinity (int() raises OverflowError) is skipped."""
    bad = b'{"t_unix_s":1717000001.0,"kind":"mavlink.estimate","seq":9,"fix_type":3,"lat_deg":1.0,'
    bad += b'"lon_deg":2.0,"horiz_sigma_m":1.0,"time_unix_usec":Infinity}\n'
    previous = read_previous_run(read_records_newest_first(_fdr_with(tmp_path, bad)))
    assert previous.last_3d is not None and previous.last_3d.lat_deg == 49.0


def test_fdr_huge_integer_time_is_skipped_by_the_startup_read(tmp_path: Path) -> None:
    """A newest record whose t_unix_s is an integer too large for a float (float() raised OverflowError;
    found by the fuzz test) is passed over for the newest record with a finite time."""
    bad = b'{"t_unix_s":' + b"9" * 400 + b',"kind":"pipeline.frame","seq":9}\n'
    previous = read_previous_run(read_records_newest_first(_fdr_with(tmp_path, bad)))
    assert previous.last_3d is not None and previous.last_record_unix_s is not None
    assert previous.last_record_unix_s < 1e10


def test_fdr_line_over_the_size_bound_is_refused_unparsed() -> None:
    """A line longer than MAX_RECORD_BYTES is not parsed (nor held whole by the readers)."""
    big = b'{"t_unix_s":1.0,"kind":"x","pad":"' + b"a" * MAX_RECORD_BYTES + b'"}\n'
    assert parse_line(big) is None
    assert parse_line(b'{"t_unix_s":1.0,"kind":"x"}\n') == {"t_unix_s": 1.0, "kind": "x"}


def test_fdr_reader_counts_hostile_lines_as_bad(tmp_path: Path) -> None:
    """FdrReader skips a nested line, a line over the size bound and a record with a huge or
    non-numeric time, counts the unreadable lines in the run, and its typed accessors skip the rest."""
    big = b'{"t_unix_s":1.0,"kind":"x","pad":"' + b"a" * (MAX_RECORD_BYTES + 10) + b'"}\n'
    odd = b'{"t_unix_s":"soon","kind":"mavlink.estimate","seq":"x","fix_type":3}\n'
    huge = b'{"t_unix_s":' + b"9" * 400 + b',"kind":"pipeline.fix","seq":1e999}\n'
    d = _fdr_with(tmp_path, NESTED_LINE, big, odd, huge)
    reader = FdrReader(d)
    runs = reader.runs()
    assert sum(r.bad_lines for r in runs) == 2
    assert len(list(reader.estimates())) == 3
    assert list(reader.fixes()) == []
    found = scan(d)
    assert (found.records, found.torn_lines, found.corrupt_lines) == (7, 0, 2)
    assert found.first_corrupt is not None and "nested too deeply" in found.first_corrupt


def test_fdr_scan_tells_torn_lines_from_corrupt_ones(tmp_path: Path) -> None:
    """A write cut short by a crash is torn (expected); JSON that is no record is corrupt."""
    found = scan(_fdr_with(tmp_path, b'{"t_unix_s":1.0,"ki\n', b"[1, 2]\n"))
    assert (found.torn_lines, found.corrupt_lines) == (1, 1)
    assert found.first_corrupt is not None and "not a record" in found.first_corrupt


def test_cli_fdr_summary_with_a_nested_line_exits_0(tmp_path: Path) -> None:
    """`gdnav fdr summary` reads past the nested line and counts it."""
    d = _fdr_with(tmp_path, NESTED_LINE)
    proc = _gdnav(tmp_path, "fdr", "summary", str(d), "--json")
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout)
    assert sum(r["bad_lines"] for r in summary["runs"]) == 1


@pytest.mark.parametrize(
    "command",
    [("fdr", "boresight"), ("replay", "--report", "r.json", "--fdr")],
    ids=["boresight", "replay"],
)
def test_cli_fdr_readers_with_a_nested_line_refuse_in_one_line(
    tmp_path: Path, command: tuple[str, ...]
) -> None:
    """`fdr boresight` and `replay --fdr` skip the nested line and refuse the FDR (it tracked no frame)
    with one line and exit 3."""
    d = _fdr_with(tmp_path, NESTED_LINE)
    line = _one_line(_gdnav(tmp_path, *command, str(d)), 3)
    assert "no run tracked any frame" in line


# --- manifests, profiles, the camera stream ---------------------------------------------------------


def _sitl_args(tmp_path: Path, *overrides: str) -> list[str]:
    """``--config sitl.yaml`` with local directories and unused loopback ports, then ``overrides``."""
    from daemon_harness import REPO, free_tcp_port, free_udp_port

    args = ["--config", str(REPO / "config" / "sitl.yaml")]
    for item in (
        f"camera.source=tcp://127.0.0.1:{free_tcp_port()}",
        f"mavlink.url=udpin:127.0.0.1:{free_udp_port()}",
        f"cache.dir={tmp_path / 'no-cache'}",
        f"fdr.dir={tmp_path / 'fdr'}",
        *overrides,
    ):
        args += ["--set", item]
    return args


@pytest.mark.parametrize(
    "manifest",
    [
        b'{"format_version": 1, "x": ' + b"[" * 50_000 + b"]" * 50_000 + b"}",
        b"[1, 2]",
        b'{"format_version": 1}',
    ],
    ids=["nested", "not-an-object", "missing-keys"],
)
def test_cli_run_hostile_cache_manifest_exits_3(tmp_path: Path, manifest: bytes) -> None:
    """A nested, non-object or incomplete manifest.json is refused at start-up: exit 3, one line naming
    the manifest (the nested one raised RecursionError)."""
    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / "manifest.json").write_bytes(manifest)
    line = _one_line(_gdnav(tmp_path, "run", *_sitl_args(tmp_path, f"cache.dir={cache}")), 3)
    assert "manifest.json" in line


def test_cache_manifest_with_infinite_numbers_is_refused(tmp_path: Path) -> None:
    """An infinite tile count (int() raises OverflowError) is a CacheManifestError, not a crash."""
    from gps_denied_onboard.components.c10_cache_build.manifest import CacheManifest, CacheManifestError

    good = {
        "format_version": 1,
        "created_utc": "x",
        "source": {"kind": "geotiff", "path": "m.tif", "sha256": "0", "crs": "EPSG:4326"},
        "zoom": 18,
        "tile_size_px": 256,
        "tile_range": {"x0": 0, "y0": 0, "x1": 1, "y1": 1},
        "bbox_lonlat": [0, 0, 1, 1],
        "mosaic_shape": [2, 2, 3],
        "tile_count": 1e999,
        "min_tile_valid_fraction": 0.5,
        "resampling": "area",
        "vpr": {"backbone": "none", "model_sha256": None},
        "artifacts": {},
    }
    (tmp_path / "manifest.json").write_text(json.dumps(good))
    with pytest.raises(CacheManifestError, match="malformed"):
        CacheManifest.load(tmp_path)


@pytest.mark.parametrize(
    "profile",
    [
        "profile: " + "[" * 3000 + "]" * 3000 + "\n",
        "a0: &a0 [x, x, x, x, x, x, x, x, x, x]\n"
        + "".join(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]\n" for i in range(1, 9)),
    ],
    ids=["nested", "alias-bomb"],
)
@pytest.mark.parametrize("command", [("run",), ("config", "check"), ("preflight", "--offline")])
def test_cli_hostile_profile_exits_2(tmp_path: Path, profile: str, command: tuple[str, ...]) -> None:
    """A profile nested past the YAML parser (RecursionError) or an alias bomb (a billion values once
    expanded: `config check` ran for minutes) is a configuration error in one line, at once."""
    bad = tmp_path / "bad.yaml"
    bad.write_text(profile)
    proc = _gdnav(tmp_path, *command, "--config", str(bad))
    line = _one_line(proc, 2) if command[0] != "preflight" else proc.stderr.strip().splitlines()[-1]
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert str(bad) in line and "not a profile" in line


def test_camera_stream_nested_header_is_a_stream_error() -> None:
    """A frame header nested past the JSON decoder (a hostile camera peer) is a FrameStreamError (the
    stream reconnects), not a RecursionError out of the camera task."""
    from gps_denied_onboard.camera.stream import MAX_HEADER_BYTES, FrameStreamError, _parse_header

    raw = b"[" * (MAX_HEADER_BYTES // 2) + b"]" * (MAX_HEADER_BYTES // 2)
    with pytest.raises(FrameStreamError, match="nested too deeply"):
        _parse_header(raw)


# --- replay inputs ----------------------------------------------------------------------------------


def test_cli_replay_unreadable_frame_image_exits_3(tmp_path: Path) -> None:
    """A frame image that OpenCV cannot read, met mid-replay, is one line naming it and exit 3 (it
    was exit 1 with a traceback)."""
    import cv2
    import numpy as np

    images = tmp_path / "img"
    images.mkdir()
    cv2.imwrite(str(images / "a.png"), np.full((48, 64, 3), 128, np.uint8))
    (images / "b.png").write_bytes(b"\x89PNG\r\n\x1a\n not really a png")
    rows = "file,lat,lon,alt_agl_m,time_unix_s\na.png,47.0,8.5,100,1\nb.png,47.0001,8.5,100,2\n"
    (tmp_path / "pose.csv").write_text(rows)
    proc = _gdnav(
        tmp_path, "replay", "--images", str(images), "--csv", str(tmp_path / "pose.csv"), "--report", "r.json"
    )
    line = _one_line(proc, 3)
    assert "b.png" in line and "not an image" in line


# --- the commands' top level ------------------------------------------------------------------------


@pytest.fixture()
def info_log() -> None:
    """The log at info on stderr, as most commands set it (earlier tests may have left it at debug, where
    the traceback is also logged as a record)."""
    from gps_denied_onboard.logging_setup import configure_logging

    configure_logging("info")


@pytest.mark.usefixtures("info_log")
def test_cli_unexpected_exception_is_one_line_exit_1_and_a_kept_traceback(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """An exception no refusal maps (here the FDR summariser failing) is one line naming the command and
    the exception, exit 1, and its traceback appended to the debug log, not printed."""
    from gps_denied_onboard import cli, cli_fdr

    def broken(_reader: object) -> dict[str, object]:
        raise ZeroDivisionError("float division by zero")

    log = tmp_path / "logs" / "debug.log"
    monkeypatch.setenv("GDNAV_DEBUG_LOG", str(log))
    monkeypatch.setattr(cli_fdr, "summarise", broken)
    code = cli.main(["fdr", "summary", str(_fdr_with(tmp_path))])
    out = capsys.readouterr()
    assert code == 1 and out.out == ""
    assert out.err.count("\n") == 1 and "Traceback" not in out.err
    expected = "gdnav: fdr summary: unexpected error: ZeroDivisionError: float division by zero"
    assert out.err.startswith(expected)
    assert str(log) in out.err
    kept = log.read_text()
    assert "Traceback" in kept and "def broken" not in kept and "in broken" in kept
    cli.main(["fdr", "summary", str(_fdr_with(tmp_path / "again"))])
    assert log.read_text().count("Traceback") == 2


@pytest.mark.usefixtures("info_log")
def test_cli_unexpected_exception_with_an_unwritable_debug_log_still_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """When the debug log cannot be written the line says so, and still no traceback reaches stderr."""
    from gps_denied_onboard import cli, cli_fdr

    def broken(_reader: object) -> dict[str, object]:
        raise KeyError("x")

    (tmp_path / "file").write_text("")
    monkeypatch.setenv("GDNAV_DEBUG_LOG", str(tmp_path / "file" / "debug.log"))
    monkeypatch.setattr(cli_fdr, "summarise", broken)
    assert cli.main(["fdr", "summary", str(_fdr_with(tmp_path))]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "traceback not kept" in err and "GDNAV_DEBUG_LOG" in err


def test_replay_nested_truth_json_is_refused(tmp_path: Path) -> None:
    """A --truth JSON nested past the decoder is a ReplayInputError naming it (it raised RecursionError)."""
    from gps_denied_onboard.cli_replay import load_truth
    from gps_denied_onboard.replay.inputs import ReplayInputError

    truth = tmp_path / "truth.json"
    truth.write_text('{"per_frame": ' + "[" * 50_000 + "]" * 50_000 + "}")
    with pytest.raises(ReplayInputError, match=r"truth\.json"):
        load_truth(truth)


def test_daemon_starts_over_an_fdr_with_a_nested_line(tmp_path: Path) -> None:
    """`gdnav run` as a real process gets to ready over an FDR holding the nested line (it crashed with
    RecursionError at every start, five times, then the unit stayed failed)."""
    from daemon_harness import build_small_cache, start_daemon, wait_for

    cache = build_small_cache(tmp_path / "map")[1]
    fdr = _fdr_with(tmp_path, NESTED_LINE)
    daemon = start_daemon(tmp_path, cache)
    assert daemon.fdr_dir == fdr
    try:
        assert wait_for(lambda: "daemon.ready" in daemon.log_text() or daemon.proc.poll() is not None, 60.0)
        assert "daemon.ready" in daemon.log_text(), daemon.log_text()[-3000:]
    finally:
        code = daemon.stop()
    assert code == 0 and "Traceback" not in daemon.log_text(), daemon.log_text()[-3000:]


_BIG_FIELD = '"' + "x" * 200_000 + '"'


@pytest.mark.parametrize(
    ("pose_row", "truth_row", "expected"),
    [
        (f"{_BIG_FIELD},47,8,100,1", f"{_BIG_FIELD},47,8", "not readable as CSV"),
        ("a.png,47,8,100,1e999", "1e999,47,8", "not a finite number"),
        ("a.png,47,8,100,nan", "nan,47,8", "not a finite number"),
    ],
    ids=["field-over-the-csv-limit", "infinite-time", "nan-time"],
)
def test_replay_csv_inputs_refuse_what_crashed_them(
    tmp_path: Path, pose_row: str, truth_row: str, expected: str
) -> None:
    """A CSV field over the csv module's limit (csv.Error) and a non-finite time (int() raised
    OverflowError/ValueError) are ReplayInputErrors naming the file, in the photo CSV and the truth CSV."""
    import cv2
    import numpy as np

    from gps_denied_onboard.cli_replay import load_truth
    from gps_denied_onboard.replay.inputs import ReplayInputError, from_csv

    images = tmp_path / "img"
    images.mkdir()
    cv2.imwrite(str(images / "a.png"), np.zeros((48, 64, 3), np.uint8))
    table = tmp_path / "pose.csv"
    table.write_text(f"file,lat,lon,alt_agl_m,time_unix_s\n{pose_row}\n")
    with pytest.raises(ReplayInputError, match=expected) as refused:
        from_csv(images, table, ground_alt_amsl_m=None, prior_sigma_m=30.0)
    assert str(table) in str(refused.value)
    truth = tmp_path / "truth.csv"
    truth.write_text(f"time_unix_s,lat,lon\n{truth_row}\n")
    with pytest.raises(ReplayInputError, match=expected) as refused:
        load_truth(truth)
    assert str(refused.value).count(str(truth)) == 1


@pytest.mark.parametrize("command", [("run",), ("config", "check")])
def test_cli_oversized_calibration_file_exits_3(tmp_path: Path, command: tuple[str, ...]) -> None:
    """A calibration file far larger than any calibration (OpenCV parsed all of it in memory) is refused
    unread: exit 3 naming camera.calibration_file and the size bound."""
    calib = tmp_path / "calib.yaml"
    with calib.open("wb") as fh:
        fh.write(b"%YAML:1.0\n---\ncomment: ")
        fh.truncate(8 << 20)
    proc = _gdnav(tmp_path, *command, *_sitl_args(tmp_path, f"camera.calibration_file={calib}"))
    line = _one_line(proc, 3)
    assert "camera.calibration_file" in line and "bytes" in line and str(calib) in line


def test_model_and_vpr_metadata_nested_json_is_refused(tmp_path: Path) -> None:
    """A nested model manifest.json, vpr_meta.json or verification.json (RecursionError before) is the
    reader's own refusal, or for verification.json 'not verified'."""
    from gps_denied_onboard.components.c10_cache_build import CacheBuildError
    from gps_denied_onboard.components.c10_cache_build.vpr_index import VPR_META_NAME, read_vpr_meta
    from gps_denied_onboard.helpers.model_manifest import MANIFEST_NAME, ModelDirError, read_manifest
    from gps_denied_onboard.models.verification import VERIFICATION_NAME, read_verification

    nested = b"[" * 50_000 + b"]" * 50_000
    for name in (MANIFEST_NAME, VPR_META_NAME, VERIFICATION_NAME):
        (tmp_path / name).write_bytes(nested)
    with pytest.raises(ModelDirError, match="nested too deeply"):
        read_manifest(tmp_path)
    with pytest.raises(CacheBuildError, match="nested too deeply"):
        read_vpr_meta(tmp_path)
    assert read_verification(tmp_path) == {}


def test_fdr_startup_read_holds_only_the_end_of_a_huge_segment(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The start-up read takes a segment from its end, at most NEWEST_FIRST_MAX_BYTES (it read the whole
    file into memory): the newest 3D estimate is still found, and the line cut at the window's start is
    not taken for a record."""
    from gps_denied_onboard.components.c13_fdr import recorder

    d = _fdr_with(tmp_path)
    seg = sorted(d.glob("fdr-*.jsonl"))[-1]
    lines = seg.read_bytes().splitlines(keepends=True)
    window = len(lines[-2]) + len(lines[-1]) + 10  # the last estimate, fdr.closed, and a cut line
    monkeypatch.setattr(recorder, "NEWEST_FIRST_MAX_BYTES", window)
    previous = read_previous_run(read_records_newest_first(d))
    assert previous.last_3d is not None and previous.last_3d.lat_deg == 49.0
    assert len(list(read_records_newest_first(d))) == 2


def test_cli_fdr_summary_with_a_time_past_the_calendar_exits_0(tmp_path: Path) -> None:
    """A record at t_unix_s 1e300 (finite, but past what datetime holds: ValueError, found by the fuzz
    test) is summarised with its time as '?'."""
    d = _fdr_with(tmp_path, b'{"t_unix_s":1e300,"kind":"fdr.opened","seq":1}\n')
    proc = _gdnav(tmp_path, "fdr", "summary", str(d), "--json")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads(proc.stdout)["runs"][-1]["start_utc"] == "?"


def test_replay_fdr_with_a_malformed_frame_image_record_is_refused(tmp_path: Path) -> None:
    """A pipeline.frame_image record without its exposure time (KeyError before) refuses the FDR by
    name."""
    from gps_denied_onboard.replay.inputs import ReplayInputError, from_fdr

    frame = b'{"t_unix_s":1717000001.0,"kind":"pipeline.frame","seq":8,"attitude_rad":[0,0,0]}\n'
    image = b'{"t_unix_s":1717000001.1,"kind":"pipeline.frame_image","seq":9,"file":"images/x.png"}\n'
    d = _fdr_with(tmp_path, frame, image)
    with pytest.raises(ReplayInputError, match="not what the daemon writes"):
        from_fdr(d)


# --- files in the FDR that are not regular files (issue 36, item 9) ---------------------------------

#: Segment names that sort after any the recorder writes now: the newest-first read meets them first.
_LATE_FIFO = "fdr-29991231T235959.998Z-000001.jsonl"
_LATE_LINK = "fdr-29991231T235959.999Z-000001.jsonl"


def _fdr_with_fifo_and_dev_zero(tmp_path: Path) -> Path:
    """A real recorder's segment with three 3D estimates, then a real FIFO (no writer: opening it for
    reading blocks) and a real symbolic link to /dev/zero (reads without end), both named as the newest
    segments, and a FIFO named as a frame image."""
    d = _fdr_with(tmp_path)
    os.mkfifo(d / _LATE_FIFO)
    os.symlink("/dev/zero", d / _LATE_LINK)
    (d / "images").mkdir(exist_ok=True)
    os.mkfifo(d / "images" / "img-29991231T235959.999Z-000001-7.jpg")
    return d


@pytest.mark.timeout(60)
def test_fdr_fifo_and_dev_zero_link_are_refused_by_the_readers(tmp_path: Path) -> None:
    """The start-up read, the recording-order read and the scan skip the FIFO and the link unopened
    (the FIFO blocked `gdnav run` before ready, the link read until MemoryError) and find the records."""
    d = _fdr_with_fifo_and_dev_zero(tmp_path)
    previous = read_previous_run(read_records_newest_first(d))
    assert previous.last_3d is not None and previous.last_3d.lat_deg == 49.0
    assert sum(1 for r in read_records(d) if r["kind"] == "mavlink.estimate") == 3
    found = scan(d)
    assert found.records >= 3 and found.segments == 1
    assert sorted(found.unreadable_segments) == [
        f"{_LATE_FIFO}: not a regular file (FIFO)",
        f"{_LATE_LINK}: not a regular file (symbolic link)",
        "img-29991231T235959.999Z-000001-7.jpg: not a regular file (FIFO)",
    ]
    assert sum(1 for _ in FdrReader(d).records("mavlink.estimate")) == 3


@pytest.mark.timeout(60)
def test_fdr_recorder_opens_over_a_fifo_and_a_dev_zero_link_and_names_them(tmp_path: Path) -> None:
    """A recorder opened over the FIFO and the link neither reads nor writes them: it records on in a
    segment of its own, and its fdr.opened record names what it refused."""
    d = _fdr_with_fifo_and_dev_zero(tmp_path)
    with FlightDataRecorder(d, max_bytes=1 << 20, segment_bytes=1 << 16) as fdr:
        fdr.record("mavlink.estimate", {"time_unix_usec": NOW_USEC + 9, "fix_type": 3})
    opened = [r for r in read_records(d) if r["kind"] == "fdr.opened"][-1]
    assert sorted(opened["refused_files"]) == [
        f"{_LATE_FIFO}: FIFO",
        f"{_LATE_LINK}: symbolic link",
        "img-29991231T235959.999Z-000001-7.jpg: FIFO",
    ]
    assert (d / _LATE_LINK).is_symlink() and os.readlink(d / _LATE_LINK) == "/dev/zero"
    assert sum(1 for r in read_records(d) if r["kind"] == "mavlink.estimate") == 4


def _gdnav_bounded(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """`gdnav ARGS` that must end within 60 s (each hung for 60 s or more over the FIFO)."""
    return subprocess.run(
        [sys.executable, "-m", "gps_denied_onboard.cli", *args],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=cwd,
    )


def test_cli_fdr_summary_names_the_fifo_and_the_link_and_reads_the_rest(tmp_path: Path) -> None:
    """`gdnav fdr summary` ends, reads the real segment and lists the two files it refused."""
    d = _fdr_with_fifo_and_dev_zero(tmp_path)
    proc = _gdnav_bounded(tmp_path, "fdr", "summary", str(d), "--json")
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout)
    assert summary["counts"]["mavlink.estimate"] == 3 and summary["segments"] == 1
    assert f"{_LATE_FIFO}: FIFO" in summary["refused_files"]
    assert f"{_LATE_LINK}: symbolic link" in summary["refused_files"]


def test_cli_fdr_summary_of_a_fifo_named_on_the_command_line_is_refused(tmp_path: Path) -> None:
    """`gdnav fdr summary FIFO` refuses it in one line instead of waiting for a writer."""
    fifo = tmp_path / "fdr-29991231T235959.999Z-000001.jsonl"
    os.mkfifo(fifo)
    line = _one_line(_gdnav_bounded(tmp_path, "fdr", "summary", str(fifo)), 2)
    assert "not a regular file" in line


def test_cli_fdr_boresight_over_a_fifo_and_a_link_ends_in_one_line(tmp_path: Path) -> None:
    """`gdnav fdr boresight` ends with its usual refusal (no run tracked a frame), not a hang."""
    d = _fdr_with_fifo_and_dev_zero(tmp_path)
    line = _one_line(_gdnav_bounded(tmp_path, "fdr", "boresight", str(d)), 3)
    assert "no run tracked any frame" in line


def test_cli_preflight_fails_the_fdr_check_on_a_fifo_naming_it(tmp_path: Path) -> None:
    """`gdnav preflight --offline` ends, and its fdr check fails naming a file that is not regular."""
    _fdr_with_fifo_and_dev_zero(tmp_path)
    proc = _gdnav_bounded(tmp_path, "preflight", "--offline", *_sitl_args(tmp_path))
    assert proc.returncode == 3, proc.stdout + proc.stderr[-3000:]
    fdr_row = next(line for line in proc.stdout.splitlines() if line.lstrip().startswith("fdr"))
    assert "not a regular file" in fdr_row, proc.stdout


def test_daemon_starts_over_an_fdr_with_a_fifo_and_a_dev_zero_link(tmp_path: Path) -> None:
    """`gdnav run` as a real process gets to ready over the FIFO and the link (it hung before ready on
    the FIFO, or ended in a MemoryError on the link) and resumes from the real segment's records."""
    from daemon_harness import build_small_cache, start_daemon, wait_for

    cache = build_small_cache(tmp_path / "map")[1]
    fdr = _fdr_with_fifo_and_dev_zero(tmp_path)
    daemon = start_daemon(tmp_path, cache)
    assert daemon.fdr_dir == fdr
    try:
        assert wait_for(lambda: "daemon.ready" in daemon.log_text() or daemon.proc.poll() is not None, 60.0)
        assert "daemon.ready" in daemon.log_text(), daemon.log_text()[-3000:]
        assert "c13.fdr.file_refused" in daemon.log_text()
    finally:
        code = daemon.stop()
    assert code == 0 and "Traceback" not in daemon.log_text(), daemon.log_text()[-3000:]
