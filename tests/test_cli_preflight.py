"""`gdnav preflight` as a real process: a pass/fail row per check, exit 0/2/3, one `gdnav:` line naming the
first failure; online against a real frame server (TCP) and a real pymavlink autopilot (UDP) on loopback."""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from daemon_harness import REPO, build_small_cache, free_tcp_port, free_udp_port
from gps_denied_onboard.cli_preflight import CHECKS, ONLINE_CHECKS
from registry_models_fixture import registry_models  # noqa: F401 - session fixture

#: The camera size of config/sitl.yaml's intrinsics.
FRAME_W_PX, FRAME_H_PX = 640, 480


@pytest.fixture(scope="module")
def small_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_small_cache(tmp_path_factory.mktemp("cache"))[1]


def _cmd(
    tmp_path: Path, cache: Path, *overrides: str, offline: bool = True, json_out: bool = False
) -> list[str]:
    """`gdnav preflight` on config/sitl.yaml with a port, a camera, a cache and an FDR of the test's own;
    later ``overrides`` win."""
    cmd = [sys.executable, "-m", "gps_denied_onboard.cli", "preflight"]
    cmd += ["--config", str(REPO / "config" / "sitl.yaml"), "--timeout", "10"]
    defaults = (
        f"camera.source=tcp://127.0.0.1:{free_tcp_port()}",
        f"mavlink.url=udpin:127.0.0.1:{free_udp_port()}",
        f"cache.dir={cache}",
        f"fdr.dir={tmp_path / 'fdr'}",
        "matcher.strategy=classical",
    )
    for item in (*defaults, *overrides):
        cmd += ["--set", item]
    return cmd + (["--offline"] if offline else []) + (["--json"] if json_out else [])


def _preflight(
    tmp_path: Path, cache: Path, *overrides: str, json_out: bool = False
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        _cmd(tmp_path, cache, *overrides, json_out=json_out),
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )


def _rows(stdout: str) -> dict[str, tuple[str, str]]:
    """The printed table: check name -> (RESULT, the rest of the line)."""
    lines = stdout.strip().splitlines()
    assert lines[0].split()[:3] == ["check", "result", "checked"], stdout
    rows = {}
    for line in lines[1:]:
        name, result, rest = line.split(None, 2)
        rows[name] = (result, rest)
    assert list(rows) == list(CHECKS), stdout
    return rows


def _failure(proc: subprocess.CompletedProcess[str], code: int, check: str) -> str:
    """Exit ``code``, the table with ``check`` failed, and one `gdnav:` line on stderr naming it (any
    other stderr line is a JSON log record). Returns that row's text."""
    assert proc.returncode == code, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    rows = _rows(proc.stdout)
    assert rows[check][0] == "FAIL", proc.stdout
    plain = [ln for ln in proc.stderr.splitlines() if ln.strip() and not ln.startswith("{")]
    assert len(plain) == 1 and plain[0].startswith(f"gdnav: preflight: {check}: "), proc.stderr
    return rows[check][1]


def test_preflight_offline_passes_without_camera_or_autopilot(tmp_path: Path, small_cache: Path) -> None:
    """With a good profile and cache, --offline passes with nothing listening on the camera or MAVLink
    side; the online checks say they were skipped."""
    proc = _preflight(tmp_path, small_cache)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stderr.strip() == ""
    rows = _rows(proc.stdout)
    for name in ("config", "cache", "calibration", "fdr", "mavlink_port"):
        assert rows[name][0] == "PASS", proc.stdout
    assert "35 tiles" in rows["cache"][1] and "sha256 of every artifact verified" in rows["cache"][1]
    assert rows["models"][0] == "SKIP" and rows["models"][1].endswith("not needed (classical)")
    assert rows["vpr"][0] == "PASS" and "geo_prior" in rows["vpr"][1]
    assert rows["tile_features"][0] == "SKIP" and "classical extracts chips live" in rows["tile_features"][1]
    for name in ONLINE_CHECKS:
        assert rows[name][0] == "SKIP" and rows[name][1].endswith("skipped (--offline)")
    assert not (tmp_path / "fdr").exists(), "the FDR check must not leave the directory behind"


