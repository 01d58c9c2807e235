"""The gradient-orientation field (``helpers/orientation_field.py``): the signal the area correlation
matches, on both sides. Properties it must have for cross-date matching and for a cache built in bands."""

from __future__ import annotations

import cv2
import numpy as np

from gps_denied_onboard.components.c3_matcher.area_search import Hypothesis, _warp_field
from gps_denied_onboard.helpers.orientation_field import (
    EDGE_MARGIN_PX,
    NODATA,
    dequantise,
    downsample2,
    orientation_field,
    quantise,
)


def _scene(seed: int = 3, size: int = 160) -> np.ndarray:
    """A grey image with fields, roads and blobs at several scales (float32, 0..255)."""
    rng = np.random.default_rng(seed)
    img = np.zeros((size, size), np.float32)
    for _ in range(40):
        x, y = rng.integers(0, size, 2)
        w, h = rng.integers(8, 50, 2)
        cv2.rectangle(img, (int(x), int(y)), (int(x + w), int(y + h)), float(rng.uniform(30, 220)), -1)
    for _ in range(6):
        p0, p1 = rng.integers(0, size, 2), rng.integers(0, size, 2)
        cv2.line(img, (int(p0[0]), int(p0[1])), (int(p1[0]), int(p1[1])), 250.0, 2)
    return cv2.GaussianBlur(img, (0, 0), 1.2) + rng.normal(0, 2.0, img.shape).astype(np.float32)


def _cos(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.vdot(a, b).real / np.sqrt(np.vdot(a, a).real * np.vdot(b, b).real))


def test_a_contrast_reversed_image_has_the_same_field() -> None:
    """Polarity-free: a field darker than the road one year and lighter the next reads the same."""
    img = _scene()
    valid = np.ones(img.shape, bool)
    z, _ = orientation_field(img, valid)
    z_rev, _ = orientation_field(255.0 - img, valid)
    assert np.abs(z - z_rev).max() < 1e-3
    assert _cos(z, z_rev) > 0.9999


def test_the_field_is_unit_bounded_and_zero_near_the_footprint_edge() -> None:
    img = _scene()
    valid = np.ones(img.shape, bool)
    valid[:, :40] = False
    z, inner = orientation_field(img, valid)
    assert np.abs(z).max() <= 1.0 + 1e-6
    assert not inner[:, : 40 + EDGE_MARGIN_PX].any() and inner[:, 40 + EDGE_MARGIN_PX :][5:-5, :-5].all()
    assert not z[:, : 40 + EDGE_MARGIN_PX].any()
    # What fills nodata does not reach a counted gradient.
    filled = img.copy()
    filled[:, :40] = 0.0
    assert np.array_equal(orientation_field(filled, valid)[0], z)


def test_a_rotated_field_is_the_field_of_the_rotated_image() -> None:
    """The search warps the field and turns its phase instead of recomputing it per hypothesis."""
    img = _scene(size=200)
    valid = np.ones(img.shape, bool)
    centre = (99.5, 99.5)
    z, _ = orientation_field(img, valid)
    hyp = Hypothesis(20.0, 1.04)  # larger than any search turns, so the phase turn shows
    warped_z, _ = _warp_field(z, None, centre, hyp)
    m = cv2.getRotationMatrix2D(centre, hyp.rotation_deg, hyp.scale)
    warped_img = cv2.warpAffine(img, m, (200, 200), flags=cv2.INTER_LINEAR)
    direct, _ = orientation_field(warped_img, valid)
    inside = np.zeros(img.shape, bool)
    inside[30:170, 30:170] = True
    assert _cos(warped_z[inside], direct[inside]) > 0.8
    # Without the phase turn the same comparison is clearly worse: the turn is what makes it right.
    unturned = warped_z * np.complex64(np.exp(2j * np.radians(hyp.rotation_deg)))
    assert _cos(unturned[inside], direct[inside]) < _cos(warped_z[inside], direct[inside]) - 0.15


def test_quantised_fields_round_trip_and_keep_nodata() -> None:
    img = _scene()
    valid = np.ones(img.shape, bool)
    valid[10:20, 10:20] = False
    z, _ = orientation_field(img, valid)
    q = quantise(z, valid)
    assert q.dtype == np.int8 and q.shape == (*img.shape, 2)
    assert (q[10:20, 10:20, 0] == NODATA).all()
    back, back_valid = dequantise(q)
    assert np.array_equal(back_valid, valid)
    assert np.abs(back - z)[valid].max() <= np.sqrt(2) * 0.5 / 127 + 1e-6


def test_downsampling_keeps_only_wholly_valid_pixels() -> None:
    grey = np.arange(16, dtype=np.float32).reshape(4, 4)
    valid = np.ones((4, 4), bool)
    valid[0, 0] = False
    g2, v2 = downsample2(grey, valid)
    assert g2.shape == (2, 2) and g2[1, 1] == np.mean([10, 11, 14, 15])
    assert v2.tolist() == [[False, True], [True, True]]
