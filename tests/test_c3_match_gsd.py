"""C3 matches at the coarser of the map's and the frame's GSD: a chip finer than the frame is downsampled
before its features are extracted, and its matches come back in the chip's own pixels."""

from __future__ import annotations

import math
from typing import ClassVar

import cv2
import numpy as np
import pytest

from gps_denied_onboard.camera.types import Attitude, CameraCalibration
from gps_denied_onboard.components.c3_matcher.base import CandidateLoopMatcher, Features
from gps_denied_onboard.components.c3_matcher.health import RollingHealthWindow
from gps_denied_onboard.config import MatcherConfig
from gps_denied_onboard.helpers.ransac_filter import RansacResult
from test_c3_matcher_contract import _frame, _rerank

CALIB = CameraCalibration.from_hfov(640, 480, 70.0)
#: Dots in the 512 px chip (x, y), sorted by x: what a feature extractor would find.
DOTS = np.array([[60.0, 450.0], [101.0, 99.0], [250.0, 380.0], [401.0, 121.0], [470.0, 300.0]])


class _DotMatcher(CandidateLoopMatcher):
    """Finds bright dots in the chip it is given; pairs them in x order with dummy query points."""

    label: ClassVar[str] = "dots"
    query_phase: ClassVar[str] = "query"
    tile_phase: ClassVar[str] = "tile"
    match_phase: ClassVar[str] = "match"

    def __init__(self, **kw: object) -> None:
        super().__init__(**kw)  # type: ignore[arg-type]
        self.query_shapes: list[tuple[int, ...]] = []
        self.tile_shapes: list[tuple[int, ...]] = []

    def extract_query(self, image_bgr: np.ndarray) -> Features:
        self.query_shapes.append(image_bgr.shape)
        kp = np.array([[10.0 * i + 20.0, 7.0 * i + 30.0] for i in range(len(DOTS))], dtype=np.float32)
        return Features(kp, np.zeros((len(kp), 4), np.float32), (image_bgr.shape[1], image_bgr.shape[0]))

    def extract_tile(self, chip_bgr: np.ndarray) -> Features:
        self.tile_shapes.append(chip_bgr.shape)
        gray = cv2.cvtColor(np.ascontiguousarray(chip_bgr), cv2.COLOR_BGR2GRAY).astype(np.float32)
        n, labels = cv2.connectedComponents((gray > 10).astype(np.uint8))
        ys, xs = np.mgrid[: gray.shape[0], : gray.shape[1]]
        centres = []
        for label in range(1, n):
            w = gray * (labels == label)
            centres.append([(w * xs).sum() / w.sum(), (w * ys).sum() / w.sum()])
        kp = np.array(sorted(centres), dtype=np.float32)
        return Features(kp, np.zeros((len(kp), 4), np.float32), (chip_bgr.shape[1], chip_bgr.shape[0]))

    def match_features(self, query: Features, tile: Features) -> np.ndarray:
        return np.hstack([query.keypoints_px, tile.keypoints_px]).astype(np.float32)


class _KeepAll:
    def filter(self, correspondences: np.ndarray, threshold_px: float) -> RansacResult:
        n = correspondences.shape[0]
        return RansacResult(correspondences.copy(), 0, 0.5, np.eye(3), np.ones(n, dtype=bool))


def _dotted_chip() -> np.ndarray:
    chip = np.zeros((512, 512, 3), np.uint8)
    for x, y in DOTS:
        cv2.circle(chip, (int(x), int(y)), 4, (255, 255, 255), -1)
    return chip


@pytest.mark.parametrize("alt_agl_m", [300.0, 100.0])
def test_chip_finer_than_the_frame_is_matched_at_the_frames_gsd(alt_agl_m: float) -> None:
    cfg = MatcherConfig(min_inliers_threshold=4)
    matcher = _DotMatcher(
        ransac_filter=_KeepAll(), fdr_client=None, health_window=RollingHealthWindow(4), config=cfg
    )
    frame = _frame(Attitude(0.0, 0.0, math.radians(10.0)), alt_agl_m)
    rerank = _rerank(frame, 1)
    handle = rerank.candidates[0].tile_pixels_handle
    handle._pixels = _dotted_chip()  # type: ignore[attr-defined]
    result = matcher.match(frame, rerank, CALIB)

    frame_gsd = alt_agl_m / CALIB.fx_px
    if frame_gsd > handle.gsd_m_px:  # 300 m: 0.66 m/px frames over a 0.3 m/px map
        side = round(512 * handle.gsd_m_px / frame_gsd)
        assert matcher.tile_shapes == [(side, side, 3)]
    else:  # 100 m: 0.22 m/px frames, the map is the coarser: the chip is matched as it is
        assert matcher.tile_shapes == [(512, 512, 3)]
    # Whatever scale the features were found at, the matches are in the chip's own pixels.
    np.testing.assert_allclose(result.best.inlier_correspondences[:, 2:], DOTS, atol=0.6)
