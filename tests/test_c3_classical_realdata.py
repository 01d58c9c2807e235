"""Classical C3 strategy on real imagery (C3-IT-01 floor: best-candidate inliers >= 80).

Query frames are crops of a real orthophoto warped by random small homographies (rotation, scale,
perspective) with photometric changes; candidates are 512x512 chips of the same raster (the true chip
and two wrong ones). The cross-date check (NAIP 2009 vs 2020) only reports its success fraction:
classical features are expected to fail across a large appearance gap.
"""

from __future__ import annotations

import glob
import math
import os
import time
import uuid
from pathlib import Path

import cv2
import numpy as np
import pytest

from gps_denied_onboard.camera.types import Attitude, CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c2_5_rerank.types import RerankCandidate, RerankResult
from gps_denied_onboard.components.c3_matcher.classical import ClassicalMatcher
from gps_denied_onboard.components.c3_matcher.errors import InsufficientInliersError
from gps_denied_onboard.components.c3_matcher.health import RollingHealthWindow
from gps_denied_onboard.components.c6_tiles.types import TileId
from gps_denied_onboard.config import MatcherConfig
from gps_denied_onboard.helpers.ransac_filter import RansacFilter

pytestmark = pytest.mark.realdata

DATA = Path("/work/shared/data")
GEOVISION = DATA / "geovision_india" / "geovision_india_z18.tif"
NAIP_DIR = DATA / "naip_timeseries" / "naip"
#: EPSG:3857 m/px of the GeoVision raster x cos(17.59 deg): ground metres per pixel.
GEOVISION_GSD_M_PX = 0.2986 * math.cos(math.radians(17.59))
FRAME_W, FRAME_H = 640, 480
CHIP_PX = 512
IT01_MIN_INLIERS = 80


