"""C4 pose solver: camera pose and position covariance from map-matched inliers on flat ground.

Input: a candidate's inliers (frame pixels, tile pixels and the tile's georeference), the calibration,
the autopilot's attitude and AGL at the exposure. Output: a ``PoseFix`` (position, covariance,
``shared_sigma_m``, the image-only tilt against the autopilot's) or a ``PoseError`` with a
:class:`PoseRejectReason`.

Rule, per candidate:
1. tile pixels -> (lon, lat) -> NED on the flat ground at ``ground_alt_amsl_m``;
2. image-only pose: planar PnP (``SOLVEPNP_IPPE``, both solutions; ``SOLVEPNP_SQPNP`` fallback) on
   centred points, then ``solvePnPRefineLM``; its residuals give ``sigma_px`` (dof 2I - 6);
3. pose with the attitude prior: a maximum a posteriori re-solve (``least_squares``, LM) with the camera's
   world-down direction against the autopilot's over ``PoseConfig.attitude_sigma_deg``; yaw stays the
   image's; at most ``max_independent_matches`` inliers count as independent evidence;
4. covariance: ``(J^T J)^-1`` of the whitened system, propagated to the camera centre, floored per axis
   at ``PoseConfig.min_sigma_m``; the floor and the attitude prior's share go into ``shared_sigma_m``;
5. gates: enough inliers, their spread, in front of the camera, height vs the autopilot's AGL, the
   image-only optical axis vs the autopilot's, a finite covariance.
Frames: world = local NED (m); camera = OpenCV; ``R_ned_cam = R^T``, optical axis in NED ``R[2, :]``.

Why the attitude prior and the floor: docs/design.md, "The attitude prior" and "`c4_pose/solver.py`: the
pose solver".
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import cv2
import numpy as np
import structlog
from scipy.optimize import least_squares

from gps_denied_onboard.camera.types import R_BODY_CAM, CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c3_matcher.types import CandidateMatchSet
from gps_denied_onboard.components.c4_pose.types import PoseError, PoseFix
from gps_denied_onboard.components.c6_tiles.types import TilePixelsHandle
from gps_denied_onboard.config import PoseConfig
from gps_denied_onboard.constants import LogEvent
from gps_denied_onboard.geo import LocalTangentPlane

_log = structlog.get_logger(__name__)

#: Default minimum standard deviation of the inliers along their minor principal axis, image px.
#: Below this the points are close to a line and the pose about that line is unobservable.
DEFAULT_MIN_SPREAD_PX: Final[float] = 8.0
#: IPPE returns two poses; a second one whose RMS error is within this factor of the best is
#: considered equally plausible and the autopilot's attitude picks between them.
_IPPE_AMBIGUITY_RATIO: Final[float] = 1.5
#: Step of the numerical derivatives with respect to the rotation vector, radians.
_ROT_EPS_RAD: Final[float] = 1e-6
#: Floor on the image noise the attitude prior is weighed against, px (exact synthetic matches).
_MIN_SIGMA_PX: Final[float] = 1e-3


class PoseRejectReason:
    """Values of ``PoseError.reason`` (logged with ``c4.pose.rejected`` and recorded by the FDR)."""

    TOO_FEW_INLIERS: Final = "too_few_inliers"
    INVALID_CORRESPONDENCES: Final = "invalid_correspondences"
    MISSING_ATTITUDE: Final = "missing_attitude"
    DEGENERATE_GEOMETRY: Final = "degenerate_geometry"
    SOLVER_FAILED: Final = "solver_failed"
    BEHIND_CAMERA: Final = "behind_camera"
    ALTITUDE_DISAGREEMENT: Final = "altitude_disagreement"
    ATTITUDE_DISAGREEMENT: Final = "attitude_disagreement"
    NON_FINITE_COVARIANCE: Final = "non_finite_covariance"


def _camera_centre(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    rot, _ = cv2.Rodrigues(rvec)
    return -rot.T @ tvec.reshape(3)


def _body_yaw_rad(rvec: np.ndarray) -> float:
    """Body yaw (NED, radians) of the solution, through the nadir mount (image top = nose)."""
    rot, _ = cv2.Rodrigues(rvec)
    r_ned_body = rot.T @ R_BODY_CAM.T
    return math.atan2(r_ned_body[1, 0], r_ned_body[0, 0])


def _wrap_pi(angle_rad: float) -> float:
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


class PoseSolver:
    """Absolute camera pose from a C3 candidate's inliers, its tile georeference and the calibration.

    ``config``: the ``pose`` section. ``ltp``: the flight's NED frame. ``ground_alt_amsl_m``: the
    flat-ground height (``terrain.ground_alt_amsl_m``). ``min_spread_px``: degeneracy threshold, see
    :data:`DEFAULT_MIN_SPREAD_PX`.
    """

    def __init__(
        self,
        config: PoseConfig,
        ltp: LocalTangentPlane,
        ground_alt_amsl_m: float,
        *,
        min_spread_px: float = DEFAULT_MIN_SPREAD_PX,
    ) -> None:
        if not math.isfinite(ground_alt_amsl_m):
            raise ValueError(f"ground_alt_amsl_m must be finite, got {ground_alt_amsl_m!r}")
        if not min_spread_px > 0:
            raise ValueError(f"min_spread_px must be > 0, got {min_spread_px!r}")
        self._config = config
        self._ltp = ltp
        self._ground_alt_amsl_m = float(ground_alt_amsl_m)
        self._min_spread_px = float(min_spread_px)

    def solve(
        self,
        frame: NavCameraFrame,
        candidate: CandidateMatchSet,
        tile: TilePixelsHandle,
        calibration: CameraCalibration,
        *,
        attitude_doubt_rad: float = 0.0,
    ) -> PoseFix:
        """Solve the camera pose for ``frame`` from ``candidate``'s inliers on ``tile``.
        ``attitude_doubt_rad``: a tilt error the autopilot's attitude may carry beyond
        ``PoseConfig.attitude_sigma_deg`` (a tilt check has shown one): the attitude prior is widened by
        it, so that the fix leans on the autopilot's tilt no more than that allows.

        Raises :class:`PoseError` (``reason`` from :class:`PoseRejectReason`) when the pose cannot be
        solved or is implausible; the rejection is logged as ``c4.pose.rejected``.
        """
        try:
            return self._solve(frame, candidate, tile, calibration, attitude_doubt_rad)
        except PoseError as exc:
            _log.warning(
                LogEvent.POSE_REJECTED,
                reason=exc.reason,
                detail=str(exc),
                frame_id=str(frame.frame_id),
                tile_id=tuple(candidate.tile_id),
                inliers=int(np.asarray(candidate.inlier_correspondences).shape[0]),
            )
            raise

    # -- steps -------------------------------------------------------------------------------------------

    def _reject(self, message: str, reason: str, frame: NavCameraFrame) -> PoseError:
        return PoseError(message, reason=reason, frame_id=frame.frame_id)

    def _solve(
        self,
        frame: NavCameraFrame,
        candidate: CandidateMatchSet,
        tile: TilePixelsHandle,
        calibration: CameraCalibration,
        attitude_doubt_rad: float,
    ) -> PoseFix:
        cfg = self._config
        corr = np.asarray(candidate.inlier_correspondences, dtype=np.float64)
        if corr.ndim != 2 or corr.shape[1] != 4:
            raise self._reject(
                f"inlier_correspondences must be (I, 4), got {corr.shape}",
                PoseRejectReason.INVALID_CORRESPONDENCES,
                frame,
            )
        n_pts = corr.shape[0]
        if n_pts < cfg.min_inliers:
            raise self._reject(
                f"{n_pts} inliers < min_inliers {cfg.min_inliers}", PoseRejectReason.TOO_FEW_INLIERS, frame
            )
        if not np.all(np.isfinite(corr)):
            raise self._reject(
                "non-finite inlier coordinates", PoseRejectReason.INVALID_CORRESPONDENCES, frame
            )
        if frame.attitude is None:
            # The frame contract: without a fresh attitude no absolute fix may come from this frame.
            raise self._reject("frame has no attitude", PoseRejectReason.MISSING_ATTITUDE, frame)

        img_px = np.ascontiguousarray(corr[:, 0:2])
        spread_px = self._minor_axis_std_px(img_px)
        if spread_px < self._min_spread_px:
            raise self._reject(
                f"inliers nearly collinear: minor-axis std {spread_px:.2f} px < {self._min_spread_px} px",
                PoseRejectReason.DEGENERATE_GEOMETRY,
                frame,
            )

        lon, lat = tile.chip_px_to_lonlat(np.ascontiguousarray(corr[:, 2:4]))
        world_ned = self._ltp.to_ned(lat, lon, np.full(n_pts, self._ground_alt_amsl_m))
        if not np.all(np.isfinite(world_ned)):
            raise self._reject(
                "tile georeference gave non-finite ground points",
                PoseRejectReason.INVALID_CORRESPONDENCES,
                frame,
            )
        centroid = world_ned.mean(axis=0)
        obj = np.ascontiguousarray(world_ned - centroid)
        k_mat, dist = calibration.K, calibration.dist
        expected_axis = frame.attitude.R_ned_cam()[:, 2]

        rvec0, tvec0 = self._pnp(obj, img_px, k_mat, dist, expected_axis, frame)
        rot0, _ = cv2.Rodrigues(rvec0)
        if not np.all((obj @ rot0.T + tvec0.reshape(1, 3))[:, 2] > 0):
            raise self._reject(
                "solution puts ground points behind the camera", PoseRejectReason.BEHIND_CAMERA, frame
            )
        # The image's own verdict on the attitude, before the prior pulls the tilt towards it.
        disagreement_rad = float(np.arccos(np.clip(rot0[2, :] @ expected_axis, -1.0, 1.0)))
        # The same on the camera's own x and y axes (fixed to the airframe: where a mount error is constant).
        down_off_cam = rot0[:, 2] - frame.attitude.R_ned_cam()[2, :]
        if disagreement_rad > math.radians(cfg.max_attitude_disagreement_deg):
            raise self._reject(
                f"optical axis {math.degrees(disagreement_rad):.1f} deg from the autopilot's "
                f"(> {cfg.max_attitude_disagreement_deg} deg)",
                PoseRejectReason.ATTITUDE_DISAGREEMENT,
                frame,
            )
        obs = _Observations(obj, img_px, k_mat, dist)
        # Correlated match errors: no more than max_independent_matches count as independent.
        dependence = math.sqrt(max(1.0, n_pts / cfg.max_independent_matches))
        sigma_px = _image_sigma_px(obs, rvec0, tvec0) * dependence
        # the autopilot's tilt, as well as the timing doubt at this attitude rate and its own recent
        # manoeuvres let it be known, and as far as a tilt check has shown it off
        timing_rad = frame.timing.attitude_sigma_rad if frame.timing is not None else 0.0
        prior = _TiltPrior(
            frame.attitude.R_ned_cam()[2, :],
            math.hypot(math.radians(cfg.attitude_sigma_deg), timing_rad, attitude_doubt_rad),
        )
        rvec, tvec = self._with_attitude_prior(obs, rvec0, tvec0, sigma_px, prior, frame)
        rot, _ = cv2.Rodrigues(rvec)
        if not np.all((obj @ rot.T + tvec.reshape(1, 3))[:, 2] > 0):
            raise self._reject(
                "solution puts ground points behind the camera", PoseRejectReason.BEHIND_CAMERA, frame
            )

        centre_local = _camera_centre(rvec, tvec)
        pos_ned = centre_local + centroid
        lat_c, lon_c, alt_c = self._ltp.to_geodetic(pos_ned)
        alt_amsl = float(alt_c)
        agl_solved = alt_amsl - self._ground_alt_amsl_m
        if agl_solved <= 0:
            raise self._reject(
                f"solved camera is {agl_solved:.1f} m above ground", PoseRejectReason.BEHIND_CAMERA, frame
            )
        if frame.alt_agl_m is not None and frame.alt_agl_m > 0:
            frac = abs(agl_solved - frame.alt_agl_m) / frame.alt_agl_m
            if frac > cfg.max_alt_disagreement_frac:
                raise self._reject(
                    f"solved AGL {agl_solved:.1f} m vs autopilot {frame.alt_agl_m:.1f} m "
                    f"({frac:.0%} > {cfg.max_alt_disagreement_frac:.0%})",
                    PoseRejectReason.ALTITUDE_DISAGREEMENT,
                    frame,
                )

        cov_ned, prior_sigma_m, yaw_sigma, residual_med_px = self._covariance(
            obs, rvec, tvec, sigma_px, prior, frame
        )
        return PoseFix(
            frame_id=frame.frame_id,
            exposure_time_unix_usec=frame.exposure_time_unix_usec,
            pos_ned_m=pos_ned,
            cov_ned_m2=cov_ned,
            lat_deg=float(lat_c),
            lon_deg=float(lon_c),
            alt_amsl_m=alt_amsl,
            yaw_rad=_body_yaw_rad(rvec),
            yaw_sigma_rad=yaw_sigma,
            attitude_disagreement_rad=disagreement_rad,
            image_tilt_off_cam_rad=(float(down_off_cam[0]), float(down_off_cam[1])),
            inlier_count=n_pts,
            residual_px=residual_med_px,
            tile_id=candidate.tile_id,
            shared_sigma_m=math.hypot(self._config.min_sigma_m, prior_sigma_m),
            attitude_doubt_rad=float(attitude_doubt_rad),
        )

    @staticmethod
    def _minor_axis_std_px(img_px: np.ndarray) -> float:
        cov = np.cov(img_px.T)
        return float(np.sqrt(max(np.linalg.eigvalsh(cov)[0], 0.0)))

    def _pnp(
        self,
        obj: np.ndarray,
        img_px: np.ndarray,
        k_mat: np.ndarray,
        dist: np.ndarray,
        expected_axis: np.ndarray,
        frame: NavCameraFrame,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Planar PnP + LM refinement; the IPPE ambiguity is resolved with the autopilot's attitude."""
        candidates: list[tuple[np.ndarray, np.ndarray, float]] = []
        try:
            n_sol, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, img_px, k_mat, dist, flags=cv2.SOLVEPNP_IPPE)
            if n_sol:
                candidates = [(r, t, float(e)) for r, t, e in zip(rvecs, tvecs, np.ravel(errs), strict=True)]
            else:
                n_sol, rvecs, tvecs, errs = cv2.solvePnPGeneric(
                    obj, img_px, k_mat, dist, flags=cv2.SOLVEPNP_SQPNP
                )
                candidates = [(r, t, float(e)) for r, t, e in zip(rvecs, tvecs, np.ravel(errs), strict=True)]
        except cv2.error as exc:
            raise PoseError(
                f"OpenCV PnP failed: {exc}",
                reason=PoseRejectReason.SOLVER_FAILED,
                frame_id=frame.frame_id,
            ) from exc
        candidates = [c for c in candidates if np.all(np.isfinite(c[0])) and np.all(np.isfinite(c[1]))]
        if not candidates:
            raise self._reject("PnP returned no solution", PoseRejectReason.SOLVER_FAILED, frame)
        best_err = min(c[2] for c in candidates)
        plausible = [c for c in candidates if c[2] <= _IPPE_AMBIGUITY_RATIO * best_err + 1e-9]

        def axis_misfit(c: tuple[np.ndarray, np.ndarray, float]) -> float:
            rot, _ = cv2.Rodrigues(c[0])
            return -float(rot[2, :] @ expected_axis)

        rvec, tvec, _ = min(plausible, key=axis_misfit)
        rvec = np.array(rvec, dtype=np.float64).reshape(3, 1)
        tvec = np.array(tvec, dtype=np.float64).reshape(3, 1)
        try:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img_px, k_mat, dist, rvec, tvec)
        except cv2.error as exc:
            raise PoseError(
                "OpenCV solvePnPRefineLM failed",
                reason=PoseRejectReason.SOLVER_FAILED,
                frame_id=frame.frame_id,
            ) from exc
        if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
            raise self._reject("refined pose is not finite", PoseRejectReason.SOLVER_FAILED, frame)
        return rvec, tvec

    def _with_attitude_prior(
        self,
        obs: _Observations,
        rvec0: np.ndarray,
        tvec0: np.ndarray,
        sigma_px: float,
        prior: _TiltPrior,
        frame: NavCameraFrame,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The maximum a posteriori pose (step 3 of the module docstring), from the image-only one."""

        def residuals(p: np.ndarray) -> np.ndarray:
            image = obs.residuals_px(p[:3], p[3:]).reshape(-1) / sigma_px
            return np.concatenate([image, prior.residual(p[:3])])

        def jacobian(p: np.ndarray) -> np.ndarray:
            return _whitened_jacobian(obs, p[:3], p[3:], sigma_px, prior)

        x0 = np.concatenate([np.ravel(rvec0), np.ravel(tvec0)])
        try:
            sol = least_squares(residuals, x0, jac=jacobian, method="lm", x_scale="jac")
        except (ValueError, np.linalg.LinAlgError, cv2.error) as exc:
            raise PoseError(
                f"pose with the attitude prior failed: {exc}",
                reason=PoseRejectReason.SOLVER_FAILED,
                frame_id=frame.frame_id,
            ) from exc
        if not (sol.success and np.all(np.isfinite(sol.x))):
            raise self._reject(
                f"pose with the attitude prior did not converge: {sol.message}",
                PoseRejectReason.SOLVER_FAILED,
                frame,
            )
        return sol.x[:3].reshape(3, 1), sol.x[3:].reshape(3, 1)

    def _covariance(
        self,
        obs: _Observations,
        rvec: np.ndarray,
        tvec: np.ndarray,
        sigma_px: float,
        prior: _TiltPrior,
        frame: NavCameraFrame,
    ) -> tuple[np.ndarray, float, float, float]:
        """(camera-centre covariance NED m^2 (floored), horizontal 1-sigma m of the part of it that comes
        from the attitude prior, yaw sigma rad, median residual px)."""
        jac_w = _whitened_jacobian(obs, rvec, tvec, sigma_px, prior)
        try:
            cov_pose = np.linalg.inv(jac_w.T @ jac_w)
        except np.linalg.LinAlgError as exc:
            raise PoseError(
                "reprojection Jacobian is singular",
                reason=PoseRejectReason.NON_FINITE_COVARIANCE,
                frame_id=frame.frame_id,
            ) from exc
        # The estimate's sensitivity to the prior's own error: cov_pose J_p^T J_p cov_pose (whitened).
        jac_p = jac_w[-2:]
        cov_from_prior = cov_pose @ jac_p.T @ jac_p @ cov_pose

        # d C / d (rvec, tvec): C = -R(r)^T t; numerical in r (central differences), exact in t.
        rot, _ = cv2.Rodrigues(rvec)
        g = np.zeros((3, 6))
        g_yaw = np.zeros(6)
        for i in range(3):
            step = np.zeros((3, 1))
            step[i] = _ROT_EPS_RAD
            g[:, i] = (_camera_centre(rvec + step, tvec) - _camera_centre(rvec - step, tvec)) / (
                2 * _ROT_EPS_RAD
            )
            g_yaw[i] = _wrap_pi(_body_yaw_rad(rvec + step) - _body_yaw_rad(rvec - step)) / (2 * _ROT_EPS_RAD)
        g[:, 3:] = -rot.T
        cov_c = g @ cov_pose @ g.T
        cov_c = 0.5 * (cov_c + cov_c.T)
        cov_prior_ne = (g @ cov_from_prior @ g.T)[:2, :2]
        yaw_var = float(g_yaw @ cov_pose @ g_yaw)
        if not (np.all(np.isfinite(cov_c)) and math.isfinite(yaw_var) and np.all(np.isfinite(cov_prior_ne))):
            raise self._reject("pose covariance is not finite", PoseRejectReason.NON_FINITE_COVARIANCE, frame)
        floor_var = self._config.min_sigma_m**2
        # Adding a non-negative diagonal keeps the matrix positive semi-definite.
        cov_c = cov_c + np.diag(np.maximum(floor_var - np.diag(cov_c), 0.0))
        prior_var = float(np.max(np.linalg.eigvalsh(0.5 * (cov_prior_ne + cov_prior_ne.T))))
        prior_sigma_m = math.sqrt(max(prior_var, 0.0))
        residual_med = float(np.median(np.linalg.norm(obs.residuals_px(rvec, tvec), axis=1)))
        return cov_c, prior_sigma_m, math.sqrt(max(yaw_var, 0.0)), residual_med


class _TiltPrior:
    """The autopilot's tilt as two residuals: world down seen from the camera (``R[:, 2]`` of the
    world-to-camera rotation ``R``) projected on the two axes across the autopilot's own, in radians over
    ``sigma_rad``. Rotating about world down (yaw) leaves it unchanged, so it says nothing of yaw.

    ``down_in_cam``: (3,) world down in the camera frame by the autopilot's attitude (``R_ned_cam[2]``).
    """

    def __init__(self, down_in_cam: np.ndarray, sigma_rad: float) -> None:
        d = np.asarray(down_in_cam, dtype=np.float64)
        d = d / np.linalg.norm(d)
        helper = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        u1 = np.cross(d, helper)
        u1 /= np.linalg.norm(u1)
        self._basis = np.vstack([u1, np.cross(d, u1)])
        self._sigma_rad = float(sigma_rad)

    def residual(self, rvec: np.ndarray) -> np.ndarray:
        rot, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
        return (self._basis @ rot[:, 2]) / self._sigma_rad

    def jacobian(self, rvec: np.ndarray) -> np.ndarray:
        """(2, 3) derivative of :meth:`residual` over rvec (central differences)."""
        r = np.ravel(np.asarray(rvec, dtype=np.float64))
        out = np.zeros((2, 3))
        for i in range(3):
            step = np.zeros(3)
            step[i] = _ROT_EPS_RAD
            out[:, i] = (self.residual(r + step) - self.residual(r - step)) / (2 * _ROT_EPS_RAD)
        return out


@dataclass(frozen=True)
class _Observations:
    """The inliers as PnP sees them: ground points (NED, centred, m), their image px (I, 2), and the
    camera's intrinsics and distortion."""

    obj: np.ndarray
    img_px: np.ndarray
    k_mat: np.ndarray
    dist: np.ndarray

    def _project(self, rvec: np.ndarray, tvec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = np.asarray(rvec, dtype=np.float64).reshape(3, 1)
        t = np.asarray(tvec, dtype=np.float64).reshape(3, 1)
        proj, jac = cv2.projectPoints(self.obj, r, t, self.k_mat, self.dist)
        return proj.reshape(-1, 2), np.asarray(jac, dtype=np.float64)[:, :6]

    def residuals_px(self, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
        """(I, 2) projected minus observed, px."""
        return self._project(rvec, tvec)[0] - self.img_px

    def jacobian(self, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
        """(2I, 6) derivative of the projections over (rvec, tvec)."""
        return self._project(rvec, tvec)[1]


def _image_sigma_px(obs: _Observations, rvec: np.ndarray, tvec: np.ndarray) -> float:
    """Per-coordinate reprojection noise of a pose, px (dof-corrected, floored at :data:`_MIN_SIGMA_PX`
    so that exact synthetic matches still give a finite weight)."""
    resid = obs.residuals_px(rvec, tvec)
    dof = 2 * resid.shape[0] - 6
    return max(math.sqrt(float(np.sum(resid**2)) / dof), _MIN_SIGMA_PX)


def _whitened_jacobian(
    obs: _Observations, rvec: np.ndarray, tvec: np.ndarray, sigma_px: float, prior: _TiltPrior
) -> np.ndarray:
    """(2I + 2, 6) Jacobian over (rvec, tvec): reprojection rows over ``sigma_px``, then the prior's two."""
    rows = obs.jacobian(rvec, tvec) / sigma_px
    return np.vstack([rows, np.hstack([prior.jacobian(rvec), np.zeros((2, 3))])])
