"""Query normalisation: bring a nav frame into the map's frame before describing it (C2, C2.5).

The cache's chips are north-up Web-Mercator squares of ``chip_size_px`` at the map's ground resolution;
a nav frame is rotated by the vehicle's heading, tilted by roll/pitch and scaled by altitude. A global
descriptor of the raw frame would have to be invariant to all three, and weights-free descriptors are
not. With the autopilot's attitude (heading included) and AGL altitude, the flat-ground homography
(``helpers.frame_rectifier.rectify_to_map_frame``) removes them: the result is a chip-like image,
north-up, at the map GSD, of the same size as a map chip, centred on the ground point under the
principal point. Pixels outside the camera footprint are 0, the same convention as nodata in the map.

There is no north-up query without heading: a frame without attitude or altitude raises
``VprBackboneError`` rather than being described in an unknown orientation (the pipeline then gives
no absolute fix for the frame, see ``pipeline.NavigationPipeline``).

``QueryNormaliser`` keeps the last result keyed by ``frame_id`` so that C2 and C2.5, which both need
the normalised query of the same frame, pay for the warp once.
"""

from __future__ import annotations

import threading
import uuid
from dataclasses import dataclass

import numpy as np

from gps_denied_onboard.camera.types import CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c2_vpr.types import VprBackboneError
from gps_denied_onboard.helpers.frame_rectifier import (
    RectificationError,
    RectifiedQuery,
    rectify_to_map_frame,
)


@dataclass(frozen=True)
class NormalisedQuery:
    """A nav frame in the map's frame.

    ``rectified``: the warp (``image`` (S, S, 3) uint8 BGR north-up at ``gsd_m_px``, S =
    ``chip_size_px``, 0 outside the footprint, and ``H_frame_to_rect`` to go back to frame pixels).
    ``frame_id``: the frame it came from.
    """

    frame_id: uuid.UUID
    rectified: RectifiedQuery

    @property
    def image(self) -> np.ndarray:
        return self.rectified.image


class QueryNormaliser:
    """Rectify nav frames north-up at ``gsd_m_px`` into ``chip_size_px`` squares (see module docstring).

    ``backbone`` names the strategy in the errors it raises. Thread-safe (one lock around the memo).
    """

    def __init__(self, *, gsd_m_px: float, chip_size_px: int, backbone: str) -> None:
        if not gsd_m_px > 0:
            raise ValueError(f"gsd_m_px must be > 0, got {gsd_m_px!r}")
        if chip_size_px < 16:
            raise ValueError(f"chip_size_px must be >= 16, got {chip_size_px!r}")
        self._gsd = float(gsd_m_px)
        self._size = int(chip_size_px)
        self._backbone = backbone
        self._lock = threading.Lock()
        self._last: NormalisedQuery | None = None

    @property
    def gsd_m_px(self) -> float:
        return self._gsd

    @property
    def chip_size_px(self) -> int:
        return self._size

    def normalise(self, frame: NavCameraFrame, calibration: CameraCalibration) -> NormalisedQuery:
        """The frame warped north-up at the map GSD; ``VprBackboneError`` without attitude/altitude or
        when the warp is impossible (horizon in view, bad altitude, frame/calibration size mismatch)."""
        with self._lock:
            last = self._last
        if last is not None and last.frame_id == frame.frame_id:
            return last
        if frame.attitude is None or frame.alt_agl_m is None:
            raise VprBackboneError(
                "no north-up query without attitude (heading) and AGL altitude at exposure",
                backbone=self._backbone,
                frame_id=frame.frame_id,
            )
        try:
            rect = rectify_to_map_frame(
                frame.image_bgr,
                calibration,
                frame.attitude,
                float(frame.alt_agl_m),
                self._gsd,
                out_size_px=self._size,
            )
        except RectificationError as exc:
            raise VprBackboneError(
                f"cannot bring the frame to the map frame: {exc}",
                backbone=self._backbone,
                frame_id=frame.frame_id,
            ) from exc
        result = NormalisedQuery(frame.frame_id, rect)
        with self._lock:
            self._last = result
        return result
