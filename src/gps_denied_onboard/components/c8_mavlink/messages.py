"""C8 outgoing messages: pure builders from an ``EstimatorState`` to pymavlink message objects.

Input: an ``EstimatorState`` and a pymavlink ``MAVLink`` instance (``connection.mav``, or
``MAVLink(None)`` in tests). Output: an encoded-but-unsent message; nothing here touches a socket.

The one rule for every autopilot and every message (``withheld_reason``): a position leaves the daemon
as one to fuse only when the daemon can back it: finite, anchored or propagated from an anchor (never dead
reckoning or no estimate), its horizontal 1-sigma finite and at most ``FIX_3D_MAX_HORIZ_SIGMA_M``, and
its start confirmed by a map fix (``EstimatorState.map_confirmed``). A message that can say "do not use"
in a way the receiver honours carries an unbacked state with that mark; a message that cannot sends
nothing:
- GPS_INPUT says it with fix_type below 3 (the real ArduPilot fuses only fix_type >= 3, DESIGN.md);
- GLOBAL_POSITION_SENSOR has no such form: PX4 reads only id, source, lat, lon, alt, eph and epv, ignores
  the GLOBAL_POSITION_UNHEALTHY flag, and resets its position to a message with ``eph`` = inf about every
  7 s (to 0,0 when lat/lon are 0; a first such message sets its origin there for good: PX4 main of
  2026-03-02, measured, DESIGN.md). So it is sent only for a backed state whose altitude (AMSL) and
  vertical sigma are finite too (``global_position_sensor_withheld``), and never flagged;
- VISION_POSITION_ESTIMATE has no fix_type either: sent only for a backed state.

Rule (what the autopilot is told):
- **fix_type** (``fix_type_for``): ``satellite_anchored`` and ``visual_propagated`` are 3 while the
  horizontal 1-sigma is at most ``FIX_3D_MAX_HORIZ_SIGMA_M`` and the position is finite (and, in
  GPS_INPUT, the speed's 1-sigma at most ``FIX_3D_MAX_SPEED_SIGMA_M_S``), else 1;
  ``dead_reckoning`` is 1 (never to be fused as a measurement); ``no_estimate`` or a non-finite position 0;
  over a stream (``Fix3dGate``, the one stateful piece here), 3D once entered stays 3D up to a speed
  1-sigma of ``FIX_3D_KEEP_SPEED_SIGMA_M_S``, and the stream's first 3D fix waits until the estimate
  has qualified for ``FIX_3D_SETTLE_S``;
  a state no map fix has confirmed since the estimator started (a start prior, however tight its stated
  sigma: ``EstimatorState.map_confirmed``) is never a 3D fix (1);
- **accuracy** fields are the state's 1-sigma values, never a constant; ``hdop``/``vdop`` are those over
  ``NOMINAL_UERE_M`` (5 m), clamped to [0.01, HDOP_MAX];
- **ignore_flags** only for fields that are truly unknown (non-finite), sent as 0, never NaN;
- **yaw**: 0 means unknown, so north is sent as 36000; **satellites_visible**: ``SATELLITES_WITH_FIX``
  while fix_type is 3, else 0;
- **GLOBAL_POSITION_SENSOR.id** is ``mavlink.global_position_sensor_id`` (PX4's ``EKF2_AGP{i}_ID``);
- **VISION_POSITION_ESTIMATE**: local NED at an origin the autopilot shares (``ned_in_frame``
  re-expresses a position through geodetic coordinates; the link decides which frame and when);
  ``reset_counter`` (``vision_position_jumped``) goes up on re-initialisation, a frame change, or a jump
  beyond ``VISION_RESET_JUMP_SIGMAS`` of the previous sigma (at least ``VISION_RESET_MIN_JUMP_M``).

Why each choice: docs/design.md, "`c8_mavlink/messages.py`: what the autopilot is told"; every message:
docs/mavlink.md.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any, Final

import numpy as np

from gps_denied_onboard.camera.types import Attitude
from gps_denied_onboard.components.c5_estimator.types import EstimatorState
from gps_denied_onboard.constants import (
    GPS_INPUT_GPS_ID,
    NV_FDR_HEALTH,
    NV_FRAME_DROPS,
    NV_HORIZ_SIGMA_M,
    NV_INLIERS,
    NV_INTEGRITY_REFUSED,
    NV_PROVENANCE,
    NV_RESIDUAL_PX,
    FdrHealthState,
    Provenance,
)
from gps_denied_onboard.geo import LocalTangentPlane, gps_week_and_ms

# pymavlink chooses the wire protocol when a dialect is loaded, from the MAVLINK20 environment variable.
# MAVLink 2 is required here (signing, GPS_INPUT.yaw extension, GLOBAL_POSITION_SENSOR id 296 > 255),
# so it is forced for the whole process before mavutil is imported, and re-applied if mavutil had
# already been imported elsewhere with MAVLink 1.
os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil

if getattr(mavutil.mavlink, "WIRE_PROTOCOL_VERSION", "") != "2.0":
    mavutil.set_dialect(mavutil.current_dialect)

#: The dialect module of every connection (pymavlink's default "all", MAVLink 2; it contains common,
#: ardupilotmega and development, so GPS_INPUT and GLOBAL_POSITION_SENSOR are both defined).
DIALECT: Final = mavutil.mavlink

#: Horizontal 1-sigma above which an anchored/VIO estimate is reported as "no fix" instead of 3D, m.
FIX_3D_MAX_HORIZ_SIGMA_M: Final[float] = 50.0
#: Speed 1-sigma above which GPS_INPUT is "no fix" instead of 3D, m/s: ArduPilot's EKF3 calls a GPS whose
#: speed accuracy (low-pass filtered, peak held with a 10 s decay) exceeds 1.5 m/s not good for flight
#: ("GPS Glitch", AP_NavEKF3_VehicleStatus.cpp calcGpsGoodForFlight), so one 3D fix sent with the 10 m/s
#: of a just-started velocity holds that state for 15 s (measured on copter SITL 4.7.0-dev after a
#: restart). The position waits the few tenths of a second VO and the next fix take to know the speed.
FIX_3D_MAX_SPEED_SIGMA_M_S: Final[float] = 1.5
#: Once GPS_INPUT is 3D, it stays 3D while the speed's 1-sigma is at most this, m/s (``Fix3dGate``; the
#: other conditions unchanged). A speed sigma above 1.5 m/s only raises EKF3's "GPS glitching" flag and
#: stops its GSF yaw estimator and GPS height (AP_NavEKF3_VehicleStatus.cpp ``calcGpsGoodForFlight`` and
#: the users of ``gpsSpdAccPass``): the position is still fused. Dropping to fix 1 instead starves the
#: EKF: where the speed sigma saw-tooths between 1.0 and 2.6 m/s at the camera rate (VO alone, or right
#: after a link cut), the emulator's square flight went 14 s without a 3D fix and failed safe to LAND.
FIX_3D_KEEP_SPEED_SIGMA_M_S: Final[float] = 3.0
#: Nominal user-equivalent range error used to turn sigmas into DOPs, m (sigma 5 m -> hdop 1.0).
NOMINAL_UERE_M: Final[float] = 5.0
#: Largest DOP sent (ArduPilot stores hdop*100 in a uint16; 99.99 is "very bad", not "unknown").
HDOP_MAX: Final[float] = 99.99
#: Synthetic satellites_visible while reporting a 3D fix.
SATELLITES_WITH_FIX: Final[int] = 10
#: STATUSTEXT.text field size, bytes.
STATUSTEXT_MAX_BYTES: Final[int] = 50
#: Variance used for attitude entries of VISION_POSITION_ESTIMATE when the attitude is not known, rad^2.
UNKNOWN_ANGLE_VARIANCE_RAD2: Final[float] = math.pi**2

#: A sent position that moves by more than this many previous 1-sigmas (beyond its velocity's
#: prediction) is a jump: VISION_POSITION_ESTIMATE.reset_counter is bumped.
VISION_RESET_JUMP_SIGMAS: Final[float] = 3.0
#: ... but never for a step shorter than this (a very confident state must not bump on noise), m.
VISION_RESET_MIN_JUMP_M: Final[float] = 0.5

#: GPS_FIX_TYPE values used by the policy.
FIX_TYPE_NO_GPS: Final[int] = 0
FIX_TYPE_NO_FIX: Final[int] = 1
FIX_TYPE_3D: Final[int] = 3

MavlinkMessage = Any  # pymavlink message objects are dynamically generated classes


def _finite(*values: float) -> bool:
    return all(math.isfinite(float(v)) for v in values)


def fix_type_for(
    provenance: Provenance,
    horiz_sigma_m: float,
    *,
    speed_sigma_m_s: float | None = None,
    max_fix_sigma_m: float = FIX_3D_MAX_HORIZ_SIGMA_M,
    max_speed_sigma_m_s: float = FIX_3D_MAX_SPEED_SIGMA_M_S,
) -> int:
    """GPS_FIX_TYPE for an estimate (see the module docstring for the policy). ``speed_sigma_m_s``: the
    horizontal speed's 1-sigma where the message carries the velocity (GPS_INPUT); None where it does
    not (GLOBAL_POSITION_SENSOR)."""
    if provenance is Provenance.NO_ESTIMATE or not _finite(horiz_sigma_m):
        return FIX_TYPE_NO_GPS
    if provenance is Provenance.DEAD_RECKONING:
        return FIX_TYPE_NO_FIX
    if speed_sigma_m_s is not None and not (
        _finite(speed_sigma_m_s) and speed_sigma_m_s <= max_speed_sigma_m_s
    ):
        return FIX_TYPE_NO_FIX
    if horiz_sigma_m <= max_fix_sigma_m:
        return FIX_TYPE_3D
    return FIX_TYPE_NO_FIX


def stated_speed_sigma_m_s(state: EstimatorState) -> float:
    """The horizontal speed 1-sigma the fix_type rule judges, m/s: inf where its covariance is not finite."""
    cov_v = np.asarray(state.cov_vel_ned_m2_s2, dtype=np.float64)
    return state.speed_sigma_m_s if np.all(np.isfinite(cov_v[:2, :2])) else math.inf


def stated_horiz_sigma_m(state: EstimatorState) -> float:
    """The horizontal 1-sigma the rule judges, m: inf where its covariance is not finite."""
    return state.horiz_sigma_m if np.all(np.isfinite(state.cov_pos_ned_m2[:2, :2])) else math.inf


def withheld_reason(
    state: EstimatorState, *, max_fix_sigma_m: float = FIX_3D_MAX_HORIZ_SIGMA_M
) -> str | None:
    """Why ``state``'s position is not one the daemon can back as a fix to fuse, or None when it is.

    The one rule for every autopilot and every message (module docstring): GPS_INPUT turns a reason into
    fix_type below 3; GLOBAL_POSITION_SENSOR and VISION_POSITION_ESTIMATE are then not sent at all."""
    if state.provenance is Provenance.NO_ESTIMATE:
        return "no estimate"
    if not _position_finite(state):
        return "position not finite"
    if state.provenance is Provenance.DEAD_RECKONING:
        return "dead reckoning (no map fix or VO to bound it)"
    horiz = stated_horiz_sigma_m(state)
    if not (_finite(horiz) and horiz <= max_fix_sigma_m):
        return f"horizontal sigma {horiz:.1f} m above {max_fix_sigma_m:g} m"
    if not state.map_confirmed:
        return "no map fix has confirmed the start"
    return None


def gps_input_fix_type(
    state: EstimatorState,
    *,
    max_fix_sigma_m: float = FIX_3D_MAX_HORIZ_SIGMA_M,
    max_speed_sigma_m_s: float = FIX_3D_MAX_SPEED_SIGMA_M_S,
) -> int:
    """GPS_INPUT's fix_type for ``state``: 0 without a finite position or sigma, 1 where
    ``withheld_reason`` has a reason or the speed's 1-sigma is above ``max_speed_sigma_m_s``, else 3."""
    if not _position_finite(state):
        return FIX_TYPE_NO_GPS
    fix = fix_type_for(
        state.provenance,
        stated_horiz_sigma_m(state),
        speed_sigma_m_s=stated_speed_sigma_m_s(state),
        max_fix_sigma_m=max_fix_sigma_m,
        max_speed_sigma_m_s=max_speed_sigma_m_s,
    )
    if fix == FIX_TYPE_3D and withheld_reason(state, max_fix_sigma_m=max_fix_sigma_m) is not None:
        return FIX_TYPE_NO_FIX
    return fix


