"""C5 navigation estimator: constant-velocity Kalman filter (filterpy) over absolute fixes and VO.

State and units
---------------
``x = [n, e, d, vn, ve, vd]`` in the flight's local NED frame: metres and metres per second. Time is
Unix microseconds (the frames' exposure times). The motion model is constant velocity driven by
continuous white-noise acceleration with spectral density ``q = accel_noise_m_s2**2`` (m^2/s^3, i.e.
``accel_noise_m_s2`` is in m/s^2/sqrt(Hz)); per axis over ``dt`` seconds the discrete process noise is
``q * [[dt^3/3, dt^2/2], [dt^2/2, dt]]`` (filterpy's ``Q_continuous_white_noise``). The model is linear,
so the "EKF" is a plain Kalman filter; geodetic output goes through the tangent plane.

Measurements
------------
- Absolute fix (C4 ``PoseFix``): 3-D position with the fix's own covariance, gated by the Mahalanobis
  distance of its horizontal part (chi-square, 2 dof, ``fix_gate_chi2``) so one wrong tile match
  cannot teleport the estimate. Re-acquisition: once the horizontal sigma exceeds
  ``reacquire_sigma_m`` the gate is bypassed (see :meth:`NavEstimator.update_fix`).
- Visual odometry (C1 ``VoMotion``): the horizontal displacement over ``dt`` used as a measurement of
  the average velocity ``delta / dt`` on ``[vn, ve]``, with covariance ``vo_noise_scale * cov / dt^2``.
  Treating the interval's mean velocity as the current one is the usual approximation at a few Hz
  for a vehicle that does not change speed much within one frame interval.
- Altitude: the autopilot's AGL plus the flat-ground height, as a scalar update on ``d``.

Provenance (what was actually fused, see :meth:`NavEstimator.provenance_at`)
---------------------------------------------------------------------------
``satellite_anchored`` while the latest measurement fused was an accepted fix (no VO update after it)
and it is at most ``fix_recent_s`` old, so the label switches on the first frame without a fix;
``visual_propagated`` when, since that fix, VO updates keep being fused (the last at most
``vo_recent_s`` old); ``dead_reckoning`` when neither (prediction only); ``no_estimate`` when not
initialised or when the horizontal sigma exceeds ``max_output_sigma_m``.
"""

from __future__ import annotations

import math
from typing import Final

import numpy as np
import structlog
from filterpy.common import Q_continuous_white_noise
from filterpy.kalman import KalmanFilter

from gps_denied_onboard.components.c1_vio.types import VoMotion
from gps_denied_onboard.components.c4_pose.types import PoseFix
from gps_denied_onboard.components.c5_estimator.types import EstimatorState, FixDecision
from gps_denied_onboard.config import EstimatorConfig
from gps_denied_onboard.constants import LogEvent, Provenance
from gps_denied_onboard.geo import LocalTangentPlane

_log = structlog.get_logger(__name__)

#: An accepted fix younger than this keeps the output ``satellite_anchored``, seconds.
DEFAULT_FIX_RECENT_S: Final[float] = 1.0
#: A VO update younger than this (and newer than the last fix) makes the output ``visual_propagated``.
DEFAULT_VO_RECENT_S: Final[float] = 2.0
#: Fixes whose exposure is older than the filter time by more than this are dropped (out of order).
DEFAULT_MAX_FIX_LAG_S: Final[float] = 1.0

