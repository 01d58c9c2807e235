"""C4 pose: absolute camera position + covariance from map-matched inliers.

The names load on first use (``helpers.lazy_exports``): the estimator needs ``types`` only, not the
solver's SciPy and OpenCV.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from gps_denied_onboard.helpers.lazy_exports import lazy_exports

if TYPE_CHECKING:
    from gps_denied_onboard.components.c4_pose.solver import (
        DEFAULT_MIN_SPREAD_PX,
        PoseRejectReason,
        PoseSolver,
    )
    from gps_denied_onboard.components.c4_pose.types import PoseError, PoseFix

__all__ = ["DEFAULT_MIN_SPREAD_PX", "PoseError", "PoseFix", "PoseRejectReason", "PoseSolver"]
__getattr__ = lazy_exports(
    __name__,
    {
        "DEFAULT_MIN_SPREAD_PX": "solver",
        "PoseRejectReason": "solver",
        "PoseSolver": "solver",
        "PoseError": "types",
        "PoseFix": "types",
    },
)