#: The stream's first 3D fix is declared only once the estimate has qualified for this long, s
#: (``Fix3dGate``). ArduPilot seeds its filtered mean GPS interval with the first interval it sees
#: (AP_GPS.cpp ``update_instance``; ``sitl/ardupilot_rules.py``), and right after a first fix the speed's
#: sigma can saw-tooth across ``FIX_3D_MAX_SPEED_SIGMA_M_S`` at the camera rate (propagation raises it,
#: each update lowers it): one 3D message followed by three of fix 1 seeds the mean at 400 ms, which
#: holds the GPS unhealthy for about 5 s. Later gaps fold into a mean of ~100 ms, and holding 3D back
#: then would only starve the EKF, so the settling is asked once. It covers one period of a 3 Hz camera.
FIX_3D_SETTLE_S: Final[float] = 0.35


class Fix3dGate:
    """GPS_INPUT's fix_type over a stream of states (``gps_input_fix_type`` for each state alone):

    - **entering 3D** takes the pure rule (speed sigma at most ``FIX_3D_MAX_SPEED_SIGMA_M_S``), and the
      stream's first 3D fix is held back as 1 (no fix) until the states have qualified for ``settle_s``
      in a row;
    - **staying 3D** takes the same rule with ``FIX_3D_KEEP_SPEED_SIGMA_M_S`` for the speed: position,
      provenance and horizontal sigma are judged exactly as alone.

    So a speed sigma that saw-tooths across 1.5 m/s neither flickers the stream nor starves the EKF,
    and a velocity just started (10 m/s sigma after a restart) never enters 3D. Not thread-safe: one
    output stream owns one gate.
    """

    def __init__(self, settle_s: float = FIX_3D_SETTLE_S) -> None:
        if not (math.isfinite(settle_s) and settle_s >= 0):
            raise ValueError(f"settle_s must be a finite number of seconds >= 0, got {settle_s}")
        self._settle_usec = round(settle_s * 1e6)
        self._since_usec: int | None = None
        self._declared = False
        self._in_3d = False

    def fix_type(self, state: EstimatorState) -> int:
        """The fix_type to send for ``state`` (a later state than the previous call's)."""
        if self._in_3d:
            keep = gps_input_fix_type(state, max_speed_sigma_m_s=FIX_3D_KEEP_SPEED_SIGMA_M_S)
            self._in_3d = keep == FIX_TYPE_3D
            if self._in_3d:
                return FIX_TYPE_3D
        fix = gps_input_fix_type(state)
        if fix != FIX_TYPE_3D:
            self._since_usec = None
            return fix
        if not self._declared:
            t = int(state.time_unix_usec)
            if self._since_usec is None or t < self._since_usec:
                self._since_usec = t
            if t - self._since_usec < self._settle_usec:
                return FIX_TYPE_NO_FIX
            self._declared = True
        self._in_3d = True
        return FIX_TYPE_3D


