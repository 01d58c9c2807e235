"""Query rectifier: nav frame -> north-up image at the map's GSD (flat ground, known attitude/AGL).

Frames are rendered with the forward camera projection (ground -> pixel), written independently of the
rectifier's inverse formulation, so agreement checks the geometry rather than restating it.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from gps_denied_onboard.camera.types import Attitude, CameraCalibration
from gps_denied_onboard.helpers.frame_rectifier import RectificationError, rectify_to_map_frame

CALIB = CameraCalibration.from_hfov(640, 480, 70.0)
GSD = 0.3  # m/px of the synthetic ground image
GROUND_CENTRE = (1000.0, 1000.0)  # ground-image px under the camera


def _ground_image() -> np.ndarray:
    rng = np.random.default_rng(1)
    small = rng.integers(0, 255, (250, 250, 3), dtype=np.uint8)
    return cv2.resize(small, (2000, 2000), interpolation=cv2.INTER_CUBIC)


def _ground_to_frame(calib: CameraCalibration, attitude: Attitude, alt_m: float) -> np.ndarray:
    """Ground-image px -> frame px: X_cam = R_cam_ned (north, east, alt), then K."""
    cx0, cy0 = GROUND_CENTRE
    # north = -(y - cy0) * GSD, east = (x - cx0) * GSD, down = alt (camera at the NED origin).
    ned_of_px = np.array([[0.0, -GSD, GSD * cy0], [GSD, 0.0, -GSD * cx0], [0.0, 0.0, alt_m]])
    return calib.K @ attitude.R_ned_cam().T @ ned_of_px


def _render(ground: np.ndarray, attitude: Attitude, alt_m: float) -> np.ndarray:
    h = _ground_to_frame(CALIB, attitude, alt_m)
    return cv2.warpPerspective(ground, h, (CALIB.width_px, CALIB.height_px), flags=cv2.INTER_LINEAR)


@pytest.mark.parametrize(
    "attitude",
    [
        Attitude(0.0, 0.0, 0.0),
        Attitude(0.05, -0.08, math.radians(120.0)),
        Attitude(-0.1, 0.12, math.radians(-40.0)),
    ],
)
def test_frame_rectifier_leaves_only_a_translation_to_the_map(attitude: Attitude) -> None:
    """Rectified px -> ground-image px is a pure translation (rotation, tilt and scale removed)."""
    alt = 150.0
    rect = rectify_to_map_frame(_render(_ground_image(), attitude, alt), CALIB, attitude, alt, GSD)
    rect_to_ground = np.linalg.inv(rect.H_frame_to_rect @ _ground_to_frame(CALIB, attitude, alt))
    rect_to_ground /= rect_to_ground[2, 2]
    np.testing.assert_allclose(rect_to_ground[:2, :2], np.eye(2), atol=1e-9)
    np.testing.assert_allclose(rect_to_ground[2, :2], 0.0, atol=1e-12)


def test_frame_rectifier_image_matches_ground_after_translation() -> None:
    """The rectified pixels equal the ground image shifted by that translation (inside the footprint)."""
    attitude, alt = Attitude(0.04, -0.06, math.radians(65.0)), 140.0
    ground = _ground_image()
    rect = rectify_to_map_frame(_render(ground, attitude, alt), CALIB, attitude, alt, GSD)
    rect_to_ground = np.linalg.inv(rect.H_frame_to_rect @ _ground_to_frame(CALIB, attitude, alt))
    tx, ty = (rect_to_ground[:2, 2] / rect_to_ground[2, 2]).round().astype(int)
    h, w = rect.image.shape[:2]
    expected = ground[ty : ty + h, tx : tx + w]
    inside = cv2.erode((rect.image.max(axis=2) > 0).astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    diff = np.abs(rect.image.astype(int) - expected.astype(int)).max(axis=2)[inside]
    assert inside.sum() > 0.3 * h * w
    assert np.median(diff) < 12


def test_frame_rectifier_rect_to_frame_px_inverts_the_warp() -> None:
    """rect_to_frame_px(H(p)) == p for frame pixels p."""
    attitude = Attitude(0.1, 0.05, 2.0)
    rect = rectify_to_map_frame(np.zeros((480, 640, 3), np.uint8), CALIB, attitude, 90.0, GSD)
    p = np.array([[0.0, 0.0], [639.0, 479.0], [320.5, 100.25]])
    in_rect = cv2.perspectiveTransform(p.reshape(-1, 1, 2), rect.H_frame_to_rect).reshape(-1, 2)
    np.testing.assert_allclose(rect.rect_to_frame_px(in_rect), p, atol=1e-3)


def test_frame_rectifier_with_distortion_maps_back_to_raw_pixels() -> None:
    """With lens distortion the way back lands on raw (distorted) pixels."""
    calib = CameraCalibration(640, 480, 500.0, 500.0, 319.5, 239.5, (-0.2, 0.05, 0.0, 0.0))
    rect = rectify_to_map_frame(np.full((480, 640, 3), 100, np.uint8), calib, Attitude(0, 0, 0.3), 100.0, GSD)
    raw = np.array([[30.0, 40.0], [600.0, 450.0], [320.0, 240.0]])
    undist = cv2.undistortPoints(raw.reshape(-1, 1, 2), calib.K, calib.dist, P=calib.K).reshape(-1, 2)
    in_rect = cv2.perspectiveTransform(undist.reshape(-1, 1, 2), rect.H_frame_to_rect).reshape(-1, 2)
    np.testing.assert_allclose(rect.rect_to_frame_px(in_rect), raw, atol=0.05)
    assert rect.image[rect.image.shape[0] // 2, rect.image.shape[1] // 2].tolist() == [100, 100, 100]


def test_frame_rectifier_fixed_output_is_centred_on_principal_point() -> None:
    """out_size_px gives a square whose centre is the ground point under the principal point."""
    attitude = Attitude(0.1, -0.1, 1.0)
    rect = rectify_to_map_frame(
        np.zeros((480, 640, 3), np.uint8), CALIB, attitude, 120.0, GSD, out_size_px=301
    )
    assert rect.image.shape == (301, 301, 3)
    centre = cv2.perspectiveTransform(np.array([[[CALIB.cx_px, CALIB.cy_px]]]), rect.H_frame_to_rect).reshape(
        2
    )
    np.testing.assert_allclose(centre, [150.0, 150.0], atol=1e-6)


def test_frame_rectifier_scale_follows_altitude_and_gsd() -> None:
    """Twice the altitude -> twice the footprint in rectified pixels."""
    att = Attitude(0.0, 0.0, 0.0)
    low = rectify_to_map_frame(np.zeros((480, 640, 3), np.uint8), CALIB, att, 50.0, GSD)
    high = rectify_to_map_frame(np.zeros((480, 640, 3), np.uint8), CALIB, att, 100.0, GSD)
    # Nadir, yaw 0: image top = nose = north, so the footprint keeps the frame's aspect.
    expected_w = 2 * 50.0 * math.tan(CALIB.hfov_rad / 2) / GSD
    assert low.image.shape[1] == pytest.approx(expected_w, abs=2)
    assert high.image.shape[1] == pytest.approx(2 * expected_w, abs=3)


@pytest.mark.parametrize(
    ("image", "attitude", "alt", "gsd", "match"),
    [
        (np.zeros((240, 320, 3), np.uint8), Attitude(0, 0, 0), 100.0, GSD, "calibration"),
        (np.zeros((480, 640, 3), np.uint8), Attitude(0, 0, 0), 0.0, GSD, "alt_agl_m"),
        (np.zeros((480, 640, 3), np.uint8), Attitude(0, 0, 0), 100.0, -1.0, "target_gsd_m_px"),
        (np.zeros((480, 640, 3), np.uint8), Attitude(0, math.radians(80), 0), 100.0, GSD, "horizon"),
        (np.zeros((480, 640, 3), np.uint8), Attitude(0, 0, 0), 2000.0, 0.05, "rectified image would be"),
    ],
)
def test_frame_rectifier_refuses_bad_inputs(
    image: np.ndarray, attitude: Attitude, alt: float, gsd: float, match: str
) -> None:
    """Wrong size, bad altitude/GSD, a horizon in view or a huge footprint -> RectificationError."""
    with pytest.raises(RectificationError, match=match):
        rectify_to_map_frame(image, CALIB, attitude, alt, gsd)
