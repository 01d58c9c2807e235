"""Procedural demo map: a seeded, synthetic orthophoto for the demo flight (no imagery is shipped).

The scene is built so that a classical feature matcher (SIFT/ORB) can localise on it without look-alike
ambiguity: an irregular patchwork of fields (Voronoi cells of an uneven point set, each with its own
colour and texture: furrows at its own orientation and spacing, speckle, or plain), hedgerows along the
field borders, a network of curving roads of varied width, villages of buildings with gabled roofs and
cast shadows, woods and scattered trees, under multi-scale brightness variation. Every choice comes from
one seeded generator, nothing repeats periodically across the map, and the same seed gives byte-identical
pixels.

Written as an RGB uint8 GeoTIFF in EPSG:3857 (deflate-compressed, tiled), square, centred on the given
point, with a ground sampling distance of ``gsd_m`` at the centre latitude.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import rasterio
from rasterio.transform import Affine
from rasterio.warp import transform as warp_transform

#: Field palette, RGB: crops, grass, stubble, bare soil, rape, fallow.
_FIELD_RGB = np.array(
    [
        [96, 128, 60],
        [120, 150, 70],
        [78, 110, 52],
        [150, 160, 90],
        [186, 170, 110],
        [200, 184, 130],
        [140, 112, 80],
        [118, 92, 66],
        [170, 140, 96],
        [205, 200, 90],
        [132, 140, 100],
        [100, 96, 70],
    ],
    dtype=np.float32,
)
_ROOF_RGB = np.array(
    [[170, 80, 60], [150, 70, 55], [120, 120, 125], [90, 90, 95], [200, 195, 185], [110, 60, 50]],
    dtype=np.float32,
)


class DemoMapError(RuntimeError):
    """The demo map could not be generated or written. ``path`` is the target file."""

    def __init__(self, message: str, *, path: str | None = None) -> None:
        super().__init__(f"{path}: {message}" if path else message)
        self.path = path


def _smooth_noise(rng: np.random.Generator, size_px: int, cells: int) -> np.ndarray:
    """(size, size) float32 in about [-1, 1]: a random ``cells`` x ``cells`` grid, bicubically enlarged."""
    grid = rng.uniform(-1.0, 1.0, size=(cells + 3, cells + 3)).astype(np.float32)
    big = cv2.resize(
        grid, (size_px + 3 * size_px // cells, size_px + 3 * size_px // cells), interpolation=cv2.INTER_CUBIC
    )
    off = (big.shape[0] - size_px) // 2
    return big[off : off + size_px, off : off + size_px]


def _voronoi_labels(
    rng: np.random.Generator, size_px: int, n_fields: int
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Label image (int32, -1 = none) and polygons of the Voronoi cells of an uneven random point set."""
    # Rejection-sample against a smooth density so field sizes vary across the map (no uniform grain).
    density = _smooth_noise(rng, 64, 4) * 0.5 + 0.5
    pts: list[tuple[float, float]] = []
    while len(pts) < n_fields:
        x, y = rng.uniform(0, size_px, size=2)
        if rng.random() < 0.15 + 0.85 * density[int(y * 64 / size_px), int(x * 64 / size_px)]:
            pts.append((float(x), float(y)))
    subdiv = cv2.Subdiv2D((-size_px, -size_px, 3 * size_px, 3 * size_px))
    subdiv.insert(pts)
    facets, _centres = subdiv.getVoronoiFacetList([])
    labels = np.full((size_px, size_px), -1, np.int32)
    polys = []
    for i, facet in enumerate(facets):
        poly = np.round(facet).astype(np.int32)
        cv2.fillPoly(labels, [poly], i)
        polys.append(poly)
    return labels, polys


def _road(rng: np.random.Generator, size_px: int) -> np.ndarray:
    """A curving road polyline that enters from one edge: (n, 2) int32 pixel coordinates."""
    side = int(rng.integers(4))
    t = float(rng.uniform(0.1, 0.9)) * size_px
    start, heading = [
        ((t, 0.0), math.pi / 2),
        ((float(size_px), t), math.pi),
        ((t, float(size_px)), -math.pi / 2),
        ((0.0, t), 0.0),
    ][side]
    heading += float(rng.uniform(-0.6, 0.6))
    x, y = start
    step = size_px / 200.0
    curvature = 0.0
    pts = [(x, y)]
    for _ in range(int(rng.integers(120, 320))):
        # Curvature is itself a random walk: bends of varied length and sharpness, no repeating shape.
        curvature = 0.9 * curvature + float(rng.normal(0.0, 0.025))
        heading += curvature
        x += step * math.cos(heading)
        y += step * math.sin(heading)
        pts.append((x, y))
        if not (-size_px * 0.05 < x < size_px * 1.05 and -size_px * 0.05 < y < size_px * 1.05):
            break
    return np.round(np.array(pts)).astype(np.int32)


