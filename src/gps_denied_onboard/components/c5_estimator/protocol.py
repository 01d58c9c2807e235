"""C5 inbound contract: the vehicle's acceleration, for IMU-driven prediction."""

from __future__ import annotations

from typing import Protocol

import numpy as np


class AccelerationSource(Protocol):
    """Where the estimator's prediction gets the vehicle's measured acceleration (C8 implements it from
    the autopilot's HIGHRES_IMU/SCALED_IMU rotated by ATTITUDE)."""

    def accel_ned_mean(self, t0_unix_usec: int, t1_unix_usec: int) -> np.ndarray | None:
        """Mean kinematic acceleration over ``[t0, t1]`` in local NED, (3,) float64, m/s^2 (gravity
        removed), or None when it is not known well enough for that interval (no samples, stale, no
        attitude to rotate them). Must not block."""
        ...
