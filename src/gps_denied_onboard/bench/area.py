"""``gdnav bench area``: the area correlation (C3 ``orientation_corr``) on real imagery, before it is trusted.

Two kinds of input, each run through the real cache build (with its orientation fields and calibration),
the real matcher, the real C4 area pose and the real integrity rule:

- **Maps of one area on several dates** (``run_dates``; NAIP's ten dates): for every ordered pair (the
  map from one date, the frames rendered from another with the SITL renderer at ``alt_agl_m``, a little
  roll and pitch and any heading), each frame is searched twice: with a prior up to ``PRIOR_OFFSET_M``
  off (the truth in the disc: a right fix should be found, within ``RIGHT_M``, and accepted) and with the
  truth 1.3-2.5 disc radii away (a wrong place: nothing may be accepted).
- **Overlapping drone photos with poses** (``run_photos``; the senseFly eBee set): one photo of each
  overlapping pair is orthorectified with its own pose into a GeoTIFF, which becomes the map; its
  neighbour, with its own pose, is the frame, its pixels whose ground (by its own pose) falls outside the
  map blacked out (what the camera saw beyond the map is no evidence either way). The prior is the
  neighbour's GNSS position up to ``PHOTO_PRIOR_OFFSET_M`` off. The truth is that GNSS position, so the
  figure carries both photos' GNSS and attitude errors.

Per pair: frames, right fixes found and accepted, the accepted fixes' error (p50 / p95 / max), wrong places
searched and accepted, the PSR and peak of right and wrong searches, and the CPU time per attempt (the
process's, so OpenCV's own threads count). Figures: docs/benchmarks.md, "Area correlation on real imagery".
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Final

import cv2
import numpy as np
import rasterio
from rasterio.transform import Affine

from gps_denied_onboard.camera.types import Attitude, CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c2_5_rerank.types import RerankCandidate, RerankResult, SearchPrior
from gps_denied_onboard.components.c3_matcher.errors import InsufficientInliersError, MatcherError
from gps_denied_onboard.components.c3_matcher.health import RollingHealthWindow
from gps_denied_onboard.components.c3_matcher.orientation_corr import MAX_RADIUS_PX, OrientationCorrMatcher
from gps_denied_onboard.components.c4_pose.area_pose import AreaPoseSolver
from gps_denied_onboard.components.c4_pose.integrity import CandidateFix, FixIntegrity, evidence_of
from gps_denied_onboard.components.c4_pose.types import PoseError
from gps_denied_onboard.components.c6_tiles.map_fields import MapFields
from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.components.c10_cache_build import build_cache_from_geotiff
from gps_denied_onboard.components.c10_cache_build.map_fields import build_map_fields
from gps_denied_onboard.config import IntegrityConfig, MatcherConfig, PoseConfig
from gps_denied_onboard.geo import LocalTangentPlane, haversine_m
from gps_denied_onboard.helpers.frame_rectifier import rectify_to_map_frame
from gps_denied_onboard.helpers.ransac_filter import RansacFilter

#: A right search starts this far from the truth at most, m (a prior of 30-50 m sigma).
PRIOR_OFFSET_M: Final = 100.0
PRIOR_SIGMA_M: Final = 50.0
#: A right fix is within this of the truth, m.
RIGHT_M: Final = 10.0
CHIP_SIZE_PX: Final = 512
#: The photo pairs' prior: a GNSS-quality start (their truth is GNSS too).
PHOTO_PRIOR_OFFSET_M: Final = 15.0
PHOTO_PRIOR_SIGMA_M: Final = 10.0
#: How well the photos' truth (GNSS and the map photo's pose) is known, m.
PHOTO_TRUTH_SIGMA_M: Final = 10.0
#: How far inside the map's footprint a frame pixel's ground must fall to be kept, m (the poses' errors).
PHOTO_OVERLAP_MARGIN_M: Final = 5.0
#: The flat ground the renders stand on (any value: the map has no height of its own).
GROUND_AMSL_M: Final = 400.0


@dataclasses.dataclass
class _Area:
    store: TileStore
    fields: MapFields
    matcher: OrientationCorrMatcher
    solver: AreaPoseSolver
    rule: FixIntegrity


def _area(cache_dir: Path, tif: Path, ground_amsl_m: float, pose: PoseConfig) -> _Area:
    build_cache_from_geotiff(tif, cache_dir, progress=False)
    build_map_fields(cache_dir, progress=False)
    store = TileStore.open(cache_dir)
    fields = MapFields.open(store)
    lon, lat = store.center_lonlat
    matcher = OrientationCorrMatcher(
        config=MatcherConfig(strategy="orientation_corr"),
        fields=fields,
        health_window=RollingHealthWindow(low_inlier_threshold=25),
        ransac_filter=RansacFilter(),
    )
    solver = AreaPoseSolver(pose, LocalTangentPlane(lat, lon, ground_amsl_m), ground_amsl_m)
    return _Area(store, fields, matcher, solver, FixIntegrity(IntegrityConfig()))


def _offset(lat: float, lon: float, north_m: float, east_m: float) -> tuple[float, float]:
    return lat + north_m / 111_320.0, lon + east_m / (111_320.0 * math.cos(math.radians(lat)))


@dataclasses.dataclass
class _Tally:
    frames: int = 0
    found: int = 0
    accepted: int = 0
    errors_m: list[float] = dataclasses.field(default_factory=list)
    wrong_searched: int = 0
    wrong_accepted: int = 0
    right_psr: list[float] = dataclasses.field(default_factory=list)
    right_peak: list[float] = dataclasses.field(default_factory=list)
    wrong_psr: list[float] = dataclasses.field(default_factory=list)
    wrong_peak: list[float] = dataclasses.field(default_factory=list)
    cpu_ms: list[float] = dataclasses.field(default_factory=list)
    refusals: dict[str, int] = dataclasses.field(default_factory=dict)

    def figures(self) -> dict[str, Any]:
        def pct(v: list[float], q: float) -> float | None:
            return round(float(np.percentile(v, q)), 3) if v else None

        return {
            "frames": self.frames,
            "right_found": self.found,
            "right_accepted": self.accepted,
            "accepted_error_m": {"p50": pct(self.errors_m, 50), "p95": pct(self.errors_m, 95),
                                 "max": round(max(self.errors_m), 2) if self.errors_m else None},
            "wrong_searched": self.wrong_searched,
            "wrong_accepted": self.wrong_accepted,
            "right_psr": {"p5": pct(self.right_psr, 5), "p50": pct(self.right_psr, 50)},
            "right_peak": {"p5": pct(self.right_peak, 5), "p50": pct(self.right_peak, 50)},
            "wrong_psr": {"p95": pct(self.wrong_psr, 95), "max": pct(self.wrong_psr, 100)},
            "wrong_peak": {"p95": pct(self.wrong_peak, 95), "max": pct(self.wrong_peak, 100)},
            "cpu_ms_per_attempt": {"p50": pct(self.cpu_ms, 50), "p95": pct(self.cpu_ms, 95)},
            "refusals": dict(sorted(self.refusals.items())),
        }  # fmt: skip


def _search(
    area: _Area, frame: NavCameraFrame, calib: CameraCalibration, lat: float, lon: float, sigma_m: float
) -> tuple[Any, Any, float] | None:
    """(the best candidate, the integrity verdict on its fix, CPU ms) of one search, or None."""
    chip = area.store.chip_around(lat, lon, CHIP_SIZE_PX)
    if chip is None:
        return None
    cand = RerankCandidate(chip.tile_id, chip, rerank_inliers=-1, vpr_distance=math.nan)
    request = RerankResult(frame.frame_id, [cand], time.monotonic_ns(), search=SearchPrior(lat, lon, sigma_m))
    t0 = time.process_time()
    try:
        best = area.matcher.match(frame, request, calib).best
        fix = area.solver.solve(frame, best)
    except (InsufficientInliersError, MatcherError, PoseError):
        return None
    cpu_ms = (time.process_time() - t0) * 1e3
    verdict = area.rule.assess(
        CandidateFix(fix, evidence_of(best, (calib.width_px, calib.height_px))),
        map_gsd_m_px=best.area.map_gsd_m_px if best.area is not None else 1.0,
    )
    return best, verdict, cpu_ms


def _judge(
    tally: _Tally,
    area: _Area,
    frame: NavCameraFrame,
    calib: CameraCalibration,
    truth: tuple[float, float],
    rng: np.random.Generator,
    *,
    prior_offset_m: float = PRIOR_OFFSET_M,
    prior_sigma_m: float = PRIOR_SIGMA_M,
    truth_sigma_m: float = 0.0,
) -> None:
    """One frame: a right search (the prior up to ``prior_offset_m`` off, stating ``prior_sigma_m``) and a
    wrong one (module docstring), its disc kept ``3 * truth_sigma_m`` farther off where the truth itself is
    uncertain (GNSS)."""
    tally.frames += 1
    a = rng.uniform(0.0, 2.0 * math.pi)
    d = rng.uniform(0.0, prior_offset_m)
    right = _search(area, frame, calib, *_offset(*truth, d * math.cos(a), d * math.sin(a)), prior_sigma_m)
    if right is not None:
        best, verdict, cpu_ms = right
        tally.cpu_ms.append(cpu_ms)
        assert best.area is not None
        tally.right_psr.append(best.area.psr)
        tally.right_peak.append(best.area.peak)
        err = haversine_m(verdict.fix.lat_deg, verdict.fix.lon_deg, *truth)
        tally.found += int(err <= RIGHT_M)
        if verdict.accepted:
            tally.accepted += 1
            tally.errors_m.append(err)
        elif verdict.reason is not None:
            tally.refusals[verdict.reason] = tally.refusals.get(verdict.reason, 0) + 1
    radius_m = MAX_RADIUS_PX * area.store.gsd_m_px * 2 ** (area.fields.calibrated_levels[-1] - 1)
    d = rng.uniform(1.3, 2.5) * radius_m + 3.0 * truth_sigma_m
    wrong = _search(area, frame, calib, *_offset(*truth, d * math.cos(a), d * math.sin(a)), 1e4)
    if wrong is not None:
        best, verdict, _ = wrong
        assert best.area is not None
        tally.wrong_searched += 1
        tally.wrong_psr.append(best.area.psr)
        tally.wrong_peak.append(best.area.peak)
        tally.wrong_accepted += int(verdict.accepted)


def run_dates(
    tifs: Sequence[Path],
    workdir: Path,
    *,
    frames: int = 12,
    alt_agl_m: float = 1200.0,
    seed: int = 0,
    echo: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Every ordered pair of ``tifs`` (map, frames): the module docstring's first kind."""
    from gps_denied_onboard.sitl.render import MapRenderer

    calib = CameraCalibration.from_hfov(640, 480, 70.0)
    areas: dict[Path, _Area] = {}
    renderers = {t: MapRenderer(t) for t in tifs}
    pairs = []
    for map_tif, frame_tif in itertools.permutations(tifs, 2):
        if map_tif not in areas:
            areas[map_tif] = _area(workdir / f"cache-{map_tif.stem}", map_tif, GROUND_AMSL_M, PoseConfig())
        area, renderer = areas[map_tif], renderers[frame_tif]
        rng = np.random.default_rng(seed)
        tally = _Tally()
        west, south, east, north = renderer.bbox_lonlat
        half = 1.2 * alt_agl_m * math.tan(math.radians(35.0)) / 111_320.0
        for _ in range(frames):
            lat = float(rng.uniform(south + 1.3 * half, north - 1.3 * half))
            lon = float(rng.uniform(west + 1.9 * half, east - 1.9 * half))
            att = Attitude(*np.radians([rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(-180, 180)]))
            image = renderer.render(calib, lat, lon, alt_agl_m, att)
            frame = NavCameraFrame(uuid.uuid4(), 0, 0, image, att, alt_agl_m, 0)
            _judge(tally, area, frame, calib, (lat, lon), rng)
        row = {"map": map_tif.name, "frames_from": frame_tif.name, **tally.figures()}
        pairs.append(row)
        echo(_line(row))
    return {"kind": "dates", "alt_agl_m": alt_agl_m, "frames_per_pair": frames, "pairs": pairs}