class RasterChip:
    """Minimal TilePixelsHandle: a read-only view of a raster window (no copy)."""

    def __init__(
        self, raster: np.ndarray, x0: int, y0: int, size: int, gsd_m_px: float, tile_no: int
    ) -> None:
        view = raster[y0 : y0 + size, x0 : x0 + size]
        view.setflags(write=False)
        self._view = view
        self.origin = (x0, y0)
        self._gsd = gsd_m_px
        self._tile_id = TileId.of(18, 17.0 + tile_no * 1e-3, 78.0 + x0 * 1e-6)

    @property
    def tile_id(self) -> TileId:
        return self._tile_id

    @property
    def gsd_m_px(self) -> float:
        return self._gsd

    def pixels(self) -> np.ndarray:
        return self._view

    def chip_px_to_lonlat(self, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = np.asarray(px, dtype=np.float64).reshape(-1, 2)
        return (p[:, 0] + self.origin[0]) * 1e-6, (p[:, 1] + self.origin[1]) * -1e-6

    def lonlat_to_chip_px(self, lon_deg: np.ndarray, lat_deg: np.ndarray) -> np.ndarray:
        return np.column_stack(
            [np.asarray(lon_deg) / 1e-6 - self.origin[0], np.asarray(lat_deg) / -1e-6 - self.origin[1]]
        )


def _read_bgr(path: Path) -> np.ndarray:
    rasterio = pytest.importorskip("rasterio")
    with rasterio.open(path) as ds:
        rgb = ds.read([1, 2, 3])
    return np.ascontiguousarray(cv2.cvtColor(rgb.transpose(1, 2, 0), cv2.COLOR_RGB2BGR))


@pytest.fixture(scope="module")
def geovision() -> np.ndarray:
    if not GEOVISION.is_file():
        pytest.skip(f"real imagery not available: {GEOVISION}")
    return _read_bgr(GEOVISION)


def _random_query_homography(
    rng: np.random.Generator, centre_xy: tuple[float, float], frame_wh: tuple[int, int]
) -> np.ndarray:
    """Query px -> raster px: +-10 deg rotation, +-10 % scale, mild perspective around the centre."""
    theta = math.radians(rng.uniform(-10, 10))
    s = rng.uniform(0.9, 1.1)
    c, si = math.cos(theta), math.sin(theta)
    to_centre = np.array([[1, 0, -frame_wh[0] / 2], [0, 1, -frame_wh[1] / 2], [0, 0, 1]], dtype=np.float64)
    rot_scale = np.array([[s * c, -s * si, 0], [s * si, s * c, 0], [0, 0, 1]])
    persp = np.array([[1, 0, 0], [0, 1, 0], [rng.uniform(-1e-4, 1e-4), rng.uniform(-1e-4, 1e-4), 1]])
    to_raster = np.array([[1, 0, centre_xy[0]], [0, 1, centre_xy[1]], [0, 0, 1]])
    return to_raster @ rot_scale @ persp @ to_centre


def _photometric(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Gamma, contrast/brightness, blur and sensor noise."""
    f = img.astype(np.float32) / 255.0
    f = np.power(f, rng.uniform(0.8, 1.25))
    f = f * rng.uniform(0.85, 1.15) + rng.uniform(-0.06, 0.06)
    out = np.clip(f * 255.0, 0, 255).astype(np.uint8)
    out = cv2.GaussianBlur(out, (0, 0), rng.uniform(0.5, 1.0))
    noise = rng.normal(0, 3.0, out.shape)
    return np.clip(out.astype(np.float32) + noise, 0, 255).astype(np.uint8)


def _frame(
    image: np.ndarray, attitude: Attitude | None = None, alt_agl_m: float | None = None
) -> NavCameraFrame:
    return NavCameraFrame(uuid.uuid4(), 0, 0, image, attitude, alt_agl_m, time.monotonic_ns())


def _matcher(**overrides: object) -> ClassicalMatcher:
    config = MatcherConfig(**overrides)  # type: ignore[arg-type]
    return ClassicalMatcher(
        RansacFilter("usac_magsac", config.ransac_confidence, config.ransac_max_iters),
        None,
        RollingHealthWindow(config.min_inliers_threshold),
        config,
    )


def _pick_chips(
    map_src: np.ndarray,
    rng: np.random.Generator,
    centre: tuple[float, float],
    footprint: np.ndarray,
    chip_px: int,
    gsd_m_px: float,
) -> list[RasterChip]:
    """True chip (first) near ``centre`` + two wrong chips that see none of the frame's footprint."""
    h, w = map_src.shape[:2]
    (fx0, fy0), (fx1, fy1) = footprint.min(axis=0), footprint.max(axis=0)
    # The true chip is offset from the frame centre like a prior with tens of metres of error.
    jx, jy = rng.uniform(-0.15, 0.15, 2) * chip_px
    tx = int(np.clip(centre[0] + jx - chip_px / 2, 0, w - chip_px))
    ty = int(np.clip(centre[1] + jy - chip_px / 2, 0, h - chip_px))
    chips = [RasterChip(map_src, tx, ty, chip_px, gsd_m_px, 0)]
    while len(chips) < 3:
        wx, wy = int(rng.uniform(0, w - chip_px)), int(rng.uniform(0, h - chip_px))
        if wx > fx1 or wx + chip_px < fx0 or wy > fy1 or wy + chip_px < fy0:
            chips.append(RasterChip(map_src, wx, wy, chip_px, gsd_m_px, len(chips)))
    return chips


def _case(
    query_src: np.ndarray,
    map_src: np.ndarray,
    rng: np.random.Generator,
    gsd_m_px: float,
    chip_px: int,
    frame_wh: tuple[int, int] = (FRAME_W, FRAME_H),
) -> tuple[NavCameraFrame, RerankResult, np.ndarray, list[RasterChip]]:
    """A warped-crop frame, its candidates (shuffled) and its true query px -> raster px homography."""
    h, w = map_src.shape[:2]
    fw, fh = frame_wh
    margin = max(fw, fh) // 2 + 40
    cx, cy = rng.uniform(margin, w - margin), rng.uniform(margin, h - margin)
    h_q2r = _random_query_homography(rng, (cx, cy), frame_wh)
    query = cv2.warpPerspective(query_src, h_q2r, frame_wh, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    query = _photometric(query, rng)
    corners = np.array([[[0, 0]], [[fw, 0]], [[fw, fh]], [[0, fh]]], dtype=np.float64)
    footprint = cv2.perspectiveTransform(corners, h_q2r).reshape(-1, 2)
    chips = _pick_chips(map_src, rng, (cx, cy), footprint, chip_px, gsd_m_px)
    frame = _frame(query)
    return frame, _rerank(frame, chips, rng), h_q2r, chips


def _rerank(frame: NavCameraFrame, chips: list[RasterChip], rng: np.random.Generator) -> RerankResult:
    order = rng.permutation(len(chips))
    cands = [RerankCandidate(chips[i].tile_id, chips[i], -1, 0.0) for i in order]
    return RerankResult(frame.frame_id, cands, time.monotonic_ns())


def _evaluate(
    matcher: ClassicalMatcher,
    frame: NavCameraFrame,
    rerank: RerankResult,
    calib: CameraCalibration,
    frame_to_raster: np.ndarray,
    chips: list[RasterChip],
) -> tuple[bool, int, float]:
    """(true chip first with >= 80 inliers, best inliers, median error px of its correspondences)."""
    try:
        result = matcher.match(frame, rerank, calib)
    except InsufficientInliersError as exc:
        return False, exc.best_inlier_count, math.inf
    best = result.best
    # The correspondences themselves: nav-frame px -> raster px via the true geometry.
    corr = best.inlier_correspondences.astype(np.float64)
    truth = cv2.perspectiveTransform(corr[:, :2].reshape(-1, 1, 2), frame_to_raster).reshape(-1, 2)
    chip = next(c for c in chips if c.tile_id == best.tile_id)
    err = np.linalg.norm(truth - (corr[:, 2:] + np.array(chip.origin)), axis=1)
    ok = best.tile_id == chips[0].tile_id and best.inlier_count >= IT01_MIN_INLIERS
    return ok, best.inlier_count, float(np.median(err))


def _trial(
    matcher: ClassicalMatcher,
    query_src: np.ndarray,
    map_src: np.ndarray,
    rng: np.random.Generator,
    gsd_m_px: float,
    chip_px: int,
    frame_wh: tuple[int, int] = (FRAME_W, FRAME_H),
) -> tuple[bool, int, float]:
    frame, rerank, h_q2r, chips = _case(query_src, map_src, rng, gsd_m_px, chip_px, frame_wh)
    calib = CameraCalibration.from_hfov(frame_wh[0], frame_wh[1], 70.0)
    return _evaluate(matcher, frame, rerank, calib, h_q2r, chips)


def test_classical_realdata_same_source_ranks_true_chip_first(geovision: np.ndarray) -> None:
    """Same-source warped frames: the true chip wins with >= 80 inliers in >= 80 % of trials."""
    rng = np.random.default_rng(20240611)
    matcher = _matcher()
    outcomes = [_trial(matcher, geovision, geovision, rng, GEOVISION_GSD_M_PX, CHIP_PX) for _ in range(10)]
    fraction = sum(o[0] for o in outcomes) / len(outcomes)
    print(
        f"\ngeovision same-source: success {fraction:.2f}; (inliers, median geo error px) = "
        f"{[(o[1], round(o[2], 2)) for o in outcomes]}"
    )
    assert fraction >= 0.8
    # Where the true chip won, its correspondences agree with the true homography to a few pixels.
    assert all(o[2] < 3.0 for o in outcomes if o[0])


def test_classical_realdata_cross_date_naip_reports_fraction() -> None:
    """Cross-date NAIP 2009 vs 2020: the success fraction is measured and reported (no floor)."""
    old = sorted(glob.glob(str(NAIP_DIR / "*2009*.tif")))
    new = sorted(glob.glob(str(NAIP_DIR / "*2020*.tif")))
    if not old or not new:
        pytest.skip(f"NAIP time series not available under {NAIP_DIR}")
    flight = _read_bgr(Path(old[0]))
    map_img = _read_bgr(Path(new[0]))
    # The two grids differ by at most ~3 m (< 1 px at 5 m/px): same pixel grid, common extent.
    h = min(flight.shape[0], map_img.shape[0])
    w = min(flight.shape[1], map_img.shape[1])
    flight, map_img = flight[:h, :w], map_img[:h, :w]
    rng = np.random.default_rng(7)
    matcher = _matcher()
    outcomes = [_trial(matcher, flight, map_img, rng, 5.0, 256, (320, 240)) for _ in range(10)]
    fraction = sum(o[0] for o in outcomes) / len(outcomes)
    print(f"\nNAIP 2009 -> 2020 cross-date: success {fraction:.2f}; inliers {[o[1] for o in outcomes]}")
    assert 0.0 <= fraction <= 1.0


def test_classical_realdata_rectified_frame_with_yaw_and_tilt(geovision: np.ndarray) -> None:
    """Perspective frames (any yaw, +-8 deg tilt, 100-140 m AGL) are rectified and matched correctly."""
    rng = np.random.default_rng(99)
    matcher = _matcher()
    calib = CameraCalibration.from_hfov(FRAME_W, FRAME_H, 70.0)
    g = GEOVISION_GSD_M_PX
    outcomes = []
    for _ in range(4):
        attitude = Attitude(
            math.radians(rng.uniform(-8, 8)),
            math.radians(rng.uniform(-8, 8)),
            math.radians(rng.uniform(-180, 180)),
        )
        alt = rng.uniform(100.0, 140.0)
        h, w = geovision.shape[:2]
        cx, cy = rng.uniform(700, w - 700), rng.uniform(700, h - 700)
        # Raster px -> frame px by the forward camera model (independent of the rectifier's maths).
        ned_of_px = np.array([[0.0, -g, g * cy], [g, 0.0, -g * cx], [0.0, 0.0, alt]])
        raster_to_frame = calib.K @ attitude.R_ned_cam().T @ ned_of_px
        image = cv2.warpPerspective(geovision, raster_to_frame, (FRAME_W, FRAME_H), flags=cv2.INTER_LINEAR)
        frame = _frame(_photometric(image, rng), attitude, alt)
        frame_to_raster = np.linalg.inv(raster_to_frame)
        corners = np.array([[[0, 0]], [[FRAME_W, 0]], [[FRAME_W, FRAME_H]], [[0, FRAME_H]]], dtype=np.float64)
        footprint = cv2.perspectiveTransform(corners, frame_to_raster).reshape(-1, 2)
        chips = _pick_chips(geovision, rng, (cx, cy), footprint, CHIP_PX, g)
        outcomes.append(_evaluate(matcher, frame, _rerank(frame, chips, rng), calib, frame_to_raster, chips))
    print(f"\ngeovision rectified: {[(o[0], o[1], round(o[2], 2)) for o in outcomes]}")
    assert sum(o[0] for o in outcomes) >= 3
    # Inlier query px are ORIGINAL frame px: they agree with the true frame -> raster mapping.
    assert all(o[2] < 3.0 for o in outcomes if o[0])


@pytest.mark.slow
def test_classical_realdata_frame_latency_cold_and_warm(geovision: np.ndarray) -> None:
    """640x480 frame + 3 chips of 512 px: report p50/p95 with a cold and a warm tile cache."""
    rng = np.random.default_rng(3)
    matcher = _matcher()
    calib = CameraCalibration.from_hfov(FRAME_W, FRAME_H, 70.0)
    cold: list[float] = []
    warm: list[float] = []
    for _ in range(12):
        frame, rerank, _, _ = _case(geovision, geovision, rng, GEOVISION_GSD_M_PX, CHIP_PX)
        matcher.tile_cache.clear()
        t0 = time.perf_counter()
        matcher.match(frame, rerank, calib)
        cold.append(time.perf_counter() - t0)
        again = _frame(_photometric(frame.image_bgr, rng))
        t0 = time.perf_counter()
        matcher.match(again, RerankResult(again.frame_id, rerank.candidates, 0), calib)
        warm.append(time.perf_counter() - t0)
    stats = {
        name: (np.percentile(v, 50) * 1e3, np.percentile(v, 95) * 1e3)
        for name, v in (("cold", cold), ("warm", warm))
    }
    print(f"\nC3 classical latency ms (p50, p95): {stats}; load average {os.getloadavg()}")
    # The target is p95 <= 250 ms cold on an idle 2-core box; the CI machine is shared, so the assertion
    # only guards against a gross regression (e.g. losing the detect scale or the tile cache).
    assert stats["cold"][1] < 1000.0
    assert stats["warm"][0] < stats["cold"][0]


def test_classical_realdata_orb_detector_matches_true_chip(geovision: np.ndarray) -> None:
    """The ORB variant (binary descriptors, Hamming matching) also finds the true chip."""
    rng = np.random.default_rng(11)
    matcher = _matcher(classical_detector="orb")
    outcomes = [_trial(matcher, geovision, geovision, rng, GEOVISION_GSD_M_PX, CHIP_PX) for _ in range(3)]
    print(f"\ngeovision ORB: {[(o[0], o[1], round(o[2], 2)) for o in outcomes]}")
    assert sum(o[0] for o in outcomes) >= 2
