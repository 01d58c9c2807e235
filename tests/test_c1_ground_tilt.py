"""C1 ground tilt: the camera's tilt to the ground from two views of it, against the autopilot's.

The geometry is checked on exact projections of ground points (no image noise): what is recovered is
the true world down in the first camera minus the reported one, whatever the reported attitude's
constant error, and an error in the relative rotation the autopilot gives between the frames stays out
of it. ``test_c1_vio.py`` checks it on frames rendered from a real orthophoto.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gps_denied_onboard.camera.types import Attitude
from gps_denied_onboard.components.c1_vio.ground_tilt import MIN_BASELINE_FRAC, ground_tilt_off_cam_rad

HEIGHT_M = 120.0


def _project(points_ned: np.ndarray, camera_ned: np.ndarray, att: Attitude) -> np.ndarray:
    """(N, 3) NED ground points -> (N, 2) normalised image coordinates of a camera at ``camera_ned``."""
    cam = (points_ned - camera_ned) @ att.R_ned_cam()  # rows: R_ned_cam^T (p - c)
    return cam[:, :2] / cam[:, 2:3]


def _views(
    att1: Attitude, att2: Attitude, step_ned_m: np.ndarray, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Normalised points of 300 flat-ground points seen from camera 1 at HEIGHT_M and camera 2 moved by
    ``step_ned_m``; only those inside a 70 deg x 55 deg view of both."""
    rng = np.random.default_rng(seed)
    ground = np.column_stack([rng.uniform(-80, 80, 300), rng.uniform(-80, 80, 300), np.full(300, HEIGHT_M)])
    c1 = np.zeros(3)
    x1, x2 = _project(ground, c1, att1), _project(ground, c1 + step_ned_m, att2)
    inside = np.all(np.abs(x1) < [0.7, 0.52], axis=1) & np.all(np.abs(x2) < [0.7, 0.52], axis=1)
    return x1[inside], x2[inside]


def _expected(true1: Attitude, reported1: Attitude) -> np.ndarray:
    return (true1.R_ned_cam()[2, :] - reported1.R_ned_cam()[2, :])[:2]


@pytest.mark.parametrize(
    ("bias_deg", "step_ned_m"),
    [((0.0, 0.0), (4.0, 0.0, 0.0)), ((3.0, 0.0), (4.0, 1.0, 0.0)), ((-2.0, 1.5), (-1.0, -3.0, -0.7))],
)
def test_the_ground_tilt_is_the_true_one_whatever_the_autopilot_says(
    bias_deg: tuple[float, float], step_ned_m: tuple[float, float, float]
) -> None:
    """A constant roll/pitch error of the autopilot (a knocked mount, an AHRS bias) is found as it is,
    turning or climbing, on the first camera's axes."""
    true1 = Attitude(math.radians(2.0), math.radians(-1.0), math.radians(30.0))
    true2 = Attitude(math.radians(3.5), math.radians(-0.2), math.radians(33.0))
    b = np.radians(bias_deg)
    rep1 = Attitude(true1.roll_rad + b[0], true1.pitch_rad + b[1], true1.yaw_rad)
    rep2 = Attitude(true2.roll_rad + b[0], true2.pitch_rad + b[1], true2.yaw_rad)
    step = np.array(step_ned_m)
    x1, x2 = _views(true1, true2, step)
    tilt = ground_tilt_off_cam_rad(x1, x2, rep1.R_ned_cam(), rep2.R_ned_cam(), step, HEIGHT_M)
    assert tilt is not None
    # Exact projections: what is left is second order (the bias times the tilt: 0.03 deg at 2.5 deg).
    np.testing.assert_allclose(np.degrees(tilt), np.degrees(_expected(true1, rep1)), atol=0.05)
    assert np.degrees(np.hypot(*tilt)) == pytest.approx(math.hypot(*bias_deg), abs=0.05)


def test_an_error_in_the_relative_rotation_stays_out_of_the_tilt() -> None:
    """The autopilot's attitude noise between the two exposures (here 0.2 deg about every axis, four
    times what the VO covariance assumes) moves the tilt found by a small fraction of itself, not by the
    rotation error scaled by the baseline (0.2 deg / 0.033 would be 6 deg)."""
    true1 = Attitude(0.0, 0.0, 0.0)
    true2 = Attitude(math.radians(1.0), 0.0, 0.0)
    step = np.array([4.0, 0.0, 0.0])
    x1, x2 = _views(true1, true2, step)
    e = math.radians(0.2)
    rep2 = Attitude(true2.roll_rad + e, true2.pitch_rad - e, true2.yaw_rad + e)
    tilt = ground_tilt_off_cam_rad(x1, x2, true1.R_ned_cam(), rep2.R_ned_cam(), step, HEIGHT_M)
    assert tilt is not None
    assert np.degrees(np.hypot(*tilt)) < 0.2


def test_no_tilt_without_a_baseline_or_points() -> None:
    """Hovering (a baseline under MIN_BASELINE_FRAC of the height), too few points or no height: None."""
    att = Attitude(0.0, 0.0, 0.0)
    hover = np.array([MIN_BASELINE_FRAC * HEIGHT_M * 0.9, 0.0, 0.0])
    x1, x2 = _views(att, att, hover)
    r = att.R_ned_cam()
    assert ground_tilt_off_cam_rad(x1, x2, r, r, hover, HEIGHT_M) is None
    step = np.array([4.0, 0.0, 0.0])
    x1, x2 = _views(att, att, step)
    assert ground_tilt_off_cam_rad(x1[:5], x2[:5], r, r, step, HEIGHT_M) is None
    assert ground_tilt_off_cam_rad(x1, x2, r, r, step, float("nan")) is None
    assert ground_tilt_off_cam_rad(x1, x2, r, r, step, HEIGHT_M) == pytest.approx((0.0, 0.0), abs=1e-6)
