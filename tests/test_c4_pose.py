"""C4 pose solver on synthetic geometry: a known camera over flat ground, projected with OpenCV."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import pytest
import structlog

from gps_denied_onboard.camera.types import Attitude, CameraCalibration, NavCameraFrame, new_frame_id
from gps_denied_onboard.components.c3_matcher.types import CandidateMatchSet
from gps_denied_onboard.components.c4_pose import PoseError, PoseRejectReason, PoseSolver
from gps_denied_onboard.components.c6_tiles.types import TileId
from gps_denied_onboard.config import PoseConfig
from gps_denied_onboard.constants import LogEvent
from gps_denied_onboard.geo import LocalTangentPlane

LTP = LocalTangentPlane(17.59, 78.12, 500.0)
GROUND_ALT_AMSL_M = 520.0
CALIB = CameraCalibration.from_hfov(640, 480, 70.0)
TRUE_POS_NED_M = np.array([300.0, -200.0, -(GROUND_ALT_AMSL_M - 500.0) - 120.0])
TRUE_ATT = Attitude(math.radians(2.0), math.radians(-3.0), math.radians(40.0))
_M_PER_DEG_LAT = 110_574.0


@dataclass(frozen=True)
class EquirectTile:
    """Test tile: a linear (equirectangular) georeference centred on (lat0, lon0)."""

    lat0_deg: float
    lon0_deg: float
    gsd: float = 0.3
    size_px: int = 1024

    @property
    def tile_id(self) -> TileId:
        return TileId.of(18, self.lat0_deg, self.lon0_deg)

    @property
    def gsd_m_px(self) -> float:
        return self.gsd

    def _deg_per_px(self) -> tuple[float, float]:
        dlat = self.gsd / _M_PER_DEG_LAT
        dlon = dlat / math.cos(math.radians(self.lat0_deg))
        return dlat, dlon

    def pixels(self) -> np.ndarray:
        return np.zeros((self.size_px, self.size_px, 3), np.uint8)

    def chip_px_to_lonlat(self, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dlat, dlon = self._deg_per_px()
        c = (self.size_px - 1) / 2.0
        p = np.asarray(px, dtype=np.float64)
        return self.lon0_deg + (p[:, 0] - c) * dlon, self.lat0_deg - (p[:, 1] - c) * dlat

    def lonlat_to_chip_px(self, lon_deg: np.ndarray, lat_deg: np.ndarray) -> np.ndarray:
        dlat, dlon = self._deg_per_px()
        c = (self.size_px - 1) / 2.0
        x = (np.asarray(lon_deg) - self.lon0_deg) / dlon + c
        y = (self.lat0_deg - np.asarray(lat_deg)) / dlat + c
        return np.stack([x, y], axis=-1)


def _tile_under_camera(pos_ned: np.ndarray = TRUE_POS_NED_M) -> EquirectTile:
    lat, lon, _ = LTP.to_geodetic(np.array([pos_ned[0] + 7.0, pos_ned[1] - 5.0, 0.0]))
    return EquirectTile(float(lat), float(lon))


def _scene(
    rng: np.random.Generator,
    n_pts: int = 100,
    noise_px: float = 0.5,
    *,
    pos_ned: np.ndarray = TRUE_POS_NED_M,
    att: Attitude = TRUE_ATT,
    calib: CameraCalibration = CALIB,
    img_px: np.ndarray | None = None,
) -> tuple[CandidateMatchSet, EquirectTile]:
    """Ground points seen by a camera at ``pos_ned`` with ``att``: correspondences + their tile."""
    r_ned_cam = att.R_ned_cam()
    if img_px is None:
        img_px = rng.uniform([20, 20], [calib.width_px - 20, calib.height_px - 20], size=(n_pts, 2))
    rays_cam = cv2.undistortPoints(img_px.reshape(-1, 1, 2), calib.K, calib.dist).reshape(-1, 2)
    rays_ned = np.hstack([rays_cam, np.ones((len(rays_cam), 1))]) @ r_ned_cam.T
    d_ground = LTP.to_ned(LTP.origin_lat_deg, LTP.origin_lon_deg, GROUND_ALT_AMSL_M)[2]
    approx = pos_ned + rays_ned * ((d_ground - pos_ned[2]) / rays_ned[:, 2:3])
    lat, lon, _ = LTP.to_geodetic(approx)
    ground = LTP.to_ned(lat, lon, np.full(len(lat), GROUND_ALT_AMSL_M))  # exactly on the ellipsoid shell
    r_cam_ned = r_ned_cam.T
    rvec, _ = cv2.Rodrigues(r_cam_ned)
    tvec = -r_cam_ned @ pos_ned
    proj, _ = cv2.projectPoints(ground, rvec, tvec, calib.K, calib.dist)
    obs = proj.reshape(-1, 2) + rng.normal(0.0, noise_px, size=(len(ground), 2))
    tile = _tile_under_camera(pos_ned)
    chip = tile.lonlat_to_chip_px(lon, lat)
    corr = np.hstack([obs, chip]).astype(np.float32)
    cand = CandidateMatchSet(tile.tile_id, len(corr), corr, 0, noise_px)
    return cand, tile


def _frame(att: Attitude | None = TRUE_ATT, alt_agl_m: float | None = 120.0) -> NavCameraFrame:
    return NavCameraFrame(
        frame_id=new_frame_id(),
        seq=1,
        exposure_time_unix_usec=1_700_000_000_000_000,
        image_bgr=np.zeros((480, 640, 3), np.uint8),
        attitude=att,
        alt_agl_m=alt_agl_m,
        received_monotonic_ns=0,
    )


def _solver(**cfg: float) -> PoseSolver:
    return PoseSolver(PoseConfig(**cfg), LTP, GROUND_ALT_AMSL_M)


def test_pose_solve_recovers_known_position() -> None:
    """100 points, 0.5 px noise at 120 m AGL -> camera position within 0.5 m and yaw within 0.5 deg."""
    cand, tile = _scene(np.random.default_rng(1))
    fix = _solver().solve(_frame(), cand, tile, CALIB)
    assert np.linalg.norm(fix.pos_ned_m - TRUE_POS_NED_M) < 0.5
    assert abs(fix.alt_amsl_m - (GROUND_ALT_AMSL_M + 120.0)) < 0.5
    lat, lon, _ = LTP.to_geodetic(TRUE_POS_NED_M)
    assert abs(fix.lat_deg - lat) * _M_PER_DEG_LAT < 0.5
    assert abs(fix.lon_deg - lon) * _M_PER_DEG_LAT * math.cos(math.radians(lat)) < 0.5
    assert abs(math.degrees(fix.yaw_rad - TRUE_ATT.yaw_rad)) < 0.5
    assert 0.0 < fix.yaw_sigma_rad < math.radians(1.0)
    assert fix.attitude_disagreement_rad < math.radians(0.5)
    assert fix.inlier_count == 100
    assert 0.3 < fix.residual_px < 1.0
    assert fix.tile_id == tile.tile_id
    assert fix.cov_ned_m2.shape == (3, 3)
    assert np.all(np.linalg.eigvalsh(fix.cov_ned_m2) > 0)


def test_pose_solve_with_lens_distortion() -> None:
    """Distorted observations are undistorted with the calibration (position still within 0.5 m)."""
    calib = CameraCalibration(640, 480, 457.0, 457.0, 322.0, 236.0, (-0.25, 0.08, 0.001, -0.0005, 0.0))
    cand, tile = _scene(np.random.default_rng(2), calib=calib)
    fix = _solver().solve(_frame(), cand, tile, calib)
    assert np.linalg.norm(fix.pos_ned_m - TRUE_POS_NED_M) < 0.5


def test_pose_yaw_follows_body_heading() -> None:
    """The fix's yaw is the body yaw through the nadir mount (image top = nose), for any heading."""
    for yaw_deg in (-170.0, -60.0, 0.0, 95.0):
        att = Attitude(0.0, 0.0, math.radians(yaw_deg))
        cand, tile = _scene(np.random.default_rng(3), att=att)
        fix = _solver().solve(_frame(att), cand, tile, CALIB)
        err = (fix.yaw_rad - att.yaw_rad + math.pi) % (2 * math.pi) - math.pi
        assert abs(math.degrees(err)) < 0.5, yaw_deg


