"""C5 navigation estimator: a Kalman filter (``kalman``, NumPy) over absolute fixes, VO, altitude and the IMU.

The filter math at one instant. When each input is fused, and whether its time is admitted at all, is
decided by :mod:`~gps_denied_onboard.components.c5_estimator.time_axis`, the only caller of the update
methods in a running daemon.

State: ``x = [n, e, d, vn, ve, vd]`` in the flight's local NED frame (m, m/s); time is Unix microseconds
of what each input describes (a frame's exposure, never its arrival).
Prediction: steps of at most ``PREDICT_STEP_S``, driven by the IMU's NED acceleration when the
:class:`~gps_denied_onboard.components.c5_estimator.protocol.AccelerationSource` has one (noise
``imu_accel_noise_m_s2``, and what the attitude's doubt puts into the rotated acceleration as a bias held
since VO or a fix last measured the motion: ``TILT_ERROR_HOLD_S``), else constant velocity (noise
``accel_noise_m_s2``).
Measurements: a C4 ``PoseFix`` (3-D, its own covariance, gated at ``fix_gate_chi2`` on the horizontal
NIS; the gate is bypassed above ``reacquire_sigma_m``; a start prior no fix has confirmed is doubted
by gated fixes that agree over ``prior_conflict_span_m``); a C1 ``VoMotion`` (the interval's mean
velocity, moved to its end with the IMU when known, covariance ``vo_noise_scale * cov / dt^2``, scaled
up while the recent VO innovations show VO noisier than it states: ``_vo_noise_factor``); the altitude
(AGL plus the flat ground, on ``d``).
Disagreement that persists is doubt, not noise (``CONSECUTIVE_GATED_INFLATE`` in a row): gated VO that
keeps saying one other velocity puts the state's velocity in doubt by VO's, and its position by what
that moved it over the frames gated (VO that says another thing each frame stays gated); gated fixes
put the position in doubt by theirs, unless VO has carried the state since its last accepted fix (then
they are a look-alike area and stay refused; VO back after a dead-reckoned stretch vouches for nothing
before it).
Shared error: ``shared_sigma_m`` bounds the part of the map fixes' error they all share
(``s <- ||I - K|| s + ||K|| s_fix`` per accepted fix) and is added to every output, so fusing more fixes
never averages it away; the gates leave it out. A slope's share (``PoseFix.slope_sigma_m``) is in the
gate and the shared error but not in the fix's weight: the estimate follows a fix over a slope, slope and
all, and says so.
Output: :class:`EstimatorState` at any time, with its provenance (:meth:`NavEstimator.provenance_at`):
``satellite_anchored`` (newest fix attempt accepted, exposed within ``anchored_window_s``),
``visual_propagated`` (VO within ``vo_recent_s``), ``dead_reckoning``, or ``no_estimate`` (not
initialised, or sigma above ``max_output_sigma_m``).

In full, with why: docs/design.md, "`c5_estimator/ekf.py`: the filter".
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
import structlog

from gps_denied_onboard.components.c1_vio.types import VoMotion
from gps_denied_onboard.components.c4_pose.types import PoseFix
from gps_denied_onboard.components.c5_estimator.kalman import KalmanState, white_noise_accel_q
from gps_denied_onboard.components.c5_estimator.protocol import AccelerationSource, ImuAcceleration
from gps_denied_onboard.components.c5_estimator.types import EstimatorState, FixDecision
from gps_denied_onboard.config import EstimatorConfig
from gps_denied_onboard.constants import LogEvent, Provenance
from gps_denied_onboard.geo import LocalTangentPlane

_log = structlog.get_logger(__name__)

#: A VO update younger than this makes the output ``visual_propagated``, seconds.
DEFAULT_VO_RECENT_S: Final[float] = 2.0
#: Longest prediction step; each step asks the acceleration source for its own mean acceleration, s.
PREDICT_STEP_S: Final[float] = 0.1

#: A VO interval longer than this with no IMU to move its mean velocity to the interval's end is a gap
#: (frames lost, attitude missing): the velocity may have changed by much more than within a frame, s.
VO_GAP_S: Final[float] = 0.5

#: How long an autopilot's tilt error holds once a manoeuvre made it, s: on ArduPilot copter SITL it
#: decayed over 5-10 s once level (``vehicle_state.AHRS_SIGMA_PER_SWING``). Rotated with that tilt, the
#: IMU's acceleration carries a bias ``b``, not white noise: over ``T`` s with nothing measuring the
#: motion it puts ``b T`` into the velocity and ``b T^2 / 2`` into the position. The prediction states it
#: as white noise whose density grows with the time since VO or a fix last measured the motion, ``3 b^2
#: min(t, TILT_ERROR_HOLD_S)``: over such a stretch that adds ``b^2 T^4 / 4`` to the position's variance
#: (the bias's, exactly) and ``1.5 b^2 T^2`` to the velocity's (1.22 times the bias's sigma), and between
#: frames that VO measures it adds little (a third of a second at 3 Hz).
TILT_ERROR_HOLD_S: Final[float] = 5.0
#: The factor on ``b^2 t`` above.
TILT_NOISE_GROWTH: Final[float] = 3.0
#: The bias's sigma per unit of the IMU answer's tilt doubt. The doubt bounds the tilt error rather than
#: being its typical size (a tenth of the swing, against 2.5-3.4 deg measured after swings of 30-50 deg,
#: and about half of it most of the time in the ArduPilot emulator's model of that measurement); a bias
#: anywhere within a bound has a sigma of the bound over sqrt(3). Taken at the whole bound, the core's
#: IMU-only prediction through a vision worker's restart stated a speed accuracy past EKF3's glitch test
#: (1.55 m/s) after a corner.
TILT_SIGMA_PER_DOUBT: Final[float] = 1.0 / math.sqrt(3.0)

#: The least horizontal 1-sigma, m, a fix is weighed by once the slope's share is taken out
#: (``_weighing_cov``).
MIN_WEIGHING_SIGMA_M: Final[float] = 0.1

#: VO updates whose normalised innovations say whether VO is as noisy as it states (``_vo_noise_factor``).
VO_NIS_WINDOW: Final[int] = 8
#: Median of a chi-square with 2 degrees of freedom: the median NIS of a consistent VO velocity.
CHI2_2DOF_MEDIAN: Final[float] = 1.386
#: The most VO's stated covariance is scaled up by the innovations it showed (5x its sigma).
VO_NOISE_FACTOR_MAX: Final[float] = 25.0

#: One gated VO velocity of a run (``EstimatorCheckpoint.vo_gated_run``): its innovation n, e (m/s), its
#: covariance nn, ne, ee (m^2/s^2) and its interval (s).
VoGated = tuple[float, float, float, float, float, float]

#: Consecutive gated fixes after which their disagreement is added to the position covariance; and
#: consecutive gated VO velocities after which theirs is added to the velocity covariance.
CONSECUTIVE_GATED_INFLATE: Final[int] = 3
#: Gated fixes, consecutive and agreeing with each other, that put an unconfirmed start prior in doubt
#: (the output then states their disagreement), and that may contradict it (over enough ground).
PRIOR_DOUBT_FIXES: Final[int] = 2
PRIOR_CONTRADICTED_FIXES: Final[int] = 5
_H_POS = np.hstack([np.eye(3), np.zeros((3, 3))])
_H_VEL_NE = np.hstack([np.zeros((2, 3)), np.eye(3)[:2]])
_H_D = np.array([[0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])
#: Keeps the horizontal (n, e) position and velocity entries of a process noise.
_HORIZ = np.outer(*(2 * [np.array([1.0, 1.0, 0.0, 1.0, 1.0, 0.0])]))


class FixReason:
    """Values of ``FixDecision.reason`` (the time axis adds its own refusals, see ``time_axis``)."""

    ACCEPTED: Final = "accepted"
    ACCEPTED_REACQUIRE: Final = "accepted_reacquire"
    GATED: Final = "gated"
    FIX_SIGMA_TOO_LARGE: Final = "fix_sigma_too_large"
    INVALID_MEASUREMENT: Final = "invalid_measurement"
    NOT_INITIALISED: Final = "not_initialised"
    #: The measurement is older than the filter's time: only the time axis may fuse it (by rewinding).
    BEHIND_FILTER: Final = "behind_filter"


def _is_covariance(cov: np.ndarray, dim: int) -> bool:
    """Finite, symmetric, positive definite ``(dim, dim)`` matrix."""
    if cov.shape != (dim, dim) or not np.all(np.isfinite(cov)):
        return False
    if not np.allclose(cov, cov.T, rtol=1e-6, atol=1e-9):
        return False
    return bool(np.all(np.linalg.eigvalsh(cov) > 0))


def _weighing_cov(cov: np.ndarray, slope_sigma_m: float) -> np.ndarray:
    """The covariance a fix is weighed by: its own, less the slope's share (``PoseFix.slope_sigma_m``),
    which the gate allowed for and the shared error states. The scales after the slope was added only
    grow a covariance, so what is left is the fix's own; ``MIN_WEIGHING_SIGMA_M`` guards the arithmetic."""
    if not (math.isfinite(slope_sigma_m) and slope_sigma_m > 0.0):
        return cov
    out = np.array(cov, dtype=np.float64, copy=True)
    vals, vecs = np.linalg.eigh(out[:2, :2] - np.eye(2) * slope_sigma_m**2)
    out[:2, :2] = (vecs * np.maximum(vals, MIN_WEIGHING_SIGMA_M**2)) @ vecs.T
    return out


