"""The slice of the shared LightGlue helper (seed AZ-278) that C3 strategies call.

Strategies type against this Protocol instead of importing ``helpers.lightglue_runtime`` so that a
test double (and the real ``LightGlueRuntime``) satisfy it structurally.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class LightGluePairMatcher(Protocol):
    def match_pair(
        self,
        kpts0: np.ndarray,
        desc0: np.ndarray,
        kpts1: np.ndarray,
        desc1: np.ndarray,
        *,
        image_size0: tuple[int, int],
        image_size1: tuple[int, int],
    ) -> tuple[np.ndarray, np.ndarray]:
        """Match two keypoint sets.

        - ``kpts0``/``kpts1``: (N0, 2) / (N1, 2) float32 pixel coordinates (x, y) in their images;
        - ``desc0``/``desc1``: (N0, D) / (N1, D) float32;
        - ``image_size0``/``image_size1``: (width_px, height_px) of the images the keypoints are in.

        Returns ``(matches, scores)``: (M, 2) int64 index pairs (i into set 0, j into set 1) and
        (M,) float32 match confidences.
        """
        ...
