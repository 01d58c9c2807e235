"""C1 frame-to-frame visual odometry for the nadir nav camera: features, homography RANSAC, ground plane.

Input: a frame with its attitude (``Attitude.R_ned_cam``) and height above ground at its exposure.
Output: a ``VoMotion`` (NED displacement since the reference frame, its covariance, the interval, and
``ground_tilt_off_cam_rad``) or a ``VoError``.

Rule, per frame:
1. features (ORB by default, or SIFT) on the grey image; too few -> ``VoError(low_texture)``;
2. k=2 matching against the reference frame with a ratio test, then homography RANSAC (over flat ground
   the true mapping is a homography);
3. each inlier's ray in NED meets the ground ``alt_agl_m`` below its camera; the displacement is the
   per-axis median of ``g_prev - g_cur``;
4. covariance: ``(pi/2) * cov(offsets) / n`` plus the errors all points share: the attitude change
   between the exposures, ``(sqrt(2) * AGL * rel_attitude_sigma_rad)^2``, and the height's scale error,
   ``(scale_sigma_frac * |displacement|)^2``;
5. ground tilt from the same inliers (``c1_vio/ground_tilt.py``) for the attitude check.
Only the reference frame's keypoints, descriptors, attitude, height and time are kept (never images). A
frame that cannot be a reference (no attitude or height, no texture) leaves the previous one in place, up
to ``max_gap_s``; a frame whose matching failed becomes the new reference.

Why the covariance is built this way: docs/design.md, "`c1_vio/homography_vo.py`: visual odometry".
"""

from __future__ import annotations

import math
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

import cv2
import numpy as np

from gps_denied_onboard.camera.types import CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c1_vio.ground_tilt import ground_tilt_off_cam_rad
from gps_denied_onboard.components.c1_vio.types import VoError, VoMotion


def _orb(max_features: int) -> cv2.Feature2D:
    # FAST threshold lowered from 20 to 12 so that low-contrast ground (scrub, bare soil) still gets
    # corners; 4 pyramid levels (1.2^3 = 1.7x scale range) instead of 8 because consecutive nadir frames
    # differ in scale only by the relative altitude change; this cuts ORB's time by about a quarter.
    return cv2.ORB.create(nfeatures=max_features, nlevels=4, fastThreshold=12)


def _sift(max_features: int) -> cv2.Feature2D:
    return cv2.SIFT.create(nfeatures=max_features)


#: Detector name -> (factory(max_features), descriptor norm for matching).
_DETECTORS: Final[dict[str, tuple[Callable[[int], cv2.Feature2D], int]]] = {
    "orb": (_orb, cv2.NORM_HAMMING),
    "sift": (_sift, cv2.NORM_L2),
}
#: Rays closer to the horizon than this (cosine of the angle to the down axis) never hit the ground
#: within a useful distance and are dropped.
_MIN_RAY_DOWN_COS: Final[float] = 0.2


class VoFailure:
    """Values of ``VoError.reason``."""

    FIRST_FRAME: Final = "first_frame"
    MISSING_ATTITUDE: Final = "missing_attitude"
    MISSING_ALTITUDE: Final = "missing_altitude"
    LOW_TEXTURE: Final = "low_texture"
    NON_INCREASING_TIME: Final = "non_increasing_time"
    GAP_TOO_LONG: Final = "gap_too_long"
    TOO_FEW_MATCHES: Final = "too_few_matches"
    TOO_FEW_INLIERS: Final = "too_few_inliers"
    BAD_SIZE: Final = "bad_image_size"


@dataclass(frozen=True)
class _Reference:
    """What is kept of the previous usable frame."""

    frame_id: uuid.UUID
    time_unix_usec: int
    keypoints_px: np.ndarray  # (N, 2) float32, original (distorted) pixels
    descriptors: np.ndarray  # (N, D) uint8 or float32
    r_ned_cam: np.ndarray  # (3, 3)
    alt_agl_m: float