def _dop(sigma_m: float) -> float:
    return float(min(max(sigma_m / NOMINAL_UERE_M, 0.01), HDOP_MAX))


def yaw_cdeg(yaw_rad: float | None) -> int:
    """GPS_INPUT.yaw: centidegrees in (0, 36000]; 0 = unknown, north = 36000."""
    if yaw_rad is None or not _finite(yaw_rad):
        return 0
    cdeg = round(math.degrees(yaw_rad) * 100.0) % 36000
    return 36000 if cdeg == 0 else int(cdeg)


def _e7(deg: float) -> int:
    return round(deg * 1e7)


def _position_finite(state: EstimatorState) -> bool:
    return (
        _finite(state.lat_deg, state.lon_deg) and abs(state.lat_deg) <= 90.0 and abs(state.lon_deg) <= 180.0
    )


def gps_input(
    mav: Any,
    state: EstimatorState,
    *,
    time_unix_usec: int,
    fix_type: int | None = None,
    satellites_visible: int | None = None,
    gps_id: int = GPS_INPUT_GPS_ID,
    max_fix_sigma_m: float = FIX_3D_MAX_HORIZ_SIGMA_M,
    alt_trusted: bool = True,
) -> MavlinkMessage:
    """GPS_INPUT (ArduPilot, GPS1_TYPE=14) for ``state`` stamped at ``time_unix_usec``.
    ``alt_trusted`` False: the altitude fields are flagged as ignored (the daemon's ground altitude
    disagrees with the autopilot's).

    ``fix_type``/``satellites_visible`` default to the policy (``fix_type_for``, ``SATELLITES_WITH_FIX``).
    ``time_unix_usec`` must be a Unix time (it also gives time_week/time_week_ms); a time before the
    GPS epoch raises ``ValueError`` because ArduPilot discards a fix with time_week 0.
    """
    week, week_ms = gps_week_and_ms(int(time_unix_usec))
    if week <= 0:
        raise ValueError(
            f"GPS_INPUT needs a Unix time after the GPS epoch, got time_unix_usec={time_unix_usec}"
        )
    horiz_sigma = state.horiz_sigma_m if np.all(np.isfinite(state.cov_pos_ned_m2[:2, :2])) else math.inf
    if fix_type is None:
        fix_type = gps_input_fix_type(state, max_fix_sigma_m=max_fix_sigma_m)
    if not _position_finite(state):
        fix_type = FIX_TYPE_NO_GPS
    if satellites_visible is None:
        satellites_visible = SATELLITES_WITH_FIX if fix_type >= FIX_TYPE_3D else 0

    flags = 0
    f = DIALECT
    vel = np.asarray(state.vel_ned_m_s, dtype=np.float64)
    cov_v = np.asarray(state.cov_vel_ned_m2_s2, dtype=np.float64)
    alt = float(state.alt_amsl_m)
    vert_sigma = state.vert_sigma_m if _finite(state.cov_pos_ned_m2[2, 2]) else math.nan
    if not alt_trusted or not _finite(alt, vert_sigma):
        flags |= f.GPS_INPUT_IGNORE_FLAG_ALT | f.GPS_INPUT_IGNORE_FLAG_VDOP
        flags |= f.GPS_INPUT_IGNORE_FLAG_VERTICAL_ACCURACY
        alt, vert_sigma = 0.0, 0.0
    horiz_vel_ok = bool(np.all(np.isfinite(vel[:2])) and np.all(np.isfinite(cov_v[:2, :2])))
    speed_sigma = state.speed_sigma_m_s if horiz_vel_ok else 0.0
    if not horiz_vel_ok:
        flags |= f.GPS_INPUT_IGNORE_FLAG_VEL_HORIZ | f.GPS_INPUT_IGNORE_FLAG_SPEED_ACCURACY
    if not _finite(vel[2], cov_v[2, 2]):
        flags |= f.GPS_INPUT_IGNORE_FLAG_VEL_VERT
    if not _finite(horiz_sigma):
        flags |= f.GPS_INPUT_IGNORE_FLAG_HORIZONTAL_ACCURACY | f.GPS_INPUT_IGNORE_FLAG_HDOP
    vn, ve = (float(vel[0]), float(vel[1])) if horiz_vel_ok else (0.0, 0.0)
    vd = float(vel[2]) if not flags & f.GPS_INPUT_IGNORE_FLAG_VEL_VERT else 0.0
    lat_e7, lon_e7 = (_e7(state.lat_deg), _e7(state.lon_deg)) if _position_finite(state) else (0, 0)
    h_acc = float(horiz_sigma) if _finite(horiz_sigma) else 0.0
    return mav.gps_input_encode(
        int(time_unix_usec),
        int(gps_id),
        flags,
        week_ms,
        week,
        int(fix_type),
        lat_e7,
        lon_e7,
        alt,
        _dop(h_acc) if h_acc > 0 else 0.01,
        _dop(vert_sigma) if vert_sigma > 0 else 0.01,
        vn,
        ve,
        vd,
        float(speed_sigma),
        h_acc,
        float(vert_sigma),
        int(satellites_visible),
        yaw_cdeg(state.yaw_rad),
    )


