"""C1 visual odometry: metric frame-to-frame motion of the nadir nav camera."""

from gps_denied_onboard.components.c1_vio.homography_vo import HomographyVo, VoFailure
from gps_denied_onboard.components.c1_vio.types import VoError, VoMotion

__all__ = ["HomographyVo", "VoError", "VoFailure", "VoMotion"]