def _rect(cx: float, cy: float, w: float, h: float, angle_rad: float) -> np.ndarray:
    """Corners (4, 2) float64 of a w x h rectangle centred at (cx, cy), rotated by angle_rad."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    half = np.array([[-w, -h], [w, -h], [w, h], [-w, h]]) / 2.0
    return half @ np.array([[c, s], [-s, c]]) + (cx, cy)


def render_demo_pixels(*, seed: int = 2026, size_px: int = 4800, gsd_m: float = 0.5) -> np.ndarray:
    """The demo scene as an (size_px, size_px, 3) uint8 RGB array (deterministic for a seed)."""
    rng = np.random.default_rng(seed)
    n = size_px
    px_per_m = 1.0 / gsd_m
    area_km2 = (n * gsd_m / 1000.0) ** 2

    # 1. Fields: Voronoi cells, each with a palette colour, a jitter, and a texture. The field layer is
    #    smooth at the pixel scale, so it is computed at half resolution and enlarged once (4x cheaper);
    #    everything drawn afterwards is at full resolution.
    m = max(n // 2, 16)
    n_fields = max(8, int(110 * area_km2))
    labels, polys_half = _voronoi_labels(rng, m, n_fields)
    polys = [p * 2 for p in polys_half]
    k = len(polys)
    colour = _FIELD_RGB[rng.integers(len(_FIELD_RGB), size=k)] * rng.uniform(0.85, 1.15, size=(k, 1))
    colour += rng.normal(0.0, 8.0, size=(k, 3))
    kind = rng.choice(4, size=k, p=[0.45, 0.2, 0.2, 0.15])  # furrows, speckle, plain, wood
    theta = rng.uniform(0.0, math.pi, size=k)
    # Furrow spacing >= 4 m = 4 half-resolution px: no aliasing at the half resolution.
    period_half_px = rng.uniform(4.0, 10.0, size=k) * px_per_m / 2.0
    stripe_amp = np.where(kind == 0, rng.uniform(8.0, 28.0, size=k), 0.0).astype(np.float32)
    speckle_amp = np.where(kind == 1, rng.uniform(12.0, 36.0, size=k), 0.0).astype(np.float32)
    colour[kind == 3] = np.array([52, 78, 40], np.float32) * rng.uniform(
        0.8, 1.2, size=(int((kind == 3).sum()), 1)
    )
    colour = colour.astype(np.float32)
    lab = np.maximum(labels, 0)

    # Furrows: amp * sin(kx x + ky y + phase) with a per-field wave vector, evaluated by broadcasting.
    kx = (np.cos(theta) * 2 * math.pi / period_half_px).astype(np.float32)
    ky = (np.sin(theta) * 2 * math.pi / period_half_px).astype(np.float32)
    phase = rng.uniform(0, 2 * math.pi, size=k).astype(np.float32)
    shade = kx[lab]
    shade *= np.arange(m, dtype=np.float32)[None, :]
    shade += ky[lab] * np.arange(m, dtype=np.float32)[:, None]
    shade += phase[lab]
    np.sin(shade, out=shade)
    shade *= stripe_amp[lab]
    # One white-noise field gives both the grain and, blurred, the speckle texture of rough fields.
    white = rng.standard_normal((m, m), dtype=np.float32)
    speckle = cv2.GaussianBlur(white, (0, 0), 0.8)
    speckle *= speckle_amp[lab]
    shade += speckle
    white *= 3.0
    shade += white
    del speckle, white
    # Multi-scale brightness variation (soil moisture, crop vigour) that crosses field borders; built at
    # half the layer's resolution (its finest scale is 150 cells) and enlarged.
    q = max(m // 2, 16)
    low = (
        18.0 * _smooth_noise(rng, q, 6) + 10.0 * _smooth_noise(rng, q, 30) + 6.0 * _smooth_noise(rng, q, 150)
    )
    shade += cv2.resize(low, (m, m), interpolation=cv2.INTER_LINEAR)
    channels = []
    for c in range(3):
        ch = colour[:, c][lab]
        ch += shade
        np.clip(ch, 0, 255, out=ch)
        channels.append(ch.astype(np.uint8))
    del shade, lab
    img = cv2.resize(cv2.merge(channels), (n, n), interpolation=cv2.INTER_LINEAR)
    del channels

    # 2. Woods: dense canopy blobs over "wood" fields.
    tree_col = np.array([40, 62, 32], np.float32)
    for i in np.flatnonzero(kind == 3):
        x0, y0, w, h = cv2.boundingRect(polys[i])
        # Voronoi cells at the border extend far outside the image: sample only the visible part.
        x0, y0 = max(x0, 0), max(y0, 0)
        w, h = min(w, n - x0), min(h, n - y0)
        if w <= 0 or h <= 0:
            continue
        count = int(w * h / (9.0 * px_per_m) ** 2 * 4) + 1
        cx = rng.uniform(x0, x0 + w, size=count).astype(np.int64)
        cy = rng.uniform(y0, y0 + h, size=count).astype(np.int64)
        radii = rng.uniform(1.5, 4.0, size=count) * px_per_m
        tones = rng.uniform(0.7, 1.4, size=count)
        inside = labels[np.minimum(cy // 2, m - 1), np.minimum(cx // 2, m - 1)] == i
        for x, y, r, tone in zip(cx[inside], cy[inside], radii[inside], tones[inside], strict=True):
            cv2.circle(img, (int(x), int(y)), int(r), (tree_col * tone).tolist(), -1, cv2.LINE_AA)

    # 3. Hedgerows and tracks along a subset of field borders.
    for poly in polys:
        if rng.random() < 0.55:
            hedge = rng.random() < 0.6
            col = (50, 72, 38) if hedge else (170, 155, 120)
            thick = max(1, int((rng.uniform(1.5, 3.5) if hedge else rng.uniform(1.0, 2.5)) * px_per_m))
            cv2.polylines(img, [poly], True, col, thick, cv2.LINE_AA)

    # 4. Roads: dark verge, then the surface; asphalt or gravel, 4-12 m wide.
    n_roads = max(3, round(2.2 * math.sqrt(area_km2) * 2))
    roads = [_road(rng, n) for _ in range(n_roads)]
    for road in roads:
        width = max(2, int(rng.uniform(4.0, 12.0) * px_per_m))
        surface = (88, 88, 92) if rng.random() < 0.6 else (178, 162, 130)
        cv2.polylines(img, [road], False, (60, 64, 52), width + max(2, int(2 * px_per_m)), cv2.LINE_AA)
        cv2.polylines(img, [road], False, surface, width, cv2.LINE_AA)
        if width > 8 * px_per_m and rng.random() < 0.7:
            cv2.polylines(img, [road], False, (215, 215, 205), max(1, int(0.3 * px_per_m)), cv2.LINE_AA)

    # 5. Villages: clusters of buildings near road points, each cluster with its own street angle.
    n_villages = max(2, int(6 * area_km2))
    sun = np.array([0.6, 0.8]) * rng.uniform(2.0, 4.0) * px_per_m  # shadow offset, px
    for _ in range(n_villages):
        road = roads[int(rng.integers(len(roads)))]
        vx, vy = road[int(rng.integers(len(road)))].astype(np.float64)
        base_angle = float(rng.uniform(0, math.pi))
        spread = rng.uniform(40.0, 120.0) * px_per_m
        for _b in range(int(rng.integers(8, 40))):
            cx, cy = vx + rng.normal(0, spread / 2), vy + rng.normal(0, spread / 2)
            length = float(rng.uniform(7.0, 28.0)) * px_per_m
            depth = float(rng.uniform(6.0, 14.0)) * px_per_m
            ang = base_angle + float(rng.choice([0.0, math.pi / 2])) + float(rng.normal(0, 0.08))
            body = _rect(cx, cy, length, depth, ang)
            cv2.fillPoly(img, [np.round(body + sun).astype(np.int32)], (45, 45, 42), cv2.LINE_AA)
            roof = _ROOF_RGB[int(rng.integers(len(_ROOF_RGB)))] * rng.uniform(0.85, 1.15)
            # Gabled roof: the two halves either side of the ridge catch the sun differently.
            half_a = _rect(cx, cy, length, depth / 2.0, ang)
            offs = np.array([-math.sin(ang), math.cos(ang)]) * depth / 4.0
            cv2.fillPoly(img, [np.round(half_a + offs).astype(np.int32)], roof.tolist(), cv2.LINE_AA)
            cv2.fillPoly(img, [np.round(half_a - offs).astype(np.int32)], (roof * 0.72).tolist(), cv2.LINE_AA)

    # 6. Scattered single trees with shadows (field corners, roadsides, anywhere).
    n_trees = int(1500 * area_km2)
    tx = rng.uniform(0, n, size=n_trees)
    ty = rng.uniform(0, n, size=n_trees)
    tr = rng.uniform(1.5, 5.0, size=n_trees) * px_per_m
    for x, y, r in zip(tx, ty, tr, strict=True):
        centre = (int(x), int(y))
        cv2.circle(img, (int(x + sun[0] * 0.8), int(y + sun[1] * 0.8)), int(r), (38, 44, 34), -1, cv2.LINE_AA)
        cv2.circle(img, centre, int(r), (46, 76, 36), -1, cv2.LINE_AA)
        cv2.circle(img, (int(x - r / 3), int(y - r / 3)), max(1, int(r / 2)), (70, 104, 52), -1, cv2.LINE_AA)

    return img


def generate_demo_map(
    path: Path,
    *,
    seed: int = 2026,
    center_lat_deg: float = 47.3977,
    center_lon_deg: float = 8.5456,
    size_m: float = 2400.0,
    gsd_m: float = 0.5,
) -> Path:
    """Write the procedural demo map to ``path`` (GeoTIFF, EPSG:3857, RGB uint8) and return ``path``.

    ``size_m``: side of the square map on the ground, m; ``gsd_m``: ground metres per pixel at the centre.
    The same arguments always give byte-identical pixels.
    """
    path = Path(path)
    if not (math.isfinite(size_m) and math.isfinite(gsd_m) and size_m > 0 and gsd_m > 0):
        raise DemoMapError(f"size_m and gsd_m must be positive, got {size_m!r}, {gsd_m!r}", path=str(path))
    if not -80.0 < center_lat_deg < 80.0:
        raise DemoMapError(f"center_lat_deg must be within +-80 deg, got {center_lat_deg!r}", path=str(path))
    size_px = round(size_m / gsd_m)
    if not 64 <= size_px <= 20000:
        raise DemoMapError(f"size_m / gsd_m = {size_px} px; expected 64..20000", path=str(path))
    rgb = render_demo_pixels(seed=seed, size_px=size_px, gsd_m=gsd_m)

    xs, ys = warp_transform("EPSG:4326", "EPSG:3857", [center_lon_deg], [center_lat_deg])
    # EPSG:3857 metres are stretched by 1/cos(lat) on the ground.
    merc_px_m = gsd_m / math.cos(math.radians(center_lat_deg))
    half_merc_m = size_px * merc_px_m / 2.0
    transform = Affine(merc_px_m, 0.0, xs[0] - half_merc_m, 0.0, -merc_px_m, ys[0] + half_merc_m)
    profile = {
        "driver": "GTiff",
        "width": size_px,
        "height": size_px,
        "count": 3,
        "dtype": "uint8",
        "crs": "EPSG:3857",
        "transform": transform,
        "compress": "deflate",
        "zlevel": 1,
        "predictor": 2,
        "tiled": True,
        "blockxsize": 256,
        "blockysize": 256,
        "photometric": "RGB",
    }
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with rasterio.open(path, "w", **profile) as dst:
            dst.write(np.transpose(rgb, (2, 0, 1)))
            dst.update_tags(
                DESCRIPTION="gps-denied-onboard procedural demo map (synthetic, no imagery)",
                SEED=str(seed),
                GSD_M=str(gsd_m),
            )
    except (rasterio.errors.RasterioError, OSError) as exc:
        raise DemoMapError(f"cannot write the demo map: {exc}", path=str(path)) from exc
    return path