def _horiz_sigma_m(p_mat: np.ndarray) -> float:
    return float(np.sqrt(np.max(np.linalg.eigvalsh(p_mat[:2, :2]))))


def _vo_agrees_with_run(
    run: tuple[VoGated, ...],
    innov: np.ndarray,
    r_mat: np.ndarray,
    dt_s: float,
    accel_density_m_s2: float,
    gate_chi2: float,
) -> bool:
    """Whether a gated VO velocity's innovation agrees with every one of ``run`` (gated VO before it, in
    a row): they differ by no more than the two VO noises and what the state's velocity may have
    wandered between them (``accel_density_m_s2`` white over the time apart) allow, gated like one
    measurement. The state's own error is common to both and cancels."""
    span_s = dt_s
    for n, e, rnn, rne, ree, run_dt_s in reversed(run):
        cov = r_mat + np.array([[rnn, rne], [rne, ree]]) + np.eye(2) * accel_density_m_s2**2 * span_s
        diff = innov - np.array([n, e])
        if float(diff @ np.linalg.solve(cov, diff)) > gate_chi2:
            return False
        span_s += run_dt_s
    return True


def _valid_accel(a: ImuAcceleration | None) -> ImuAcceleration | None:
    if a is None:
        return None
    arr = np.asarray(a.mean_ned_m_s2, dtype=np.float64).reshape(-1)
    tilt = float(a.tilt_bound_m_s2)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)) or not (math.isfinite(tilt) and tilt >= 0.0):
        return None
    return ImuAcceleration(arr, tilt)