def global_position_sensor_withheld(
    state: EstimatorState, *, max_fix_sigma_m: float = FIX_3D_MAX_HORIZ_SIGMA_M
) -> str | None:
    """Why GLOBAL_POSITION_SENSOR is not sent for ``state`` (None: it is): ``withheld_reason``, or an
    altitude or vertical sigma that is not finite. PX4 sets its origin's altitude from the first message
    it takes (a NaN ``alt`` left the global altitude invalid for good, DESIGN.md): that message waits."""
    reason = withheld_reason(state, max_fix_sigma_m=max_fix_sigma_m)
    if reason is not None:
        return reason
    if not _finite(state.alt_amsl_m):
        return "altitude (AMSL) not finite"
    vert = state.vert_sigma_m if _finite(state.cov_pos_ned_m2[2, 2]) else math.inf
    if not _finite(vert):
        return "vertical sigma not finite"
    return None


def global_position_sensor(
    mav: Any,
    state: EstimatorState,
    *,
    time_unix_usec: int,
    processing_time_usec: int,
    target_system: int,
    sensor_id: int,
    max_fix_sigma_m: float = FIX_3D_MAX_HORIZ_SIGMA_M,
) -> MavlinkMessage:
    """GLOBAL_POSITION_SENSOR (PX4 main since 2026-02-27; id 296, in pymavlink's common/ardupilotmega
    dialects) for a backed ``state``; raises ``ValueError`` naming the reason for any other
    (``global_position_sensor_withheld``): this message has no form PX4 reads as "do not use".

    ``sensor_id`` is the message's ``id`` (uint8): PX4 uses it only when an ``EKF2_AGP{i}_ID`` equals it.
    source = GLOBAL_POSITION_SRC_VISION; flags 0. ``alt_ellipsoid`` is NaN, MAVLink's "not available" for
    a float: the daemon knows AMSL only, and any finite ellipsoid height it made up would be wrong by the
    geoid's undulation (PX4 does not read the field). ``processing_time_usec`` = transmission time minus
    the time the state is valid for (clamped to uint32; PX4 ignores it and stamps on arrival).
    """
    reason = global_position_sensor_withheld(state, max_fix_sigma_m=max_fix_sigma_m)
    if reason is not None:
        raise ValueError(f"GLOBAL_POSITION_SENSOR is not sent for this state: {reason}")
    return mav.global_position_sensor_encode(
        int(target_system),
        0,
        int(sensor_id),
        int(time_unix_usec),
        int(min(max(processing_time_usec, 0), 0xFFFFFFFF)),
        DIALECT.GLOBAL_POSITION_SRC_VISION,
        0,
        _e7(state.lat_deg),
        _e7(state.lon_deg),
        math.nan,
        float(state.alt_amsl_m),
        float(stated_horiz_sigma_m(state)),
        float(state.vert_sigma_m),
    )


