"""Edits to the daemon's map for SITL scenarios: map gaps and look-alike traps laid out along the path.

The nav frames keep being rendered from the unedited world; only the map the cache is built from
changes. So a ``featureless`` corridor is a stretch where the map no longer shows what the camera sees
(new construction, a season change, missing imagery): the matcher must fail there while visual
odometry keeps working. A ``lookalike`` moves the corridor's content by ``offset_m`` and flattens the
true place: the only match the daemon can find is wrong by that offset.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import rasterio
from rasterio.warp import transform as warp_transform

from gps_denied_onboard.sitl.scenario import MapEdit, MapEditKind, Trajectory

#: Spacing of the path samples that draw a corridor, m.
_PATH_STEP_M = 2.0
#: Extra half width beyond the camera footprint radius, m.
_MARGIN_M = 10.0


class MapEditError(RuntimeError):
    """A map edit cannot be applied (it falls off the map, or the map cannot be written)."""


def _path_px(traj: Trajectory, edit: MapEdit, ds: rasterio.io.DatasetReader) -> np.ndarray:
    """Raster pixel coordinates (N, 2) float of the path between the edit's fractions."""
    s = np.arange(
        edit.path_from * traj.path_length_m, edit.path_to * traj.path_length_m + _PATH_STEP_M, _PATH_STEP_M
    )
    lat, lon = zip(*(traj.point_at_distance(float(v)) for v in s), strict=True)
    xs, ys = warp_transform("EPSG:4326", ds.crs, list(lon), list(lat))
    inv = ~ds.transform
    cols, rows = inv @ (np.asarray(xs), np.asarray(ys))
    return np.column_stack([cols, rows])


def _metres_to_px(
    ds: rasterio.io.DatasetReader, lat_deg: float, lon_deg: float, north_m: float, east_m: float
) -> tuple[float, float]:
    """Raster pixel displacement (dcol, drow) of a small ground offset at a point."""
    k_n = 111_320.0
    k_e = 111_320.0 * np.cos(np.radians(lat_deg))
    xs, ys = warp_transform(
        "EPSG:4326", ds.crs, [lon_deg, lon_deg + east_m / k_e], [lat_deg, lat_deg + north_m / k_n]
    )
    inv = ~ds.transform
    c0, r0 = inv @ (xs[0], ys[0])
    c1, r1 = inv @ (xs[1], ys[1])
    return c1 - c0, r1 - r0


def _flatten(img: np.ndarray, mask: np.ndarray) -> None:
    """Replace masked pixels (all bands) with a very low-pass version of the image: colour stays about
    right, texture (and so every feature) is gone."""
    small = cv2.resize(
        img, (max(1, img.shape[1] // 64), max(1, img.shape[0] // 64)), interpolation=cv2.INTER_AREA
    )
    low = cv2.resize(small, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_LINEAR)
    img[mask] = low[mask]


def apply_map_edits(
    src: Path, dst: Path, traj: Trajectory, edits: tuple[MapEdit, ...], ground_gsd_m: float
) -> Path:
    """Write ``dst``: ``src`` with ``edits`` applied (same CRS, transform, bands and dtype)."""
    with rasterio.open(src) as ds:
        bands = ds.read()  # (B, H, W)
        profile = ds.profile.copy()
        img = np.ascontiguousarray(np.moveaxis(bands, 0, -1))  # (H, W, B)
        h, w = img.shape[:2]
        for edit in edits:
            half_m = (
                edit.half_width_m if edit.half_width_m is not None else traj.footprint_radius_m + _MARGIN_M
            )
            thickness = max(1, round(2.0 * half_m / ground_gsd_m))
            pts = _path_px(traj, edit, ds)
            mask_u8 = np.zeros((h, w), np.uint8)
            cv2.polylines(mask_u8, [np.round(pts).astype(np.int32)], False, 255, thickness=thickness)
            mask = mask_u8 > 0
            if not mask.any():
                raise MapEditError(f"map edit {edit} does not touch the map {src}")
            if edit.kind is MapEditKind.LOOKALIKE:
                mid_lat, mid_lon = traj.point_at_distance(
                    0.5 * (edit.path_from + edit.path_to) * traj.path_length_m
                )
                dc, dr = _metres_to_px(ds, mid_lat, mid_lon, *edit.offset_m)
                shift = np.array([[1, 0, dc], [0, 1, dr]], dtype=np.float32)
                moved = cv2.warpAffine(
                    img, shift, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
                )
                moved_mask = cv2.warpAffine(mask_u8, shift, (w, h), flags=cv2.INTER_NEAREST) > 0
                if not moved_mask.any():
                    raise MapEditError(f"look-alike offset {edit.offset_m} m moves the corridor off the map")
                _flatten(img, mask)
                # Where the true corridor and its copy overlap, the copy wins; the rest stays flat.
                img[moved_mask] = moved[moved_mask]
            else:
                _flatten(img, mask)
        # Lossless, plain RGB: a JPEG/YCbCr source profile cannot be re-used with another compression.
        for key in ("photometric", "jpeg_quality", "jpegtablesmode"):
            profile.pop(key, None)
        profile.update(compress="deflate", **({"photometric": "RGB"} if img.shape[2] == 3 else {}))
        dst.parent.mkdir(parents=True, exist_ok=True)
        tmp = dst.with_name(dst.name + ".part")
        tmp.unlink(missing_ok=True)
        profile["driver"] = "GTiff"
        with rasterio.open(tmp, "w", **profile) as out:
            out.write(np.moveaxis(img, -1, 0))
        tmp.replace(dst)  # a half-written map never looks finished
    return dst