@dataclass(frozen=True)
class PriorConflict:
    """A run of consecutive gated fixes that agree with each other while the start prior is unconfirmed:
    where the state was at the first (NE, m), the newest's innovation (m) and covariance, the state's
    horizontal covariance then (m^2), and how many."""

    first_pos_ne: np.ndarray
    innov_ne: np.ndarray
    fix_cov_ne: np.ndarray
    p_ne: np.ndarray
    count: int


@dataclass(frozen=True)
class EstimatorCheckpoint:
    """Everything :meth:`NavEstimator.restore` needs to put the filter back exactly (copies)."""

    x: np.ndarray
    p_mat: np.ndarray
    time_usec: int | None
    last_fix_usec: int | None
    last_no_fix_usec: int | None
    last_vo_usec: int | None
    consecutive_gated: int
    yaw_rad: float | None
    shared_sigma_m: float
    imu_trusted: bool = True
    prior_conflict: PriorConflict | None = None
    map_confirmed: bool = False
    vo_nis: tuple[float, ...] = ()
    #: The VO velocities gated in a row that agree with each other (``update_vo``): per frame its
    #: innovation (n, e; m/s), its covariance (nn, ne, ee; m^2/s^2) and its interval, s.
    vo_gated_run: tuple[VoGated, ...] = ()
    #: Since the last accepted fix the state has moved without VO for longer than ``vo_recent_s`` (a
    #: dead-reckoned stretch), so VO fused now does not vouch for its position.
    dr_since_fix: bool = False