def set_gps_global_origin(
    mav: Any, ltp: LocalTangentPlane, *, target_system: int, time_usec: int
) -> MavlinkMessage:
    """SET_GPS_GLOBAL_ORIGIN (id 48) offering ``ltp``'s origin as the autopilot's local NED origin:
    latitude/longitude degE7, altitude in mm above mean sea level (the ltp's origin height is AMSL)."""
    return mav.set_gps_global_origin_encode(
        int(target_system),
        _e7(ltp.origin_lat_deg),
        _e7(ltp.origin_lon_deg),
        round(ltp.origin_alt_m * 1000.0),
        int(time_usec),
    )


def timesync(mav: Any, *, tc1_ns: int, ts1_ns: int) -> MavlinkMessage:
    """TIMESYNC: a request (``tc1_ns`` = 0, ``ts1_ns`` = our now) or the answer to another node's
    request (``tc1_ns`` = our now, ``ts1_ns`` = theirs, echoed)."""
    return mav.timesync_encode(int(tc1_ns), int(ts1_ns))


def request_message(
    mav: Any, *, target_system: int, target_component: int, message_id: int
) -> MavlinkMessage:
    """COMMAND_LONG MAV_CMD_REQUEST_MESSAGE for ``message_id`` (e.g. GPS_GLOBAL_ORIGIN, id 49)."""
    return mav.command_long_encode(
        int(target_system),
        int(target_component),
        DIALECT.MAV_CMD_REQUEST_MESSAGE,
        0,
        float(message_id),
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
    )