def _orthophoto(image: np.ndarray, calib: CameraCalibration, att: Attitude, agl_m: float,
                lat: float, lon: float, path: Path) -> None:  # fmt: skip
    """``image`` warped north-up with its own pose and written as a GeoTIFF (EPSG:3857) whose nadir pixel
    is at (``lat``, ``lon``)."""
    gsd = agl_m / calib.fx_px
    rect = rectify_to_map_frame(image, calib, att, agl_m, gsd)
    ray = att.R_ned_cam().T @ np.array([0.0, 0.0, 1.0])
    p = rect.H_frame_to_rect @ (calib.K @ ray)
    nx, ny = p[0] / p[2], p[1] / p[2]
    r = 6_378_137.0
    x0 = math.radians(lon) * r
    y0 = math.log(math.tan(math.pi / 4 + math.radians(lat) / 2)) * r
    step = gsd / math.cos(math.radians(lat))  # Web-Mercator metres per ground metre at this latitude
    transform = Affine(step, 0.0, x0 - (nx + 0.5) * step, 0.0, -step, y0 + (ny + 0.5) * step)
    rgb = cv2.cvtColor(rect.image, cv2.COLOR_BGR2RGB)
    with rasterio.open(path, "w", driver="GTiff", width=rgb.shape[1], height=rgb.shape[0], count=3,
                       dtype="uint8", crs="EPSG:3857", transform=transform, nodata=0) as dst:  # fmt: skip
        dst.write(np.transpose(rgb, (2, 0, 1)))


