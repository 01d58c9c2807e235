"""C4 pose: absolute camera position + covariance from map-matched inliers."""

from gps_denied_onboard.components.c4_pose.solver import DEFAULT_MIN_SPREAD_PX, PoseRejectReason, PoseSolver
from gps_denied_onboard.components.c4_pose.types import PoseError, PoseFix

__all__ = ["DEFAULT_MIN_SPREAD_PX", "PoseError", "PoseFix", "PoseRejectReason", "PoseSolver"]
