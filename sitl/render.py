"""Nav-camera renderer: the perspective view of a georeferenced map from a camera pose over flat ground.

Geometry
--------
The ground is the plane ``down = 0`` of a local NED frame whose origin is the point below the camera; the
camera is at ``(0, 0, -alt_agl_m)`` with rotation ``Attitude.R_ned_cam()`` (nadir mount, image top =
nose; see ``gps_denied_onboard.camera.types``). A pixel ``(u, v)`` looks along
``r = R_ned_cam K^-1 [u, v, 1]`` and meets the ground at ``(N, E) = alt * (r_N, r_E) / r_D``, so
image -> ground is the homography ``diag(alt, alt, 1) R_ned_cam K^-1``. Ground -> raster pixel is a local
affine map fitted, per frame, to a few points around the nadir taken through WGS84 to the raster's CRS
(``rasterio.warp.transform``) and its geotransform; over a camera footprint (hundreds of metres) it is
exact to far below a pixel for EPSG:4326, EPSG:3857 and UTM. The composition is one ``cv2.warpPerspective``.

Pixels are addressed with OpenCV's convention (integer coordinates at pixel centres) in both the frame and
the raster. Where the map is much finer than the frame's ground sampling, the raster is sampled from a
Gaussian pyramid level so that the frame does not alias. Pixels that see off the map, nodata, or the sky
are 0.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import rasterio
from rasterio.enums import ColorInterp
from rasterio.warp import transform as warp_transform

from gps_denied_onboard.camera.types import Attitude, CameraCalibration
from gps_denied_onboard.geo import LocalTangentPlane

#: Rays closer to the horizon than this (|r_D| / |r|) are treated as missing the ground.
_MIN_RAY_DOWN = 1e-3


class RenderError(RuntimeError):
    """The map cannot be opened/used, or a render request is invalid. ``path`` is the map file."""

    def __init__(self, message: str, *, path: str | None = None) -> None:
        super().__init__(f"{path}: {message}" if path else message)
        self.path = path


def _to_bgr_u8(bands: np.ndarray, interp: tuple[ColorInterp, ...], path: str) -> np.ndarray:
    """(C, H, W) raster bands -> (H, W, 3) uint8 BGR. RGB(A/NIR) is reordered; one band is grey."""
    count = bands.shape[0]
    if count == 1 or count == 2:
        idx = [0, 0, 0]
    else:
        order = {ci: i for i, ci in enumerate(interp)}
        if all(c in order for c in (ColorInterp.red, ColorInterp.green, ColorInterp.blue)):
            idx = [order[ColorInterp.blue], order[ColorInterp.green], order[ColorInterp.red]]
        else:
            # Untagged multiband imagery (NAIP: R, G, B, NIR) is RGB-first by convention.
            idx = [2, 1, 0]
    data = bands[idx]
    if data.dtype != np.uint8:
        # Deeper imagery: stretch the 0.5-99.5 percentiles to 0-255 (a fixed scale would be arbitrary).
        finite = data[np.isfinite(data)] if np.issubdtype(data.dtype, np.floating) else data.ravel()
        if finite.size == 0:
            raise RenderError("raster holds no finite values", path=path)
        lo, hi = np.percentile(finite, [0.5, 99.5])
        scale = 255.0 / max(float(hi - lo), 1e-12)
        data = np.clip((np.nan_to_num(data.astype(np.float64), nan=lo) - lo) * scale, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(np.transpose(data, (1, 2, 0)))


class MapRenderer:
    """A GeoTIFF held in memory (any CRS; 1, 3 or 4 bands), rendered from camera poses.

    Attributes: ``path``; ``crs`` (rasterio CRS); ``pixels_bgr`` ((H, W, 3) uint8, read-only, nodata = 0);
    ``bbox_lonlat`` (W, S, E, N degrees: the largest lon/lat-aligned box inside the raster, so every point
    of it is on the map); ``ground_gsd_m`` (ground metres per raster pixel at the map centre).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        where = str(self.path)
        if not self.path.is_file():
            raise RenderError("map file not found", path=where)
        try:
            with rasterio.open(self.path) as ds:
                if ds.crs is None:
                    raise RenderError("map has no CRS (not georeferenced)", path=where)
                if ds.count < 1:
                    raise RenderError("map has no bands", path=where)
                self.crs = ds.crs
                self._transform = ds.transform
                bands = ds.read()
                mask = ds.dataset_mask()
                interp = tuple(ds.colorinterp)
        except rasterio.errors.RasterioError as exc:
            raise RenderError(f"cannot read map: {exc}", path=where) from exc
        pixels = _to_bgr_u8(bands, interp, where)
        pixels[mask == 0] = 0
        pixels.setflags(write=False)
        self.pixels_bgr = pixels
        self.height_px, self.width_px = pixels.shape[:2]
        self._pyramid: list[np.ndarray] = [pixels]
        self._inv_transform = ~self._transform
        self.bbox_lonlat = self._inscribed_bbox_lonlat()
        west, south, east, north = self.bbox_lonlat
        centre = self._ground_to_raster_affine((south + north) / 2.0, (west + east) / 2.0, 50.0)
        self.ground_gsd_m = 1.0 / math.sqrt(abs(np.linalg.det(centre[:, :2])))

    # -- georeferencing -----------------------------------------------------------------------------------

    def _inscribed_bbox_lonlat(self) -> tuple[float, float, float, float]:
        """Largest lon/lat box inside the raster's footprint (which is a rotated quad for UTM)."""
        t = np.linspace(0.0, 1.0, 33)
        w, h = self.width_px, self.height_px
        edges = {
            "top": (t * w, np.zeros_like(t)),
            "bottom": (t * w, np.full_like(t, h)),
            "left": (np.zeros_like(t), t * h),
            "right": (np.full_like(t, w), t * h),
        }
        lonlat = {}
        for name, (cols, rows) in edges.items():
            xs, ys = self._transform @ (cols, rows)
            lons, lats = warp_transform(self.crs, "EPSG:4326", list(xs), list(ys))
            lonlat[name] = (np.asarray(lons), np.asarray(lats))
        return (
            float(lonlat["left"][0].max()),
            float(lonlat["bottom"][1].max()),
            float(lonlat["right"][0].min()),
            float(lonlat["top"][1].min()),
        )

    def _ground_to_raster_affine(self, lat_deg: float, lon_deg: float, radius_m: float) -> np.ndarray:
        """(2, 3) affine: local (north_m, east_m, 1) around (lat, lon) -> raster (col, row), OpenCV px."""
        ltp = LocalTangentPlane(lat_deg, lon_deg, 0.0)
        g = np.array([-1.0, 0.0, 1.0]) * radius_m
        nn, ee = np.meshgrid(g, g, indexing="ij")
        ne = np.column_stack([nn.ravel(), ee.ravel()])
        lats, lons, _ = ltp.to_geodetic(np.column_stack([ne, np.zeros(len(ne))]))
        xs, ys = warp_transform("EPSG:4326", self.crs, list(lons), list(lats))
        cols, rows = self._inv_transform @ (np.asarray(xs), np.asarray(ys))
        # Geotransform pixel (0, 0) is the top-left corner of the first pixel; OpenCV's is its centre.
        dst = np.column_stack([np.asarray(cols) - 0.5, np.asarray(rows) - 0.5])
        design = np.column_stack([ne, np.ones(len(ne))])
        coef, *_ = np.linalg.lstsq(design, dst, rcond=None)
        return coef.T

    def _level(self, level: int) -> np.ndarray:
        while len(self._pyramid) <= level:
            self._pyramid.append(cv2.pyrDown(self._pyramid[-1]))
        return self._pyramid[level]

    # -- rendering ----------------------------------------------------------------------------------------

    def render(
        self, calib: CameraCalibration, lat_deg: float, lon_deg: float, alt_agl_m: float, attitude: Attitude
    ) -> np.ndarray:
        """The nav-camera image at this pose: (calib.height_px, calib.width_px, 3) uint8 BGR.

        ``lat_deg``/``lon_deg``: WGS84 position of the camera; ``alt_agl_m``: its height above the flat
        ground, m; ``attitude``: body attitude in NED. The calibration must have no distortion.
        """
        if calib.dist_coeffs and any(c != 0.0 for c in calib.dist_coeffs):
            raise RenderError("distorted calibrations are not rendered; the SITL camera is an ideal pinhole")
        if not (math.isfinite(alt_agl_m) and alt_agl_m > 0.0):
            raise RenderError(f"alt_agl_m must be a positive number, got {alt_agl_m!r}")
        w, h = calib.width_px, calib.height_px
        out_shape = (h, w, 3)

        ray_from_px = attitude.R_ned_cam() @ np.linalg.inv(calib.K)
        img_to_ne = np.diag([alt_agl_m, alt_agl_m, 1.0]) @ ray_from_px
        corners = np.array(
            [[0.0, 0.0, 1.0], [w - 1.0, 0.0, 1.0], [w - 1.0, h - 1.0, 1.0], [0.0, h - 1.0, 1.0]]
        )
        corner_rays = corners @ ray_from_px.T
        down = corner_rays[:, 2] / np.linalg.norm(corner_rays, axis=1)
        sees_sky = bool(np.any(down <= _MIN_RAY_DOWN))

        # Fit the local affine over the footprint (capped: beyond a few km the view is not a drone view).
        if sees_sky:
            radius = 10.0 * alt_agl_m
        else:
            ne = corners @ img_to_ne.T
            radius = float(np.max(np.hypot(ne[:, 0] / ne[:, 2], ne[:, 1] / ne[:, 2])))
        radius = min(max(radius, 10.0), 20.0 * alt_agl_m)
        affine = self._ground_to_raster_affine(lat_deg, lon_deg, radius)

        # Anti-aliasing: sample from the pyramid level whose pixels are no finer than the frame's.
        frame_gsd_m = alt_agl_m / min(calib.fx_px, calib.fy_px)
        ratio = frame_gsd_m / self.ground_gsd_m
        level = math.floor(math.log2(ratio)) if ratio >= 2.0 else 0
        level = min(level, 8)
        scale = 0.5**level  # pyrDown: level-L pixel x sits at level-0 pixel x * 2^L
        src = self._level(level)

        img_to_src = np.diag([scale, scale, 1.0]) @ np.vstack([affine, [0.0, 0.0, 1.0]]) @ img_to_ne
        if sees_sky:
            x0, y0 = 0, 0
            x1, y1 = src.shape[1], src.shape[0]
        else:
            pts = corners @ img_to_src.T
            pts = pts[:, :2] / pts[:, 2:3]
            x0 = max(math.floor(pts[:, 0].min()) - 2, 0)
            y0 = max(math.floor(pts[:, 1].min()) - 2, 0)
            x1 = min(math.ceil(pts[:, 0].max()) + 3, src.shape[1])
            y1 = min(math.ceil(pts[:, 1].max()) + 3, src.shape[0])
            if x1 <= x0 or y1 <= y0:
                return np.zeros(out_shape, np.uint8)
        # Warp from the footprint's window only: faster, and keeps remap's int16 coordinates in range.
        shift = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
        frame = cv2.warpPerspective(
            src[y0:y1, x0:x1],
            shift @ img_to_src,
            (w, h),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=(0, 0, 0),
        )
        if sees_sky:
            uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
            r = ray_from_px
            ray_d = r[2, 0] * uu + r[2, 1] * vv + r[2, 2]
            ray_n = np.sqrt(
                (r[0, 0] * uu + r[0, 1] * vv + r[0, 2]) ** 2
                + (r[1, 0] * uu + r[1, 1] * vv + r[1, 2]) ** 2
                + ray_d**2
            )
            frame[ray_d / ray_n <= _MIN_RAY_DOWN] = 0
        return frame