@pytest.mark.parametrize("alt_agl_m", [120.0, 1200.0])
def test_pose_covariance_consistent_monte_carlo(alt_agl_m: float) -> None:
    """Mean normalised position error squared over 60 trials is near 3 (3 dof): the covariance is honest,
    with independent pixel noise and an autopilot attitude off by the stated sigma. At 120 m AGL the
    image pins the tilt; at 1200 m the attitude prior carries much of it."""
    rng = np.random.default_rng(4)
    sigma_att_deg = 0.5
    solver = _solver(min_sigma_m=1e-4, attitude_sigma_deg=sigma_att_deg, max_independent_matches=10_000)
    pos = np.array([TRUE_POS_NED_M[0], TRUE_POS_NED_M[1], -(GROUND_ALT_AMSL_M - 500.0) - alt_agl_m])
    nees = []
    for _ in range(60):
        cand, tile = _scene(rng, n_pts=60, noise_px=1.0, pos_ned=pos)
        d_roll, d_pitch = np.radians(rng.normal(0.0, sigma_att_deg, 2))
        reported = Attitude(TRUE_ATT.roll_rad + d_roll, TRUE_ATT.pitch_rad + d_pitch, TRUE_ATT.yaw_rad)
        fix = solver.solve(_frame(reported, alt_agl_m), cand, tile, CALIB)
        err = fix.pos_ned_m - pos
        nees.append(float(err @ np.linalg.solve(fix.cov_ned_m2, err)))
    assert 1.5 < float(np.mean(nees)) < 5.0


