"""C4 contracts: an absolute position fix from one matched frame."""

from __future__ import annotations

import uuid
from dataclasses import dataclass

import numpy as np

from gps_denied_onboard.components.c6_tiles.types import TileId


@dataclass(frozen=True)
class PoseFix:
    frame_id: uuid.UUID
    exposure_time_unix_usec: int
    #: Camera position in the flight's local NED frame, (3,) float64, metres.
    pos_ned_m: np.ndarray
    #: Covariance of ``pos_ned_m``, (3, 3) float64, m^2; from the solver's Jacobian and residuals.
    cov_ned_m2: np.ndarray
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    #: Heading of the camera solution (body yaw), radians, NED; and its 1-sigma.
    yaw_rad: float
    yaw_sigma_rad: float
    #: Angle between the image-only pose's camera axis (before the attitude prior) and the autopilot's,
    #: radians (the plausibility gate; recorded as ``fix_image_tilt_off_deg``). None: the fix measured no
    #: tilt of its own (an area alignment, ``c4_pose/area_pose.py``: the frame was rectified with the
    #: autopilot's).
    attitude_disagreement_rad: float | None
    #: The same on the camera's x and y axes: world down seen by the image-only pose minus world down by
    #: the autopilot's attitude, radians (small angles). The camera is fixed to the airframe, so an AHRS
    #: or mount error is the same from fix to fix here (``c4_pose/attitude_check.py``). None as above.
    image_tilt_off_cam_rad: tuple[float, float] | None
    inlier_count: int
    #: Median reprojection residual of the inliers, px; NaN for an area alignment (no points).
    residual_px: float
    tile_id: TileId
    #: Per-axis horizontal 1-sigma, metres, of the part of this fix's error that every fix against the
    #: same map shares (the map's georeference, terrain that is not flat, consistently biased matches).
    #: It is inside ``cov_ned_m2`` too; it is carried apart because fusing more fixes does not average
    #: it away, so the estimator keeps it out of the reduction (see ``c5_estimator/ekf.py``).
    shared_sigma_m: float
    #: The tilt error, radians, beyond ``PoseConfig.attitude_sigma_deg`` that the solve allowed the
    #: autopilot's attitude (a tilt check had shown one; ``NavigationPipeline``): 0 for a fix that leans
    #: on it as usual, and for one that measured no tilt of its own.
    attitude_doubt_rad: float = 0.0
    #: Per-axis horizontal 1-sigma, metres, of the error a ground sloping as steeply as the tilt a check
    #: showed would make of this fix (``NavigationPipeline._with_slope_doubt``). It is inside
    #: ``cov_ned_m2`` and ``shared_sigma_m`` like any regional error, so every gate allows for it and
    #: every output after it states it; but the estimator weighs the fix without it
    #: (``c5_estimator/ekf.py``): it is one error for all the fixes over that ground, not noise that
    #: fusing fewer of them would avoid, and a right fix stated as weak lets VO, de-rotated with the same
    #: wrong tilt, carry the estimate away from it.
    slope_sigma_m: float = 0.0

    @property
    def horiz_sigma_m(self) -> float:
        """Horizontal 1-sigma, metres: sqrt of the larger eigenvalue of the NE covariance."""
        return float(np.sqrt(np.max(np.linalg.eigvalsh(self.cov_ned_m2[:2, :2]))))


class PoseError(RuntimeError):
    """A pose could not be solved or was rejected as degenerate/implausible; ``reason`` says why."""

    def __init__(self, message: str, *, reason: str, frame_id: uuid.UUID | None = None) -> None:
        super().__init__(f"{message} (reason={reason}, frame={frame_id})")
        self.reason = reason
        self.frame_id = frame_id
