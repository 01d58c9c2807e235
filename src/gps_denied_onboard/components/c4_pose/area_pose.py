"""C4: the pose of an area alignment (C3 ``orientation_corr``): where the camera is, and how well that is
known, when the whole frame was matched as one image.

The alignment gives the ground point under the camera directly (the frame was rectified about it), so the
position needs no solve: it is that point, at the height the alignment measured (the autopilot's height
times the winning scale). What the alignment cannot see is the camera's tilt: the frame was rectified
with the autopilot's, so a tilt error ``e`` moves every ground point, the nadir included, by
``agl * tan(e)``, and the image cannot tell. That, not the correlation, is the larger part of the error at
height (0.25 deg at 1200 m AGL is 5 m).

Covariance, per horizontal axis, as variances that add:
- the tilt: ``agl * tan(sigma_tilt)``, with ``sigma_tilt`` the attitude's (``pose.attitude_sigma_deg``)
  and the frame's timing doubt at its attitude rate (``FrameTiming.attitude_sigma_rad``) together;
- the map's registration: ``pose.min_sigma_m``;
- the alignment: ``ALIGNMENT_SIGMA_PX`` of the map's pixel (a sub-pixel peak on a strong correlation).
The integrity rule then floors it at the map's pixel and inflates it as the evidence weakens
(``c4_pose/integrity.py``). The tilt and the registration are the same for the fixes around this one, so
they are also its ``shared_sigma_m``: fusing many fixes does not average them away.

A fix of this kind measures no tilt of its own (``attitude_disagreement_rad`` and
``image_tilt_off_cam_rad`` are None): the tilt checks learn nothing from it and are not fed by it.
"""

from __future__ import annotations

import math
from typing import Final

import numpy as np

from gps_denied_onboard.camera.types import NavCameraFrame
from gps_denied_onboard.components.c3_matcher.types import CandidateMatchSet
from gps_denied_onboard.components.c4_pose.solver import PoseRejectReason
from gps_denied_onboard.components.c4_pose.types import PoseError, PoseFix
from gps_denied_onboard.config import PoseConfig
from gps_denied_onboard.geo import LocalTangentPlane

#: The alignment's own 1-sigma per axis on a strong peak, map px (sub-pixel refinement of an FFT peak).
ALIGNMENT_SIGMA_PX: Final = 0.25
#: A grid step's uniform spread, as a sigma: step / sqrt(12).
_UNIFORM_SIGMA: Final = 1.0 / math.sqrt(12.0)


class AreaPoseSolver:
    """``PoseFix`` from a candidate's ``AreaAlignment`` (module docstring)."""

    def __init__(self, config: PoseConfig, ltp: LocalTangentPlane, ground_alt_amsl_m: float) -> None:
        if not math.isfinite(ground_alt_amsl_m):
            raise ValueError(f"ground_alt_amsl_m must be finite, got {ground_alt_amsl_m!r}")
        self._config = config
        self._ltp = ltp
        self._ground_alt_amsl_m = float(ground_alt_amsl_m)

    def solve(self, frame: NavCameraFrame, candidate: CandidateMatchSet) -> PoseFix:
        """The fix of ``candidate``'s alignment for ``frame``. Raises ``PoseError`` when the candidate
        has no alignment, the frame no attitude or height, or the alignment's height disagrees with the
        autopilot's beyond ``pose.max_alt_disagreement_frac``."""
        area = candidate.area
        if area is None:
            raise PoseError(
                "candidate has no area alignment",
                reason=PoseRejectReason.INVALID_CORRESPONDENCES,
                frame_id=frame.frame_id,
            )
        if frame.attitude is None or frame.alt_agl_m is None or not frame.alt_agl_m > 0.0:
            raise PoseError(
                "frame has no attitude or height",
                reason=PoseRejectReason.MISSING_ATTITUDE,
                frame_id=frame.frame_id,
            )
        cfg = self._config
        if abs(area.height_scale - 1.0) > cfg.max_alt_disagreement_frac:
            raise PoseError(
                f"aligned height is {area.height_scale:.2f} x the autopilot's",
                reason=PoseRejectReason.ALTITUDE_DISAGREEMENT,
                frame_id=frame.frame_id,
            )
        values = (area.nadir_lat_deg, area.nadir_lon_deg, area.height_scale, area.map_gsd_m_px)
        if not all(math.isfinite(v) for v in values):
            raise PoseError(
                "alignment is not finite",
                reason=PoseRejectReason.INVALID_CORRESPONDENCES,
                frame_id=frame.frame_id,
            )
        agl_m = frame.alt_agl_m * area.height_scale
        alt_amsl = self._ground_alt_amsl_m + agl_m
        pos = np.asarray(self._ltp.to_ned(area.nadir_lat_deg, area.nadir_lon_deg, alt_amsl), dtype=np.float64)
        timing_rad = frame.timing.attitude_sigma_rad if frame.timing is not None else 0.0
        tilt_rad = math.hypot(math.radians(cfg.attitude_sigma_deg), timing_rad)
        tilt_m = agl_m * math.tan(min(tilt_rad, math.radians(45.0)))
        align_m = ALIGNMENT_SIGMA_PX * area.map_gsd_m_px
        horiz_var = tilt_m**2 + cfg.min_sigma_m**2 + align_m**2
        vert_sigma = frame.alt_agl_m * area.height_scale_step * _UNIFORM_SIGMA
        cov = np.diag([horiz_var, horiz_var, max(vert_sigma, cfg.min_sigma_m) ** 2])
        yaw = frame.attitude.yaw_rad + area.heading_offset_rad
        return PoseFix(
            frame_id=frame.frame_id,
            exposure_time_unix_usec=frame.exposure_time_unix_usec,
            pos_ned_m=pos,
            cov_ned_m2=cov,
            lat_deg=float(area.nadir_lat_deg),
            lon_deg=float(area.nadir_lon_deg),
            alt_amsl_m=float(alt_amsl),
            yaw_rad=float(math.atan2(math.sin(yaw), math.cos(yaw))),
            yaw_sigma_rad=area.heading_step_rad * _UNIFORM_SIGMA,
            attitude_disagreement_rad=None,
            image_tilt_off_cam_rad=None,
            inlier_count=0,
            residual_px=math.nan,
            tile_id=candidate.tile_id,
            shared_sigma_m=math.hypot(tilt_m, cfg.min_sigma_m),
        )