def test_the_autopilot_tilt_steadies_a_fix_the_image_cannot_pin() -> None:
    """At 1200 m AGL a degree of tilt is 21 m on the ground, and 2 px of match noise leaves the image's
    own tilt loose: the attitude prior halves the position error of the image-only pose, the fix's
    sigma covers what is left, and the prior's part of that sigma is carried as shared error."""
    rng = np.random.default_rng(7)
    pos = np.array([TRUE_POS_NED_M[0], TRUE_POS_NED_M[1], -(GROUND_ALT_AMSL_M - 500.0) - 1200.0])
    image_only = _solver(attitude_sigma_deg=90.0, max_independent_matches=100_000)
    with_prior = _solver()
    err_image, err_prior = [], []
    for _ in range(30):
        cand, tile = _scene(rng, n_pts=150, noise_px=2.0, pos_ned=pos)
        a = image_only.solve(_frame(alt_agl_m=1200.0), cand, tile, CALIB)
        b = with_prior.solve(_frame(alt_agl_m=1200.0), cand, tile, CALIB)
        err_image.append(float(np.hypot(*(a.pos_ned_m - pos)[:2])))
        err_prior.append(float(np.hypot(*(b.pos_ned_m - pos)[:2])))
        assert err_prior[-1] < 3.0 * b.horiz_sigma_m
        assert PoseConfig().min_sigma_m < b.shared_sigma_m < b.horiz_sigma_m
    assert np.mean(err_prior) < 0.6 * np.mean(err_image), (np.mean(err_prior), np.mean(err_image))


def test_pose_sigma_grows_with_pixel_noise() -> None:
    """More pixel noise -> larger position sigma (the covariance comes from the residuals)."""
    solver = _solver(min_sigma_m=1e-4)
    low = solver.solve(
        _frame(), _scene(np.random.default_rng(5), noise_px=0.3)[0], _tile_under_camera(), CALIB
    )
    high = solver.solve(
        _frame(), _scene(np.random.default_rng(5), noise_px=3.0)[0], _tile_under_camera(), CALIB
    )
    assert np.trace(high.cov_ned_m2) > 20.0 * np.trace(low.cov_ned_m2)


def test_pose_sigma_floored_by_config() -> None:
    """Per-axis sigma never drops below min_sigma_m, however small the residuals."""
    cand, tile = _scene(np.random.default_rng(6), noise_px=0.05)
    fix = _solver(min_sigma_m=2.0).solve(_frame(), cand, tile, CALIB)
    assert np.all(np.sqrt(np.diag(fix.cov_ned_m2)) >= 2.0 - 1e-9)
    assert fix.horiz_sigma_m >= 2.0 - 1e-9


def _rejection(solver: PoseSolver, frame: NavCameraFrame, cand: CandidateMatchSet, tile: EquirectTile) -> str:
    with pytest.raises(PoseError) as info:
        solver.solve(frame, cand, tile, CALIB)
    return info.value.reason


