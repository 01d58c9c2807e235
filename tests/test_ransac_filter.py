"""Shared RansacFilter (seed AZ-282): inliers, MEDIAN residual, degenerate inputs, determinism."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from gps_denied_onboard.helpers.ransac_filter import RansacFilter

H_TRUE = np.array([[0.95, -0.2, 40.0], [0.18, 0.97, -25.0], [2e-5, -1e-5, 1.0]])


def _correspondences(n_in: int, n_out: int, noise_px: float, seed: int = 0) -> np.ndarray:
    if n_in + n_out == 0:
        return np.empty((0, 4), dtype=np.float32)
    rng = np.random.default_rng(seed)
    q = rng.uniform(0, 512, (n_in + n_out, 2))
    t = cv2.perspectiveTransform(q.reshape(-1, 1, 2), H_TRUE).reshape(-1, 2)
    t[:n_in] += rng.normal(0, noise_px, (n_in, 2))
    t[n_in:] = rng.uniform(0, 512, (n_out, 2))  # gross outliers
    return np.hstack([q, t]).astype(np.float32)


def test_ransac_filter_recovers_homography_and_rejects_outliers() -> None:
    """200 noisy inliers + 100 outliers: ~all inliers kept, outliers counted, H close to the truth."""
    corr = _correspondences(200, 100, 0.5)
    result = RansacFilter().filter(corr, threshold_px=3.0)
    assert 190 <= result.inlier_count <= 205
    assert result.ransac_outlier_count == 300 - result.inlier_count
    assert result.inlier_correspondences.dtype == np.float32 and result.inlier_correspondences.shape[1] == 4
    assert result.homography is not None and result.homography.shape == (3, 3)
    probe = np.array([[[100.0, 100.0]], [[400.0, 300.0]]])
    np.testing.assert_allclose(
        cv2.perspectiveTransform(probe, result.homography), cv2.perspectiveTransform(probe, H_TRUE), atol=1.0
    )


def test_ransac_filter_residual_is_median_not_mean() -> None:
    """The residual is the median of the inliers' reprojection errors (INV-8)."""
    corr = _correspondences(200, 0, 0.8, seed=3)
    result = RansacFilter().filter(corr, threshold_px=3.0)
    assert result.homography is not None
    inl = result.inlier_correspondences.astype(np.float64)
    err = np.linalg.norm(
        cv2.perspectiveTransform(inl[:, :2].reshape(-1, 1, 2), result.homography).reshape(-1, 2) - inl[:, 2:],
        axis=1,
    )
    assert result.per_candidate_residual_px == pytest.approx(float(np.median(err)), rel=1e-6)
    assert result.per_candidate_residual_px != pytest.approx(float(np.mean(err)), rel=1e-3)
    assert (err <= 3.0).all()


@pytest.mark.parametrize("n", [0, 1, 3])
def test_ransac_filter_fewer_than_four_gives_empty_result(n: int) -> None:
    """Fewer than 4 correspondences -> empty inliers, inf residual, no exception."""
    result = RansacFilter().filter(_correspondences(n, 0, 0.0), threshold_px=3.0)
    assert result.inlier_correspondences.shape == (0, 4)
    assert result.ransac_outlier_count == n
    assert math.isinf(result.per_candidate_residual_px) and result.homography is None


def test_ransac_filter_degenerate_collinear_gives_empty_result() -> None:
    """All points on one line (no homography) -> empty result, not an exception."""
    x = np.linspace(0, 500, 50)
    corr = np.column_stack([x, x, x * 2, x * 2]).astype(np.float32)
    result = RansacFilter().filter(corr, threshold_px=3.0)
    assert result.inlier_count == 0 and result.homography is None


def test_ransac_filter_non_finite_input_gives_empty_result() -> None:
    """NaN in the correspondences -> empty result."""
    corr = _correspondences(50, 0, 0.5)
    corr[3, 1] = np.nan
    assert RansacFilter().filter(corr, threshold_px=3.0).inlier_count == 0


def test_ransac_filter_is_deterministic() -> None:
    """Same input -> bit-identical inliers and residual (needed for C3 AC-10)."""
    corr = _correspondences(150, 150, 1.0, seed=9)
    a = RansacFilter().filter(corr, threshold_px=3.0)
    b = RansacFilter().filter(corr, threshold_px=3.0)
    assert np.array_equal(a.inlier_correspondences, b.inlier_correspondences)
    assert a.per_candidate_residual_px == b.per_candidate_residual_px


def test_ransac_filter_rejects_bad_arguments() -> None:
    """Unknown method, wrong shape, non-positive threshold -> ValueError naming the problem."""
    with pytest.raises(ValueError, match="usac_magsac"):
        RansacFilter(method="lmeds")
    with pytest.raises(ValueError, match=r"\(M, 4\)"):
        RansacFilter().filter(np.zeros((10, 3), np.float32), threshold_px=3.0)
    with pytest.raises(ValueError, match="threshold_px"):
        RansacFilter().filter(np.zeros((10, 4), np.float32), threshold_px=0.0)
