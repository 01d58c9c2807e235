"""How much a picture of the ground has to match on: one measure for nav frames and for map chips.

``edge_share`` is the share of an image, brought to about ``WORK_WIDTH_PX`` across (a nav frame at
100-150 m AGL and a 512 px map chip both end up near a metre a pixel), whose gradient after a light
blur is at least ``MIN_GRADIENT_DN`` grey levels a pixel. It is absolute on purpose: the orientation
field (``helpers/orientation_field.py``) weighs each edge against its neighbourhood, so sensor noise on
a blank frame scores there about as much as a textured field does; here it scores nothing. A frame of
fog, snow or water (``sitl`` map gaps: ``featureless``) and a covered lens (``blackout``) measure below
1 %, the procedural demo map and real orthophotos tens of percent (``docs/design.md``, "A wrong prior
is found out").

It is what ``c5_estimator/prior_doubt.py`` asks of a frame, and of the map where the prior puts it,
before a failed fix attempt on it counts against the prior.
"""

from __future__ import annotations

from typing import Final

import cv2
import numpy as np

#: Width the image is brought to before the gradient is measured, px.
WORK_WIDTH_PX: Final = 160
#: Gaussian blur before the gradient, px at the working width: photon noise is not texture.
BLUR_SIGMA_PX: Final = 1.0
#: A pixel is an edge where its gradient is at least this, grey levels per pixel at the working width.
MIN_GRADIENT_DN: Final = 3.0


def edge_share(image: np.ndarray) -> float:
    """Share (0..1) of ``image`` ((H, W) grey or (H, W, 3) BGR, uint8) that is edges (module docstring).
    0 for an image too small to measure. Pure (no state), about a millisecond for a 640 x 480 frame."""
    arr = np.asarray(image)
    if arr.ndim == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_BGR2GRAY)
    if arr.ndim != 2 or min(arr.shape) < 8:
        return 0.0
    h, w = arr.shape
    scale = min(1.0, WORK_WIDTH_PX / float(w))
    size = (max(8, round(w * scale)), max(8, round(h * scale)))
    small = cv2.resize(arr.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), BLUR_SIGMA_PX, borderType=cv2.BORDER_REFLECT)
    # Sobel 3x3 sums 4 differences two pixels apart: / 8 gives grey levels per pixel.
    gx = cv2.Sobel(small, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 8.0, borderType=cv2.BORDER_REFLECT)
    gy = cv2.Sobel(small, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 8.0, borderType=cv2.BORDER_REFLECT)
    inner = (slice(2, -2), slice(2, -2))  # the border's reflection is not the ground's
    mag2 = (gx * gx + gy * gy)[inner]
    return float(np.mean(mag2 >= MIN_GRADIENT_DN * MIN_GRADIENT_DN))