def ned_in_frame(pos_ned_m: np.ndarray, own: LocalTangentPlane, other: LocalTangentPlane) -> np.ndarray:
    """A (3,) NED position in ``own`` re-expressed in ``other``'s NED frame, through WGS84 geodetic.

    The two frames' axes differ by the angle between their verticals (distance / Earth radius, 1e-4 rad
    for 600 m), so a covariance is carried over unrotated."""
    if own == other:
        return np.asarray(pos_ned_m, dtype=np.float64).copy()
    lat, lon, alt = own.to_geodetic(np.asarray(pos_ned_m, dtype=np.float64))
    return np.asarray(other.to_ned(lat, lon, alt), dtype=np.float64)


def vision_position_jumped(previous: EstimatorState, current: EstimatorState) -> bool:
    """True when ``current`` jumped away from ``previous`` (both sent in the same frame): its position
    differs from ``previous`` carried forward at ``previous``'s velocity by more than
    ``VISION_RESET_JUMP_SIGMAS`` times ``previous``'s horizontal (resp. vertical) 1-sigma, and by more
    than ``VISION_RESET_MIN_JUMP_M``. Non-finite inputs are not a jump (re-initialisation is detected
    from the provenance)."""
    dt_s = (int(current.time_unix_usec) - int(previous.time_unix_usec)) / 1e6
    vel = np.asarray(previous.vel_ned_m_s, dtype=np.float64)
    if not np.all(np.isfinite(vel)):
        vel = np.zeros(3)
    step = np.asarray(current.pos_ned_m, dtype=np.float64) - (
        np.asarray(previous.pos_ned_m, dtype=np.float64) + vel * max(dt_s, 0.0)
    )
    cov = np.asarray(previous.cov_pos_ned_m2, dtype=np.float64)
    if not (np.all(np.isfinite(step)) and np.all(np.isfinite(cov))):
        return False
    horiz_m, vert_m = float(np.hypot(step[0], step[1])), abs(float(step[2]))
    horiz_limit = max(VISION_RESET_JUMP_SIGMAS * previous.horiz_sigma_m, VISION_RESET_MIN_JUMP_M)
    vert_limit = max(VISION_RESET_JUMP_SIGMAS * previous.vert_sigma_m, VISION_RESET_MIN_JUMP_M)
    return horiz_m > horiz_limit or vert_m > vert_limit


