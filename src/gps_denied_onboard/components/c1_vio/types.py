"""C1 contracts: frame-to-frame motion of the nadir camera."""

from __future__ import annotations

import uuid
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class VoMotion:
    """Horizontal displacement of the camera between two frames, in local NED metres."""

    frame_id: uuid.UUID
    prev_frame_id: uuid.UUID
    dt_s: float
    #: (2,) float64 north/east displacement, metres, from the previous frame to this one.
    delta_ne_m: np.ndarray
    #: (2, 2) float64 covariance of ``delta_ne_m``, m^2.
    cov_ne_m2: np.ndarray
    inlier_count: int
    #: World down as the two frames' ground plane shows it minus world down as the autopilot's attitude
    #: says, on the previous frame's camera x and y axes, rad (``c1_vio/ground_tilt.py``); None when the
    #: frames cannot tell (too short a baseline).
    ground_tilt_off_cam_rad: tuple[float, float] | None = None


class VoError(RuntimeError):
    """No trustworthy motion between the two frames (low texture, too few inliers, no attitude)."""

    def __init__(self, message: str, *, reason: str) -> None:
        super().__init__(f"{message} (reason={reason})")
        self.reason = reason