class HomographyVo:
    """Metric frame-to-frame motion of the nadir camera from consecutive :class:`NavCameraFrame`.

    ``calibration``: the nav camera's intrinsics (frames must have its size). ``detector``: ``orb``
    (default, fastest) or ``sift``. ``min_inliers``: fewest homography inliers accepted.
    ``ratio_test``: Lowe ratio for matches. ``ransac_threshold_px``: homography reprojection threshold.
    ``max_gap_s``: longest interval measured (older references are dropped). ``rel_attitude_sigma_rad``,
    ``scale_sigma_frac``: the common-error terms of the covariance (module docstring).
    """

    def __init__(
        self,
        calibration: CameraCalibration,
        *,
        max_features: int = 1000,
        min_inliers: int = 30,
        detector: str = "orb",
        ratio_test: float = 0.8,
        ransac_threshold_px: float = 3.0,
        max_gap_s: float = 2.0,
        rel_attitude_sigma_rad: float = math.radians(0.05),
        scale_sigma_frac: float = 0.01,
    ) -> None:
        if detector not in _DETECTORS:
            raise ValueError(f"unknown VO detector {detector!r}; valid: {sorted(_DETECTORS)}")
        if max_features < 8 or min_inliers < 4:
            raise ValueError(
                f"need max_features >= 8 and min_inliers >= 4, got {max_features}, {min_inliers}"
            )
        if not (
            0 < ratio_test <= 1
            and ransac_threshold_px > 0
            and max_gap_s > 0
            and rel_attitude_sigma_rad > 0
            and scale_sigma_frac > 0
        ):
            raise ValueError(
                "ratio_test must be in (0, 1]; ransac_threshold_px, max_gap_s, rel_attitude_sigma_rad and "
                "scale_sigma_frac must be > 0"
            )
        factory, norm = _DETECTORS[detector]
        self._calibration = calibration
        self._features = factory(max_features)
        self._matcher = cv2.BFMatcher(norm)
        self._min_inliers = min_inliers
        self._ratio = ratio_test
        self._ransac_px = ransac_threshold_px
        self._max_gap_usec = int(max_gap_s * 1e6)
        self._rel_attitude_sigma_rad = rel_attitude_sigma_rad
        self._scale_sigma_frac = scale_sigma_frac
        self._ref: _Reference | None = None

    def reset(self) -> None:
        """Forget the reference frame (the next frame starts a new chain)."""
        self._ref = None

    def process(self, frame: NavCameraFrame) -> VoMotion:
        """Motion of the camera from the previous usable frame to ``frame``.

        Raises :class:`VoError` (``reason`` from :class:`VoFailure`) when there is no trustworthy
        motion: the first frame, no attitude/altitude, low texture, too few matches/inliers, a time
        step that is not positive or longer than ``max_gap_s``.
        """
        cal = self._calibration
        if frame.width_px != cal.width_px or frame.height_px != cal.height_px:
            raise VoError(
                f"frame is {frame.width_px}x{frame.height_px}, calibration is {cal.width_px}x{cal.height_px}",
                reason=VoFailure.BAD_SIZE,
            )
        if frame.attitude is None:
            raise VoError(f"frame {frame.seq} has no attitude", reason=VoFailure.MISSING_ATTITUDE)
        alt = frame.alt_agl_m
        if alt is None or not math.isfinite(alt) or alt <= 0:
            raise VoError(f"frame {frame.seq} has no usable AGL ({alt!r})", reason=VoFailure.MISSING_ALTITUDE)

        grey = cv2.cvtColor(frame.image_bgr, cv2.COLOR_BGR2GRAY)
        keypoints, descriptors = self._features.detectAndCompute(grey, None)
        if descriptors is None or len(keypoints) < self._min_inliers:
            raise VoError(
                f"frame {frame.seq}: {len(keypoints)} features < {self._min_inliers}",
                reason=VoFailure.LOW_TEXTURE,
            )
        current = _Reference(
            frame_id=frame.frame_id,
            time_unix_usec=frame.exposure_time_unix_usec,
            keypoints_px=np.array([kp.pt for kp in keypoints], dtype=np.float32),
            descriptors=descriptors,
            r_ned_cam=frame.attitude.R_ned_cam(),
            alt_agl_m=float(alt),
        )
        previous, self._ref = self._ref, current
        if previous is None:
            raise VoError("first frame: reference stored", reason=VoFailure.FIRST_FRAME)
        dt_usec = current.time_unix_usec - previous.time_unix_usec
        if dt_usec <= 0:
            raise VoError(
                f"exposure time did not advance ({dt_usec} us)", reason=VoFailure.NON_INCREASING_TIME
            )
        if dt_usec > self._max_gap_usec:
            raise VoError(f"{dt_usec / 1e6:.2f} s since the reference frame", reason=VoFailure.GAP_TOO_LONG)

        prev_px, cur_px = self._match(previous, current)
        prev_norm, cur_norm = self._normalised(prev_px), self._normalised(cur_px)
        g_prev = self._ground_points(prev_norm, previous)
        g_cur = self._ground_points(cur_norm, current)
        valid = np.isfinite(g_prev[:, 0]) & np.isfinite(g_cur[:, 0])
        offsets = (g_prev - g_cur)[valid]
        n = offsets.shape[0]
        if n < self._min_inliers:
            raise VoError(f"{n} usable ground points < {self._min_inliers}", reason=VoFailure.TOO_FEW_INLIERS)
        delta_ne = np.median(offsets, axis=0)
        cov = (math.pi / 2.0) * np.cov(offsets.T) / n
        agl_m = 0.5 * (previous.alt_agl_m + current.alt_agl_m)
        common_var = (math.sqrt(2.0) * agl_m * self._rel_attitude_sigma_rad) ** 2 + (
            self._scale_sigma_frac * float(np.hypot(*delta_ne))
        ) ** 2
        cov = cov + np.eye(2) * common_var
        displacement_ned = np.array([delta_ne[0], delta_ne[1], previous.alt_agl_m - current.alt_agl_m])
        tilt = ground_tilt_off_cam_rad(
            prev_norm, cur_norm, previous.r_ned_cam, current.r_ned_cam, displacement_ned, previous.alt_agl_m
        )
        return VoMotion(
            frame_id=frame.frame_id,
            prev_frame_id=previous.frame_id,
            dt_s=dt_usec / 1e6,
            delta_ne_m=delta_ne,
            cov_ne_m2=cov,
            inlier_count=n,
            ground_tilt_off_cam_rad=tilt,
        )

    def _match(self, previous: _Reference, current: _Reference) -> tuple[np.ndarray, np.ndarray]:
        """Ratio-tested matches filtered by a RANSAC homography: (prev px (M, 2), current px (M, 2))."""
        pairs = self._matcher.knnMatch(previous.descriptors, current.descriptors, k=2)
        good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < self._ratio * p[1].distance]
        if len(good) < self._min_inliers:
            raise VoError(f"{len(good)} matches < {self._min_inliers}", reason=VoFailure.TOO_FEW_MATCHES)
        prev_px = previous.keypoints_px[[m.queryIdx for m in good]]
        cur_px = current.keypoints_px[[m.trainIdx for m in good]]
        _, mask = cv2.findHomography(
            prev_px, cur_px, cv2.RANSAC, self._ransac_px, maxIters=2000, confidence=0.995
        )
        if mask is None:
            raise VoError("homography RANSAC found no model", reason=VoFailure.TOO_FEW_INLIERS)
        inl = mask.ravel().astype(bool)
        if int(inl.sum()) < self._min_inliers:
            raise VoError(
                f"{int(inl.sum())} homography inliers < {self._min_inliers}", reason=VoFailure.TOO_FEW_INLIERS
            )
        return prev_px[inl], cur_px[inl]

    def _normalised(self, px: np.ndarray) -> np.ndarray:
        """(M, 2) pixels -> (M, 2) undistorted normalised image coordinates."""
        cal = self._calibration
        return cv2.undistortPoints(px.reshape(-1, 1, 2).astype(np.float64), cal.K, cal.dist).reshape(-1, 2)

    def _ground_points(self, norm: np.ndarray, ref: _Reference) -> np.ndarray:
        """(M, 2) normalised image points -> (M, 2) north/east of their ground points relative to the
        camera, metres; NaN rows for rays that do not reach the ground steeply enough."""
        rays_cam = np.hstack([norm, np.ones((norm.shape[0], 1))])
        rays_ned = rays_cam @ ref.r_ned_cam.T
        down_cos = rays_ned[:, 2] / np.linalg.norm(rays_ned, axis=1)
        scale = np.where(down_cos > _MIN_RAY_DOWN_COS, ref.alt_agl_m / rays_ned[:, 2], np.nan)
        return rays_ned[:, :2] * scale[:, None]
