"""Contracts for what the camera side hands to the pipeline.

Frames and axes
---------------
- World frame: local NED (north, east, down), metres, origin set by the estimator.
- Body frame: FRD (forward, right, down); attitude is roll/pitch/yaw (ZYX Tait-Bryan, radians) of body in
  NED, as in MAVLink ATTITUDE.
- Camera frame: OpenCV (x right in the image, y down in the image, z along the optical axis). The nav
  camera looks straight down with the top of the image towards the nose: x_cam = body right,
  y_cam = body backward, z_cam = body down (``R_BODY_CAM``).
"""

from __future__ import annotations

import math
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import numpy as np

#: Rotation taking camera-frame vectors to body-frame (FRD) vectors for the nadir mount.
R_BODY_CAM: np.ndarray = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
R_BODY_CAM.setflags(write=False)

#: The largest calibration file read (OpenCV's are a few hundred bytes), bytes.
MAX_CALIBRATION_FILE_BYTES: Final[int] = 1 << 20


class CalibrationError(ValueError):
    """A calibration file or block is missing, malformed or inconsistent."""

    def __init__(self, message: str, *, path: str | None = None) -> None:
        super().__init__(f"{path}: {message}" if path else message)
        self.path = path


@dataclass(frozen=True)
class CameraCalibration:
    """Pinhole intrinsics with OpenCV distortion (k1, k2, p1, p2[, k3...]) for one image size."""

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    dist_coeffs: tuple[float, ...] = ()

    @property
    def K(self) -> np.ndarray:
        """Camera matrix, (3, 3) float64."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        """Distortion coefficients, (n,) float64 (empty when there is no distortion)."""
        return np.asarray(self.dist_coeffs, dtype=np.float64)

    @property
    def hfov_rad(self) -> float:
        return 2.0 * math.atan2(self.width_px / 2.0, self.fx_px)

    @classmethod
    def from_hfov(cls, width_px: int, height_px: int, hfov_deg: float) -> CameraCalibration:
        """Ideal pinhole with square pixels and a centred principal point."""
        fx = (width_px / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(width_px, height_px, fx, fx, (width_px - 1) / 2.0, (height_px - 1) / 2.0, ())

    @classmethod
    def from_opencv_yaml(cls, path: str | Path) -> CameraCalibration:
        """Read an OpenCV calibration file (``camera_matrix``, ``distortion_coefficients``,
        ``image_width``, ``image_height``), as written by OpenCV's calibration sample."""
        import cv2

        p = Path(path)
        if not p.is_file():
            raise CalibrationError("calibration file not found", path=str(p))
        size = p.stat().st_size
        if size > MAX_CALIBRATION_FILE_BYTES:  # OpenCV would parse all of it, in memory
            raise CalibrationError(
                f"{size} bytes, more than the {MAX_CALIBRATION_FILE_BYTES} a calibration file takes",
                path=str(p),
            )
        try:
            fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
            try:
                k_node = fs.getNode("camera_matrix")
                if k_node.empty():
                    raise CalibrationError("missing 'camera_matrix' (expected a 3x3 matrix)", path=str(p))
                k = k_node.mat()
                if k is None or k.shape != (3, 3):
                    raise CalibrationError("'camera_matrix' must be 3x3", path=str(p))
                d_node = fs.getNode("distortion_coefficients")
                d_mat = None if d_node.empty() else d_node.mat()
                if not d_node.empty() and d_mat is None:
                    raise CalibrationError("'distortion_coefficients' must be a matrix", path=str(p))
                d = () if d_mat is None else tuple(float(v) for v in d_mat.ravel())
                w = int(fs.getNode("image_width").real())
                h = int(fs.getNode("image_height").real())
            finally:
                fs.release()
        except (cv2.error, SystemError) as exc:
            # A file OpenCV cannot parse: its YAML parser raises cv2.error, which OpenCV 5's binding
            # re-raises from FileStorage's constructor as a SystemError chained to it.
            reason = exc.__cause__ if isinstance(exc, SystemError) and exc.__cause__ is not None else exc
            raise CalibrationError(
                f"not an OpenCV calibration file: {' '.join(str(reason).split())}", path=str(p)
            ) from exc
        if w <= 0 or h <= 0:
            raise CalibrationError("missing or non-positive 'image_width'/'image_height'", path=str(p))
        fx, fy, cx, cy = float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])
        if not all(math.isfinite(v) for v in (fx, fy, cx, cy, *d)) or fx <= 0 or fy <= 0:
            raise CalibrationError(
                "'camera_matrix' and 'distortion_coefficients' must be finite, with fx, fy > 0", path=str(p)
            )
        return cls(w, h, fx, fy, cx, cy, d)


