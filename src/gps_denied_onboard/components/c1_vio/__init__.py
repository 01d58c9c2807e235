"""C1 visual odometry: metric frame-to-frame motion of the nadir nav camera.

The names load on first use (``helpers.lazy_exports``): the estimator needs ``types`` only, not OpenCV.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from gps_denied_onboard.helpers.lazy_exports import lazy_exports

if TYPE_CHECKING:
    from gps_denied_onboard.components.c1_vio.homography_vo import HomographyVo, VoFailure
    from gps_denied_onboard.components.c1_vio.types import VoError, VoMotion

__all__ = ["HomographyVo", "VoError", "VoFailure", "VoMotion"]
__getattr__ = lazy_exports(
    __name__,
    {"HomographyVo": "homography_vo", "VoFailure": "homography_vo", "VoError": "types", "VoMotion": "types"},
)
