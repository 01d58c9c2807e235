"""C5 estimator: fuses absolute fixes, visual odometry, altitude and the IMU on one time axis; labels the
provenance."""

from gps_denied_onboard.components.c5_estimator.ekf import (
    DEFAULT_VO_RECENT_S,
    EstimatorCheckpoint,
    FixReason,
    NavEstimator,
)
from gps_denied_onboard.components.c5_estimator.protocol import AccelerationSource
from gps_denied_onboard.components.c5_estimator.time_axis import (
    Admission,
    Refusal,
    TimeAxis,
    TimeAxisStats,
)
from gps_denied_onboard.components.c5_estimator.types import EstimatorState, FixDecision

__all__ = [
    "DEFAULT_VO_RECENT_S",
    "AccelerationSource",
    "Admission",
    "EstimatorCheckpoint",
    "EstimatorState",
    "FixDecision",
    "FixReason",
    "NavEstimator",
    "Refusal",
    "TimeAxis",
    "TimeAxisStats",
]