def _serve_autopilot(port: int, stop: threading.Event) -> None:
    from gps_denied_onboard.sitl.autopilot import SimAutopilot

    ap = SimAutopilot(port)
    try:
        while not stop.is_set():
            # Sent before the preflight's socket is bound too: the ICMP "port unreachable" that comes
            # back surfaces as an error on a later send.
            try:
                ap.send_heartbeat()
                ap.send_system_time(time.time())
                ap.poll()  # answers the preflight's TIMESYNC
            except OSError:
                pass
            stop.wait(0.05)
    finally:
        ap.close()


async def _online_preflight(tmp_path: Path, cache: Path) -> tuple[subprocess.CompletedProcess[str], int]:
    from gps_denied_onboard.camera.stream import encode_frame
    from gps_denied_onboard.sitl.frame_server import FrameServer

    server = FrameServer()
    cam_port = await server.start()
    mav_port = free_udp_port()
    stop = threading.Event()
    autopilot = threading.Thread(target=_serve_autopilot, args=(mav_port, stop), daemon=True)
    autopilot.start()
    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, (FRAME_H_PX, FRAME_W_PX, 3), dtype=np.uint8)
    frame = encode_frame(image, seq=1, exposure_time_unix_usec=int(time.time() * 1e6))

    async def camera() -> None:
        await asyncio.wait_for(server.client_connected.wait(), 30)
        await server.send(frame)

    cmd = _cmd(
        tmp_path,
        cache,
        f"camera.source=tcp://127.0.0.1:{cam_port}",
        f"mavlink.url=udpin:127.0.0.1:{mav_port}",
        offline=False,
    )
    sender = asyncio.create_task(camera())
    try:
        proc = await asyncio.create_subprocess_exec(
            *cmd, cwd=tmp_path, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE
        )
        out, err = await asyncio.wait_for(proc.communicate(), 60)
        await sender
    finally:
        sender.cancel()
        stop.set()
        autopilot.join(5)
        await server.close()
    assert proc.returncode is not None
    return subprocess.CompletedProcess(cmd, proc.returncode, out.decode(), err.decode()), server.delivered


def test_preflight_online_passes_with_camera_and_autopilot(tmp_path: Path, small_cache: Path) -> None:
    """Online, a frame server's one 640x480 frame and a SimAutopilot's HEARTBEAT + TIMESYNC answer make
    every check pass, with the measured waits in the table."""
    proc, delivered = asyncio.run(_online_preflight(tmp_path, small_cache))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert delivered == 1
    rows = _rows(proc.stdout)
    assert rows["camera"][0] == "PASS" and f"{FRAME_W_PX}x{FRAME_H_PX} px frame decoded" in rows["camera"][1]
    assert rows["autopilot"][0] == "PASS", proc.stdout
    autopilot = rows["autopilot"][1]
    assert "HEARTBEAT from system 1" in autopilot and "TIMESYNC answered after" in autopilot


def test_preflight_online_without_camera_or_autopilot_exits_3(tmp_path: Path, small_cache: Path) -> None:
    """Online, with nothing serving the camera or the autopilot, both checks fail after --timeout."""
    cmd = _cmd(tmp_path, small_cache, offline=False)
    cmd[cmd.index("--timeout") + 1] = "1"
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=60, cwd=tmp_path)
    row = _failure(proc, 3, "camera")
    assert "no frame within 1 s" in row
    rows = _rows(proc.stdout)
    assert rows["autopilot"][0] == "FAIL" and "no HEARTBEAT from system 1 within 1 s" in rows["autopilot"][1]
    assert "(and 1 more failed check(s))" in proc.stderr