class NavEstimator:
    """Fuses C4 fixes, C1 motion, the autopilot's altitude and (through ``accel_source``) its IMU.

    ``config``: the ``estimator`` section; ``ltp``: the flight's NED frame (geodetic output).
    ``accel_source``: measured acceleration for the prediction (None: constant velocity only).
    ``vo_recent_s``: the provenance window of VO (see the module docstring; the fix's window is
    ``config.anchored_window_s``).
    Not thread-safe: the time axis owns it and serialises every call.
    """

    def __init__(
        self,
        config: EstimatorConfig,
        ltp: LocalTangentPlane,
        *,
        accel_source: AccelerationSource | None = None,
        vo_recent_s: float = DEFAULT_VO_RECENT_S,
    ) -> None:
        if not (math.isfinite(vo_recent_s) and vo_recent_s > 0):
            raise ValueError(f"vo_recent_s must be a positive number of seconds, got {vo_recent_s!r}")
        self._config = config
        self._ltp = ltp
        self._accel = accel_source
        #: Off while the autopilot's attitude is found wrong: its IMU's accelerations are rotated into NED
        #: with that attitude, and 3 deg of tilt leaks 0.5 m/s^2 of gravity into the horizontal.
        self._imu_trusted = True
        self._fix_recent_s = config.anchored_window_s
        self._vo_recent_s = vo_recent_s
        self._kf = KalmanState.zeros(6)
        self._time_usec: int | None = None
        self._last_fix_usec: int | None = None
        self._last_no_fix_usec: int | None = None
        self._consecutive_gated = 0
        #: Gated fixes contradicting a start prior no fix has confirmed (``_note_prior_conflict``).
        self._prior_conflict: PriorConflict | None = None
        #: A map fix has confirmed the state since ``initialise`` (or it started from a resumed 3D
        #: estimate): only then may the output be a 3D fix (``EstimatorState.map_confirmed``).
        self._map_confirmed = False
        self._last_vo_usec: int | None = None
        self._vo_gated_run: tuple[VoGated, ...] = ()
        self._dr_since_fix = False
        #: The normalised innovations of the newest VO updates against VO's stated covariance (gated
        #: ones too), the newest last (``_vo_noise_factor``).
        self._vo_nis: tuple[float, ...] = ()
        self._yaw_rad: float | None = None
        #: Bound on the fixes' common (map) error the position carries, metres per axis (see above).
        self._shared_sigma_m = 0.0
        self._provenance = Provenance.NO_ESTIMATE
        #: False while the time axis re-applies measurements after a rewind: their events were logged
        #: when they first arrived, so a replay must not log them again.
        self.logging_enabled = True
        #: False during a whole rewind: the label is only re-derived (and a change logged) at its end,
        #: so the intermediate states of a rewind never show as provenance transitions.
        self.provenance_live = True

    def _emit(self, level: str, event: str, **fields: Any) -> None:
        if self.logging_enabled:
            getattr(_log, level)(event, **fields)

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
        map_confirmed: bool = False,
    ) -> None:
        """(Re)start at ``pos_ned_m`` (3,) with 1-sigma ``sigma_m`` per axis, at rest with
        ``vel_sigma_m_s`` per axis. Forgets previous fixes, VO and yaw. ``map_confirmed``: the start is
        the previous run's own 3D output (resumed), not a claim no map fix has checked."""
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
        self._last_no_fix_usec = None
        self._consecutive_gated = 0
        self._prior_conflict = None
        self._map_confirmed = bool(map_confirmed)
        self._last_vo_usec = None
        self._vo_gated_run = ()
        self._dr_since_fix = False
        self._vo_nis = ()
        self._yaw_rad = None
        self._shared_sigma_m = 0.0
        self._emit(
            "info",
            LogEvent.ESTIMATOR_INITIALISED,
            pos_ned_m=pos.tolist(),
            sigma_m=sigma_m,
            vel_sigma_m_s=vel_sigma_m_s,
            time_unix_usec=self._time_usec,
            map_confirmed=self._map_confirmed,
        )
        self._refresh_provenance()

    def checkpoint(self) -> EstimatorCheckpoint:
        """A copy of the whole filter state (for the time axis to rewind to)."""
        return EstimatorCheckpoint(
            self._kf.x.copy(),
            self._kf.P.copy(),
            self._time_usec,
            self._last_fix_usec,
            self._last_no_fix_usec,
            self._last_vo_usec,
            self._consecutive_gated,
            self._yaw_rad,
            self._shared_sigma_m,
            self._imu_trusted,
            self._prior_conflict,
            self._map_confirmed,
            self._vo_nis,
            self._vo_gated_run,
            self._dr_since_fix,
        )

    def restore(self, cp: EstimatorCheckpoint) -> None:
        """Put the filter back to ``cp`` exactly (the provenance label is re-derived, not logged)."""
        self._kf.x = cp.x.copy()
        self._kf.P = cp.p_mat.copy()
        self._time_usec = cp.time_usec
        self._last_fix_usec = cp.last_fix_usec
        self._last_no_fix_usec = cp.last_no_fix_usec
        self._last_vo_usec = cp.last_vo_usec
        self._consecutive_gated = cp.consecutive_gated
        self._yaw_rad = cp.yaw_rad
        self._shared_sigma_m = cp.shared_sigma_m
        self._imu_trusted = cp.imu_trusted
        self._prior_conflict = cp.prior_conflict
        self._map_confirmed = cp.map_confirmed
        self._vo_nis = cp.vo_nis
        self._vo_gated_run = cp.vo_gated_run
        self._dr_since_fix = cp.dr_since_fix

    # -- prediction ---------------------------------------------------------------------------------------

    def _step(self, x: np.ndarray, p_mat: np.ndarray, t0: int, t1: int) -> tuple[np.ndarray, np.ndarray]:
        """One prediction step ``t0 -> t1`` (t1 > t0) on copies; returns (x, P)."""
        dt = (t1 - t0) / 1e6
        accel = self._imu_accel(t0, t1)
        f_mat = np.eye(6)
        f_mat[0:3, 3:6] = dt * np.eye(3)
        if accel is None:
            q_mat = white_noise_accel_q(dt, self._config.accel_noise_m_s2**2)
        else:
            q_mat = white_noise_accel_q(dt, self._config.imu_accel_noise_m_s2**2)
            tilt_q = self._tilt_q(accel, (t0 + t1) // 2)
            if tilt_q > 0.0:  # a tilt turns the specific force sideways: horizontal only
                q_mat = q_mat + white_noise_accel_q(dt, tilt_q) * _HORIZ
        x_new = f_mat @ x
        if accel is not None:
            x_new[0:3] += 0.5 * dt * dt * accel.mean_ned_m_s2
            x_new[3:6] += dt * accel.mean_ned_m_s2
        return x_new, f_mat @ p_mat @ f_mat.T + q_mat

    def _tilt_q(self, accel: ImuAcceleration, t_usec: int) -> float:
        """The tilt doubt's spectral density at ``t_usec``, (m/s^2)^2/Hz (``TILT_ERROR_HOLD_S``): it grows
        with the time since VO or a fix last measured the motion (the whole hold before either did)."""
        if accel.tilt_bound_m_s2 <= 0.0:
            return 0.0
        seen = max((t for t in (self._last_vo_usec, self._last_fix_usec) if t is not None), default=None)
        held_s = TILT_ERROR_HOLD_S if seen is None else min(max(t_usec - seen, 0) / 1e6, TILT_ERROR_HOLD_S)
        return TILT_NOISE_GROWTH * (TILT_SIGMA_PER_DOUBT * accel.tilt_bound_m_s2) ** 2 * held_s

    def _accel_density_m_s2(self, accel: ImuAcceleration | None, t_usec: int) -> float:
        """The prediction's horizontal white acceleration noise density at ``t_usec`` (``_step``):
        constant velocity's without the IMU, else the IMU's own and its tilt doubt's."""
        if accel is None:
            return self._config.accel_noise_m_s2
        return math.sqrt(self._config.imu_accel_noise_m_s2**2 + self._tilt_q(accel, t_usec))

    def _imu_accel(self, t0: int, t1: int) -> ImuAcceleration | None:
        """The IMU's mean NED acceleration over ``[t0, t1]``, or None (no IMU, no valid sample, or the
        attitude it is rotated with found wrong)."""
        if self._accel is None or not self._imu_trusted:
            return None
        return _valid_accel(self._accel.accel_ned_mean(t0, t1))

    def set_imu_trusted(self, trusted: bool) -> None:
        """Use the IMU in the prediction (True) or predict as without one (False: the autopilot's
        attitude, which rotates its accelerations, was found wrong by ``c4_pose/attitude_check``)."""
        self._imu_trusted = bool(trusted)

    def _propagate(self, x: np.ndarray, p_mat: np.ndarray, t0: int, t1: int) -> tuple[np.ndarray, np.ndarray]:
        step_usec = int(PREDICT_STEP_S * 1e6)
        t = t0
        while t < t1:
            t_next = min(t1, t + step_usec)
            x, p_mat = self._step(x, p_mat, t, t_next)
            t = t_next
        return x, p_mat

    def predict_to(self, time_unix_usec: int) -> None:
        """Propagate the state to ``time_unix_usec``. Earlier times are logged and ignored (the filter
        never runs backwards; rewinding is the time axis' job); no-op before :meth:`initialise`."""
        if self._time_usec is None:
            return
        t = int(time_unix_usec)
        if t < self._time_usec:
            self._emit(
                "warning",
                LogEvent.ESTIMATOR_TIME_BACKWARDS,
                requested_unix_usec=t,
                filter_unix_usec=self._time_usec,
                lag_s=(self._time_usec - t) / 1e6,
            )
            return
        if t == self._time_usec:
            return
        x, p_mat = self._propagate(self._kf.x.reshape(-1), self._kf.P, self._time_usec, t)
        self._kf.x = x.reshape(6, 1)
        self._kf.P = p_mat
        self._time_usec = t
        self._refresh_provenance()

    # -- updates ------------------------------------------------------------------------------------------

    def _behind(self, t_usec: int) -> FixDecision | None:
        if self._time_usec is not None and t_usec < self._time_usec:
            return FixDecision(False, math.nan, FixReason.BEHIND_FILTER)
        return None

    def update_fix(self, fix: PoseFix) -> FixDecision:
        """Fuse an absolute fix at its exposure time (the filter is predicted to it first; a fix older
        than the filter's time is refused with ``behind_filter``: the time axis rewinds for those).

        Gate: the horizontal innovation's NIS must be <= ``fix_gate_chi2``. Re-acquisition: when the
        prior horizontal sigma exceeds ``reacquire_sigma_m`` the gate is bypassed, because after a long
        gap the prior is mostly model extrapolation; if it is even slightly over-confident, a gate
        would reject every correct fix from then on and the estimator could never recover. The risk is
        bounded: C2 already searched around the prior, and a fix whose own horizontal sigma exceeds
        ``reacquire_sigma_m`` is still refused (it would not re-anchor anything).
        """
        if self._time_usec is None:
            return FixDecision(False, math.nan, FixReason.NOT_INITIALISED)
        pos = np.asarray(fix.pos_ned_m, dtype=np.float64).reshape(-1)
        cov = np.asarray(fix.cov_ned_m2, dtype=np.float64)
        shared = float(fix.shared_sigma_m)
        if (
            pos.shape != (3,)
            or not np.all(np.isfinite(pos))
            or not _is_covariance(cov, 3)
            or not (math.isfinite(shared) and shared >= 0.0)
        ):
            self._emit(
                "warning", LogEvent.ESTIMATOR_FIX_REJECTED, reason=FixReason.INVALID_MEASUREMENT, nis=None
            )
            return FixDecision(False, math.nan, FixReason.INVALID_MEASUREMENT)
        behind = self._behind(fix.exposure_time_unix_usec)
        if behind is not None:
            return behind
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
                self._emit(
                    "warning",
                    LogEvent.ESTIMATOR_FIX_REJECTED,
                    reason=FixReason.FIX_SIGMA_TOO_LARGE,
                    nis=nis,
                    gate=gate,
                    fix_sigma_m=fix.horiz_sigma_m,
                )
                self._note_no_fix_at(self._time_usec)
                return FixDecision(False, nis, FixReason.FIX_SIGMA_TOO_LARGE)
            reason = FixReason.ACCEPTED_REACQUIRE
            self._emit(
                "info",
                LogEvent.ESTIMATOR_REACQUIRED,
                nis=nis,
                prior_sigma_m=prior_sigma,
                jump_m=float(np.hypot(*innov)),
            )
        elif nis > gate:
            self._consecutive_gated += 1
            self._emit(
                "warning",
                LogEvent.ESTIMATOR_FIX_REJECTED,
                reason=FixReason.GATED,
                nis=nis,
                gate=gate,
                innovation_m=float(np.hypot(*innov)),
                tile_id=tuple(fix.tile_id),
                consecutive=self._consecutive_gated,
            )
            vo_recent = (
                self._last_vo_usec is not None
                and (self._time_usec - self._last_vo_usec) / 1e6 <= self._vo_recent_s
            )
            if vo_recent and self._last_fix_usec is None:
                self._note_prior_conflict(x[:2], p_mat[:2, :2], innov, cov[:2, :2])
            if self._consecutive_gated >= CONSECUTIVE_GATED_INFLATE and not (
                vo_recent and not self._dr_since_fix
            ):
                # Several fixes in a row disagree with a state that nothing corroborates: an unmodelled
                # manoeuvre is as likely as a wrong match, so the stated accuracy is no longer honest
                # and the disagreement is added to the position covariance. While VO has carried the
                # state since its last accepted fix, its motion is measured all the way, and a run of
                # disagreeing fixes is far more likely a look-alike area: those stay rejected (the
                # wrong-tile trap). VO back after a dead-reckoned stretch measures the motion since, not
                # what the stretch did to the position: it vouches for nothing before it.
                self._kf.P[:2, :2] += np.outer(innov, innov)
                self._consecutive_gated = 0
                self._emit(
                    "warning",
                    LogEvent.ESTIMATOR_COVARIANCE_INFLATED,
                    innovation_m=float(np.hypot(*innov)),
                    horiz_sigma_m=_horiz_sigma_m(self._kf.P),
                )
            self._note_no_fix_at(self._time_usec)
            return FixDecision(False, nis, FixReason.GATED)
        else:
            reason = FixReason.ACCEPTED

        self._prior_conflict = None
        self._map_confirmed = True
        self._dr_since_fix = False
        self._kf.update(pos.reshape(3, 1), R=_weighing_cov(cov, float(fix.slope_sigma_m)), H=_H_POS)
        gain_ne = self._kf.K[:2, :2]
        self._shared_sigma_m = (
            float(np.linalg.norm(np.eye(2) - gain_ne, 2)) * self._shared_sigma_m
            + float(np.linalg.norm(gain_ne, 2)) * shared
        )
        self._consecutive_gated = 0
        self._last_fix_usec = self._time_usec
        if math.isfinite(fix.yaw_rad):
            self._yaw_rad = float(fix.yaw_rad)
        self._refresh_provenance()
        return FixDecision(True, nis, reason)

    def _note_prior_conflict(
        self, pos_ne: np.ndarray, p_ne: np.ndarray, innov: np.ndarray, fix_cov_ne: np.ndarray
    ) -> None:
        """A fix was gated while VO runs and no fix has confirmed the start prior yet.

        The wrong-tile-trap rule keeps such fixes out: VO measures the state's motion, so fixes that
        disagree with it are most likely a look-alike. That holds once fixes have anchored the state. A
        start prior (a configured position, HOME_POSITION, a resumed estimate) has nothing behind it but
        its stated sigma: measured before this rule (nominal_real, the configured start 150 m off at a
        stated 30 m), the daemon sent 792 of 807 GPS_INPUT beyond 3 sigma, fix_type 3 at 30 m for the
        whole flight, and gated 162 right fixes. Consecutive gated fixes that agree with each other
        (their innovations within the gate of each other, the VO drift between them included) form a
        run. From the second, the prior is in doubt: the output's shared error is raised to cover the
        disagreement (the gates leave it out, so nothing is fused on it). When the run has
        ``PRIOR_CONTRADICTED_FIXES`` fixes over ``prior_conflict_span_m`` of ground, more than a
        look-alike patch, the prior is contradicted: the disagreement is added to the position
        covariance, and the next agreeing fix re-anchors the state. A fix that is accepted ends the
        run (the prior is confirmed, and the rule no longer applies)."""
        run = self._prior_conflict
        agrees = False
        if run is not None:
            drift = p_ne - run.p_ne
            vals, vecs = np.linalg.eigh((drift + drift.T) / 2.0)
            s_mat = fix_cov_ne + run.fix_cov_ne + (vecs * np.clip(vals, 0.0, None)) @ vecs.T
            d = innov - run.innov_ne
            agrees = float(d @ np.linalg.solve(s_mat, d)) <= self._config.fix_gate_chi2
        first = run.first_pos_ne if run is not None and agrees else pos_ne.copy()
        count = run.count + 1 if run is not None and agrees else 1
        self._prior_conflict = PriorConflict(first, innov.copy(), fix_cov_ne.copy(), p_ne.copy(), count)
        if count < PRIOR_DOUBT_FIXES:
            return
        disagreement_m = float(np.hypot(*innov))
        if disagreement_m > self._shared_sigma_m:
            self._shared_sigma_m = disagreement_m
            self._emit(
                "warning",
                LogEvent.ESTIMATOR_COVARIANCE_INFLATED,
                reason="prior_in_doubt",
                innovation_m=disagreement_m,
                fixes=count,
            )
        span_m = float(np.hypot(*(pos_ne - first)))
        if count >= PRIOR_CONTRADICTED_FIXES and span_m >= self._config.prior_conflict_span_m:
            self._kf.P[:2, :2] += np.outer(innov, innov)
            self._prior_conflict = None
            self._emit(
                "warning",
                LogEvent.ESTIMATOR_COVARIANCE_INFLATED,
                reason="prior_contradicted",
                innovation_m=disagreement_m,
                fixes=count,
                span_m=span_m,
                horiz_sigma_m=_horiz_sigma_m(self._kf.P),
            )
        self._refresh_provenance()

    def _note_no_fix_at(self, t_usec: int) -> None:
        if self._last_no_fix_usec is None or t_usec > self._last_no_fix_usec:
            self._last_no_fix_usec = t_usec

    def note_no_fix(self, time_unix_usec: int) -> None:
        """An absolute-fix attempt on the frame exposed at ``time_unix_usec`` gave no fix (too few
        inliers, pose rejected, no tiles...): ``satellite_anchored`` ends at the filter's time. Does not
        move the filter's clock."""
        if self._time_usec is None:
            return
        self._note_no_fix_at(int(time_unix_usec))
        self._refresh_provenance()

    def raise_position_sigma(self, sigma_m: float) -> None:
        """The state's position may be off the map by up to ``sigma_m`` (1 sigma per axis) more than its
        covariance says (``c4_pose/attitude_check.py``: the fixes fused before the check saw the
        autopilot's tilt off, and VO, leaned on that tilt): every horizontal eigenvalue of the filter's
        covariance is raised to at least ``sigma_m**2``; the state itself is not moved.

        This is the filter's own covariance, not the shared error ``s`` (which every map fix carries
        too and the gates leave out): a fix solved once the attitude is right does not carry the error
        the wrong attitude put into the state, so the gates that compare the two must allow for it.
        Kept in ``s`` (as it was before), a cross-date flight at 1200 m AGL with 3 deg on the roll for
        30 s stated 231 m honestly but refused every right fix after the offset as too far from the
        state (90 m off), to the end of the flight (``docs/benchmarks.md``)."""
        if self._time_usec is None or not (math.isfinite(sigma_m) and sigma_m >= 0.0):
            return
        vals, vecs = np.linalg.eigh(self._kf.P[:2, :2])
        short = np.clip(float(sigma_m) ** 2 - vals, 0.0, None)
        if np.any(short > 0.0):
            self._kf.P[:2, :2] += (vecs * short) @ vecs.T
            self._kf.P = (self._kf.P + self._kf.P.T) / 2.0
        self._refresh_provenance()

    def update_vo(self, motion: VoMotion, *, time_unix_usec: int) -> FixDecision:
        """Fuse VO motion over ``[time_unix_usec - dt, time_unix_usec]`` (``time_unix_usec``: the exposure
        of the frame that ends the interval) as the horizontal velocity at that time (see the module
        docstring). The velocity innovation is gated with ``fix_gate_chi2`` (2 dof) so a VO blunder
        cannot corrupt the velocity.
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
            self._emit(
                "warning", LogEvent.ESTIMATOR_VO_REJECTED, reason=FixReason.INVALID_MEASUREMENT, dt_s=dt
            )
            return FixDecision(False, math.nan, FixReason.INVALID_MEASUREMENT)
        t = int(time_unix_usec)
        behind = self._behind(t)
        if behind is not None:
            return behind
        self.predict_to(t)
        vel = delta / dt
        accel = None
        if self._accel is not None:
            accel = self._imu_accel(t - round(dt * 1e6), t)
            if accel is not None:
                vel = vel + accel.mean_ned_m_s2[:2] * (dt / 2.0)
        r_mat = self._config.vo_noise_scale * cov / dt**2
        if accel is None and dt > VO_GAP_S:
            # Over a gap the interval's mean velocity can differ from the end velocity by an unmeasured
            # manoeuvre (soak: 2 s without attitude in a turn left the fixes after it 4 sigma off):
            # add what the constant-velocity model allows for, so VO does not claim the end velocity.
            r_mat = r_mat + np.eye(2) * (self._config.accel_noise_m_s2 * dt / 2.0) ** 2
        x = self._kf.x.reshape(-1)
        innov = vel - x[3:5]
        stated_nis = float(innov @ np.linalg.solve(self._kf.P[3:5, 3:5] + r_mat, innov))
        self._vo_nis = (*self._vo_nis, stated_nis)[-VO_NIS_WINDOW:]
        factor = _vo_noise_factor(self._vo_nis)
        if factor > 1.0:
            r_mat = r_mat * factor
        s_mat = self._kf.P[3:5, 3:5] + r_mat
        nis = float(innov @ np.linalg.solve(s_mat, innov))
        if nis > self._config.fix_gate_chi2:
            density = self._accel_density_m_s2(accel, t)
            run = self._vo_gated_run
            if not _vo_agrees_with_run(run, innov, r_mat, dt, density, self._config.fix_gate_chi2):
                run = ()  # VO saying something else again: a new run starts with this frame
            entry: VoGated = (
                float(innov[0]),
                float(innov[1]),
                float(r_mat[0, 0]),
                float(r_mat[0, 1]),
                float(r_mat[1, 1]),
                dt,
            )
            self._vo_gated_run = run = (*run, entry)
            self._emit(
                "warning",
                LogEvent.ESTIMATOR_VO_REJECTED,
                reason=FixReason.GATED,
                nis=nis,
                gate=self._config.fix_gate_chi2,
                noise_factor=round(factor, 2),
                consecutive=len(run),
            )
            if len(run) >= CONSECUTIVE_GATED_INFLATE:
                # VO has said one other velocity frame after frame: a manoeuvre the state's velocity did
                # not follow is as likely as VO being wrong. So the velocity the state claims is in doubt
                # by what VO says, and its position by what that difference moved it over the frames
                # gated: the stated accuracy covers VO being right, and VO is heard again. VO that says
                # a different thing each frame (a blunder, or a camera whose lateness is not yet
                # measured de-rotated with the wrong attitude in a turn) agrees with no run and stays
                # gated: that is VO's noise, not the state's doubt.
                mean = np.mean([e[:2] for e in run], axis=0)
                drift = mean * sum(e[5] for e in run)
                self._kf.P[3:5, 3:5] += np.outer(mean, mean)
                self._kf.P[:2, :2] += np.outer(drift, drift)
                self._vo_gated_run = ()
                self._emit(
                    "warning",
                    LogEvent.ESTIMATOR_COVARIANCE_INFLATED,
                    what="velocity",
                    innovation_m_s=float(np.hypot(*mean)),
                    speed_sigma_m_s=float(np.sqrt(np.trace(self._kf.P[3:5, 3:5]) / 2.0)),
                    horiz_sigma_m=_horiz_sigma_m(self._kf.P),
                )
            return FixDecision(False, nis, FixReason.GATED)
        if self._last_fix_usec is not None:
            carried_usec = max(self._last_fix_usec, self._last_vo_usec or self._last_fix_usec)
            if (self._time_usec - carried_usec) / 1e6 > self._vo_recent_s:
                self._dr_since_fix = True  # VO back after a stretch the state was dead-reckoned through
        self._kf.update(vel.reshape(2, 1), R=r_mat, H=_H_VEL_NE)
        self._vo_gated_run = ()
        self._last_vo_usec = self._time_usec
        self._refresh_provenance()
        return FixDecision(True, nis, FixReason.ACCEPTED)

    def update_altitude(
        self, alt_agl_m: float, ground_alt_amsl_m: float, sigma_m: float, *, time_unix_usec: int | None = None
    ) -> FixDecision:
        """Fuse the autopilot's height above ground (flat ground at ``ground_alt_amsl_m``) on ``d`` at
        ``time_unix_usec`` (default: the filter's time). Not gated: the autopilot's altitude is the
        more trusted source."""
        if self._time_usec is None:
            return FixDecision(False, math.nan, FixReason.NOT_INITIALISED)
        if not (math.isfinite(alt_agl_m) and math.isfinite(ground_alt_amsl_m) and sigma_m > 0):
            return FixDecision(False, math.nan, FixReason.INVALID_MEASUREMENT)
        if time_unix_usec is not None:
            behind = self._behind(int(time_unix_usec))
            if behind is not None:
                return behind
            self.predict_to(int(time_unix_usec))
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
        x, p_mat = self._propagate(x, p_mat, self._time_usec, int(time_unix_usec))
        return x, p_mat, int(time_unix_usec)

    def provenance_at(self, time_unix_usec: int | None = None) -> Provenance:
        """The provenance label at ``time_unix_usec`` (default: the filter's time), without side effects."""
        if self._time_usec is None:
            return Provenance.NO_ESTIMATE
        t = self._time_usec if time_unix_usec is None else int(time_unix_usec)
        _, p_mat, t = self._predicted(t)
        return self._label(p_mat, t)

    def _output_cov_pos(self, p_mat: np.ndarray) -> np.ndarray:
        """The position covariance an output states: the filter's plus the shared fix error."""
        cov = p_mat[:3, :3].copy()
        cov[:2, :2] += np.eye(2) * self._shared_sigma_m**2
        return cov

    def _label(self, p_mat: np.ndarray, t: int) -> Provenance:
        if _horiz_sigma_m(self._output_cov_pos(p_mat)) > self._config.max_output_sigma_m:
            return Provenance.NO_ESTIMATE
        if (
            self._last_fix_usec is not None
            and (self._last_no_fix_usec is None or self._last_fix_usec >= self._last_no_fix_usec)
            and (t - self._last_fix_usec) / 1e6 <= self._fix_recent_s
        ):
            return Provenance.SATELLITE_ANCHORED
        if self._last_vo_usec is not None and (t - self._last_vo_usec) / 1e6 <= self._vo_recent_s:
            return Provenance.VISUAL_PROPAGATED
        return Provenance.DEAD_RECKONING

    def _refresh_provenance(self, label: Provenance | None = None) -> None:
        if not self.provenance_live:
            return
        new = self.provenance_at() if label is None else label
        if new is not self._provenance:
            self._emit(
                "info", LogEvent.PROVENANCE_CHANGED, **{"from": self._provenance.value, "to": new.value}
            )
            self._provenance = new

    def state(self, time_unix_usec: int | None = None) -> EstimatorState:
        """The estimate predicted to ``time_unix_usec`` (default: the filter's time).

        Does not change the filter (a pure prediction on copies), so output can be produced at any rate
        between measurements; the only side effect is the ``provenance_changed`` log when the label
        at that time differs from the last one logged. Before :meth:`initialise` the state is
        ``no_estimate`` with NaN position and infinite covariance.
        """
        if self._time_usec is None:
            return EstimatorState.no_estimate(int(time_unix_usec or 0))
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
            cov_pos_ned_m2=self._output_cov_pos(p_mat),
            cov_vel_ned_m2_s2=p_mat[3:, 3:].copy(),
            lat_deg=float(lat),
            lon_deg=float(lon),
            alt_amsl_m=float(alt),
            yaw_rad=self._yaw_rad,
            last_fix_age_s=fix_age,
            shared_sigma_m=self._shared_sigma_m,
            map_confirmed=self._map_confirmed,
        )


def _vo_noise_factor(nis: tuple[float, ...]) -> float:
    """How much noisier VO has shown itself than it states: the median of its newest normalised
    innovations (``nis``, gated ones included) over a consistent VO's (``CHI2_2DOF_MEDIAN``), where that
    is beyond twice it over at least half a window, else 1; at most ``VO_NOISE_FACTOR_MAX``.

    A gate alone cannot tell a blunder from a VO whose noise is understated: VO that alternates about
    the truth by more than it states (measured on PX4 SIH landing at 30 m AGL over weak texture: +0.6
    and -0.7 m east a frame while the truth moved under 0.2 m) was fused on one side and gated on the
    other, and the state ran off 10 m in 5 s at a stated 1.4 m. The median leaves one
    blunder among consistent updates gated as before."""
    if len(nis) < VO_NIS_WINDOW // 2:
        return 1.0
    median = float(np.median(nis))
    if median <= 2.0 * CHI2_2DOF_MEDIAN:
        return 1.0
    return min(median / CHI2_2DOF_MEDIAN, VO_NOISE_FACTOR_MAX)
