"""What a late fix costs the time axis: the rewind's wall time and how many inputs it fuses again.

    .venv/bin/python tools/time_axis_rewind.py [--frame-hz 3] [--repeats 20]

The real ``NavEstimator`` and ``TimeAxis`` (``components/c5_estimator``) are fed what the pipeline feeds
them per frame (VO, the autopilot's height, a no-fix note) for 70 s of a straight flight at 20 m/s,
then one absolute fix exposed DELAY seconds before the newest input, for each DELAY. The fix is fused
at its own time and everything after it again (``TimeAxis._fuse``): that is work done under the axis'
lock, which the 10 Hz output waits for.

The acceleration source is a constant here (the daemon's reads the autopilot's IMU buffer, a mean over
a few samples per call); the figures are the estimator's and the axis' own work. A one-off measurement
tool for ``docs/benchmarks.md``: the daemon does not use it.
"""

from __future__ import annotations

import argparse
import statistics
import time
import uuid
from collections.abc import Callable

import numpy as np

from gps_denied_onboard.components.c1_vio.types import VoMotion
from gps_denied_onboard.components.c4_pose.types import PoseFix
from gps_denied_onboard.components.c5_estimator import NavEstimator, TimeAxis
from gps_denied_onboard.components.c5_estimator.protocol import ImuAcceleration
from gps_denied_onboard.components.c6_tiles.types import TileId
from gps_denied_onboard.config import EstimatorConfig
from gps_denied_onboard.geo import LocalTangentPlane
from gps_denied_onboard.logging_setup import configure_logging

LTP = LocalTangentPlane(47.0, -99.2, 600.0)
T0_USEC = 1_800_000_000_000_000
FLIGHT_S = 70.0
SPEED_M_S = 20.0
AGL_M = 1200.0
DELAYS_S = (0.5, 2.0, 5.0, 10.0, 15.0, 20.0, 30.0, 45.0)


class _ConstAccel:
    def accel_ned_mean(self, t0_unix_usec: int, t1_unix_usec: int) -> ImuAcceleration:
        return ImuAcceleration(np.zeros(3))


def _fix(t_usec: int) -> PoseFix:
    pos = np.array([SPEED_M_S * (t_usec - T0_USEC) / 1e6, 0.0, -AGL_M])
    lat, lon, alt = LTP.to_geodetic(pos)
    return PoseFix(
        frame_id=uuid.uuid4(),
        exposure_time_unix_usec=t_usec,
        pos_ned_m=pos,
        cov_ned_m2=np.diag([25.0, 25.0, 100.0]),
        lat_deg=float(lat),
        lon_deg=float(lon),
        alt_amsl_m=float(alt),
        yaw_rad=0.0,
        yaw_sigma_rad=0.01,
        attitude_disagreement_rad=0.001,
        image_tilt_off_cam_rad=(0.0, 0.0),
        inlier_count=200,
        residual_px=0.8,
        tile_id=TileId.of(15, float(lat), float(lon)),
        shared_sigma_m=5.0,
    )


def _flown_axis(frame_hz: float) -> tuple[TimeAxis, int]:
    """An axis after FLIGHT_S of per-frame inputs; returns it and the newest input's time."""
    now = [T0_USEC]
    est = NavEstimator(EstimatorConfig(), LTP, accel_source=_ConstAccel())
    axis = TimeAxis(est, max_delay_s=60.0, max_frame_age_s=1.0, clock_unix_usec=lambda: now[0])
    axis.initialise(np.array([0.0, 0.0, -AGL_M]), 10.0, T0_USEC)
    dt_s = 1.0 / frame_hz
    t = T0_USEC
    for _ in range(int(FLIGHT_S * frame_hz)):
        t += round(dt_s * 1e6)
        now[0] = t
        motion = VoMotion(uuid.uuid4(), uuid.uuid4(), dt_s, np.array([SPEED_M_S * dt_s, 0.0]), np.eye(2), 300)
        axis.fuse_vo(motion, t)
        axis.fuse_altitude(AGL_M, 600.0, 1.0, t)
        axis.note_no_fix(t)
    return axis, t


def _timed(call: Callable[[], object]) -> float:
    start = time.perf_counter()
    call()
    return (time.perf_counter() - start) * 1e3


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frame-hz", type=float, default=3.0, help="camera rate, Hz (default 3)")
    parser.add_argument("--repeats", type=int, default=20, help="runs per delay (default 20)")
    args = parser.parse_args(argv)
    configure_logging("error", json=False)

    print(f"{args.frame_hz:g} Hz frames")
    print(f"{'fix late by (s)':>16} {'inputs fused again':>19} {'rewind ms p50':>14} {'max':>8}")
    for delay_s in DELAYS_S:
        costs = []
        replayed = 0
        for _ in range(args.repeats):
            axis, head = _flown_axis(args.frame_hz)
            t_fix = head - round(delay_s * 1e6)
            replayed = sum(1 for e in axis._entries if e.time_usec > t_fix)  # the axis' own store
            costs.append(_timed(lambda a=axis, tf=t_fix: a.fuse_fix(_fix(tf))))
            assert axis.stats().rewinds == 1, "the late fix was not fused at its own time"
        print(f"{delay_s:>16g} {replayed:>19d} {statistics.median(costs):>14.2f} {max(costs):>8.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