def _inside_map(
    image: np.ndarray,
    calib: CameraCalibration,
    att: Attitude,
    agl_m: float,
    lat_lon: tuple[float, float],
    tif: Path,
) -> np.ndarray:
    """``image`` with the pixels whose ground (by its own pose) falls outside the map's footprint, less
    ``PHOTO_OVERLAP_MARGIN_M``, set to 0 (nodata, as the rectifier reads it)."""
    from rasterio.warp import transform as warp_transform

    from gps_denied_onboard.helpers.frame_rectifier import frame_to_ground_homography

    h, w = image.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w]
    px = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    g = frame_to_ground_homography(calib, att, agl_m) @ px
    north, east = g[0] / g[2], g[1] / g[2]
    lat0, lon0 = lat_lon
    lat = lat0 + north / 111_320.0
    lon = lon0 + east / (111_320.0 * math.cos(math.radians(lat0)))
    with rasterio.open(tif) as ds:
        mx, my = warp_transform("EPSG:4326", ds.crs, lon.tolist(), lat.tolist())
        rows, cols = rasterio.transform.rowcol(ds.transform, mx, my)
        valid = ds.read(1) > 0
        step_m = abs(ds.transform.a) * math.cos(math.radians(lat0))
    margin = max(1, round(PHOTO_OVERLAP_MARGIN_M / step_m))
    valid = cv2.erode(valid.astype(np.uint8), np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)) > 0
    r, c = np.asarray(rows), np.asarray(cols)
    inside = (r >= 0) & (r < valid.shape[0]) & (c >= 0) & (c < valid.shape[1])
    keep = np.zeros(r.shape, bool)
    keep[inside] = valid[r[inside], c[inside]]
    out = image.copy()
    out[~keep.reshape(h, w)] = 0
    return out