def test_preflight_tampered_cache_exits_3(tmp_path: Path, small_cache: Path) -> None:
    """One flipped byte in the middle of the cache's mosaic fails the cache row (sha256 mismatch) with
    exit 3, though cache.verify_hashes is off (preflight reads every byte whatever the profile says: the
    daemon's start does not); the other checks still run."""
    from gps_denied_onboard.components.c10_cache_build.manifest import CacheManifest

    cache = tmp_path / "cache"
    shutil.copytree(small_cache, cache)
    mosaic = cache / CacheManifest.load(cache).mosaic_name
    data = bytearray(mosaic.read_bytes())
    data[len(data) // 2] ^= 0xFF
    mosaic.write_bytes(bytes(data))
    row = _failure(_preflight(tmp_path, cache, "cache.verify_hashes=false"), 3, "cache")
    assert str(cache) in row and mosaic.name in row and "sha256 mismatch" in row, row
    assert _rows(_preflight(tmp_path, cache).stdout)["fdr"][0] == "PASS"


def test_preflight_taken_udp_port_exits_3(tmp_path: Path, small_cache: Path) -> None:
    """A udpin port that another socket holds (bound with SO_REUSEADDR, as pymavlink binds) fails the
    mavlink_port row with exit 3."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other:
        other.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        other.bind(("127.0.0.1", 0))
        port = other.getsockname()[1]
        row = _failure(
            _preflight(tmp_path, small_cache, f"mavlink.url=udpin:127.0.0.1:{port}"), 3, "mavlink_port"
        )
    assert f"UDP port {port}" in row and "already bound" in row


def test_preflight_fdr_dir_with_missing_parent_exits_3(tmp_path: Path, small_cache: Path) -> None:
    """An fdr.dir whose parent does not exist (a mistyped path) fails the fdr row with exit 3."""
    fdr = tmp_path / "no-such-dir" / "fdr"
    row = _failure(_preflight(tmp_path, small_cache, f"fdr.dir={fdr}"), 3, "fdr")
    assert f"nor does its parent {fdr.parent}" in row
    assert not fdr.parent.exists()


def test_preflight_fdr_dir_that_is_a_file_exits_3(tmp_path: Path, small_cache: Path) -> None:
    """An fdr.dir that is a regular file fails the fdr row with exit 3."""
    fdr = tmp_path / "fdr-file"
    fdr.write_text("")
    row = _failure(_preflight(tmp_path, small_cache, f"fdr.dir={fdr}"), 3, "fdr")
    assert "is not a directory" in row


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a mode 0500 directory")
def test_preflight_unwritable_fdr_dir_exits_3(tmp_path: Path, small_cache: Path) -> None:
    """An FDR directory this user cannot write in fails the fdr row with exit 3."""
    fdr = tmp_path / "fdr"
    fdr.mkdir(mode=0o500)
    try:
        row = _failure(_preflight(tmp_path, small_cache, f"fdr.dir={fdr}"), 3, "fdr")
    finally:
        fdr.chmod(0o700)
    assert "cannot write" in row


def test_preflight_fdr_without_room_for_max_bytes_exits_3(tmp_path: Path, small_cache: Path) -> None:
    """An fdr.max_bytes larger than the file system's free space fails with how much is missing."""
    row = _failure(_preflight(tmp_path, small_cache, f"fdr.max_bytes={1 << 60}"), 3, "fdr")
    assert "missing" in row and "needed" in row


def test_preflight_learned_matcher_without_model_manifest_exits_3(tmp_path: Path, small_cache: Path) -> None:
    """A learned strategy whose model directory has no manifest fails the models row with exit 3."""
    models = tmp_path / "models"
    models.mkdir()
    proc = _preflight(
        tmp_path, small_cache, "matcher.strategy=aliked_lightglue", f"matcher.model_dir={models}"
    )
    row = _failure(proc, 3, "models")
    assert "matcher.model_dir" in row


def test_preflight_vlad_without_its_index_fails_the_vpr_row(tmp_path: Path, small_cache: Path) -> None:
    """The cache has no VLAD index (it was never built with `gdnav cache vpr`): the daemon would refuse
    to start, so the preflight's vpr row fails with exit 3 and says how to build it."""
    row = _failure(_preflight(tmp_path, small_cache, "vpr.strategy=vlad"), 3, "vpr")
    assert "gdnav cache vpr" in row, row


@pytest.mark.slow
def test_preflight_reports_xfeat_tile_features_absent_then_built(
    tmp_path: Path,
    small_cache: Path,
    registry_models: Callable[[str], Path],  # noqa: F811
) -> None:
    """XFeat from the registry export: without precomputed tile features the row passes under ``auto``
    and says every chip is extracted live, fails under ``require``; after `gdnav cache features` it
    passes with every tile's features verified."""
    model_dir = registry_models("xfeat")
    cache = tmp_path / "cache"
    shutil.copytree(small_cache, cache)
    xfeat = ("matcher.strategy=xfeat", f"matcher.model_dir={model_dir}", f"cache.dir={cache}")
    rows = _rows(_preflight(tmp_path, cache, *xfeat).stdout)
    assert rows["models"][0] == "PASS", rows
    assert rows["tile_features"][0] == "PASS" and "extracted live" in rows["tile_features"][1], rows
    row = _failure(_preflight(tmp_path, cache, *xfeat, "matcher.tile_features=require"), 3, "tile_features")
    assert "gdnav cache features" in row or "no precomputed" in row or "absent" in row, row

    build = [sys.executable, "-m", "gps_denied_onboard.cli", "cache", "features", "--quiet"]
    build += ["--config", str(REPO / "config" / "sitl.yaml"), "--cache", str(cache)]
    for item in xfeat:
        build += ["--set", item]
    done = subprocess.run(build, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    proc = _preflight(tmp_path, cache, *xfeat, "matcher.tile_features=require")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows = _rows(proc.stdout)
    assert rows["tile_features"][0] == "PASS", rows
    assert "35 tiles of precomputed features, sha256 verified" in rows["tile_features"][1], rows


def test_preflight_bad_config_exits_2(tmp_path: Path, small_cache: Path) -> None:
    """An invalid profile exits 2 with the config row failed, naming the key, and nothing else checked."""
    proc = _preflight(tmp_path, small_cache, "mavlink.url=udpin:nohostport")
    row = _failure(proc, 2, "config")
    assert "mavlink.url" in row
    rows = _rows(proc.stdout)
    assert all(rows[name][0] == "SKIP" for name in CHECKS[1:]), proc.stdout


def test_preflight_json_lists_every_check(tmp_path: Path, small_cache: Path) -> None:
    """--json prints one object with every check in order, its status, what it checked and the detail."""
    proc = _preflight(tmp_path, small_cache, json_out=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    report = json.loads(proc.stdout)
    assert report["ok"] is True and report["exit_code"] == 0
    assert [c["name"] for c in report["checks"]] == list(CHECKS)
    for check in report["checks"]:
        assert check["status"] in {"pass", "skip"} and check["checked"] and check["detail"]
        assert isinstance(check["seconds"], float | int) and check["seconds"] >= 0
    assert {c["name"]: c["status"] for c in report["checks"]}["cache"] == "pass"


def test_preflight_json_on_failure_still_lists_every_check(tmp_path: Path, small_cache: Path) -> None:
    """--json with a failing check: exit 3, ok false, and the failed row among all of them."""
    fdr = tmp_path / "no-such-dir" / "fdr"
    proc = _preflight(tmp_path, small_cache, f"fdr.dir={fdr}", json_out=True)
    assert proc.returncode == 3, proc.stdout + proc.stderr
    report = json.loads(proc.stdout)
    assert report["ok"] is False and report["exit_code"] == 3
    statuses = {c["name"]: c["status"] for c in report["checks"]}
    assert list(statuses) == list(CHECKS) and statuses["fdr"] == "fail"


def _map_centre(cache: Path) -> tuple[float, float]:
    west, south, east, north = json.loads((cache / "manifest.json").read_text())["bbox_lonlat"]
    return (south + north) / 2.0, (west + east) / 2.0


def test_preflight_start_point_off_the_map_exits_3(tmp_path: Path, small_cache: Path) -> None:
    """A configured start point thousands of km off the map fails the start_point row (it passed)."""
    proc = _preflight(tmp_path, small_cache, "init.lat_deg=10.0", "init.lon_deg=10.0")
    row = _failure(proc, 3, "start_point")
    assert "init.lat_deg/lon_deg" in row and "km off the map" in row


def test_preflight_start_point_on_the_map_passes(tmp_path: Path, small_cache: Path) -> None:
    """The map's centre as the start point passes; with no start point and --offline the row is skipped
    (HOME_POSITION comes from the autopilot)."""
    lat, lon = _map_centre(small_cache)
    proc = _preflight(tmp_path, small_cache, f"init.lat_deg={lat}", f"init.lon_deg={lon}")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    row = _rows(proc.stdout)["start_point"]
    assert row[0] == "PASS" and row[1].endswith(f"init.lat_deg/lon_deg {lat:.6f}, {lon:.6f}: on the map")
    rows = _rows(_preflight(tmp_path, small_cache).stdout)
    assert rows["start_point"][0] == "SKIP" and "HOME_POSITION" in rows["start_point"][1]


def _fdr_segment(fdr: Path, *extra: bytes) -> None:
    from gps_denied_onboard.components.c13_fdr import FlightDataRecorder

    with FlightDataRecorder(fdr, max_bytes=1 << 20, segment_bytes=1 << 16) as rec:
        rec.record("pipeline.frame", {"frame_seq": 1})
    with sorted(fdr.glob("fdr-*.jsonl"))[-1].open("ab") as fh:
        for line in extra:
            fh.write(line)


def test_preflight_fdr_with_a_corrupt_line_exits_3(tmp_path: Path, small_cache: Path) -> None:
    """A deeply nested FDR line (it crashed `gdnav run` at every start, and preflight passed it) fails
    the fdr row, naming the segment and line."""
    fdr = tmp_path / "fdr"
    _fdr_segment(fdr, b'{"t_unix_s":1.0,"kind":"x","v":' + b"[" * 50_000 + b"]" * 50_000 + b"}\n")
    row = _failure(_preflight(tmp_path, small_cache, f"fdr.dir={fdr}"), 3, "fdr")
    assert "never writes" in row and "nested too deeply" in row and ".jsonl:4" in row


def test_preflight_fdr_with_a_torn_line_passes(tmp_path: Path, small_cache: Path) -> None:
    """A line torn by a crash is what the recorder expects: the fdr row passes and counts it."""
    fdr = tmp_path / "fdr"
    _fdr_segment(fdr, b'{"t_unix_s":1.0,"kind":"mavlink.est\n')
    proc = _preflight(tmp_path, small_cache, f"fdr.dir={fdr}")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    row = _rows(proc.stdout)["fdr"]
    assert row[0] == "PASS" and "3 records in 1 segment(s) read, 1 torn line(s) skipped" in row[1]


def test_preflight_fdr_segment_that_cannot_be_read_exits_3(tmp_path: Path, small_cache: Path) -> None:
    """A segment the user cannot read (here: a directory under a segment's name) fails the fdr row."""
    fdr = tmp_path / "fdr"
    _fdr_segment(fdr)
    (fdr / "fdr-20990101T000000.000Z-000001.jsonl").mkdir()
    row = _failure(_preflight(tmp_path, small_cache, f"fdr.dir={fdr}"), 3, "fdr")
    assert "fdr-20990101T000000.000Z-000001.jsonl" in row and "cannot be read" in row


def test_preflight_misspelt_rerank_strategy_fails_the_config_row(tmp_path: Path, small_cache: Path) -> None:
    """A rerank.strategy `run` refuses fails preflight's config row too (exit 3, as `run`)."""
    row = _failure(_preflight(tmp_path, small_cache, "rerank.strategy=inlier"), 3, "config")
    assert "rerank.strategy" in row and "'inlier'" in row


def test_preflight_checks_the_area_correlations_fields_where_auto_would_fly_them(
    tmp_path: Path, small_cache: Path
) -> None:
    """auto on a CPU with the cache's calibrated orientation fields flies the area rung: preflight opens and
    verifies them as the start does and says what the calibration found; fields damaged on disk fail the
    check naming the file; a cache without fields skips it."""
    import shutil

    from gps_denied_onboard.components.c10_cache_build.map_fields import build_map_fields, field_file_names

    auto = ("matcher.strategy=auto", "matcher.model_dir=null")
    rows = _rows(_preflight(tmp_path, small_cache, *auto).stdout)
    assert rows["map_fields"][0] == "SKIP" and "not used" in rows["map_fields"][1], rows
    cache = tmp_path / "with_fields"
    shutil.copytree(small_cache, cache)
    build_map_fields(cache, progress=False)
    proc = _preflight(tmp_path, cache, *auto)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    row = _rows(proc.stdout)["map_fields"]
    assert row[0] == "PASS" and "sha256 verified" in row[1] and "level 1" in row[1], row
    damaged = cache / field_file_names(2)[0]
    data = bytearray(damaged.read_bytes())
    data[-10] ^= 0xFF
    damaged.write_bytes(bytes(data))
    text = _failure(_preflight(tmp_path, cache, *auto), 3, "map_fields")
    assert "field_l2.npy" in text and "sha256" in text, text
