"""How far apart two orthophotos of the same ground put the same features: the map pair's own error.

    .venv/bin/python tools/map_pair_offset.py MAP.tif OTHER.tif [OTHER.tif ...]
    .venv/bin/python tools/map_pair_offset.py --strategy xfeat --model-dir models MAP.tif OTHER.tif

Each OTHER is resampled onto MAP's grid. Two ways to measure, which need not agree (they did not on the
NAIP pair 2009/2014, ``docs/benchmarks.md``):

- blocks (default): both images are turned into gradient magnitude (field boundaries, roads and shores
  survive years of crop and water changes better than colour does), and square blocks of MAP are found
  in OTHER by normalised cross-correlation within +/- SEARCH_PX, to a sub-pixel peak. Blocks whose peak
  is weak or not unique are dropped.
- ``--strategy S --model-dir D``: the daemon's C3 strategy S matches WINDOW_PX windows of OTHER to the
  same windows of MAP, as ``gdnav match`` does (``cli_match.match_pair``); each window's homography moves the
  window's centre by the shift. Windows with fewer than MIN_WINDOW_INLIERS inliers are dropped; with
  ``--per-window`` each window's centre (MAP px) and shift are printed.

Prints, per OTHER, the median east/north shift in metres of OTHER's features against MAP's and its
spread. The local shift is error a fix against MAP from frames that look like OTHER can carry; on the
NAIP pair it explained part of the fixes' scatter, not their shared offset (``docs/benchmarks.md``,
"Camera boresight"). A one-off measurement tool: the daemon does not use it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
import rasterio
from rasterio.warp import Resampling, reproject

BLOCK_PX = 96
WINDOW_PX = 256
WINDOW_STEP_PX = 55
MIN_WINDOW_INLIERS = 25
SEARCH_PX = 8
MIN_PEAK = 0.5
#: A second peak this close to the first makes the block ambiguous.
UNIQUE_RATIO = 0.9


def _rgb_on(grid: rasterio.DatasetReader, path: str) -> np.ndarray:
    """(3, H, W) float32 R, G, B of ``path`` resampled onto ``grid`` (rasterio: libtiff would read NAIP's
    band 4, NIR, as alpha)."""
    with rasterio.open(path) as src:
        bands = np.zeros((3, grid.height, grid.width), np.float32)
        for b in range(3):
            reproject(
                src.read(b + 1).astype(np.float32),
                bands[b],
                src_transform=src.transform,
                src_crs=src.crs,
                dst_transform=grid.transform,
                dst_crs=grid.crs,
                resampling=Resampling.bilinear,
            )
    return bands


def _gradient_on(grid: rasterio.DatasetReader, path: str) -> np.ndarray:
    grey = cv2.GaussianBlur(_rgb_on(grid, path).mean(axis=0), (0, 0), 1.0)
    return np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1))


def _subpixel(r: np.ndarray, x: int, y: int) -> tuple[float, float]:
    dx = 0.5 * (r[y, x - 1] - r[y, x + 1]) / (r[y, x - 1] - 2 * r[y, x] + r[y, x + 1])
    dy = 0.5 * (r[y - 1, x] - r[y + 1, x]) / (r[y - 1, x] - 2 * r[y, x] + r[y + 1, x])
    return x + float(dx), y + float(dy)


def block_shifts_m(map_path: str, other_path: str) -> np.ndarray:
    """(N, 2) east, north shifts (m) of ``other``'s features against ``map``'s, one row per block."""
    with rasterio.open(map_path) as grid:
        a, b = _gradient_on(grid, map_path), _gradient_on(grid, other_path)
        gsd_x, gsd_y = abs(grid.transform.a), abs(grid.transform.e)
    rows = []
    margin = SEARCH_PX + 10
    for y in range(margin, a.shape[0] - BLOCK_PX - margin, BLOCK_PX // 2):
        for x in range(margin, a.shape[1] - BLOCK_PX - margin, BLOCK_PX // 2):
            window = b[y - SEARCH_PX : y + BLOCK_PX + SEARCH_PX, x - SEARCH_PX : x + BLOCK_PX + SEARCH_PX]
            r = cv2.matchTemplate(window, a[y : y + BLOCK_PX, x : x + BLOCK_PX], cv2.TM_CCOEFF_NORMED)
            _, peak, _, (px, py) = cv2.minMaxLoc(r)
            if peak < MIN_PEAK or not (0 < px < 2 * SEARCH_PX and 0 < py < 2 * SEARCH_PX):
                continue
            rest = r.copy()
            rest[max(0, py - 2) : py + 3, max(0, px - 2) : px + 3] = -1.0
            if rest.max() > UNIQUE_RATIO * peak:
                continue
            fx, fy = _subpixel(r, px, py)
            rows.append(((fx - SEARCH_PX) * gsd_x, -(fy - SEARCH_PX) * gsd_y))
    return np.array(rows).reshape(-1, 2)


def _bgr_on(grid: rasterio.DatasetReader, path: str) -> np.ndarray:
    bands = _rgb_on(grid, path)
    return np.ascontiguousarray(np.clip(bands[::-1], 0, 255).astype(np.uint8).transpose(1, 2, 0))


def window_shifts_m(
    map_path: str, other_path: str, strategy: str, model_dir: str | None, per_window: bool
) -> np.ndarray:
    """(N, 2) east, north shifts (m) of ``other``'s features against ``map``'s, one row per window,
    measured by the C3 strategy ``strategy``."""
    from gps_denied_onboard.cli_match import _StageTimer, build_matcher, match_pair

    with rasterio.open(map_path) as grid:
        a, b = _bgr_on(grid, map_path), _bgr_on(grid, other_path)
        gsd_x, gsd_y = abs(grid.transform.a), abs(grid.transform.e)
    timer = _StageTimer()
    matcher = build_matcher(strategy, Path(model_dir) if model_dir else None, MIN_WINDOW_INLIERS, timer)
    rows = []
    s = WINDOW_PX
    centre = np.array([[[s / 2.0, s / 2.0]]])
    for y in range(20, a.shape[0] - s - 20, WINDOW_STEP_PX):
        for x in range(20, a.shape[1] - s - 20, WINDOW_STEP_PX):
            window_other = np.ascontiguousarray(b[y : y + s, x : x + s])
            window_map = np.ascontiguousarray(a[y : y + s, x : x + s])
            found = match_pair(matcher, window_other, window_map, 1, timer, origin_px=(x, y))
            if found.homography is None:
                continue
            moved = cv2.perspectiveTransform(centre, found.homography).reshape(2)
            # OTHER px minus MAP px of the same feature; rows grow southwards.
            east_m, north_m = (s / 2.0 - moved[0]) * gsd_x, -(s / 2.0 - moved[1]) * gsd_y
            rows.append((east_m, north_m))
            if per_window:
                print(
                    f"  window centre col {x + s // 2} row {y + s // 2}: east {east_m:+.1f} m, "
                    f"north {north_m:+.1f} m, {found.inliers} inliers"
                )
    return np.array(rows).reshape(-1, 2)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    parser.add_argument("map")
    parser.add_argument("others", nargs="+")
    parser.add_argument("--strategy", help="measure with this C3 strategy instead of gradient blocks")
    parser.add_argument("--model-dir", help="gdnav models export output, for a learned strategy")
    parser.add_argument("--per-window", action="store_true", help="print each window's shift")
    args = parser.parse_args(argv)
    from gps_denied_onboard.logging_setup import configure_logging

    configure_logging("warning", json=False)
    for other in args.others:
        if args.strategy:
            d = window_shifts_m(args.map, other, args.strategy, args.model_dir, args.per_window)
            unit = "windows"
        else:
            d, unit = block_shifts_m(args.map, other), "blocks"
        if not len(d):
            print(f"{other}: no {unit[:-1]} matched")
            continue
        e, n = np.median(d, axis=0)
        iqr = np.subtract(*np.percentile(d, [75, 25], axis=0))
        print(
            f"{other}: {len(d)} {unit}; median shift east {e:+.2f} m, north {n:+.2f} m "
            f"(|.| {np.hypot(e, n):.2f} m); interquartile range east {iqr[0]:.2f} m, north {iqr[1]:.2f} m"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