def pose_covariance_upper(cov_pos_ned_m2: np.ndarray, attitude_var_rad2: Sequence[float]) -> list[float]:
    """21-element row-major upper triangle of the 6x6 (x, y, z, roll, pitch, yaw) covariance."""
    full = np.zeros((6, 6), dtype=np.float64)
    full[:3, :3] = np.asarray(cov_pos_ned_m2, dtype=np.float64)
    full[3, 3], full[4, 4], full[5, 5] = (float(v) for v in attitude_var_rad2)
    return [float(full[i, j]) for i in range(6) for j in range(i, 6)]


def vision_position_estimate(
    mav: Any,
    state: EstimatorState,
    *,
    time_usec: int,
    reset_counter: int,
    attitude: Attitude | None = None,
    attitude_var_rad2: Sequence[float] | None = None,
    pos_ned_m: np.ndarray | None = None,
) -> MavlinkMessage:
    """VISION_POSITION_ESTIMATE in the local NED frame of ``state`` (its origin must be the autopilot's
    EKF origin, set with SET_GPS_GLOBAL_ORIGIN), or at ``pos_ned_m`` (3,) when given: ``state``'s
    position already re-expressed in the autopilot's frame (``ned_in_frame``). Attitude entries are the
    given attitude, or zeros with ``UNKNOWN_ANGLE_VARIANCE_RAD2`` variances when unknown (yaw from
    ``state.yaw_rad`` when known)."""
    pos = np.asarray(state.pos_ned_m if pos_ned_m is None else pos_ned_m, dtype=np.float64)
    if attitude is not None:
        roll, pitch, yaw = attitude.roll_rad, attitude.pitch_rad, attitude.yaw_rad
        var = attitude_var_rad2 or (0.01, 0.01, 0.05)
    else:
        roll, pitch = 0.0, 0.0
        yaw = state.yaw_rad if state.yaw_rad is not None else 0.0
        var = attitude_var_rad2 or (UNKNOWN_ANGLE_VARIANCE_RAD2,) * 3
    return mav.vision_position_estimate_encode(
        int(time_usec),
        float(pos[0]),
        float(pos[1]),
        float(pos[2]),
        float(roll),
        float(pitch),
        float(yaw),
        pose_covariance_upper(state.cov_pos_ned_m2, var),
        int(reset_counter) & 0xFF,
    )


