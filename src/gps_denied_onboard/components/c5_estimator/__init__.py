"""C5 estimator: fuses absolute fixes, visual odometry and altitude; labels the provenance."""

from gps_denied_onboard.components.c5_estimator.ekf import (
    DEFAULT_FIX_RECENT_S,
    DEFAULT_MAX_FIX_LAG_S,
    DEFAULT_VO_RECENT_S,
    FixReason,
    NavEstimator,
)
from gps_denied_onboard.components.c5_estimator.types import EstimatorState, FixDecision

__all__ = [
    "DEFAULT_FIX_RECENT_S",
    "DEFAULT_MAX_FIX_LAG_S",
    "DEFAULT_VO_RECENT_S",
    "EstimatorState",
    "FixDecision",
    "FixReason",
    "NavEstimator",
]
