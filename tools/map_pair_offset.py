"""How far apart two orthophotos of the same ground put the same features: the map pair's own error.

    .venv/bin/python tools/map_pair_offset.py MAP.tif OTHER.tif [OTHER.tif ...]

Each OTHER is resampled onto MAP's grid; both are turned into gradient magnitude (field boundaries,
roads and shores survive years of crop and water changes better than colour does), and square blocks of
MAP are found in OTHER by normalised cross-correlation within +/- SEARCH_PX, to a sub-pixel peak. Blocks
whose peak is weak or not unique are dropped. Prints, per OTHER, the median east/north shift in metres
of OTHER's features against MAP's and its spread. A fix against MAP from frames that look like OTHER
cannot be better than this shift (``docs/benchmarks.md``, "Camera boresight"). A one-off measurement
tool: the daemon does not use it.
"""

from __future__ import annotations

import sys

import cv2
import numpy as np
import rasterio
from rasterio.warp import Resampling, reproject

BLOCK_PX = 96
SEARCH_PX = 8
MIN_PEAK = 0.5
#: A second peak this close to the first makes the block ambiguous.
UNIQUE_RATIO = 0.9


def _gradient_on(grid: rasterio.DatasetReader, path: str) -> np.ndarray:
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
    grey = cv2.GaussianBlur(bands.mean(axis=0), (0, 0), 1.0)
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


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    map_path = argv[0]
    for other in argv[1:]:
        d = block_shifts_m(map_path, other)
        if not len(d):
            print(f"{other}: no block matched")
            continue
        e, n = np.median(d, axis=0)
        iqr = np.subtract(*np.percentile(d, [75, 25], axis=0))
        print(
            f"{other}: {len(d)} blocks; median shift east {e:+.2f} m, north {n:+.2f} m "
            f"(|.| {np.hypot(e, n):.2f} m); interquartile range east {iqr[0]:.2f} m, north {iqr[1]:.2f} m"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
