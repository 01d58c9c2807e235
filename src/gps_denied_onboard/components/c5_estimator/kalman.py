"""The linear Kalman filter's two steps, in NumPy alone: the navigator core imports no SciPy.

The estimator's model is linear (constant velocity, or driven by the IMU's acceleration), so its filter is
the textbook one; :mod:`~gps_denied_onboard.components.c5_estimator.ekf` decides what is fused and when.
This module decides only the arithmetic:

- **prediction noise**: a continuous white-noise acceleration of spectral density ``q`` (m^2/s^3) on each
  axis, integrated over ``dt``: per axis ``q [[dt^3/3, dt^2/2], [dt^2/2, dt]]`` on (position, velocity),
  laid out for the state ``[n, e, d, vn, ve, vd]``;
- **update**: the gain from the innovation covariance, the covariance in Joseph form
  (``(I - KH) P (I - KH)^T + K R K^T``), which stays symmetric and positive under rounding, then
  symmetrised.

Why not filterpy (the design's first choice): it imports SciPy's statistics at import time (0.5-0.8 s on
two cores), and the core must be back on the air within a second of a restart (issue 36).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def white_noise_accel_q(dt_s: float, spectral_density: float, axes: int = 3) -> np.ndarray:
    """Process noise over ``dt_s`` for ``axes`` position-velocity pairs, state ordered
    ``[p_1..p_axes, v_1..v_axes]``; ``spectral_density``: the acceleration's (m/s^2)^2 per Hz."""
    if not (np.isfinite(dt_s) and dt_s >= 0):
        raise ValueError(f"dt_s must be a finite number of seconds >= 0, got {dt_s!r}")
    block = spectral_density * np.array([[dt_s**3 / 3.0, dt_s**2 / 2.0], [dt_s**2 / 2.0, dt_s]])
    return np.kron(block, np.eye(axes))  # (position, velocity) blocks, each diagonal over the axes


@dataclass
class KalmanState:
    """The filter's mean ``x`` (n, 1), covariance ``P`` (n, n) and the last update's gain ``K``."""

    x: np.ndarray
    P: np.ndarray
    K: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    @classmethod
    def zeros(cls, dim_x: int) -> KalmanState:
        return cls(np.zeros((dim_x, 1)), np.eye(dim_x))

    def update(self, z: np.ndarray, R: np.ndarray, H: np.ndarray) -> None:
        """Fuse the measurement ``z`` (m, 1) of ``H x`` with covariance ``R`` (m, m)."""
        y = z - H @ self.x
        pht = self.P @ H.T
        s_mat = H @ pht + R
        gain = np.linalg.solve(s_mat.T, pht.T).T  # P H^T S^-1 (S symmetric)
        self.x = self.x + gain @ y
        i_kh = np.eye(self.P.shape[0]) - gain @ H
        p_mat = i_kh @ self.P @ i_kh.T + gain @ R @ gain.T
        self.P = (p_mat + p_mat.T) / 2.0
        self.K = gain
