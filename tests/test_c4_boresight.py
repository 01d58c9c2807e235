"""The camera mount (``CameraMount``) and the boresight a flight measures (``c4_pose/boresight.py``).

The ground-tilt geometry is the real C1 function on exact projections of flat ground, as in
``test_c1_ground_tilt.py``: a camera mounted off nadir shows, against the autopilot's attitude, the tilt
the boresight estimate turns into a mount; with that mount set, nothing is left.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from gps_denied_onboard.camera.types import Attitude, CameraMount
from gps_denied_onboard.cli import main
from gps_denied_onboard.components.c1_vio.ground_tilt import ground_tilt_off_cam_rad
from gps_denied_onboard.components.c4_pose.boresight import MIN_SAMPLES, TiltOffset, estimate_boresight
from gps_denied_onboard.components.c13_fdr import FlightDataRecorder
from gps_denied_onboard.config import config_to_dict, load_config
from gps_denied_onboard.constants import FdrKind

HEIGHT_M = 120.0
ATTITUDES = [
    Attitude(0.0, 0.0, 0.0),
    Attitude(math.radians(4.0), math.radians(-2.0), math.radians(135.0)),
    Attitude(math.radians(-6.0), math.radians(3.0), math.radians(-70.0)),
]


@pytest.mark.parametrize("att", ATTITUDES)
def test_a_mount_moves_world_down_in_the_camera_by_its_angles(att: Attitude) -> None:
    """To first order a mount roll r and pitch p move world-down on the camera's x and y axes by +r and
    +p, at any heading and bank: the relation ``gdnav fdr boresight`` adds a measured tilt with."""
    mount = CameraMount(math.radians(0.4), math.radians(-0.3))
    shifted = mount.camera_attitude(att).R_ned_cam()[2, :] - att.R_ned_cam()[2, :]
    np.testing.assert_allclose(np.degrees(shifted[:2]), [0.4, -0.3], atol=0.01)
    # Only the camera's tilt changes: the optical axis turns by the mount's angle, no more.
    axis_turn = math.degrees(
        math.acos(np.clip(mount.camera_attitude(att).R_ned_cam()[:, 2] @ att.R_ned_cam()[:, 2], -1, 1))
    )
    assert axis_turn == pytest.approx(0.5, abs=0.01)


def test_the_nadir_mount_is_the_autopilots_attitude_and_angles_round_trip() -> None:
    att = ATTITUDES[1]
    assert CameraMount().camera_attitude(att) is att
    back = Attitude.from_R_ned_body(att.R_ned_body())
    np.testing.assert_allclose(
        [back.roll_rad, back.pitch_rad, back.yaw_rad], [att.roll_rad, att.pitch_rad, att.yaw_rad]
    )
    with pytest.raises(ValueError, match="finite"):
        CameraMount(math.nan, 0.0)


def _pair_tilt(true_mount: CameraMount, set_mount: CameraMount, seed: int) -> tuple[float, float]:
    """VO's ground tilt between two frames of a camera mounted ``true_mount`` off nadir, the autopilot
    reporting the body's attitude exactly, with ``set_mount`` configured."""
    rng = np.random.default_rng(seed)
    body1 = Attitude(*rng.uniform(-0.05, 0.05, 2), rng.uniform(-math.pi, math.pi))
    body2 = Attitude(body1.roll_rad + 0.01, body1.pitch_rad - 0.005, body1.yaw_rad + 0.02)
    heading = rng.uniform(-math.pi, math.pi)
    step = np.array([4.0 * math.cos(heading), 4.0 * math.sin(heading), 0.0])  # 3 % of the height
    cam1, cam2 = true_mount.camera_attitude(body1), true_mount.camera_attitude(body2)
    ground = np.column_stack([rng.uniform(-80, 80, 300), rng.uniform(-80, 80, 300), np.full(300, HEIGHT_M)])

    def project(att: Attitude, at: np.ndarray) -> np.ndarray:
        cam = (ground - at) @ att.R_ned_cam()
        return cam[:, :2] / cam[:, 2:3]

    x1, x2 = project(cam1, np.zeros(3)), project(cam2, step)
    seen = np.all(np.abs(x1) < [0.7, 0.52], axis=1) & np.all(np.abs(x2) < [0.7, 0.52], axis=1)
    r1, r2 = set_mount.camera_attitude(body1).R_ned_cam(), set_mount.camera_attitude(body2).R_ned_cam()
    tilt = ground_tilt_off_cam_rad(x1[seen], x2[seen], r1, r2, step, HEIGHT_M)
    assert tilt is not None
    return tilt


def test_a_mounted_camera_shows_its_mount_and_the_measured_mount_removes_it() -> None:
    """A camera 0.6 deg right and 0.4 deg back of nadir: VO's ground tilts say so against the body's
    attitude, the estimate from them is that mount, and flown with it nothing is left."""
    true_mount = CameraMount(math.radians(0.6), math.radians(-0.4))
    tilts = np.degrees([_pair_tilt(true_mount, CameraMount(), seed) for seed in range(40)])
    estimate = estimate_boresight(tilts, np.empty((0, 2)), (0.0, 0.0))
    assert estimate.settable, estimate.why
    assert estimate.mount_deg == pytest.approx((0.6, -0.4), abs=0.03)
    measured = CameraMount(*np.radians(estimate.mount_deg))
    left = np.degrees([_pair_tilt(true_mount, measured, seed) for seed in range(40, 60)])
    assert np.abs(left).max() < 0.03
    # Measured again on a flight with that mount: the tilt left is added to it, not put in its place.
    again = estimate_boresight(left, np.empty((0, 2)), estimate.mount_deg)
    assert again.mount_deg == pytest.approx((0.6, -0.4), abs=0.03)