@dataclass(frozen=True)
class Attitude:
    """Body attitude in NED at one instant, radians (MAVLink ATTITUDE convention)."""

    roll_rad: float
    pitch_rad: float
    yaw_rad: float

    def R_ned_body(self) -> np.ndarray:
        """Rotation body(FRD) -> NED, (3, 3) float64, ZYX order."""
        cr, sr = math.cos(self.roll_rad), math.sin(self.roll_rad)
        cp, sp = math.cos(self.pitch_rad), math.sin(self.pitch_rad)
        cy, sy = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return np.array(
            [
                [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                [-sp, cp * sr, cp * cr],
            ]
        )

    def R_ned_cam(self) -> np.ndarray:
        """Rotation camera -> NED for the nadir mount, (3, 3) float64."""
        return self.R_ned_body() @ R_BODY_CAM

    @classmethod
    def from_R_ned_body(cls, r_ned_body: np.ndarray) -> Attitude:
        """The ZYX roll, pitch and yaw of a body -> NED rotation (the inverse of :meth:`R_ned_body`)."""
        r = np.asarray(r_ned_body, dtype=np.float64)
        pitch = -math.asin(max(-1.0, min(1.0, float(r[2, 0]))))
        roll = math.atan2(float(r[2, 1]), float(r[2, 2]))
        return cls(roll, pitch, math.atan2(float(r[1, 0]), float(r[0, 0])))


@dataclass(frozen=True)
class CameraMount:
    """The nav camera's boresight: its rotation from the nominal nadir mount (``R_BODY_CAM``), rad, about
    the body's x (roll, forward) and then y (pitch, right) axes (``camera.mount_roll_deg``,
    ``camera.mount_pitch_deg``).

    The camera's attitude is then ``R_ned_body @ R_x(roll) @ R_y(pitch) @ R_BODY_CAM``. To first order a
    mount roll ``r`` and pitch ``p`` move world-down in the camera by ``(+r, +p)`` on its x and y axes:
    the image-minus-autopilot tilt the tilt checks see (``PoseFix.image_tilt_off_cam_rad``,
    ``VoMotion.ground_tilt_off_cam_rad``) is what the mount must add (``gdnav fdr boresight``). It holds
    an AHRS's roll/pitch bias as well as a mount's: from the camera's side the two are the same.
    """

    roll_rad: float = 0.0
    pitch_rad: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.roll_rad) and math.isfinite(self.pitch_rad)):
            raise ValueError(f"mount angles must be finite, got {self.roll_rad!r}, {self.pitch_rad!r}")

    @property
    def is_nadir(self) -> bool:
        return self.roll_rad == 0.0 and self.pitch_rad == 0.0

    def camera_attitude(self, autopilot: Attitude) -> Attitude:
        """The attitude whose nadir camera (``Attitude.R_ned_cam``) is this mount's camera on a body at
        ``autopilot``."""
        if self.is_nadir:
            return autopilot
        cr, sr = math.cos(self.roll_rad), math.sin(self.roll_rad)
        cp, sp = math.cos(self.pitch_rad), math.sin(self.pitch_rad)
        r_x = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
        r_y = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
        return Attitude.from_R_ned_body(autopilot.R_ned_body() @ r_x @ r_y)


@dataclass(frozen=True)
class FrameTiming:
    """How well a frame's exposure time is known, and what an error in it costs.

    ``down_rate_cam_rad_s``: how fast world-down moved in the camera at the exposure (the autopilot's
    attitude), camera x and y, rad/s; ``stamp_offset_s``: the camera lateness subtracted from its stamp;
    ``sigma_s``: 1-sigma of the exposure time after that (the camera's and the autopilot clock's doubt);
    ``ahrs_sigma_rad``: how far the autopilot's roll and pitch may stray after its recent manoeuvres
    (``VehicleStateTracker.ahrs_doubt_rad``), 1 sigma.
    """

    down_rate_cam_rad_s: tuple[float, float]
    stamp_offset_s: float
    sigma_s: float
    ahrs_sigma_rad: float = 0.0

    @property
    def tilt_sigma_rad(self) -> float:
        """The tilt error the timing doubt makes at this rate, rad (1 sigma)."""
        return math.hypot(*self.down_rate_cam_rad_s) * self.sigma_s

    @property
    def attitude_sigma_rad(self) -> float:
        """Everything this frame adds to the doubt of the autopilot's tilt, rad (1 sigma)."""
        return math.hypot(self.tilt_sigma_rad, self.ahrs_sigma_rad)


@dataclass(frozen=True)
class NavCameraFrame:
    """One nav-camera image and the vehicle state at its exposure.

    ``image_bgr``: (H, W, 3) uint8, BGR (OpenCV order). ``attitude`` and ``alt_agl_m`` are the
    autopilot's values interpolated to the exposure time, or None when they were stale or missing
    (the pipeline then must not produce an absolute fix from this frame).
    """

    frame_id: uuid.UUID
    seq: int
    exposure_time_unix_usec: int
    image_bgr: np.ndarray
    attitude: Attitude | None
    alt_agl_m: float | None
    received_monotonic_ns: int
    #: How well the exposure time is known (None in replays and tests that do not say).
    timing: FrameTiming | None = None
    #: Aircraft-side annotations (e.g. the source's own sequence); never used for navigation.
    meta: dict[str, object] = field(default_factory=dict, compare=False)

    @property
    def height_px(self) -> int:
        return int(self.image_bgr.shape[0])

    @property
    def width_px(self) -> int:
        return int(self.image_bgr.shape[1])


def new_frame_id() -> uuid.UUID:
    return uuid.uuid4()
