"""Geodesy shared by every stage: WGS84 <-> local NED tangent plane, and GPS time.

The tangent-plane maths is pymap3d's (WGS84 through ECEF), vectorised over numpy arrays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pymap3d

#: Seconds between the Unix epoch and the GPS epoch (1980-01-06T00:00:00Z).
_GPS_EPOCH_UNIX_S = 315_964_800
#: GPS - UTC leap seconds, valid since 2017-01-01 (no leap second announced since).
GPS_UTC_LEAP_S = 18
_WEEK_S = 7 * 24 * 3600


@dataclass(frozen=True)
class LocalTangentPlane:
    """A local NED frame anchored at (origin_lat_deg, origin_lon_deg, origin_alt_m) on WGS84."""

    origin_lat_deg: float
    origin_lon_deg: float
    origin_alt_m: float = 0.0

    def to_ned(self, lat_deg, lon_deg, alt_m) -> np.ndarray:  # type: ignore[no-untyped-def]
        """Geodetic -> NED metres. Scalars give (3,), arrays of shape S give S + (3,)."""
        n, e, d = pymap3d.geodetic2ned(
            np.asarray(lat_deg, dtype=np.float64),
            np.asarray(lon_deg, dtype=np.float64),
            np.asarray(alt_m, dtype=np.float64),
            self.origin_lat_deg,
            self.origin_lon_deg,
            self.origin_alt_m,
        )
        return np.stack([np.asarray(n), np.asarray(e), np.asarray(d)], axis=-1)

    def to_geodetic(self, ned_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """NED metres (..., 3) -> (lat_deg, lon_deg, alt_m), each of shape (...)."""
        ned = np.asarray(ned_m, dtype=np.float64)
        lat, lon, alt = pymap3d.ned2geodetic(
            ned[..., 0], ned[..., 1], ned[..., 2], self.origin_lat_deg, self.origin_lon_deg, self.origin_alt_m
        )
        return np.asarray(lat), np.asarray(lon), np.asarray(alt)


def gps_week_and_ms(time_unix_usec: int) -> tuple[int, int]:
    """GPS week number and milliseconds into the week for a Unix time in microseconds."""
    gps_ms = (time_unix_usec // 1000) - _GPS_EPOCH_UNIX_S * 1000 + GPS_UTC_LEAP_S * 1000
    week, ms = divmod(gps_ms, _WEEK_S * 1000)
    return int(week), int(ms)


def haversine_m(lat1_deg: float, lon1_deg: float, lat2_deg, lon2_deg):  # type: ignore[no-untyped-def]
    """Great-circle distance in metres (mean Earth radius); vectorised over the second point."""
    r = 6_371_008.8
    p1, p2 = np.radians(lat1_deg), np.radians(np.asarray(lat2_deg, dtype=np.float64))
    dp = p2 - p1
    dl = np.radians(np.asarray(lon2_deg, dtype=np.float64) - lon1_deg)
    a = np.sin(dp / 2) ** 2 + np.cos(p1) * np.cos(p2) * np.sin(dl / 2) ** 2
    return 2 * r * np.arcsin(np.sqrt(a))