def test_the_estimate_is_as_sure_as_its_samples_and_says_why_not() -> None:
    """Noisy tilts (0.6 deg per pair, as VO at 120 m AGL): the 99 % interval holds the true offset 99 %
    of the time (500 flights of 400 pairs) and is within 0.1 deg; too few tilts, or too wide an
    interval, is not settable and says so."""
    truth = np.array([-0.2, 0.15])
    missed = 0
    for seed in range(500):
        tilts = truth + np.random.default_rng(seed).normal(0.0, 0.6, (400, 2))
        e = estimate_boresight(tilts, np.empty((0, 2)), (0.1, 0.0), max_half_width_deg=0.1)
        assert e.vo is not None and e.settable, e.why
        missed += sum(
            abs(m - t) > h for m, t, h in zip(e.vo.mean_deg, truth, e.vo.half_width_deg, strict=True)
        )
        assert e.mount_deg == pytest.approx((0.1 + e.vo.mean_deg[0], e.vo.mean_deg[1]))
    assert missed / 1000 < 0.02
    many = truth + np.random.default_rng(0).normal(0.0, 0.6, (400, 2))
    few = estimate_boresight(many[: MIN_SAMPLES - 1], np.empty((0, 2)), (0.0, 0.0))
    assert not few.settable and f"at least {MIN_SAMPLES}" in (few.why or "")
    wide = estimate_boresight(many[:60], np.empty((0, 2)), (0.0, 0.0), max_half_width_deg=0.1)
    assert not wide.settable and "wider than 0.1 deg" in (wide.why or "")
    none = estimate_boresight(np.empty((0, 2)), many[:10], (0.0, 0.0))
    assert none.mount_deg is None and not none.settable and none.fixes is not None
    assert TiltOffset.of(np.array([[np.nan, 0.0], [0.1, 0.2]])) is None  # one finite sample: no interval


def _flight(fdr: FlightDataRecorder, mount_deg: tuple[float, float], tilt_deg: np.ndarray) -> None:
    """One run as the daemon records it: its config, then a frame per tilt (and a frame VO gave none)."""
    config = load_config(
        None, [f"camera.mount_roll_deg={mount_deg[0]}", f"camera.mount_pitch_deg={mount_deg[1]}"]
    )
    fdr.record(FdrKind.CONFIG, {"config": config_to_dict(config)})
    fdr.record(FdrKind.FRAME, {"frame_seq": 0, "ground_tilt_check": None})
    for i, (x, y) in enumerate(tilt_deg, start=1):
        fdr.record(
            FdrKind.FRAME, {"frame_seq": i, "ground_tilt_check": {"tilt_off_deg": [x, y], "off": False}}
        )
    for i in (1, 2, 3):
        fdr.record(FdrKind.FIX, {"frame_seq": i, "attitude_check": {"tilt_off_deg": [0.1 * i, -0.1]}})
    fdr.record(FdrKind.FIX, {"frame_seq": 4, "attitude_check": None})  # no pose solved


def test_gdnav_fdr_boresight_reads_the_runs_mount_and_adds_what_is_left(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two runs: the first flown nadir shows the offset, the second flown with it set shows nothing left;
    either way the mount to set is the same. A run that is not there, or no recorder, exits 3."""
    rng = np.random.default_rng(3)
    d = tmp_path / "fdr"
    with FlightDataRecorder(d, 1 << 22, 1 << 20) as fdr:
        _flight(fdr, (0.0, 0.0), np.array([-0.2, 0.15]) + rng.normal(0.0, 0.3, (300, 2)))
    with FlightDataRecorder(d, 1 << 22, 1 << 20) as fdr:
        _flight(fdr, (-0.2, 0.15), rng.normal(0.0, 0.3, (300, 2)))
    for run in ([], ["--run", "0"]):
        assert main(["fdr", "boresight", str(d), "--json", *run]) == 0
        out = json.loads(capsys.readouterr().out)
        assert out["runs"] == 2 and out["run"] == (0 if run else 1)
        assert out["settable"] and out["vo_ground_tilt"]["samples"] == 300 and out["fixes"]["samples"] == 3
        assert out["mount_deg"] == pytest.approx([-0.2, 0.15], abs=0.07)
    assert main(["fdr", "boresight", str(d)]) == 0
    text = capsys.readouterr().out
    assert "flown with camera.mount_roll_deg -0.200, camera.mount_pitch_deg +0.150" in text
    assert "set: camera.mount_roll_deg:" in text
    assert main(["fdr", "boresight", str(d), "--run", "2"]) == 3
    assert "--run 2" in capsys.readouterr().err
    assert main(["fdr", "boresight", str(tmp_path / "nothing")]) == 3
    assert "no such file or directory" in capsys.readouterr().err
