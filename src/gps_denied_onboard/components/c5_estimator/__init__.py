"""C5 estimator: fuses absolute fixes, visual odometry, altitude and the IMU on one time axis; labels the
provenance.

The names below load on first use (PEP 562): the filter pulls in the VO and pose types' packages (OpenCV
among them), and the MAVLink link, which needs only ``types``, must be able to start before them
(``daemon.beacon``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from gps_denied_onboard.helpers.lazy_exports import lazy_exports

if TYPE_CHECKING:
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

#: Each exported name and the submodule that defines it.
_HOME = {
    "DEFAULT_VO_RECENT_S": "ekf",
    "EstimatorCheckpoint": "ekf",
    "FixReason": "ekf",
    "NavEstimator": "ekf",
    "AccelerationSource": "protocol",
    "Admission": "time_axis",
    "Refusal": "time_axis",
    "TimeAxis": "time_axis",
    "TimeAxisStats": "time_axis",
    "EstimatorState": "types",
    "FixDecision": "types",
}

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
__getattr__ = lazy_exports(__name__, _HOME)
