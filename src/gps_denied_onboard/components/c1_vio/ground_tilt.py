"""C1 ground tilt: the camera's tilt to the ground plane from two frames, without the autopilot's tilt.

Why
---
The pose solver, VO and the IMU prediction all lean on the autopilot's roll and pitch. The attitude
check (``c4_pose/attitude_check.py``) tests that tilt against the image-only tilt of the absolute
fixes, so it is as quick as the matcher: with DISK or ALIKED on a 2-core CPU (a fix every 7-12 s) a
3 deg roll error lasting 25 s was never proven, and VO and the IMU carried the estimate 5-8 m off at a
stated 2 m (``docs/benchmarks.md``). Two consecutive frames of flat ground also say where the ground's
normal lies in the camera, at the camera rate and with no map.

Geometry
--------
Camera coordinates of frame 1 (``X1``) and frame 2 (``X2 = R X1 + t``); the ground is the plane
``n . X1 = d`` (``n``: unit normal towards the ground, i.e. world down in camera 1's axes; ``d``: height
above the ground, m). Normalised image points then map as ``x2 ~ H x1`` with
``H = lambda (R + t n^T / d)``, so ``R^T H / lambda - I = u n^T`` with ``u = R^T t / d = -C / d``, where
``C`` is camera 2's centre in camera 1's axes (the displacement). ``lambda`` is the middle singular
value of ``H`` (a planar homography's middle singular value is 1 before scaling).

The autopilot's attitude gives ``R`` and (with VO's metric displacement and the height) ``u``; the
upper-left 2 x 2 block of ``u n^T`` then pins ``(n_x, n_y)``. Only its symmetric trace-free part is
used: ``M11 - M22 = u_x n_x - u_y n_y`` and ``M12 + M21 = u_x n_y + u_y n_x``, a 2 x 2 system with
determinant ``|u_xy|^2``. Errors that do not belong to the ground plane drop out of that part: an error
in the relative rotation the autopilot gives (to first order a skew matrix: anti-symmetric in the
block, the rest off it), and an error in ``lambda`` or in the along-axis motion (a multiple of the
identity). An error in ``u`` scales the tilt found by the same fraction (1 % of VO's scale: 0.03 deg of
3 deg). A tilt error ``b`` that is the same in both frames (a mount or AHRS bias) changes ``R`` and
the displacement only to second order, so what is found is the true tilt to the ground, and minus the
autopilot's ``R_ned_cam^T [0, 0, 1]`` it is the same quantity the pose solver reports for a fix
(``PoseFix.image_tilt_off_cam_rad``: image minus autopilot, camera x and y).

Precision comes from the baseline: a tilt ``b`` changes the flow across the image by about
``|u| tan b`` of the focal length, so the estimate is as good as ``|u|`` is large. Measured over the
GeoVision orthophoto rendered at 120 m AGL, 12 m/s, 3 Hz (``|u|`` 0.033, ORB, 600-800 homography
inliers): 0.5 deg scatter per axis per pair, no bias beyond 0.05 deg. Below ``MIN_BASELINE_FRAC``
(hovering, or very high) no tilt is given.

What it measures is the tilt to the ground the frames see: a hillside reads as tilt, as it does for
the fixes' image-only tilt (the pose is solved against flat ground too). In SITL the ground is flat.
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
