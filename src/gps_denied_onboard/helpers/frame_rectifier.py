"""Warp a nav-camera frame into a north-up image at the map's ground resolution.

Why: the satellite chips are north-up Web-Mercator images at ``gsd_m_px``; the nav frame is rotated by
the vehicle's yaw, tilted by roll/pitch and scaled by altitude. With the autopilot's attitude and AGL
altitude, a flat-ground homography removes all three, so a matcher only has to recover a
translation-dominated homography (and features that are not rotation-invariant work at all).

Geometry (flat ground, camera at the NED origin, ground plane ``down = alt_agl_m``):
a pixel ``u`` has the NED ray ``d = R_ned_cam K^-1 u``; it meets the ground at
``(north, east) = alt * (d_n / d_d, d_e / d_d)``. Rectified pixels have east along +x and north along
-y at ``1 / target_gsd_m_px`` px per metre. Hence, in homogeneous coordinates,

    H_frame_to_rect = A @ diag(alt, alt, 1) @ R_ned_cam @ K^-1,   A = [[0, 1/g, cx], [-1/g, 0, cy], [0, 0, 1]]

``H_frame_to_rect`` is defined on UNDISTORTED frame pixels; when the calibration has distortion, the
warp and ``RectifiedQuery.rect_to_frame_px`` apply it, so both go to and from the raw frame exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import cv2
import numpy as np

from gps_denied_onboard.camera.types import Attitude, CameraCalibration

#: Refuse rectified images larger than this on a side: such a footprint means a ray near the horizon
#: (extreme tilt) or a wrong altitude, and the warp would cost more than the whole frame budget.
MAX_RECTIFIED_SIDE_PX: Final[int] = 4096

# A corner ray must point at least this much downwards (cosine with the down axis) to hit the ground
# at a sane distance; ~84 degrees off-nadir.
_MIN_DOWN_COMPONENT: Final[float] = 0.1


class RectificationError(ValueError):
    """The frame cannot be rectified (bad altitude, ray above the horizon, size mismatch...)."""


@dataclass(frozen=True)
class RectifiedQuery:
    """A nav frame warped north-up at the map's GSD.

    - ``image``: (h, w, 3) uint8 BGR, east = +x, north = -y, ``gsd_m_px`` metres per pixel;
      pixels outside the camera footprint are 0.
    - ``H_frame_to_rect``: (3, 3) float64, undistorted frame px -> rectified px, H[2, 2] = 1.
    - ``calibration``: the calibration used (for distortion on the way back).
    """

    image: np.ndarray
    H_frame_to_rect: np.ndarray
    gsd_m_px: float
    calibration: CameraCalibration

    def rect_to_frame_px(self, pts_rect: np.ndarray) -> np.ndarray:
        """Rectified pixels (N, 2) -> original (raw, distorted) frame pixels (N, 2) float32."""
        pts = np.asarray(pts_rect, dtype=np.float64).reshape(-1, 2)
        if pts.shape[0] == 0:
            return np.empty((0, 2), dtype=np.float32)
        undist = cv2.perspectiveTransform(pts.reshape(-1, 1, 2), np.linalg.inv(self.H_frame_to_rect))
        undist = undist.reshape(-1, 2)
        if self.calibration.dist.size == 0:
            return undist.astype(np.float32)
        return _distort(undist, self.calibration).astype(np.float32)


def _distort(undist_px: np.ndarray, calibration: CameraCalibration) -> np.ndarray:
    """Undistorted pixel coordinates (N, 2) -> distorted (raw) pixel coordinates (N, 2) float64."""
    k = calibration.K
    norm = np.column_stack(
        [
            (undist_px[:, 0] - k[0, 2]) / k[0, 0],
            (undist_px[:, 1] - k[1, 2]) / k[1, 1],
            np.ones(undist_px.shape[0]),
        ]
    )
    zero = np.zeros(3)
    raw, _ = cv2.projectPoints(norm.reshape(-1, 1, 3), zero, zero, k, calibration.dist)
    return raw.reshape(-1, 2)


def frame_to_ground_homography(
    calibration: CameraCalibration, attitude: Attitude, alt_agl_m: float
) -> np.ndarray:
    """Undistorted frame px -> homogeneous ground (north_m, east_m, 1) relative to the nadir point,
    (3, 3) float64."""
    r_ned_cam = attitude.R_ned_cam()
    return np.diag([alt_agl_m, alt_agl_m, 1.0]) @ r_ned_cam @ np.linalg.inv(calibration.K)


def principal_ground_offset_m(
    calibration: CameraCalibration, attitude: Attitude, alt_agl_m: float
) -> tuple[float, float] | None:
    """(north_m, east_m) of the ground under the principal point from the nadir point; None when the
    height is not a finite positive number or the principal ray does not meet the ground."""
    if not (math.isfinite(alt_agl_m) and alt_agl_m > 0.0):
        return None
    ray = frame_to_ground_homography(calibration, attitude, alt_agl_m) @ np.array(
        [calibration.cx_px, calibration.cy_px, 1.0]
    )
    if ray[2] <= 0.0:
        return None
    return float(ray[0] / ray[2]), float(ray[1] / ray[2])


def rectify_to_map_frame(
    frame_image: np.ndarray,
    calibration: CameraCalibration,
    attitude: Attitude,
    alt_agl_m: float,
    target_gsd_m_px: float,
    *,
    out_size_px: int | None = None,
) -> RectifiedQuery:
    """Warp ``frame_image`` (H, W, 3) uint8 to a north-up image at ``target_gsd_m_px``.

    ``out_size_px=None``: the output is the bounding box of the frame's ground footprint. An int: a
    square of that side centred on the ground point under the principal point. Raises
    ``RectificationError`` for a non-positive altitude/GSD, a frame whose size differs from the
    calibration's, or a footprint that reaches the horizon or exceeds ``MAX_RECTIFIED_SIDE_PX``.
    """
    img = np.asarray(frame_image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise RectificationError(f"frame must be (H, W, 3) uint8, got {img.shape} {img.dtype}")
    h, w = img.shape[:2]
    if (w, h) != (calibration.width_px, calibration.height_px):
        raise RectificationError(
            f"frame is {w}x{h} px but the calibration is for {calibration.width_px}x{calibration.height_px}"
        )
    if not (math.isfinite(alt_agl_m) and alt_agl_m > 0):
        raise RectificationError(f"alt_agl_m must be finite and > 0, got {alt_agl_m!r}")
    if not (math.isfinite(target_gsd_m_px) and target_gsd_m_px > 0):
        raise RectificationError(f"target_gsd_m_px must be finite and > 0, got {target_gsd_m_px!r}")

    g = frame_to_ground_homography(calibration, attitude, alt_agl_m)
    # Corners of the image, undistorted, as NED rays: all must hit the ground in front of the camera.
    corners = np.array([[0.0, 0.0], [w - 1.0, 0.0], [w - 1.0, h - 1.0], [0.0, h - 1.0]])
    if calibration.dist.size:
        corners = cv2.undistortPoints(
            corners.reshape(-1, 1, 2), calibration.K, calibration.dist, P=calibration.K
        ).reshape(-1, 2)
    rays = (attitude.R_ned_cam() @ np.linalg.inv(calibration.K) @ np.column_stack([corners, np.ones(4)]).T).T
    down = rays[:, 2] / np.linalg.norm(rays, axis=1)
    if (down < _MIN_DOWN_COMPONENT).any():
        raise RectificationError(
            f"camera footprint reaches the horizon (corner ray down-cosines {np.round(down, 3).tolist()})"
        )

    # Ground (north, east) -> rectified px before the final offset.
    scale = 1.0 / target_gsd_m_px
    a0 = np.array([[0.0, scale, 0.0], [-scale, 0.0, 0.0], [0.0, 0.0, 1.0]])
    h0 = a0 @ g
    if out_size_px is None:
        pc = cv2.perspectiveTransform(corners.reshape(-1, 1, 2), h0).reshape(-1, 2)
        x0, y0 = np.floor(pc.min(axis=0))
        x1, y1 = np.ceil(pc.max(axis=0))
        out_w, out_h = int(x1 - x0) + 1, int(y1 - y0) + 1
        offset = np.array([-x0, -y0])
    else:
        if out_size_px < 1:
            raise RectificationError(f"out_size_px must be >= 1, got {out_size_px!r}")
        centre = cv2.perspectiveTransform(
            np.array([[[calibration.cx_px, calibration.cy_px]]], dtype=np.float64), h0
        ).reshape(2)
        out_w = out_h = int(out_size_px)
        offset = np.array([(out_w - 1) / 2.0, (out_h - 1) / 2.0]) - centre
    if max(out_w, out_h) > MAX_RECTIFIED_SIDE_PX:
        raise RectificationError(
            f"rectified image would be {out_w}x{out_h} px (> {MAX_RECTIFIED_SIDE_PX}); "
            f"alt_agl_m={alt_agl_m:.1f}, gsd={target_gsd_m_px:.3f} m/px"
        )
    shift = np.array([[1.0, 0.0, offset[0]], [0.0, 1.0, offset[1]], [0.0, 0.0, 1.0]])
    h_frame_to_rect = shift @ h0
    h_frame_to_rect = h_frame_to_rect / h_frame_to_rect[2, 2]

    if calibration.dist.size == 0:
        out = cv2.warpPerspective(
            img, h_frame_to_rect, (out_w, out_h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
        )
    else:
        # Exact with distortion: rectified px -> undistorted px (inverse H) -> raw px, then remap.
        xs, ys = np.meshgrid(np.arange(out_w, dtype=np.float64), np.arange(out_h, dtype=np.float64))
        grid = np.stack([xs.ravel(), ys.ravel()], axis=1)
        undist = cv2.perspectiveTransform(grid.reshape(-1, 1, 2), np.linalg.inv(h_frame_to_rect))
        raw = _distort(undist.reshape(-1, 2), calibration).astype(np.float32)
        map_x = raw[:, 0].reshape(out_h, out_w)
        map_y = raw[:, 1].reshape(out_h, out_w)
        out = cv2.remap(img, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return RectifiedQuery(
        image=out, H_frame_to_rect=h_frame_to_rect, gsd_m_px=float(target_gsd_m_px), calibration=calibration
    )
