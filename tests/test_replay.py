"""``gdnav replay``: an FDR of a real SITL flight replayed exactly; photos + CSV (snowpeak); a real .tlog
written with pymavlink plus rendered frames; and the refusals (exit 2/3, one line)."""

from __future__ import annotations

import csv
import json
import math
import shutil
import struct
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml

from daemon_harness import build_small_cache, fly_small_map
from gps_denied_onboard.cli import main
from gps_denied_onboard.components.c13_fdr import list_segments

ROOT = Path(__file__).resolve().parents[1]
SITL_CONFIG = ROOT / "config" / "sitl.yaml"
SNOWPEAK = Path("/work/shared/data/snowpeak_ebee")
#: Ground height of the snowpeak site: the median altitude of the eBee's own track (snowpea1.kml) while it
#: stood at the launch point, 06:15-06:19 UTC (121.1-124.2 m over 2410 points).
SNOWPEAK_GROUND_AMSL_M = 122.7


def _replay(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(["replay", *argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def _assert_one_line_refusal(code: int, err: str, expected_code: int, *needles: str) -> None:
    assert code == expected_code, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("gdnav: "), err
    assert "Traceback" not in err
    for n in needles:
        assert n in lines[0], lines[0]


# -- an FDR of a SITL flight, replayed ---------------------------------------------------------------


@pytest.fixture(scope="module")
def sitl_flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The smoke flight at 10 Hz (so the fix path is fused behind newer frames and rewinds the axis),
    the daemon as its own process, recording every frame as PNG."""
    from gps_denied_onboard.sitl.scenario import BUILTIN_SCENARIOS_DIR

    root = tmp_path_factory.mktemp("replay_sitl")
    smoke = yaml.safe_load((BUILTIN_SCENARIOS_DIR / "smoke.yaml").read_text())
    scenario = root / "smoke10.yaml"
    scenario.write_text(yaml.safe_dump({**smoke, "name": "smoke10", "frame_rate_hz": 10.0}))
    fly_small_map(
        root,
        str(scenario),
        overrides=("matcher.strategy=classical", "fdr.frame_jpeg_every_n=1", "fdr.frames_format=png"),
    )
    return root


def _records(fdr: Path) -> list[dict[str, Any]]:
    out = []
    for seg in list_segments(fdr):
        out += [json.loads(line) for line in seg.read_text().splitlines() if line.strip()]
    return out


@pytest.mark.sitl
def test_replay_sitl_fdr_reproduces_every_frame_exactly(
    sitl_flight: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A SITL flight (real daemon process, UDP/TCP) replayed from its FDR with the recorded config: every
    per-frame estimate equals the recorded one, and the SITL metrics are reported against the truth."""
    fdr = sitl_flight / "work" / "fdr"
    recs = _records(fdr)
    units = [r for r in recs if r["kind"] == "estimator.input"]
    assert any(u["accel"] for u in units), "the recording must exercise the IMU-driven prediction"
    report_path = sitl_flight / "replay.json"
    records_path = sitl_flight / "replay_records.jsonl"
    code, out, err = _replay(
        [
            "--fdr",
            str(fdr),
            "--truth",
            str(sitl_flight / "out" / "report.json"),
            "--report",
            str(report_path),
            "--records",
            str(records_path),
        ],
        capsys,
    )
    assert code == 0, err
    # The replay's own records (--records): its fix attempts are the flight's, verdict for verdict.
    replayed = [json.loads(line) for line in records_path.read_text().splitlines()]
    recorded_config = next(r for r in recs if r["kind"] == "daemon.config")["config"]
    assert replayed[0]["kind"] == "daemon.config" and replayed[0]["config"] == recorded_config
    flown = {r["exposure_time_unix_usec"]: r for r in recs if r["kind"] == "pipeline.fix"}
    again = {r["exposure_time_unix_usec"]: r for r in replayed if r["kind"] == "pipeline.fix"}
    assert again.keys() == flown.keys() and flown
    verdict = ("fix_accepted", "no_fix_reason")
    assert all([again[t][k] for k in verdict] == [r[k] for k in verdict] for t, r in flown.items())
    report = json.loads(report_path.read_text())
    rep = report["reproduction"]
    assert report["mode"] == "exact" and report["divergence"] is None, report
    assert rep["frames_recorded"] >= 30
    assert rep["all_equal"] and rep["complete"], rep["first_difference"]
    assert rep["max_position_difference_m"] == 0.0
    assert report["journal"]["units_replayed"] == report["journal"]["units_total"] == len(units)
    m = report["metrics"]
    assert m["availability"] >= 0.9 and m["consistency"]["beyond_3sigma"] == 0, m
    assert m["analysis"]["accepted_fixes_beyond_3sigma"] == 0
    # Every attempt is listed, and every accepted one is scored within its own 3 sigma.
    attempts = m["analysis"]["fix_attempts"]
    assert len(attempts) == m["analysis"]["fdr_fix_attempts"] == report["fix"]["attempts"]
    accepted = [a for a in attempts if a["accepted"]]
    assert len(accepted) == report["fix"]["accepted"] >= 1
    assert all(a["error_sigma"] <= 3.0 and a["inliers"] >= 1 for a in accepted), accepted
    assert "reproduction:" in out and "vs truth:" in out


@pytest.mark.sitl
def test_replay_sitl_fdr_detects_a_changed_imu_answer(
    sitl_flight: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The comparison can fail: one recorded IMU answer nudged by 0.5 m/s^2 changes the replayed estimates
    (and a replay without the journal differs too), and the report says from which frame."""
    src = sitl_flight / "work" / "fdr"
    copy = sitl_flight / "fdr_edited"
    shutil.copytree(src, copy, dirs_exist_ok=True)
    seg = list_segments(copy)[0]
    lines = seg.read_text().splitlines()
    for i, line in enumerate(lines):
        rec = json.loads(line)
        if (
            rec["kind"] == "estimator.input"
            and rec["unit"] == "track"
            and rec["accel"]
            and rec["accel"][0][2]
        ):
            rec["accel"][0][2][0] += 0.5
            lines[i] = json.dumps(rec, separators=(",", ":"))
            break
    else:
        pytest.fail("no IMU answer to edit")
    seg.write_text("\n".join(lines) + "\n")
    code, _, err = _replay(["--fdr", str(copy), "--report", str(sitl_flight / "edited.json")], capsys)
    assert code == 0, err
    edited = json.loads((sitl_flight / "edited.json").read_text())["reproduction"]
    assert not edited["all_equal"] and edited["first_difference"] is not None
    code, _, err = _replay(
        ["--fdr", str(src), "--sequential", "--report", str(sitl_flight / "seq.json")], capsys
    )
    assert code == 0, err
    seq = json.loads((sitl_flight / "seq.json").read_text())
    assert seq["mode"] == "sequential" and not seq["reproduction"]["all_equal"]


@pytest.mark.sitl
def test_replay_sitl_fdr_with_missing_images_says_how_far_it_is_exact(
    sitl_flight: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The last frame's image lost (a kill between its record and its image): exact up to it, and the
    report says where it stopped. The first frame's image lost (the images budget): frame by frame, and
    the report says why it is not exact."""
    from gps_denied_onboard.components.c13_fdr.recorder import list_images

    for which, expect in (("last", "exact"), ("first", "sequential")):
        copy = sitl_flight / f"fdr_no_{which}"
        shutil.copytree(sitl_flight / "work" / "fdr", copy, dirs_exist_ok=True)
        images = list_images(copy)
        (images[-1] if which == "last" else images[0]).unlink()
        out = sitl_flight / f"no_{which}.json"
        code, _, err = _replay(["--fdr", str(copy), "--report", str(out)], capsys)
        assert code == 0, err
        report = json.loads(out.read_text())
        assert report["mode"] == expect, report["not_exact_because"]
        rep = report["reproduction"]
        if which == "last":
            assert rep["all_equal"] and not rep["complete"]
            assert rep["frames_replayed"] == rep["frames_recorded"] - 1
            assert "no image" in report["stopped"]
        else:
            assert any("first frame has no image" in r for r in report["not_exact_because"])


@pytest.mark.sitl
def test_replay_whose_first_frames_lost_their_images_starts_from_the_runs_estimate_there(
    sitl_flight: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The images budget deleted the first half of the run's images: the replay starts at the first frame
    with one, from the run's own estimate there (not the start prior, given where the vehicle no longer
    is), and everything it sends with fix_type 3 stays within its stated accuracy against the truth."""
    from gps_denied_onboard.components.c13_fdr.recorder import list_images

    copy = sitl_flight / "fdr_no_first_half"
    shutil.copytree(sitl_flight / "work" / "fdr", copy, dirs_exist_ok=True)
    images = list_images(copy)
    for image in images[: len(images) // 2]:
        image.unlink()
    out = sitl_flight / "no_first_half.json"
    code, _, err = _replay(
        ["--fdr", str(copy), "--truth", str(sitl_flight / "out" / "report.json"), "--report", str(out)],
        capsys,
    )
    assert code == 0, err
    report = json.loads(out.read_text())
    first = report["per_frame"][0]
    recorded = next(
        r for r in _records(copy) if r.get("kind") == "pipeline.frame" and r["frame_seq"] == first["seq"]
    )
    assert report["prior"]["source"] == "fdr_estimate"
    assert (report["prior"]["lat_deg"], report["prior"]["sigma_m"]) == (
        recorded["lat_deg"],
        recorded["horiz_sigma_m"],
    )
    assert any(f"starts at frame {first['seq']}" in n for n in report["notes"]), report["notes"]
    m = report["metrics"]
    assert m["consistency"]["beyond_3sigma"] == 0 and m["availability"] >= 0.9, m["consistency"]


@pytest.mark.sitl
def test_replay_sitl_fdr_refuses_a_missing_cache_and_a_bad_override(
    sitl_flight: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The recorded config with its map cache gone: exit 3 naming the cache; an unknown override: exit 2;
    a run index the FDR does not have: exit 2. One line each."""
    fdr = str(sitl_flight / "work" / "fdr")
    code, _, err = _replay(["--fdr", fdr, "--set", f"cache.dir={sitl_flight / 'gone'}"], capsys)
    _assert_one_line_refusal(code, err, 3, "cache")
    code, _, err = _replay(["--fdr", fdr, "--set", "estimator.no_such_key=1"], capsys)
    _assert_one_line_refusal(code, err, 2, "no_such_key")
    code, _, err = _replay(["--fdr", fdr, "--run", "7"], capsys)
    _assert_one_line_refusal(code, err, 2, "--run 7")


# -- photos + CSV: the snowpeak eBee flight -----------------------------------------------------------


@pytest.mark.realdata
def test_replay_snowpeak_photos_vo_only_never_claims_a_fix(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Three consecutive real eBee photos (4 s apart) with the CSV's positions as truth, no map: the replay
    runs end to end, measures VO between them, anchors nothing and says so; VO's displacement is within
    35 % of the GPS truth's (calibration from EXIF, heights from the launch point's altitude)."""
    if not (SNOWPEAK / "present_images_pose.csv").is_file():
        pytest.skip(f"{SNOWPEAK} is absent")
    rows = list(csv.DictReader((SNOWPEAK / "present_images_pose.csv").read_text().splitlines()))
    subset = [r for r in rows if r["fileName"] in {"IMG_2280.JPG", "IMG_2281.JPG", "IMG_2282.JPG"}]
    assert len(subset) == 3
    csv_path = tmp_path / "pose.csv"
    with csv_path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(subset)
    report_path = tmp_path / "snowpeak.json"
    code, out, err = _replay(
        [
            "--images", str(SNOWPEAK / "img"), "--csv", str(csv_path),
            "--ground-alt-amsl", str(SNOWPEAK_GROUND_AMSL_M),
            "--calibration", "exif", "--image-scale", "0.25",
            "--vo-max-gap-s", "5", "--report", str(report_path),
        ],
        capsys,
    )  # fmt: skip
    assert code == 0, err
    report = json.loads(report_path.read_text())
    assert report["frames_tracked"] == 3 and report["map"] is None
    assert report["fix"]["accepted"] == 0 and report["anchored_frames"] == 0
    assert report["fix"]["no_fix_reasons"] == {"no_map": 3}
    assert "satellite_anchored" not in report["provenance_counts"]
    assert report["calibration"]["width_px"] == 1152 and 780 < report["calibration"]["fx_px"] < 830
    vo = report["vo_intervals"]
    assert len(vo) == 2, report["vo"]
    for v in vo:
        assert abs(v["vo_m"] - v["truth_m"]) <= 0.35 * v["truth_m"], v
    assert "fix path: not run: no map cache" in out


# -- a MAVLink telemetry log plus frames --------------------------------------------------------------


def _write_tlog(path: Path, samples: list[tuple[float, Any]], t0_unix_s: float) -> None:
    """A real .tlog as MAVProxy writes it: each packet preceded by its 64-bit big-endian Unix time in us."""
    from pymavlink.dialects.v20 import ardupilotmega as mav2

    class _Sink:
        def write(self, _b: bytes) -> None:  # pack() needs a file; the bytes are taken from pack()
            pass

    mav = mav2.MAVLink(_Sink(), srcSystem=1, srcComponent=1)
    with path.open("wb") as fh:
        for t, msg in sorted(samples, key=lambda s: s[0]):
            fh.write(struct.pack(">Q", round(t * 1e6)) + msg.pack(mav))
    assert path.stat().st_size > 0


def _write_bin(path: Path, states: list[tuple[float, Any]]) -> None:
    """A real ArduPilot DataFlash (.bin) log as pymavlink's DFReader reads it: FMT records, a GPS record
    with the GPS week and time of week (the log's clock), ATT (degrees) and POS (degrees, RelHomeAlt)."""
    head = b"\xa3\x95"
    sizes = {"Q": 8, "f": 4, "L": 4, "I": 4, "H": 2}

    def fmt(type_id: int, name: str, form: str, cols: str) -> bytes:
        length = 3 + sum(sizes[c] for c in form)
        return (
            head
            + bytes([128])
            + struct.pack("<BB4s16s64s", type_id, length, name.encode(), form.encode(), cols.encode())
        )

    def rec(type_id: int, form: str, *vals: Any) -> bytes:
        return head + bytes([type_id]) + struct.pack("<" + form.replace("L", "i"), *vals)

    t_first = states[0][0]
    gps_epoch_unix_s = 315964800  # 1980-01-06; DataFlash GPS time runs 18 leap seconds ahead of UTC
    gps_s = t_first + 18 - gps_epoch_unix_s
    with path.open("wb") as fh:
        fh.write(fmt(130, "GPS", "QIH", "TimeUS,GMS,GWk"))
        fh.write(fmt(131, "ATT", "Qfff", "TimeUS,Roll,Pitch,Yaw"))
        fh.write(fmt(132, "POS", "QLLf", "TimeUS,Lat,Lng,RelHomeAlt"))
        fh.write(rec(130, "QIH", 1_000_000, round((gps_s % 604800) * 1000), int(gps_s // 604800)))
        for i, (t, s) in enumerate(states):
            us = 1_000_000 + round((t - t_first) * 1e6)
            yaw_deg = math.degrees(s.yaw_rad) % 360.0
            fh.write(rec(131, "Qfff", us, math.degrees(s.roll_rad), math.degrees(s.pitch_rad), yaw_deg))
            if i % 5 == 0:
                fh.write(rec(132, "QLLf", us, round(s.lat_deg * 1e7), round(s.lon_deg * 1e7), s.alt_agl_m))


@pytest.mark.parametrize("log_format", ["tlog", "bin", "tlog+video"])
def test_replay_telemetry_log_with_rendered_frames_anchors_on_the_map(
    log_format: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A log (a .tlog written with pymavlink: SYSTEM_TIME, ATTITUDE, GLOBAL_POSITION_INT; or a DataFlash
    .bin: ATT, POS) and frames rendered along the same flight over a real cache (an image directory, or an
    MJPEG video at 3 fps): the replay reads the log through pymavlink, interpolates attitude and height to
    each frame, anchors on the map, and scores against the log's positions."""
    from pymavlink.dialects.v20 import ardupilotmega as mav2

    from gps_denied_onboard.camera.types import CameraCalibration
    from gps_denied_onboard.sitl.render import MapRenderer
    from gps_denied_onboard.sitl.scenario import load_scenario

    map_path, cache = build_small_cache(tmp_path)
    cfg = yaml.safe_load(SITL_CONFIG.read_text())
    ground = float(cfg["terrain"]["ground_alt_amsl_m"])
    renderer = MapRenderer(map_path)
    traj = load_scenario("smoke").resolve(renderer.bbox_lonlat, ground)
    calib = CameraCalibration.from_hfov(640, 480, 70.0)
    t0, boot0 = 1_700_000_000.0, 1_699_999_000.0
    frames_dir = tmp_path / "frames"
    frames_dir.mkdir()
    times = []
    for k in range(12):
        t_s = 1.0 + k / 3.0
        s = traj.truth_at(t_s)
        img = renderer.render(calib, s.lat_deg, s.lon_deg, s.alt_agl_m, s.attitude)
        name = f"f{k:03d}.png"
        assert cv2.imwrite(str(frames_dir / name), img)
        times.append({"file": name, "time_unix_s": f"{t0 + t_s:.6f}"})
    if log_format == "tlog+video":
        video = tmp_path / "nav.avi"
        writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 3.0, (640, 480))
        assert writer.isOpened()
        for row in times:
            writer.write(cv2.imread(str(frames_dir / row["file"])))
        writer.release()
    times_csv = tmp_path / "frame_times.csv"
    with times_csv.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["file", "time_unix_s"])
        w.writeheader()
        w.writerows(times)
    states = [(t0 + i / 50.0, traj.truth_at(i / 50.0)) for i in range(6 * 50)]
    log = tmp_path / f"flight.{log_format.split('+')[0]}"
    if log_format == "bin":
        _write_bin(log, states)
    else:
        samples: list[tuple[float, Any]] = []
        for i, (t, s) in enumerate(states):
            boot_ms = round((t - boot0) * 1e3)
            samples.append(
                (t, mav2.MAVLink_attitude_message(boot_ms, s.roll_rad, s.pitch_rad, s.yaw_rad, 0, 0, 0))
            )
            if i % 5 == 0:
                samples.append(
                    (
                        t,
                        mav2.MAVLink_global_position_int_message(
                            boot_ms, round(s.lat_deg * 1e7), round(s.lon_deg * 1e7),
                            round(s.alt_amsl_m * 1e3), round(s.alt_agl_m * 1e3), 0, 0, 0, 65535,
                        ),
                    )
                )  # fmt: skip
            if i % 50 == 0:
                samples.append((t, mav2.MAVLink_system_time_message(round(t * 1e6), boot_ms)))
        _write_tlog(log, samples, t0)
    report_path = tmp_path / "log.json"
    code, out, err = _replay(
        [
            "--tlog", str(log),
            *(
                ["--video", str(video), "--video-start-unix-s", f"{t0 + 1.0:.6f}"]
                if log_format == "tlog+video"
                else ["--images", str(frames_dir), "--frame-times", str(times_csv)]
            ),
            "--config", str(SITL_CONFIG), "--cache", str(cache), "--set", "matcher.strategy=classical",
            "--report", str(report_path),
        ],
        capsys,
    )  # fmt: skip
    assert code == 0, err
    report = json.loads(report_path.read_text())
    assert report["frames_tracked"] == 12 and report["source"].startswith("tlog:")
    assert report["fix"]["accepted"] >= 8, report["fix"]
    m = report["metrics"]
    assert m["horizontal_error_m"]["p95"] is not None and m["horizontal_error_m"]["p95"] < 5.0, m
    assert m["consistency"]["beyond_3sigma"] == 0 and m["analysis"]["accepted_fixes_beyond_3sigma"] == 0
    # attitude and height came from the log, interpolated to each frame: VO measured every interval
    assert report["vo"]["intervals_measured"] == 11, report["vo"]
    assert "anchored frames:" in out


# -- refusals ---------------------------------------------------------------------------------------


def test_replay_refuses_no_input_and_two_inputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Exactly one input: none or two is exit 2, one line."""
    code, _, err = _replay([], capsys)
    _assert_one_line_refusal(code, err, 2, "exactly one of")
    code, _, err = _replay(["--fdr", str(tmp_path), "--tlog", str(tmp_path / "x.tlog")], capsys)
    _assert_one_line_refusal(code, err, 2, "exactly one of")
    code, _, err = _replay(["--fdr", str(tmp_path), "--image-scale", "0"], capsys)
    _assert_one_line_refusal(code, err, 2, "--image-scale")


def test_replay_refuses_missing_or_empty_fdr(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A missing FDR directory, one without segments, and a run without frame images: exit 3, naming it."""
    code, _, err = _replay(["--fdr", str(tmp_path / "nope")], capsys)
    _assert_one_line_refusal(code, err, 3, "nope")
    code, _, err = _replay(["--fdr", str(tmp_path)], capsys)
    _assert_one_line_refusal(code, err, 3, "no FDR segments")
    from gps_denied_onboard.components.c13_fdr import FlightDataRecorder

    fdr_dir = tmp_path / "fdr"
    with FlightDataRecorder(fdr_dir, max_bytes=1 << 20, segment_bytes=1 << 16) as fdr:
        fdr.record(
            "pipeline.frame",
            {"frame_seq": 1, "exposure_time_unix_usec": 1, "attitude_rad": None, "alt_agl_m": None},
        )
    code, _, err = _replay(["--fdr", str(fdr_dir)], capsys)
    _assert_one_line_refusal(code, err, 3, "none of their images", "frame_jpeg_every_n")


def test_replay_refuses_bad_csv(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A CSV without a position column, a row naming a missing image, no height: exit 3 naming the file;
    --csv without --images: exit 2."""
    images = tmp_path / "img"
    images.mkdir()
    cv2.imwrite(str(images / "a.png"), np.zeros((48, 64, 3), np.uint8))
    bad = tmp_path / "bad.csv"
    bad.write_text("file,lon\na.png,8.5\n")
    code, _, err = _replay(["--images", str(images), "--csv", str(bad)], capsys)
    _assert_one_line_refusal(code, err, 3, "bad.csv", "no lat column")
    missing = tmp_path / "missing.csv"
    missing.write_text("file,lat,lon,alt_agl_m,time_unix_s\nb.png,47.0,8.5,100,1\n")
    code, _, err = _replay(["--images", str(images), "--csv", str(missing)], capsys)
    _assert_one_line_refusal(code, err, 3, "missing.csv:2", "b.png")
    no_height = tmp_path / "no_height.csv"
    no_height.write_text("file,lat,lon,time_unix_s\na.png,47.0,8.5,1\n")
    code, _, err = _replay(["--images", str(images), "--csv", str(no_height)], capsys)
    _assert_one_line_refusal(code, err, 3, "no height above ground")
    code, _, err = _replay(["--csv", str(missing)], capsys)
    _assert_one_line_refusal(code, err, 2, "--images")


def test_replay_refuses_a_log_without_telemetry(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A .tlog with no ATTITUDE/GLOBAL_POSITION_INT (here: garbage bytes, then a HEARTBEAT-only log): exit
    3 naming what is missing."""
    from pymavlink.dialects.v20 import ardupilotmega as mav2

    images = tmp_path / "img"
    images.mkdir()
    cv2.imwrite(str(images / "a.png"), np.zeros((48, 64, 3), np.uint8))
    garbage = tmp_path / "garbage.tlog"
    garbage.write_bytes(bytes(range(256)) * 8)
    code, _, err = _replay(["--tlog", str(garbage), "--images", str(images)], capsys)
    _assert_one_line_refusal(code, err, 3, "garbage.tlog", "ATTITUDE")
    hb = tmp_path / "hb.tlog"
    _write_tlog(hb, [(1.7e9 + i, mav2.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3)) for i in range(5)], 1.7e9)
    code, _, err = _replay(["--tlog", str(hb), "--images", str(images)], capsys)
    _assert_one_line_refusal(code, err, 3, "hb.tlog", "found 0 and 0")
    code, _, err = _replay(["--tlog", str(hb)], capsys)
    _assert_one_line_refusal(code, err, 2, "--images DIR or --video FILE")
