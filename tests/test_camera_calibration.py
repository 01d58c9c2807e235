"""Reading an OpenCV calibration file: a real one loads; anything else is a CalibrationError naming it."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from gps_denied_onboard.camera.types import CalibrationError, CameraCalibration


def _write_calibration(path: Path, k: np.ndarray) -> Path:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", k)
    fs.write("distortion_coefficients", np.array([[0.1, -0.01, 0.0, 0.0, 0.0]]))
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.release()
    return path


def test_calibration_written_by_opencv_loads(tmp_path: Path) -> None:
    """A file written by cv2.FileStorage gives its intrinsics and distortion back."""
    k = np.array([[500.0, 0.0, 320.0], [0.0, 510.0, 240.0], [0.0, 0.0, 1.0]])
    cal = CameraCalibration.from_opencv_yaml(_write_calibration(tmp_path / "cam.yaml", k))
    assert (cal.width_px, cal.height_px, cal.fx_px, cal.fy_px, cal.cx_px, cal.cy_px) == (
        640,
        480,
        500.0,
        510.0,
        320.0,
        240.0,
    )
    assert cal.dist_coeffs == pytest.approx((0.1, -0.01, 0.0, 0.0, 0.0))


@pytest.mark.parametrize(
    ("content", "match"),
    [
        (b"garbage: [[[\x00\x01 not yaml %YAML\n", "not an OpenCV calibration file"),
        (b"\xff\xfe\x00binary", "not an OpenCV calibration file"),
        (b"%YAML:1.0\nimage_width: 640\n", "missing 'camera_matrix'"),
    ],
)
def test_calibration_garbage_is_a_calibration_error(tmp_path: Path, content: bytes, match: str) -> None:
    """A file OpenCV cannot parse, or one without a camera matrix, is refused naming the file."""
    path = tmp_path / "cam.yaml"
    path.write_bytes(content)
    with pytest.raises(CalibrationError, match=match) as err:
        CameraCalibration.from_opencv_yaml(path)
    assert err.value.path == str(path)


def test_calibration_non_finite_or_non_positive_focal_is_refused(tmp_path: Path) -> None:
    """A NaN in the camera matrix or a negative focal length is refused."""
    for name, fx in (("nan.yaml", float("nan")), ("neg.yaml", -500.0)):
        k = np.array([[fx, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
        with pytest.raises(CalibrationError, match="must be finite, with fx, fy > 0"):
            CameraCalibration.from_opencv_yaml(_write_calibration(tmp_path / name, k))
