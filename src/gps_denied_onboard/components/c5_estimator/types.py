"""C5 contracts: the fused navigation state sent to the autopilot."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gps_denied_onboard.constants import Provenance


@dataclass(frozen=True)
class EstimatorState:
    """Estimate valid at ``time_unix_usec``. Every field that leaves the process carries its sigma."""

    time_unix_usec: int
    provenance: Provenance
    #: (3,) float64 NED position, metres, in the flight's local tangent plane.
    pos_ned_m: np.ndarray
    #: (3,) float64 NED velocity, m/s.
    vel_ned_m_s: np.ndarray
    #: (3, 3) position covariance m^2, (3, 3) velocity covariance (m/s)^2.
    cov_pos_ned_m2: np.ndarray
    cov_vel_ned_m2_s2: np.ndarray
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    #: Heading of the vehicle (from the last accepted fix or the autopilot), radians; None if unknown.
    yaw_rad: float | None
    #: Seconds since the last accepted absolute fix (inf when none yet).
    last_fix_age_s: float
    #: Per-axis horizontal 1-sigma, metres, of the map's common error that ``cov_pos_ned_m2`` includes
    #: (``PoseFix.shared_sigma_m``, see ``ekf.py``). A map fix carries the same error, so a comparison
    #: with one uses :attr:`map_frame_cov_ne_m2`, which leaves it out.
    shared_sigma_m: float
    #: Whether a map fix has confirmed the state since the estimator started (or it started from the
    #: previous run's own 3D output, resumed). A start prior nothing has confirmed is a claim: it is never
    #: sent as a 3D fix (``c8_mavlink/messages.py``, ``c5_estimator/prior_doubt.py``).
    map_confirmed: bool = True

    @property
    def map_frame_cov_ne_m2(self) -> np.ndarray:
        """(2, 2) horizontal covariance, m^2, relative to the map (without the map's common error)."""
        return self.cov_pos_ned_m2[:2, :2] - np.eye(2) * self.shared_sigma_m**2

    @property
    def horiz_sigma_m(self) -> float:
        return float(np.sqrt(np.max(np.linalg.eigvalsh(self.cov_pos_ned_m2[:2, :2]))))

    @property
    def vert_sigma_m(self) -> float:
        return float(np.sqrt(self.cov_pos_ned_m2[2, 2]))

    @property
    def speed_sigma_m_s(self) -> float:
        return float(np.sqrt(np.max(np.linalg.eigvalsh(self.cov_vel_ned_m2_s2[:2, :2]))))

    @classmethod
    def no_estimate(cls, time_unix_usec: int) -> EstimatorState:
        """No estimate at ``time_unix_usec``: NaN position, infinite covariance (fix_type 0)."""
        nan3 = np.full(3, np.nan)
        inf_cov = np.diag(np.full(3, np.inf))
        return cls(
            time_unix_usec=int(time_unix_usec),
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
            shared_sigma_m=0.0,
        )


@dataclass(frozen=True)
class FixDecision:
    """What the estimator did with one measurement (absolute fix or VO motion).

    ``nis``: normalised innovation squared of the horizontal part (chi-square, 2 dof) before the update;
    NaN when it was not computed (e.g. not initialised, invalid input). ``reason``: ``accepted``,
    ``accepted_reacquire``, ``gated``, ``fix_sigma_too_large``, ``invalid_measurement``,
    ``not_initialised``.
    """

    accepted: bool
    nis: float
    reason: str
