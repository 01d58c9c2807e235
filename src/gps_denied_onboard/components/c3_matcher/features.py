"""Local features: the value the C3 strategies' extract hooks return and precomputed tile sets hold.

Imported by the candidate loop (``base``), the learned strategies (``learned``) and the precomputed tile
features (``tile_features``), which therefore need not import each other.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from gps_denied_onboard.components.c6_tiles.types import TilePixelsHandle


@dataclass(frozen=True)
class Features:
    """Local features of one image.

    - ``keypoints_px``: (N, 2) float32 (x, y) pixels of the image they were extracted from;
    - ``descriptors``: (N, D), float32 (learned, SIFT) or uint8 (binary ORB/AKAZE);
    - ``image_size``: (width_px, height_px) of that image.
    """

    keypoints_px: np.ndarray
    descriptors: np.ndarray
    image_size: tuple[int, int]

    @property
    def count(self) -> int:
        return int(self.keypoints_px.shape[0])


def no_features(image_size: tuple[int, int], descriptor_dim: int, dtype: type = np.float32) -> Features:
    """An empty feature set (an image with no texture is not an error)."""
    return Features(
        np.empty((0, 2), dtype=np.float32), np.empty((0, descriptor_dim), dtype=dtype), image_size
    )


class TileFeatureSource(Protocol):
    """Precomputed tile features (``c3_matcher.tile_features.PrecomputedTileFeatures``)."""

    @property
    def identity(self) -> Any: ...

    def lookup(self, handle: TilePixelsHandle, chip_wh: tuple[int, int]) -> Features | None: ...