def run_photos(
    images_dir: Path,
    csv_path: Path,
    pairs: Sequence[tuple[str, str]],
    workdir: Path,
    *,
    ground_alt_amsl_m: float,
    image_scale: float,
    echo: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Each (map photo, frame photo) of ``pairs``: the module docstring's second kind."""
    from gps_denied_onboard.replay.inputs import calibration_from_exif, from_csv

    source = from_csv(
        images_dir, csv_path, ground_alt_amsl_m=ground_alt_amsl_m, image_scale=image_scale, prior_sigma_m=10.0
    )
    by_name = {f.name: (f, t) for f, t in zip(source.frames, source.truth, strict=True)}
    rows = []
    for map_name, frame_name in pairs:
        (mf, mt), (ff, ft) = by_name[map_name], by_name[frame_name]
        calib = calibration_from_exif(images_dir / map_name, scale=image_scale)
        assert mf.attitude is not None and mf.alt_agl_m is not None
        assert ff.attitude is not None and ff.alt_agl_m is not None
        tif = workdir / f"ortho-{Path(map_name).stem}.tif"
        _orthophoto(mf.load(), calib, mf.attitude, mf.alt_agl_m, mt.lat_deg, mt.lon_deg, tif)
        area = _area(workdir / f"cache-{Path(map_name).stem}", tif, ground_alt_amsl_m, PoseConfig())
        image = _inside_map(ff.load(), calib, ff.attitude, ff.alt_agl_m, (ft.lat_deg, ft.lon_deg), tif)
        frame = NavCameraFrame(uuid.uuid4(), 0, 0, image, ff.attitude, ff.alt_agl_m, 0)
        tally = _Tally()
        _judge(
            tally,
            area,
            frame,
            calib,
            (ft.lat_deg, ft.lon_deg),
            np.random.default_rng(0),
            prior_offset_m=PHOTO_PRIOR_OFFSET_M,
            prior_sigma_m=PHOTO_PRIOR_SIGMA_M,
            truth_sigma_m=PHOTO_TRUTH_SIGMA_M,
        )
        baseline = haversine_m(mt.lat_deg, mt.lon_deg, ft.lat_deg, ft.lon_deg)
        row = {"map": map_name, "frames_from": frame_name, "baseline_m": round(baseline, 1),
               "alt_agl_m": round(ff.alt_agl_m, 1), **tally.figures()}  # fmt: skip
        rows.append(row)
        echo(_line(row))
    return {"kind": "photos", "pairs": rows}


def _line(row: dict[str, Any]) -> str:
    e, rp, wp = row["accepted_error_m"], row["right_psr"], row["wrong_psr"]
    found = f"{row['right_found']} within {RIGHT_M:g} m"
    right = f"right {row['right_accepted']}/{row['frames']} accepted ({found})"
    wrong = f"wrong {row['wrong_accepted']}/{row['wrong_searched']} accepted"
    return (
        f"{row['map']:>34} <- {row['frames_from']:<34} {right}, error p50 {e['p50']} p95 {e['p95']} m; "
        f"{wrong}; PSR right p5 {rp['p5']} wrong max {wp['max']}; CPU {row['cpu_ms_per_attempt']['p50']} ms; "
        f"refused {row['refusals']}"
    )
