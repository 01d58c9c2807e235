"""The gradient-orientation field: what the area correlation (C3 ``orientation_corr``) matches, and what
the map cache stores (C10 ``map_fields``). One definition for both sides, so a frame and the map are
described by the same numbers.

For a grey image, the field at a pixel is one complex number ``z = w * exp(2i theta)``:
- ``theta`` is the gradient direction (Sobel 3x3 after a Gaussian blur of ``BLUR_SIGMA_PX``). Doubling
  it makes the field polarity-free: an edge and the same edge with its contrast reversed (a field darker
  than the road one year, lighter the next) give the same ``z``. Across dates, edge *positions* survive
  far better than grey levels: measured on NAIP, grey NCC and phase correlation found a third to a half
  of the cross-date frames, this field all of them (docs/design.md, "Area correlation").
- ``w = |g| / (|g| + SOFT_KNEE * m)`` weighs each edge by its strength relative to ``m``, the mean
  gradient magnitude of its neighbourhood (a square of ``LOCAL_SIDE_PX``, a box filter: a fifth of the
  cost of a Gaussian of the same reach, and the field is computed twice per fix). It saturates at 1, so a
  sharp, high-contrast year cannot outweigh a soft one's structure, and noise on flat ground (small
  ``|g|`` against its surroundings) counts little.
- Pixels whose gradient would reach outside the valid footprint (nodata, the frame's edge) are 0.

Two fields correlate as ``Re sum conj(a) b = sum w_a w_b cos(2 (theta_a - theta_b))``.

Stored fields are quantised to int8 pairs (``quantise``): real and imaginary parts times 127, with
``NODATA`` (-128) in the real part where the map has no data.
"""

from __future__ import annotations

from typing import Final

import cv2
import numpy as np

#: Version of this definition; caches record it with their fields and a mismatch means rebuild.
FIELD_VERSION: Final = "orientation-v2"
#: Gaussian blur before the gradient, px: the gradient of a blurred image is its edges, not its noise.
BLUR_SIGMA_PX: Final = 1.0
#: The neighbourhood an edge's strength is judged against, px (Gaussian sigma).
LOCAL_SIDE_PX: Final = 17
#: ``w`` is one half where an edge is this many times its neighbourhood's mean gradient.
SOFT_KNEE: Final = 1.0
#: How far inside the valid footprint a pixel must be for its gradient to count, px: the blur's kernel
#: reaches 4 px (OpenCV's 9-tap kernel at sigma 1) and the Sobel one more, so no counted gradient sees a
#: pixel outside the footprint (what fills nodata does not matter, and a band of a map gives the same
#: field as the whole map).
EDGE_MARGIN_PX: Final = 5
#: The int8 value that marks nodata in the real part of a quantised field.
NODATA: Final = -128
_SCALE: Final = 127.0
_EPS: Final = 1e-6


def orientation_field(grey: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The field of ``grey`` (H, W) float32 where ``valid`` (H, W) bool is true.

    Returns ``(z, inner)``: ``z`` (H, W) complex64, ``|z| <= 1``, 0 where ``inner`` is false; ``inner``
    (H, W) bool, the pixels at least ``EDGE_MARGIN_PX`` inside ``valid`` (their gradient sees only valid
    pixels). Raises ValueError on shapes that disagree or an image too small to differentiate.
    """
    g = np.asarray(grey, dtype=np.float32)
    v = np.asarray(valid, dtype=bool)
    if g.ndim != 2 or g.shape != v.shape:
        raise ValueError(f"grey {g.shape} and valid {v.shape} must be the same 2-D shape")
    if min(g.shape) < 2 * EDGE_MARGIN_PX + 1:
        raise ValueError(f"image {g.shape} is too small for an orientation field")
    kernel = np.ones((2 * EDGE_MARGIN_PX + 1, 2 * EDGE_MARGIN_PX + 1), np.uint8)
    inner = cv2.erode(v.astype(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    # Nodata is filled with the valid mean so that the blur does not smear a cliff into the margin.
    if not v.all():
        fill = float(g[v].mean()) if v.any() else 0.0
        g = np.where(v, g, np.float32(fill))
    b = cv2.GaussianBlur(g, (0, 0), BLUR_SIGMA_PX, borderType=cv2.BORDER_REFLECT)
    gx = cv2.Sobel(b, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT)
    gy = cv2.Sobel(b, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT)
    m2 = gx * gx + gy * gy
    mag = np.sqrt(m2)
    # The neighbourhood's mean magnitude over valid pixels only (normalised convolution).
    inner_f = inner.astype(np.float32)
    box = (LOCAL_SIDE_PX, LOCAL_SIDE_PX)
    num = cv2.blur(mag * inner_f, box, borderType=cv2.BORDER_CONSTANT)
    den = cv2.blur(inner_f, box, borderType=cv2.BORDER_CONSTANT)
    local = num / np.maximum(den, _EPS)
    w = mag / (mag + SOFT_KNEE * local + _EPS)
    scale = w / (m2 + _EPS)
    z = np.empty(g.shape, np.complex64)
    z.real = (gx * gx - gy * gy) * scale
    z.imag = 2.0 * gx * gy * scale
    z[~inner] = 0
    return z, inner


def quantise(z: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``z`` (H, W) complex, ``|z| <= 1``, as (H, W, 2) int8; ``NODATA`` in the real part where
    ``valid`` is false."""
    out = np.empty((*z.shape, 2), np.int8)
    out[..., 0] = np.clip(np.rint(z.real * _SCALE), -127, 127)
    out[..., 1] = np.clip(np.rint(z.imag * _SCALE), -127, 127)
    out[..., 0][~np.asarray(valid, dtype=bool)] = NODATA
    out[..., 1][~np.asarray(valid, dtype=bool)] = 0
    return out


def dequantise(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 2) int8 -> ``(z, valid)``: (H, W) complex64 (0 at nodata) and (H, W) bool."""
    arr = np.asarray(q)
    valid = arr[..., 0] != NODATA
    z = np.empty(arr.shape[:2], np.complex64)
    z.real = arr[..., 0].astype(np.float32) / _SCALE
    z.imag = arr[..., 1].astype(np.float32) / _SCALE
    z[~valid] = 0
    return z, valid


def downsample2(grey: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One pyramid level down: 2 x 2 means of ``grey`` (H, W) float32, and ``valid`` where all four
    were valid. Odd trailing rows/columns are dropped (the level's pixel (i, j) covers (2i..2i+1,
    2j..2j+1) of the level above, so pixel centres map as ``x_coarse = (x + 0.5) / 2 - 0.5``)."""
    g = np.asarray(grey, dtype=np.float32)
    v = np.asarray(valid, dtype=bool)
    h, w = (g.shape[0] // 2) * 2, (g.shape[1] // 2) * 2
    g4 = g[:h, :w].reshape(h // 2, 2, w // 2, 2)
    v4 = v[:h, :w].reshape(h // 2, 2, w // 2, 2)
    return g4.mean(axis=(1, 3)), np.asarray(v4.all(axis=(1, 3)), dtype=bool)


def grey_of(bgr: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 BGR -> (H, W) float32 luminance (OpenCV's weights)."""
    return cv2.cvtColor(np.asarray(bgr), cv2.COLOR_BGR2GRAY).astype(np.float32)