def named_values(
    mav: Any,
    *,
    time_boot_ms: int,
    provenance: Provenance,
    inliers: int,
    residual_px: float | None,
    horiz_sigma_m: float,
    frame_drops: int,
    fdr_health: FdrHealthState,
    integrity_refused: int = 0,
) -> list[MavlinkMessage]:
    """NAMED_VALUE_INT/FLOAT set shown by ground stations: GDN_PROV (provenance code), GDN_INL, GDN_RES,
    GDN_HSIG, GDN_DROP, GDN_FDR (flight data recorder: 0 ok, 1 degraded, 2 failing), GDN_IREF (fixes
    the integrity rule refused). A residual of None
    (no match this frame) and non-finite floats are sent as NaN (the GCS shows "nan", i.e. unknown)."""
    t = int(time_boot_ms) & 0xFFFFFFFF

    def _i32(v: int) -> int:
        return int(min(max(int(v), -(2**31)), 2**31 - 1))

    return [
        mav.named_value_int_encode(t, NV_PROVENANCE.encode(), provenance.code),
        mav.named_value_int_encode(t, NV_INLIERS.encode(), _i32(inliers)),
        mav.named_value_float_encode(
            t, NV_RESIDUAL_PX.encode(), math.nan if residual_px is None else float(residual_px)
        ),
        mav.named_value_float_encode(t, NV_HORIZ_SIGMA_M.encode(), float(horiz_sigma_m)),
        mav.named_value_int_encode(t, NV_FRAME_DROPS.encode(), _i32(frame_drops)),
        mav.named_value_int_encode(t, NV_FDR_HEALTH.encode(), FdrHealthState(fdr_health).code),
        mav.named_value_int_encode(t, NV_INTEGRITY_REFUSED.encode(), _i32(integrity_refused)),
    ]


def clip_statustext(text: str, max_bytes: int = STATUSTEXT_MAX_BYTES) -> bytes:
    """Printable ASCII cut to ``max_bytes``: ground stations decode STATUSTEXT as ASCII, so other
    characters become "?" (one byte each, so a cut never splits a character); controls become spaces."""
    clean = "".join(ch if ch.isprintable() else " " for ch in text)
    return clean.encode("ascii", errors="replace")[:max_bytes]


def statustext(mav: Any, severity: int, text: str) -> MavlinkMessage:
    """STATUSTEXT with ``severity`` (MAV_SEVERITY_*) and ``text`` truncated to 50 bytes."""
    if not 0 <= int(severity) <= 7:
        raise ValueError(f"STATUSTEXT severity must be a MAV_SEVERITY (0..7), got {severity}")
    return mav.statustext_encode(int(severity), clip_statustext(text), 0, 0)


def heartbeat(mav: Any, system_status: int) -> MavlinkMessage:
    """HEARTBEAT of this daemon: MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID."""
    return mav.heartbeat_encode(
        DIALECT.MAV_TYPE_ONBOARD_CONTROLLER, DIALECT.MAV_AUTOPILOT_INVALID, 0, 0, int(system_status)
    )
