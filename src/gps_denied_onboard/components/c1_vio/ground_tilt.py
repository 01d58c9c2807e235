"""C1 ground tilt: the camera's tilt to the ground plane from two frames, without the autopilot's tilt.

The attitude check on the absolute fixes is only as quick as the matcher; two consecutive frames of flat
ground also say where the ground's normal lies in the camera, at the camera rate and with no map. This
module measures it, for the second instance of ``c4_pose/attitude_check.py``.

Input: the frame-to-frame homography ``H`` in normalised image points, the autopilot's relative rotation
``R``, and VO's metric displacement over the height (``u = R^T t / d``). Output: the tilt to the ground,
minus the autopilot's, on the camera's x and y axes (the quantity ``PoseFix.image_tilt_off_cam_rad``
gives for a fix), or none when the baseline ``|u|`` is below ``MIN_BASELINE_FRAC`` (hovering, very high).

Rule: ``R^T H / lambda - I = u n^T`` (``lambda``: the middle singular value of ``H``); the symmetric
trace-free part of its upper-left 2 x 2 block, ``M11 - M22 = u_x n_x - u_y n_y`` and
``M12 + M21 = u_x n_y + u_y n_x``, pins ``(n_x, n_y)``. Errors in the relative rotation, in ``lambda`` and
in the along-axis motion drop out of that part; a bias the same in both frames changes it only to second
order. A hillside reads as tilt.

Geometry and precision in full: docs/design.md, "`c1_vio/ground_tilt.py`: VO's ground tilt".
"""

from __future__ import annotations

import math
from typing import Final

import cv2
import numpy as np

#: Fewest points for the least-squares homography.
MIN_POINTS: Final[int] = 8
#: Shortest baseline, as a fraction of the height (|u| above), at which a tilt is given: below it the
#: flow that carries the tilt is smaller than the matches' noise (about 0.7 deg per pair at 0.02).
MIN_BASELINE_FRAC: Final[float] = 0.01
#: A plane normal further than this from the camera axis (deg) is no nadir view of flat ground.
MAX_TILT_DEG: Final[float] = 45.0


def ground_tilt_off_cam_rad(
    pts1_norm: np.ndarray,
    pts2_norm: np.ndarray,
    r_ned_cam1: np.ndarray,
    r_ned_cam2: np.ndarray,
    displacement_ned_m: np.ndarray,
    height_m: float,
) -> tuple[float, float] | None:
    """World down as the two frames' ground plane shows it, minus world down as ``r_ned_cam1`` says,
    on camera 1's x and y axes, rad; None when the frames cannot tell (too short a baseline, too few
    points, a degenerate homography).

    ``pts1_norm``, ``pts2_norm``: (N, 2) matching ground points in normalised (undistorted) image
    coordinates of frame 1 and frame 2. ``r_ned_cam1``, ``r_ned_cam2``: the autopilot's camera -> NED
    rotations at the two exposures. ``displacement_ned_m``: camera 2's position minus camera 1's, NED,
    m. ``height_m``: camera 1's height above the ground, m.
    """
    if pts1_norm.shape[0] < MIN_POINTS or pts1_norm.shape != pts2_norm.shape:
        return None
    if not (math.isfinite(height_m) and height_m > 0.0):
        return None
    c_cam1 = r_ned_cam1.T @ np.asarray(displacement_ned_m, dtype=np.float64)
    u = -c_cam1 / height_m
    if not np.all(np.isfinite(u)) or float(np.hypot(u[0], u[1])) < MIN_BASELINE_FRAC:
        return None
    h, _ = cv2.findHomography(pts1_norm.astype(np.float64), pts2_norm.astype(np.float64), 0)
    if h is None or not np.all(np.isfinite(h)):
        return None
    lam = float(np.linalg.svd(h, compute_uv=False)[1])
    if lam <= 0.0:
        return None
    if np.linalg.det(h) < 0.0:  # H is found up to sign; the plane's keeps the orientation
        lam = -lam
    r_21 = r_ned_cam2.T @ r_ned_cam1  # camera 1 axes -> camera 2 axes
    m = r_21.T @ h / lam - np.eye(3)
    a = np.array([[u[0], -u[1]], [u[1], u[0]]])
    rhs = np.array([m[0, 0] - m[1, 1], m[0, 1] + m[1, 0]])
    n_xy = np.linalg.solve(a, rhs)
    if not np.all(np.isfinite(n_xy)) or float(np.hypot(*n_xy)) > math.sin(math.radians(MAX_TILT_DEG)):
        return None
    down_cam1 = r_ned_cam1[2, :]  # world down in camera 1's axes, as the autopilot says
    return float(n_xy[0] - down_cam1[0]), float(n_xy[1] - down_cam1[1])