#: Consecutive gated fixes after which their disagreement is added to the position covariance.
CONSECUTIVE_GATED_INFLATE: Final[int] = 3
_H_POS = np.hstack([np.eye(3), np.zeros((3, 3))])
_H_VEL_NE = np.hstack([np.zeros((2, 3)), np.eye(3)[:2]])
_H_D = np.array([[0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])


class FixReason:
    """Values of ``FixDecision.reason``."""

    ACCEPTED: Final = "accepted"
    ACCEPTED_REACQUIRE: Final = "accepted_reacquire"
    GATED: Final = "gated"
    FIX_SIGMA_TOO_LARGE: Final = "fix_sigma_too_large"
    INVALID_MEASUREMENT: Final = "invalid_measurement"
    NOT_INITIALISED: Final = "not_initialised"
    STALE: Final = "stale"


def _is_covariance(cov: np.ndarray, dim: int) -> bool:
    """Finite, symmetric, positive definite ``(dim, dim)`` matrix."""
    if cov.shape != (dim, dim) or not np.all(np.isfinite(cov)):
        return False
    if not np.allclose(cov, cov.T, rtol=1e-6, atol=1e-9):
        return False
    return bool(np.all(np.linalg.eigvalsh(cov) > 0))


def _horiz_sigma_m(p_mat: np.ndarray) -> float:
    return float(np.sqrt(np.max(np.linalg.eigvalsh(p_mat[:2, :2]))))


class NavEstimator:
    """Fuses C4 fixes, C1 motion and the autopilot's altitude into the navigation state.

    ``config``: the ``estimator`` section; ``ltp``: the flight's NED frame (geodetic output).
    ``fix_recent_s`` / ``vo_recent_s``: provenance windows (see the module docstring);
    ``max_fix_lag_s``: how late a fix may arrive and still be fused (at the filter's current time).
    Not thread-safe: one pipeline worker owns it.
    """

    def __init__(
        self,
        config: EstimatorConfig,
        ltp: LocalTangentPlane,
        *,
        fix_recent_s: float = DEFAULT_FIX_RECENT_S,
        vo_recent_s: float = DEFAULT_VO_RECENT_S,
        max_fix_lag_s: float = DEFAULT_MAX_FIX_LAG_S,
    ) -> None:
        for name, value in (
            ("fix_recent_s", fix_recent_s),
            ("vo_recent_s", vo_recent_s),
            ("max_fix_lag_s", max_fix_lag_s),
        ):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number of seconds, got {value!r}")
        self._config = config
        self._ltp = ltp
        self._fix_recent_s = fix_recent_s
        self._vo_recent_s = vo_recent_s
        self._max_fix_lag_s = max_fix_lag_s
        self._kf = KalmanFilter(dim_x=6, dim_z=3)
        self._time_usec: int | None = None
        self._last_fix_usec: int | None = None
        self._consecutive_gated = 0
        self._last_vo_usec: int | None = None
        self._yaw_rad: float | None = None
        self._provenance = Provenance.NO_ESTIMATE

    # -- lifecycle ----------------------------------------------------------------------------------------

    @property
    def is_initialised(self) -> bool:
        return self._time_usec is not None

    @property
    def time_unix_usec(self) -> int | None:
        """Time of the filter's current estimate, or None before :meth:`initialise`."""
        return self._time_usec

    @property
    def provenance(self) -> Provenance:
        """The label at the filter's current time (as last logged)."""
        return self._provenance

    def initialise(
        self,
        pos_ned_m: np.ndarray,
        sigma_m: float,
        time_unix_usec: int,
        *,
        vel_sigma_m_s: float = 10.0,
    ) -> None:
        """(Re)start at ``pos_ned_m`` (3,) with 1-sigma ``sigma_m`` per axis, at rest with
        ``vel_sigma_m_s`` per axis. Forgets previous fixes, VO and yaw."""
        pos = np.asarray(pos_ned_m, dtype=np.float64).reshape(-1)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)):
            raise ValueError(f"pos_ned_m must be 3 finite numbers, got {pos_ned_m!r}")
        for name, value in (("sigma_m", sigma_m), ("vel_sigma_m_s", vel_sigma_m_s)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value!r}")
        self._kf.x = np.concatenate([pos, np.zeros(3)]).reshape(6, 1)
        self._kf.P = np.diag([sigma_m**2] * 3 + [vel_sigma_m_s**2] * 3)
        self._time_usec = int(time_unix_usec)
        self._last_fix_usec = None
        self._consecutive_gated = 0
        self._last_vo_usec = None
        self._yaw_rad = None
        _log.info(
            LogEvent.ESTIMATOR_INITIALISED,
            pos_ned_m=pos.tolist(),
            sigma_m=sigma_m,
            vel_sigma_m_s=vel_sigma_m_s,
            time_unix_usec=self._time_usec,
        )
        self._refresh_provenance()

    # -- prediction ---------------------------------------------------------------------------------------

    def _transition(self, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        f_mat = np.eye(6)
        f_mat[0:3, 3:6] = dt_s * np.eye(3)
        q_mat = Q_continuous_white_noise(
            dim=2,
            dt=dt_s,
            spectral_density=self._config.accel_noise_m_s2**2,
            block_size=3,
            order_by_dim=False,
        )
        return f_mat, q_mat

    def predict_to(self, time_unix_usec: int) -> None:
        """Propagate the state to ``time_unix_usec``. Earlier times are logged and ignored (the filter
        never runs backwards); no-op before :meth:`initialise`."""
        if self._time_usec is None:
            return
        t = int(time_unix_usec)
        if t < self._time_usec:
            _log.warning(
                LogEvent.ESTIMATOR_TIME_BACKWARDS,
                requested_unix_usec=t,
                filter_unix_usec=self._time_usec,
                lag_s=(self._time_usec - t) / 1e6,
            )
            return
        if t == self._time_usec:
            return
        f_mat, q_mat = self._transition((t - self._time_usec) / 1e6)
        self._kf.predict(F=f_mat, Q=q_mat)
        self._time_usec = t
        self._refresh_provenance()

    # -- updates ------------------------------------------------------------------------------------------

    def update_fix(self, fix: PoseFix) -> FixDecision:
        """Fuse an absolute fix (after predicting to its exposure time).

        Gate: the horizontal innovation's NIS must be <= ``fix_gate_chi2``. Re-acquisition: when the
        prior horizontal sigma exceeds ``reacquire_sigma_m`` the gate is bypassed, because after a long
        gap the prior is mostly model extrapolation; if it is even slightly over-confident, a gate
        would reject every correct fix from then on and the estimator could never recover. The risk is
        bounded: C2 already searched around the prior, and a fix whose own horizontal sigma exceeds
        ``reacquire_sigma_m`` is still refused (it would not re-anchor anything).
        Fixes older than ``max_fix_lag_s`` relative to the filter are refused as stale; younger late
        fixes are applied at the filter's time.
        """
        if self._time_usec is None:
            return FixDecision(False, math.nan, FixReason.NOT_INITIALISED)
        pos = np.asarray(fix.pos_ned_m, dtype=np.float64).reshape(-1)
        cov = np.asarray(fix.cov_ned_m2, dtype=np.float64)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)) or not _is_covariance(cov, 3):
            _log.warning(LogEvent.ESTIMATOR_FIX_REJECTED, reason=FixReason.INVALID_MEASUREMENT, nis=None)
            return FixDecision(False, math.nan, FixReason.INVALID_MEASUREMENT)
        lag_s = (self._time_usec - fix.exposure_time_unix_usec) / 1e6
        if lag_s > self._max_fix_lag_s:
            _log.warning(LogEvent.ESTIMATOR_FIX_REJECTED, reason=FixReason.STALE, lag_s=lag_s, nis=None)
            return FixDecision(False, math.nan, FixReason.STALE)
        self.predict_to(fix.exposure_time_unix_usec)

        x = self._kf.x.reshape(-1)
        p_mat = self._kf.P
        innov = pos[:2] - x[:2]
        s_mat = p_mat[:2, :2] + cov[:2, :2]
        nis = float(innov @ np.linalg.solve(s_mat, innov))
        prior_sigma = _horiz_sigma_m(p_mat)
        gate = self._config.fix_gate_chi2
        if prior_sigma > self._config.reacquire_sigma_m:
            if fix.horiz_sigma_m > self._config.reacquire_sigma_m:
                _log.warning(
                    LogEvent.ESTIMATOR_FIX_REJECTED,
                    reason=FixReason.FIX_SIGMA_TOO_LARGE,
                    nis=nis,
                    gate=gate,
                    fix_sigma_m=fix.horiz_sigma_m,
                )
                return FixDecision(False, nis, FixReason.FIX_SIGMA_TOO_LARGE)
            reason = FixReason.ACCEPTED_REACQUIRE
            _log.info(
                LogEvent.ESTIMATOR_REACQUIRED,
                nis=nis,
                prior_sigma_m=prior_sigma,
                jump_m=float(np.hypot(*innov)),
            )
        elif nis > gate:
            self._consecutive_gated += 1
            _log.warning(
                LogEvent.ESTIMATOR_FIX_REJECTED,
                reason=FixReason.GATED,
                nis=nis,
                gate=gate,
                innovation_m=float(np.hypot(*innov)),
                tile_id=tuple(fix.tile_id),
                consecutive=self._consecutive_gated,
            )
            vo_corroborates = (
                self._last_vo_usec is not None
                and (self._time_usec - self._last_vo_usec) / 1e6 <= self._vo_recent_s
            )
            if self._consecutive_gated >= CONSECUTIVE_GATED_INFLATE and not vo_corroborates:
                # Several fixes in a row disagree with a state that nothing corroborates (no recent VO):
                # an unmodelled manoeuvre is as likely as a wrong match, so the stated accuracy is no
                # longer honest and the disagreement is added to the position covariance. While VO is
                # being fused the state's motion is measured, and a run of disagreeing fixes is far more
                # likely a look-alike area: those stay rejected (the wrong-tile trap).
                self._kf.P[:2, :2] += np.outer(innov, innov)
                self._consecutive_gated = 0
                _log.warning(LogEvent.ESTIMATOR_COVARIANCE_INFLATED, innovation_m=float(np.hypot(*innov)),
                             horiz_sigma_m=_horiz_sigma_m(self._kf.P))
            return FixDecision(False, nis, FixReason.GATED)
        else:
            reason = FixReason.ACCEPTED

        self._kf.update(pos.reshape(3, 1), R=cov, H=_H_POS)
        self._consecutive_gated = 0
        self._last_fix_usec = self._time_usec
        if math.isfinite(fix.yaw_rad):
            self._yaw_rad = float(fix.yaw_rad)
        self._refresh_provenance()
        return FixDecision(True, nis, reason)

    def update_vo(self, motion: VoMotion, *, time_unix_usec: int | None = None) -> FixDecision:
        """Fuse VO motion as the average horizontal velocity ``delta / dt`` at the filter's time.

        ``VoMotion`` carries no timestamp: pass the current frame's exposure time as
        ``time_unix_usec`` to predict to it first (or call :meth:`predict_to` before). The velocity
        innovation is gated with ``fix_gate_chi2`` (2 dof) so a VO blunder cannot corrupt the velocity.
        """
        if self._time_usec is None:
            return FixDecision(False, math.nan, FixReason.NOT_INITIALISED)
        delta = np.asarray(motion.delta_ne_m, dtype=np.float64).reshape(-1)
        cov = np.asarray(motion.cov_ne_m2, dtype=np.float64)
        dt = float(motion.dt_s)
        if (
            not (math.isfinite(dt) and dt > 0)
            or delta.shape != (2,)
            or not np.all(np.isfinite(delta))
            or not _is_covariance(cov, 2)
        ):
            _log.warning(LogEvent.ESTIMATOR_VO_REJECTED, reason=FixReason.INVALID_MEASUREMENT, dt_s=dt)
            return FixDecision(False, math.nan, FixReason.INVALID_MEASUREMENT)
        if time_unix_usec is not None:
            self.predict_to(time_unix_usec)
        vel = delta / dt
        r_mat = self._config.vo_noise_scale * cov / dt**2
        x = self._kf.x.reshape(-1)
        innov = vel - x[3:5]
        s_mat = self._kf.P[3:5, 3:5] + r_mat
        nis = float(innov @ np.linalg.solve(s_mat, innov))
        if nis > self._config.fix_gate_chi2:
            _log.warning(
                LogEvent.ESTIMATOR_VO_REJECTED,
                reason=FixReason.GATED,
                nis=nis,
                gate=self._config.fix_gate_chi2,
            )
            return FixDecision(False, nis, FixReason.GATED)
        self._kf.update(vel.reshape(2, 1), R=r_mat, H=_H_VEL_NE)
        self._last_vo_usec = self._time_usec
        self._refresh_provenance()
        return FixDecision(True, nis, FixReason.ACCEPTED)

    def update_altitude(self, alt_agl_m: float, ground_alt_amsl_m: float, sigma_m: float) -> FixDecision:
        """Fuse the autopilot's height above ground (flat ground at ``ground_alt_amsl_m``) on ``d``, at
        the filter's current time. Not gated: the autopilot's altitude is the more trusted source."""
        if self._time_usec is None:
            return FixDecision(False, math.nan, FixReason.NOT_INITIALISED)
        if not (math.isfinite(alt_agl_m) and math.isfinite(ground_alt_amsl_m) and sigma_m > 0):
            return FixDecision(False, math.nan, FixReason.INVALID_MEASUREMENT)
        x = self._kf.x.reshape(-1)
        lat, lon, _ = self._ltp.to_geodetic(x[:3])
        d_meas = float(self._ltp.to_ned(lat, lon, ground_alt_amsl_m + alt_agl_m)[2])
        s_var = float(self._kf.P[2, 2]) + sigma_m**2
        nis = (d_meas - x[2]) ** 2 / s_var
        self._kf.update(np.array([[d_meas]]), R=np.array([[sigma_m**2]]), H=_H_D)
        return FixDecision(True, float(nis), FixReason.ACCEPTED)

    # -- output -------------------------------------------------------------------------------------------

    def _predicted(self, time_unix_usec: int) -> tuple[np.ndarray, np.ndarray, int]:
        """(x (6,), P (6, 6), time) predicted to ``time_unix_usec`` without touching the filter; times
        before the filter's are answered with the current estimate (no retrodiction)."""
        if self._time_usec is None:
            raise RuntimeError("estimator is not initialised; call initialise() first")
        x = self._kf.x.reshape(-1).copy()
        p_mat = self._kf.P.copy()
        if time_unix_usec <= self._time_usec:
            return x, p_mat, self._time_usec
        f_mat, q_mat = self._transition((time_unix_usec - self._time_usec) / 1e6)
        return f_mat @ x, f_mat @ p_mat @ f_mat.T + q_mat, int(time_unix_usec)

    def provenance_at(self, time_unix_usec: int | None = None) -> Provenance:
        """The provenance label at ``time_unix_usec`` (default: the filter's time), without side effects."""
        if self._time_usec is None:
            return Provenance.NO_ESTIMATE
        t = self._time_usec if time_unix_usec is None else int(time_unix_usec)
        _, p_mat, t = self._predicted(t)
        return self._label(p_mat, t)

    def _label(self, p_mat: np.ndarray, t: int) -> Provenance:
        if _horiz_sigma_m(p_mat) > self._config.max_output_sigma_m:
            return Provenance.NO_ESTIMATE
        fix_is_latest = self._last_vo_usec is None or (
            self._last_fix_usec is not None and self._last_vo_usec <= self._last_fix_usec
        )
        if (
            self._last_fix_usec is not None
            and fix_is_latest
            and (t - self._last_fix_usec) / 1e6 <= self._fix_recent_s
        ):
            return Provenance.SATELLITE_ANCHORED
        if (
            self._last_vo_usec is not None
            and (self._last_fix_usec is None or self._last_vo_usec >= self._last_fix_usec)
            and (t - self._last_vo_usec) / 1e6 <= self._vo_recent_s
        ):
            return Provenance.VISUAL_PROPAGATED
        return Provenance.DEAD_RECKONING

    def _refresh_provenance(self, label: Provenance | None = None) -> None:
        new = self.provenance_at() if label is None else label
        if new is not self._provenance:
            _log.info(LogEvent.PROVENANCE_CHANGED, **{"from": self._provenance.value, "to": new.value})
            self._provenance = new

    def state(self, time_unix_usec: int | None = None) -> EstimatorState:
        """The estimate predicted to ``time_unix_usec`` (default: the filter's time).

        Does not change the filter (a pure prediction on copies), so output can be produced at any rate
        between measurements; the only side effect is the ``provenance_changed`` log when the label
        at that time differs from the last one logged. Before :meth:`initialise` the state is
        ``no_estimate`` with NaN position and infinite covariance.
        """
        if self._time_usec is None:
            nan3 = np.full(3, np.nan)
            inf_cov = np.diag(np.full(3, np.inf))
            return EstimatorState(
                time_unix_usec=int(time_unix_usec or 0),
                provenance=Provenance.NO_ESTIMATE,
                pos_ned_m=nan3,
                vel_ned_m_s=nan3.copy(),
                cov_pos_ned_m2=inf_cov,
                cov_vel_ned_m2_s2=inf_cov.copy(),
                lat_deg=math.nan,
                lon_deg=math.nan,
                alt_amsl_m=math.nan,
                yaw_rad=None,
                last_fix_age_s=math.inf,
            )
        t_req = self._time_usec if time_unix_usec is None else int(time_unix_usec)
        x, p_mat, t = self._predicted(t_req)
        label = self._label(p_mat, t)
        if t_req >= self._time_usec:
            # Only label changes at or after the filter's time are news; a query for the past is not.
            self._refresh_provenance(label)
        lat, lon, alt = self._ltp.to_geodetic(x[:3])
        fix_age = math.inf if self._last_fix_usec is None else (t - self._last_fix_usec) / 1e6
        return EstimatorState(
            time_unix_usec=t,
            provenance=label,
            pos_ned_m=x[:3].copy(),
            vel_ned_m_s=x[3:].copy(),
            cov_pos_ned_m2=p_mat[:3, :3].copy(),
            cov_vel_ned_m2_s2=p_mat[3:, 3:].copy(),
            lat_deg=float(lat),
            lon_deg=float(lon),
            alt_amsl_m=float(alt),
            yaw_rad=self._yaw_rad,
            last_fix_age_s=fix_age,
        )
