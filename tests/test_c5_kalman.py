"""The estimator's Kalman arithmetic (``c5_estimator.kalman``) against independent forms of the same
filter: the process noise against the integral that defines it, the update against the information form."""

from __future__ import annotations

import numpy as np
import pytest

from gps_denied_onboard.components.c5_estimator.kalman import KalmanState, white_noise_accel_q


def test_process_noise_is_the_integrated_white_noise_acceleration_per_axis() -> None:
    """Q = integral over [0, dt] of F(s) G q G^T F(s)^T ds, with F the constant-velocity transition and G
    putting the acceleration on the velocity: summed numerically, for each of the three axes, with the
    state laid out [n, e, d, vn, ve, vd] and no coupling between axes."""
    dt, q = 0.1, 0.49
    s = np.linspace(0.0, dt, 20001)
    # F(s) G = [s, 1] for one axis' (position, velocity)
    col = np.stack([s, np.ones_like(s)])
    integrand = q * np.einsum("is,js->ijs", col, col)
    expected_axis = (integrand[..., 1:] + integrand[..., :-1]).sum(axis=2) * (s[1] - s[0]) / 2.0  # trapezoid
    got = white_noise_accel_q(dt, q)
    assert got.shape == (6, 6)
    for axis in range(3):
        idx = [axis, axis + 3]
        np.testing.assert_allclose(got[np.ix_(idx, idx)], expected_axis, rtol=1e-6)
    mask = np.zeros((6, 6), bool)
    for axis in range(3):
        mask[np.ix_([axis, axis + 3], [axis, axis + 3])] = True
    assert np.all(got[~mask] == 0.0)
    np.testing.assert_array_equal(white_noise_accel_q(0.0, q), np.zeros((6, 6)))
    with pytest.raises(ValueError, match="dt_s"):
        white_noise_accel_q(-0.1, q)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_update_matches_the_information_form(seed: int) -> None:
    """After fusing z = H x + v (v ~ N(0, R)): P+^-1 = P^-1 + H^T R^-1 H and x+ = P+ (P^-1 x + H^T R^-1 z),
    the same filter written the other way; P+ symmetric, and the gain kept."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(6, 6))
    p_mat = a @ a.T + 0.5 * np.eye(6)
    x = rng.normal(size=(6, 1))
    h_mat = rng.normal(size=(2, 6))
    b = rng.normal(size=(2, 2))
    r_mat = b @ b.T + 0.1 * np.eye(2)
    z = rng.normal(size=(2, 1))
    state = KalmanState(x.copy(), p_mat.copy())
    state.update(z, r_mat, h_mat)
    info = np.linalg.inv(p_mat) + h_mat.T @ np.linalg.inv(r_mat) @ h_mat
    p_post = np.linalg.inv(info)
    x_post = p_post @ (np.linalg.solve(p_mat, x) + h_mat.T @ np.linalg.solve(r_mat, z))
    np.testing.assert_allclose(state.P, p_post, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(state.x, x_post, rtol=1e-8, atol=1e-10)
    np.testing.assert_array_equal(state.P, state.P.T)
    assert state.K.shape == (6, 2)
    np.testing.assert_allclose(state.K, p_post @ h_mat.T @ np.linalg.inv(r_mat), rtol=1e-8, atol=1e-10)