def test_pose_rejects_too_few_inliers() -> None:
    """Fewer inliers than min_inliers -> too_few_inliers, logged as c4.pose.rejected."""
    cand, tile = _scene(np.random.default_rng(7), n_pts=10)
    with structlog.testing.capture_logs() as logs:
        reason = _rejection(_solver(min_inliers=12), _frame(), cand, tile)
    assert reason == PoseRejectReason.TOO_FEW_INLIERS
    assert any(e["event"] == LogEvent.POSE_REJECTED and e["reason"] == reason for e in logs)


def test_pose_rejects_collinear_points() -> None:
    """Inliers along one image line (plus sub-pixel jitter) -> degenerate_geometry."""
    rng = np.random.default_rng(8)
    t = rng.uniform(0, 1, 60)
    line = np.stack([40 + 560 * t, 60 + 360 * t], axis=1) + rng.normal(0, 0.5, (60, 2))
    cand, tile = _scene(rng, img_px=line, noise_px=0.2)
    assert _rejection(_solver(), _frame(), cand, tile) == PoseRejectReason.DEGENERATE_GEOMETRY


def test_pose_rejects_altitude_disagreement() -> None:
    """Solved AGL 120 m vs autopilot 60 m -> altitude_disagreement; unknown AGL skips the check."""
    cand, tile = _scene(np.random.default_rng(9))
    assert _rejection(_solver(), _frame(alt_agl_m=60.0), cand, tile) == PoseRejectReason.ALTITUDE_DISAGREEMENT
    fix = _solver().solve(_frame(alt_agl_m=None), cand, tile, CALIB)
    assert np.linalg.norm(fix.pos_ned_m - TRUE_POS_NED_M) < 0.5


def test_pose_rejects_attitude_disagreement() -> None:
    """Autopilot says 25 deg roll while the image says ~2 deg -> attitude_disagreement."""
    cand, tile = _scene(np.random.default_rng(10))
    wrong = Attitude(math.radians(25.0), TRUE_ATT.pitch_rad, TRUE_ATT.yaw_rad)
    assert _rejection(_solver(), _frame(att=wrong), cand, tile) == PoseRejectReason.ATTITUDE_DISAGREEMENT


def test_pose_rejects_missing_attitude() -> None:
    """A frame without attitude cannot give an absolute fix."""
    cand, tile = _scene(np.random.default_rng(11))
    assert _rejection(_solver(), _frame(att=None), cand, tile) == PoseRejectReason.MISSING_ATTITUDE


def test_pose_rejects_non_finite_correspondences() -> None:
    """NaN in the inliers -> invalid_correspondences rather than a NaN pose."""
    cand, tile = _scene(np.random.default_rng(12))
    corr = cand.inlier_correspondences.copy()
    corr[3, 2] = np.nan
    bad = CandidateMatchSet(cand.tile_id, cand.inlier_count, corr, 0, 0.5)
    assert _rejection(_solver(), _frame(), bad, tile) == PoseRejectReason.INVALID_CORRESPONDENCES


def test_pose_rejects_solver_failure(monkeypatch: pytest.MonkeyPatch) -> None:
    """An OpenCV error inside PnP becomes solver_failed (with the cause chained)."""
    cand, tile = _scene(np.random.default_rng(13))

    def broken(*_args: object, **_kwargs: object) -> None:
        raise cv2.error("synthetic failure")

    monkeypatch.setattr(cv2, "solvePnPGeneric", broken)
    with pytest.raises(PoseError) as info:
        _solver().solve(_frame(), cand, tile, CALIB)
    assert info.value.reason == PoseRejectReason.SOLVER_FAILED
    assert isinstance(info.value.__cause__, cv2.error)


def test_pose_rejects_non_finite_covariance(monkeypatch: pytest.MonkeyPatch) -> None:
    """A Jacobian with NaNs (e.g. a numerically broken projection) -> non_finite_covariance."""
    cand, tile = _scene(np.random.default_rng(14))
    real = cv2.projectPoints

    def nan_jacobian(*args: Any, **kwargs: Any) -> tuple[np.ndarray, np.ndarray]:
        proj, jac = real(*args, **kwargs)
        return proj, np.full_like(jac, np.nan)

    monkeypatch.setattr(cv2, "projectPoints", nan_jacobian)
    assert _rejection(_solver(), _frame(), cand, tile) == PoseRejectReason.NON_FINITE_COVARIANCE
