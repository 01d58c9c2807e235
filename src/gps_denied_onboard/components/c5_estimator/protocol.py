"""C5 inbound contract: the vehicle's acceleration, for IMU-driven prediction."""

from __future__ import annotations

from typing import NamedTuple, Protocol

import numpy as np


class ImuAcceleration(NamedTuple):
    """The IMU's answer for one prediction interval.

    ``mean_ned_m_s2``: mean kinematic acceleration in local NED, (3,) float64, m/s^2 (gravity removed).
    ``tilt_bound_m_s2``: the most, per horizontal axis, that the attitude's own error may put into it:
    the specific force is rotated into NED with the autopilot's roll and pitch, and a tilt error of
    ``e`` rad turns ``|f| e`` of it sideways (3 deg in a hover: 0.5 m/s^2). 0 when the attitude is not
    in doubt."""

    mean_ned_m_s2: np.ndarray
    tilt_bound_m_s2: float = 0.0


class AccelerationSource(Protocol):
    """Where the estimator's prediction gets the vehicle's measured acceleration (C8 implements it from
    the autopilot's HIGHRES_IMU/SCALED_IMU rotated by ATTITUDE)."""

    def accel_ned_mean(self, t0_unix_usec: int, t1_unix_usec: int) -> ImuAcceleration | None:
        """The mean acceleration over ``[t0, t1]`` with its tilt doubt, or None when it is not known well
        enough for that interval (no samples, stale, no attitude to rotate them). Must not block."""
        ...
