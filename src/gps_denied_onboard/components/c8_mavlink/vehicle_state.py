"""C8 inbound: the autopilot's attitude, altitude, home, local-frame origin (GPS_GLOBAL_ORIGIN), IMU,
flight phase (armed, landed state) and liveness, from decoded MAVLink messages.

Only the configured autopilot's messages are used: source system ``autopilot_system_id`` and
component 1 (MAV_COMP_ID_AUTOPILOT1). A HEARTBEAT counts only when it also declares a real autopilot
(``autopilot != MAV_AUTOPILOT_INVALID``) and is not a GCS/onboard-controller type, so a ground station
or another companion computer cannot keep the link "alive".

Time
----
Samples are stored in the autopilot's boot time (``time_boot_ms`` / ``time_usec`` since boot), which
keeps their spacing exact. Queries in the daemon's time are mapped through the one
``clock.AutopilotClock`` (TIMESYNC answers, bounded by every timestamped message's receive time); the
autopilot's SYSTEM_TIME Unix time is never used for it. Boot time going back by more than
``OFFSET_RESET_S`` (a reboot) clears every buffer: the old samples belong to the previous boot.

Altitude (above home, i.e. AGL over flat ground at home height), in priority order, the first source
with a sample within ``altitude_max_age_s`` of the query wins:
1. ALTITUDE.altitude_relative (the autopilot's own "relative to home" output);
2. GLOBAL_POSITION_INT.relative_alt (mm);
3. VFR_HUD.alt (AMSL) minus the HOME_POSITION altitude (only once home is known; VFR_HUD has no
   timestamp, so its receive time is used).
"""

from __future__ import annotations

import bisect
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import Any, Final

import numpy as np
import structlog

from gps_denied_onboard.camera.types import Attitude
from gps_denied_onboard.clock import AutopilotClock, TimeSource
from gps_denied_onboard.components.c5_estimator.protocol import ImuAcceleration
from gps_denied_onboard.components.c8_mavlink.messages import DIALECT
from gps_denied_onboard.components.c8_mavlink.px4_params import bytewise_to_value
from gps_denied_onboard.constants import LogEvent

_log = structlog.get_logger(__name__)

#: MAV_COMP_ID_AUTOPILOT1.
AUTOPILOT_COMPONENT_ID: Final[int] = 1
#: Ring-buffer length per series (ATTITUDE at 50 Hz -> 10 s).
BUFFER_LEN: Final[int] = 512
#: Attitude is extrapolated past the newest sample (or before the oldest) by at most this, then held.
EXTRAPOLATION_LIMIT_S: Final[float] = 0.05
#: How far an autopilot's attitude estimate strays from the truth after it manoeuvres, per radian its
#: roll and pitch swung over the last ``AHRS_SWING_WINDOW_S`` (1 sigma). Measured on ArduPilot copter SITL
#: 4.7.0-dev flying autopilot_square on GPS_INPUT: ATTITUDE minus SIMSTATE reached 2.5-3.4 deg while roll
#: and pitch swung through 30-50 deg, and decayed over 5-10 s once level.
AHRS_SIGMA_PER_SWING: Final[float] = 0.1
AHRS_SWING_WINDOW_S: Final[float] = 8.0
#: Boot time going back this much = reboot.
OFFSET_RESET_S: Final[float] = 1.0
#: An IMU sample farther than this from an interval cannot describe it (prediction falls back to
#: constant velocity), s.
IMU_MAX_GAP_S: Final[float] = 0.1
#: Standard gravity, m/s^2 (NED down is positive; a level accelerometer at rest reads -g on body z).
GRAVITY_M_S2: Final[float] = 9.80665
#: The autopilot's position report (and the EKF flags beside it) is used at most this old, s.
POSITION_MAX_AGE_S: Final[float] = 2.0
#: time_usec values above this are Unix times (after 2001-09-09), below it times since boot.
_UNIX_USEC_THRESHOLD: Final[int] = 1_000_000_000_000_000

_NOT_AUTOPILOT_TYPES: Final[frozenset[int]] = frozenset(
    {
        DIALECT.MAV_TYPE_GCS,
        DIALECT.MAV_TYPE_ONBOARD_CONTROLLER,
        DIALECT.MAV_TYPE_GIMBAL,
        DIALECT.MAV_TYPE_ADSB,
        DIALECT.MAV_TYPE_CAMERA,
    }
)


class AltitudeSource(str, Enum):
    ALTITUDE = "altitude"
    GLOBAL_POSITION_INT = "global_position_int"
    VFR_HUD = "vfr_hud"


@dataclass(frozen=True)
class ImuSample:
    """Latest HIGHRES_IMU or SCALED_IMU, SI units, body FRD. ``msg_type`` names the source message."""

    msg_type: str
    time_boot_usec: int
    accel_m_s2: tuple[float, float, float]
    gyro_rad_s: tuple[float, float, float]


@dataclass(frozen=True)
class AutopilotPosition:
    """The autopilot's own position estimate (GLOBAL_POSITION_INT) and what its EKF says of it
    (EKF_STATUS_REPORT), for the restart rules (F8) in ``c5_estimator.prior``."""

    lat_deg: float
    lon_deg: float
    #: Ground velocity north/east, m/s.
    vel_ne_m_s: tuple[float, float]
    #: When the estimate was valid, Unix us (the autopilot's boot time mapped to Unix time).
    time_unix_usec: int
    #: EKF_STATUS_REPORT.flags received within ``POSITION_MAX_AGE_S`` of the position, or None.
    ekf_flags: int | None

    @property
    def horizontal_position_valid(self) -> bool:
        """The EKF says its absolute horizontal position is good and it is not in constant-position
        mode (ArduPilot sets that when it has lost every position source)."""
        if self.ekf_flags is None:
            return False
        good = self.ekf_flags & DIALECT.EKF_POS_HORIZ_ABS
        const = self.ekf_flags & DIALECT.EKF_CONST_POS_MODE
        return bool(good) and not const


@dataclass(frozen=True)
class GroundPosition:
    """The autopilot's own position while the vehicle stood on the ground in this run (GLOBAL_POSITION_INT
    with EKF_STATUS_REPORT vouching for it: its GNSS before the denial, which a spoofer may have dragged),
    for the cross-checks of the start points in ``c5_estimator.prior``."""

    lat_deg: float
    lon_deg: float
    #: When it was received, Unix s.
    recv_unix_s: float
    #: Its stated horizontal 1-sigma (GPS_RAW_INT.h_acc with a 3D fix, received within
    #: ``POSITION_MAX_AGE_S``), m; None when the autopilot states none.
    sigma_m: float | None


#: GPS_FIX_TYPE_3D: GPS_RAW_INT's accuracy is taken only with at least a 3D fix.
_GPS_FIX_3D: Final[int] = 3
#: MAV_LANDED_STATE values that mean the vehicle is flying.
_FLYING: Final[frozenset[int]] = frozenset(
    {DIALECT.MAV_LANDED_STATE_IN_AIR, DIALECT.MAV_LANDED_STATE_TAKEOFF, DIALECT.MAV_LANDED_STATE_LANDING}
)
#: MAV_LANDED_STATE values an autopilot may report (UNDEFINED says nothing and is not kept).
_LANDED_STATES: Final[frozenset[int]] = frozenset(
    {
        DIALECT.MAV_LANDED_STATE_ON_GROUND,
        DIALECT.MAV_LANDED_STATE_IN_AIR,
        DIALECT.MAV_LANDED_STATE_TAKEOFF,
        DIALECT.MAV_LANDED_STATE_LANDING,
    }
)


@dataclass(frozen=True)
class FlightPhase:
    """What the autopilot says of the vehicle being on the ground or in the air, for the start-up rules
    (F8) in ``c5_estimator.prior``: HEARTBEAT's MAV_MODE_FLAG_SAFETY_ARMED and
    EXTENDED_SYS_STATE.landed_state (MAV_LANDED_STATE), each None when not received recently."""

    armed: bool | None
    landed_state: int | None
    #: When the autopilot last said the vehicle was on the ground (disarmed, or landed_state
    #: ON_GROUND), Unix s, in this run; None if it never did.
    last_on_ground_unix_s: float | None


@dataclass(frozen=True)
class VehicleStateSnapshot:
    """What the tracker knows, for status reports and the FDR."""

    autopilot_seen: bool
    link_alive: bool
    last_heartbeat_unix_s: float | None
    time_source: TimeSource
    boot_to_unix_offset_usec: int | None
    home: tuple[float, float, float] | None
    attitude_samples: int
    latest_attitude_time_unix_usec: int | None
    messages_used: int
    messages_ignored: int


class _Series:
    """Time-sorted samples keyed by autopilot boot time (usec), bounded length."""

    def __init__(self, maxlen: int = BUFFER_LEN) -> None:
        self.t_usec: list[int] = []
        self.values: list[tuple[float, ...]] = []
        self._maxlen = maxlen

    def add(self, t_usec: int, value: tuple[float, ...]) -> None:
        if not self.t_usec or t_usec > self.t_usec[-1]:
            self.t_usec.append(t_usec)
            self.values.append(value)
        else:
            i = bisect.bisect_left(self.t_usec, t_usec)
            if i < len(self.t_usec) and self.t_usec[i] == t_usec:
                self.values[i] = value  # duplicate timestamp: keep the latest
                return
            self.t_usec.insert(i, t_usec)
            self.values.insert(i, value)
        if len(self.t_usec) > self._maxlen:
            del self.t_usec[0], self.values[0]

    def clear(self) -> None:
        self.t_usec.clear()
        self.values.clear()

    def __len__(self) -> int:
        return len(self.t_usec)


def _wrap_pi(angle_rad: float) -> float:
    """Angle in [-pi, pi)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def _interp(
    series: _Series, t_usec: int, *, max_age_usec: int, extrap_usec: int, wrap: tuple[bool, ...]
) -> tuple[float, ...] | None:
    """Value at ``t_usec``: linear between bracketing samples (angles with wrap[i] interpolated along the
    short arc), extrapolated from the end pair by at most ``extrap_usec`` and then held; None when the
    nearest sample is more than ``max_age_usec`` away."""
    ts = series.t_usec
    if not ts:
        return None
    i = bisect.bisect_left(ts, t_usec)
    nearest = min(
        (abs(ts[j] - t_usec) for j in (i - 1, i) if 0 <= j < len(ts)),
        default=None,
    )
    if nearest is None or nearest > max_age_usec:
        return None
    if i < len(ts) and ts[i] == t_usec:
        return series.values[i]
    if 0 < i < len(ts):
        j0, j1, t_eff = i - 1, i, t_usec
    elif len(ts) == 1:
        return series.values[0]
    elif i == 0:
        j0, j1 = 0, 1
        t_eff = max(t_usec, ts[0] - extrap_usec)
    else:
        j0, j1 = len(ts) - 2, len(ts) - 1
        t_eff = min(t_usec, ts[-1] + extrap_usec)
    t0, t1 = ts[j0], ts[j1]
    frac = (t_eff - t0) / (t1 - t0)
    out = []
    for k, (a, b) in enumerate(zip(series.values[j0], series.values[j1], strict=True)):
        if wrap[k]:
            out.append(_wrap_pi(a + frac * _wrap_pi(b - a)))
        else:
            out.append(a + frac * (b - a))
    return tuple(out)


class VehicleStateTracker:
    """Autopilot state from decoded pymavlink messages; thread-safe (fed by the event loop, queried by the
    pipeline thread). Stale data is invalid: every query returns None rather than reuse an old value."""

    def __init__(
        self,
        autopilot_system_id: int,
        attitude_max_age_s: float,
        altitude_max_age_s: float,
        link_timeout_s: float,
        clock: Callable[[], float] = time.time,
        autopilot_clock: AutopilotClock | None = None,
    ) -> None:
        """``clock``: the daemon's now, Unix seconds; ``autopilot_clock``: the mapping of the autopilot's
        boot time onto it (a new one when not given)."""
        if attitude_max_age_s <= 0 or altitude_max_age_s <= 0 or link_timeout_s <= 0:
            raise ValueError(
                "max ages and link timeout must be > 0, got "
                f"attitude={attitude_max_age_s}, altitude={altitude_max_age_s}, link={link_timeout_s}"
            )
        self.autopilot_system_id = int(autopilot_system_id)
        self._att_max_usec = int(attitude_max_age_s * 1e6)
        self._alt_max_usec = int(altitude_max_age_s * 1e6)
        self._extrap_usec = int(min(EXTRAPOLATION_LIMIT_S, attitude_max_age_s) * 1e6)
        self._link_timeout_s = float(link_timeout_s)
        self._clock = clock
        self._lock = threading.Lock()
        self._attitude = _Series()
        self._alt: dict[AltitudeSource, _Series] = {s: _Series() for s in AltitudeSource}
        self._home: tuple[float, float, float] | None = None
        #: Whether the newest HOME_POSITION came signed (MAVLink 2 signing): an unsigned one is a claim
        #: anyone on the link could have made.
        self._home_signed = False
        #: GPS_RAW_INT: (receive time as boot usec, fix_type, h_acc m or None).
        self._gps_raw: tuple[int, int, float | None] | None = None
        #: The autopilot's own position while on the ground (``ground_position``).
        self._ground_position: GroundPosition | None = None
        #: The autopilot's local-frame origin from GPS_GLOBAL_ORIGIN (lat_deg, lon_deg, alt_amsl_m).
        self._gps_origin: tuple[float, float, float] | None = None
        self._imu: ImuSample | None = None
        #: GLOBAL_POSITION_INT: (boot usec, lat_deg, lon_deg, vn_m_s, ve_m_s); EKF_STATUS_REPORT:
        #: (receive time as boot usec, flags).
        self._position: tuple[int, float, float, float, float] | None = None
        self._ekf_flags: tuple[int, int] | None = None
        #: When GLOBAL_POSITION_INT and EKF_STATUS_REPORT last arrived, whatever they said (Unix s, receive
        #: time): an autopilot without a position has still answered (``estimate_answered_since``).
        self._answered_s: dict[str, float] = {}
        #: GLOBAL_POSITION_INT's alt - relative_alt while it has a position: (boot usec, ground AMSL m).
        self._ground_alt: tuple[int, float] | None = None
        #: Specific force, body FRD, m/s^2, keyed by boot time.
        self._accel_body = _Series()
        self._ap_clock = autopilot_clock if autopilot_clock is not None else AutopilotClock()
        self._last_boot_usec: int | None = None
        self._last_heartbeat_s: float | None = None
        #: Flight phase (``flight_phase``): HEARTBEAT's armed flag and EXTENDED_SYS_STATE.landed_state, each
        #: with its receive time (Unix s); when either last said "on the ground" (disarmed, ON_GROUND).
        self._armed: tuple[float, bool] | None = None
        self._landed_state: tuple[float, int] | None = None
        self._last_on_ground_s: float | None = None
        self._autopilot_seen = False
        #: HEARTBEAT.autopilot (MAV_AUTOPILOT_*) of the autopilot, once seen.
        self._autopilot_kind: int | None = None
        #: PARAM_VALUE answers: name -> (value, receive time Unix s); integers decoded as the autopilot
        #: encodes them.
        self._params: dict[str, tuple[float, float]] = {}
        self._used = 0
        self._ignored = 0

    # --- input --------------------------------------------------------------------------------------
    def handle(self, msg: Any, recv_time_unix_s: float) -> bool:
        """Use one decoded message received at ``recv_time_unix_s``; returns True if it was used."""
        try:
            src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
            mtype = msg.get_type()
        except AttributeError:
            self._ignored += 1
            return False
        if src_sys != self.autopilot_system_id or src_comp != AUTOPILOT_COMPONENT_ID:
            self._ignored += 1
            return False
        handler = _HANDLERS.get(mtype)
        if handler is None:
            self._ignored += 1
            return False
        recv_usec = int(recv_time_unix_s * 1e6)
        with self._lock:
            used = handler(self, msg, recv_usec)
            if used:
                self._used += 1
            else:
                self._ignored += 1
        return used

    def _on_heartbeat(self, msg: Any, recv_usec: int) -> bool:
        if msg.autopilot == DIALECT.MAV_AUTOPILOT_INVALID or msg.type in _NOT_AUTOPILOT_TYPES:
            return False
        self._last_heartbeat_s = recv_usec / 1e6
        self._autopilot_kind = int(msg.autopilot)
        self._note_armed(bool(int(msg.base_mode) & DIALECT.MAV_MODE_FLAG_SAFETY_ARMED), recv_usec / 1e6)
        if not self._autopilot_seen:
            self._autopilot_seen = True
            _log.info(
                LogEvent.MAVLINK_AUTOPILOT_SEEN,
                system_id=self.autopilot_system_id,
                mav_type=int(msg.type),
                autopilot=int(msg.autopilot),
            )
        return True

    def _note_armed(self, armed: bool, recv_s: float) -> None:
        self._armed = (recv_s, armed)
        if not armed:
            self._last_on_ground_s = recv_s

    def _on_extended_sys_state(self, msg: Any, recv_usec: int) -> bool:
        landed = int(msg.landed_state)
        if landed not in _LANDED_STATES:
            return False
        recv_s = recv_usec / 1e6
        self._landed_state = (recv_s, landed)
        if landed == DIALECT.MAV_LANDED_STATE_ON_GROUND:
            self._last_on_ground_s = recv_s
        return True

    def _note_boot_time(self, boot_usec: int) -> None:
        """Detect an autopilot reboot (boot time going back) and drop the previous boot's samples."""
        last = self._last_boot_usec
        if last is not None and boot_usec < last - OFFSET_RESET_S * 1e6:
            self._attitude.clear()
            self._accel_body.clear()
            for s in self._alt.values():
                s.clear()
            self._imu = None
            self._gps_origin = None  # a rebooted autopilot has no origin until it reports one again
            self._position = None
            self._ekf_flags = None
            self._ground_alt = None
        if last is None or boot_usec > last or boot_usec < last - OFFSET_RESET_S * 1e6:
            self._last_boot_usec = boot_usec

    def _timestamped(self, boot_usec: int, recv_usec: int) -> int:
        """Register a boot-time stamp received at ``recv_usec``; returns the boot time (usec)."""
        self._note_boot_time(boot_usec)
        self._ap_clock.note_stamp(boot_usec, recv_usec)
        return boot_usec

    def _to_boot_usec(self, time_usec: int, recv_usec: int) -> int:
        """A message's ``time_usec`` as boot time: a Unix stamp is on the autopilot's own Unix clock,
        which is not ours, so such a message counts as sampled when it was received."""
        if time_usec >= _UNIX_USEC_THRESHOLD:
            return self._recv_as_boot(recv_usec)
        return self._timestamped(time_usec, recv_usec)

    def _recv_as_boot(self, recv_usec: int) -> int:
        offset = self._offset_usec()
        return int(recv_usec - offset) if offset is not None else recv_usec

    def _on_system_time(self, msg: Any, recv_usec: int) -> bool:
        # its boot time bounds the mapping like any stamp; its Unix time is the autopilot's own, unused
        self._timestamped(int(msg.time_boot_ms) * 1000, recv_usec)
        return True

    def _on_timesync(self, msg: Any, recv_usec: int) -> bool:
        if int(msg.tc1) == 0:
            return False  # a request (the link answers it), not an answer
        return self._ap_clock.answer(int(msg.tc1), int(msg.ts1), recv_usec)

    def _on_param_value(self, msg: Any, recv_usec: int) -> bool:
        """PARAM_VALUE: PX4 sends integer parameters byte-wise in the float field
        (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE); ArduPilot casts them (ENCODE_C_CAST)."""
        name = msg.param_id.decode("ascii", "replace") if isinstance(msg.param_id, bytes) else msg.param_id
        name = str(name).rstrip("\x00")
        value = float(msg.param_value)
        if self._autopilot_kind == DIALECT.MAV_AUTOPILOT_PX4:
            value = bytewise_to_value(value, int(msg.param_type))
        self._params[name] = (value, recv_usec / 1e6)
        return True

    def _on_attitude(self, msg: Any, recv_usec: int) -> bool:
        vals = (float(msg.roll), float(msg.pitch), float(msg.yaw))
        if not all(math.isfinite(v) for v in vals):
            return False
        t = self._timestamped(int(msg.time_boot_ms) * 1000, recv_usec)
        self._attitude.add(t, vals)
        return True

    def _on_altitude(self, msg: Any, recv_usec: int) -> bool:
        rel = float(msg.altitude_relative)
        if not math.isfinite(rel):
            return False
        self._alt[AltitudeSource.ALTITUDE].add(self._to_boot_usec(int(msg.time_usec), recv_usec), (rel,))
        return True

    def _on_global_position_int(self, msg: Any, recv_usec: int) -> bool:
        self._answered_s["GLOBAL_POSITION_INT"] = recv_usec / 1e6
        t = self._timestamped(int(msg.time_boot_ms) * 1000, recv_usec)
        self._alt[AltitudeSource.GLOBAL_POSITION_INT].add(t, (int(msg.relative_alt) / 1000.0,))
        lat_deg, lon_deg = int(msg.lat) / 1e7, int(msg.lon) / 1e7
        # (0, 0) is what an autopilot without a position sends.
        if abs(lat_deg) <= 90.0 and abs(lon_deg) <= 180.0 and (lat_deg, lon_deg) != (0.0, 0.0):
            self._position = (t, lat_deg, lon_deg, int(msg.vx) / 100.0, int(msg.vy) / 100.0)
            # the ground under home, AMSL: only once the EKF has an origin (before it, alt is 0)
            self._ground_alt = (t, (int(msg.alt) - int(msg.relative_alt)) / 1000.0)
            self._note_ground_position(lat_deg, lon_deg, recv_usec)
        return True

    def _note_ground_position(self, lat_deg: float, lon_deg: float, recv_usec: int) -> None:
        """Keep the autopilot's position as the ground position while the vehicle is on the ground (its
        newest armed or landed state, fresh, says so and nothing says it flies) and its EKF vouches for
        its absolute horizontal position (flags received within ``POSITION_MAX_AGE_S``)."""
        recv_s = recv_usec / 1e6
        boot = self._recv_as_boot(recv_usec)
        max_age_usec = POSITION_MAX_AGE_S * 1e6

        def fresh(sample: tuple[float, Any] | None) -> Any:
            if sample is None or not 0.0 <= recv_s - sample[0] <= self._link_timeout_s:
                return None
            return sample[1]

        landed, armed = fresh(self._landed_state), fresh(self._armed)
        on_ground = (landed == DIALECT.MAV_LANDED_STATE_ON_GROUND or armed is False) and landed not in _FLYING
        flags = self._ekf_flags
        if not on_ground or flags is None or abs(flags[0] - boot) > max_age_usec:
            return
        if not AutopilotPosition(lat_deg, lon_deg, (0.0, 0.0), 0, flags[1]).horizontal_position_valid:
            return
        sigma: float | None = None
        raw = self._gps_raw
        if raw is not None and abs(raw[0] - boot) <= max_age_usec and raw[1] >= _GPS_FIX_3D:
            sigma = raw[2]
        self._ground_position = GroundPosition(lat_deg, lon_deg, recv_s, sigma)

    def _on_gps_raw_int(self, msg: Any, recv_usec: int) -> bool:
        h_acc_mm = int(getattr(msg, "h_acc", 0) or 0)  # a MAVLink 2 extension: 0 when not stated
        h_acc_m = h_acc_mm / 1000.0 if h_acc_mm else None
        self._gps_raw = (self._recv_as_boot(recv_usec), int(msg.fix_type), h_acc_m)
        return True

    def _on_ekf_status_report(self, msg: Any, recv_usec: int) -> bool:
        self._answered_s["EKF_STATUS_REPORT"] = recv_usec / 1e6
        self._ekf_flags = (self._recv_as_boot(recv_usec), int(msg.flags))
        return True

    def _on_vfr_hud(self, msg: Any, recv_usec: int) -> bool:
        if self._home is None or not math.isfinite(float(msg.alt)):
            return False
        rel = float(msg.alt) - self._home[2]
        self._alt[AltitudeSource.VFR_HUD].add(self._recv_as_boot(recv_usec), (rel,))
        return True

    def _on_home_position(self, msg: Any, recv_usec: int) -> bool:
        self._home = (int(msg.latitude) / 1e7, int(msg.longitude) / 1e7, int(msg.altitude) / 1000.0)
        self._home_signed = bool(msg.get_signed()) if hasattr(msg, "get_signed") else False
        return True

    def _on_gps_global_origin(self, msg: Any, recv_usec: int) -> bool:
        lat_deg, lon_deg = int(msg.latitude) / 1e7, int(msg.longitude) / 1e7
        if abs(lat_deg) > 90.0 or abs(lon_deg) > 180.0:
            return False
        self._gps_origin = (lat_deg, lon_deg, int(msg.altitude) / 1000.0)
        return True

    def _add_imu(self, sample: ImuSample) -> bool:
        if not all(math.isfinite(v) for v in (*sample.accel_m_s2, *sample.gyro_rad_s)):
            return False
        self._imu = sample
        self._accel_body.add(sample.time_boot_usec, sample.accel_m_s2)
        return True

    def _on_highres_imu(self, msg: Any, recv_usec: int) -> bool:
        t = self._to_boot_usec(int(msg.time_usec), recv_usec)
        return self._add_imu(
            ImuSample(
                "HIGHRES_IMU",
                t,
                (float(msg.xacc), float(msg.yacc), float(msg.zacc)),
                (float(msg.xgyro), float(msg.ygyro), float(msg.zgyro)),
            )
        )

    def _on_scaled_imu(self, msg: Any, recv_usec: int) -> bool:
        t = self._timestamped(int(msg.time_boot_ms) * 1000, recv_usec)
        g = GRAVITY_M_S2 / 1000.0  # mG -> m/s^2
        return self._add_imu(
            ImuSample(
                msg.get_type(),
                t,
                (msg.xacc * g, msg.yacc * g, msg.zacc * g),
                (msg.xgyro / 1000.0, msg.ygyro / 1000.0, msg.zgyro / 1000.0),  # mrad/s -> rad/s
            )
        )

    # --- queries ------------------------------------------------------------------------------------
    def _offset_usec(self) -> float | None:
        """The daemon's clock minus the autopilot's boot time, now, us (``clock.AutopilotClock``)."""
        return self._ap_clock.offset_usec(self._clock() * 1e6)

    @property
    def time_source(self) -> TimeSource:
        return self._ap_clock.source

    @property
    def autopilot_clock(self) -> AutopilotClock:
        return self._ap_clock

    def attitude_at(self, time_unix_usec: int) -> Attitude | None:
        """Autopilot attitude at a Unix time, or None when no sample lies within attitude_max_age_s."""
        with self._lock:
            offset = self._offset_usec()
            if offset is None:
                return None
            vals = _interp(
                self._attitude,
                int(time_unix_usec - offset),
                max_age_usec=self._att_max_usec,
                extrap_usec=self._extrap_usec,
                wrap=(True, False, True),
            )
        return None if vals is None else Attitude(vals[0], vals[1], vals[2])

    def latest_attitude_unix_usec(self) -> int | None:
        """The newest ATTITUDE sample's time in the daemon's clock, or None."""
        with self._lock:
            offset = self._offset_usec()
            if offset is None or not self._attitude.t_usec:
                return None
            return int(self._attitude.t_usec[-1] + offset)

    def ahrs_doubt_rad(self, time_unix_usec: int) -> float | None:
        """How far the autopilot's roll and pitch may be from the truth at a time in the daemon's clock
        after its manoeuvres, rad (1 sigma): ``AHRS_SIGMA_PER_SWING`` times how far roll and pitch swung
        over the ``AHRS_SWING_WINDOW_S`` before it. None without attitude samples there."""
        with self._lock:
            offset = self._offset_usec()
            if offset is None:
                return None
            return self._ahrs_doubt_boot(int(time_unix_usec - offset))

    def _ahrs_doubt_boot(self, b1_usec: int) -> float | None:
        """``ahrs_doubt_rad`` at the autopilot's boot time ``b1_usec``; the caller holds the lock."""
        ts = self._attitude.t_usec
        b0 = b1_usec - int(AHRS_SWING_WINDOW_S * 1e6)
        lo, hi = bisect.bisect_left(ts, b0), bisect.bisect_right(ts, b1_usec)
        if hi - lo < 2:
            return None
        vals = np.asarray(self._attitude.values[lo:hi], dtype=np.float64)[:, :2]
        swing = np.ptp(vals, axis=0)
        return float(AHRS_SIGMA_PER_SWING * np.hypot(swing[0], swing[1]))

    def down_cam_curve(self, time_unix_usec: int, offsets_s: np.ndarray) -> np.ndarray | None:
        """World-down in the camera (nadir mount, each instant's own axes) at ``time_unix_usec`` plus each
        of ``offsets_s``, (len(offsets_s), 2) on the camera's x and y axes: what a timing error turns
        into a tilt error. None when any of them is unknown."""
        with self._lock:
            offset = self._offset_usec()
            if offset is None:
                return None
            out = np.empty((len(offsets_s), 2))
            for k, dt_s in enumerate(offsets_s):
                vals = _interp(
                    self._attitude,
                    int(time_unix_usec + dt_s * 1e6 - offset),
                    max_age_usec=self._att_max_usec,
                    extrap_usec=self._extrap_usec,
                    wrap=(True, False, True),
                )
                if vals is None:
                    return None
                out[k] = Attitude(vals[0], vals[1], vals[2]).R_ned_cam()[2, :2]
        return out

    def alt_agl_at(self, time_unix_usec: int) -> float | None:
        """Height above home (AGL over flat ground at home height), m, at a Unix time; None when stale."""
        with self._lock:
            offset = self._offset_usec()
            if offset is None:
                return None
            t = int(time_unix_usec - offset)
            for source in AltitudeSource:
                vals = _interp(
                    self._alt[source], t, max_age_usec=self._alt_max_usec, extrap_usec=0, wrap=(False,)
                )
                if vals is not None:
                    return float(vals[0])
        return None

    def accel_ned_mean(self, t0_unix_usec: int, t1_unix_usec: int) -> ImuAcceleration | None:
        """Mean kinematic acceleration over ``[t0, t1]`` (Unix usec) in NED, (3,) m/s^2: each IMU sample's
        specific force rotated by the attitude at its own time, plus gravity (the C5
        ``AccelerationSource``). Samples inside the interval are averaged; an interval shorter than the
        IMU period uses the nearest sample. None when no sample lies within ``IMU_MAX_GAP_S`` of both
        ends, or no attitude is known at a sample's time: the prediction then must not pretend.

        Its tilt bound is the mean specific force's magnitude times the attitude's own doubt at ``t1``
        (``ahrs_doubt_rad``): the rotation that puts the specific force into NED is as wrong as the
        autopilot's roll and pitch."""
        with self._lock:
            offset = self._offset_usec()
            ts = self._accel_body.t_usec
            if offset is None or not ts:
                return None
            b0, b1 = int(t0_unix_usec - offset), int(t1_unix_usec - offset)
            gap = int(IMU_MAX_GAP_S * 1e6)
            lo = bisect.bisect_left(ts, b0)
            hi = bisect.bisect_right(ts, b1)
            if lo < hi:
                idx = range(lo, hi)
            else:  # no sample inside: the nearest one
                mid = (b0 + b1) // 2
                near = min((j for j in (lo - 1, lo) if 0 <= j < len(ts)), key=lambda j: abs(ts[j] - mid))
                idx = range(near, near + 1)
            if ts[idx[0]] - b0 > gap or b1 - ts[idx[-1]] > gap:
                return None
            total = np.zeros(3)
            for j in idx:
                att = _interp(
                    self._attitude,
                    ts[j],
                    max_age_usec=self._att_max_usec,
                    extrap_usec=self._extrap_usec,
                    wrap=(True, False, True),
                )
                if att is None:
                    return None
                r_ned_body = Attitude(att[0], att[1], att[2]).R_ned_body()
                total += r_ned_body @ np.asarray(self._accel_body.values[j], dtype=np.float64)
            specific = total / len(idx)
            doubt_rad = self._ahrs_doubt_boot(b1) or 0.0
        mean = specific.copy()
        mean[2] += GRAVITY_M_S2
        return ImuAcceleration(mean, float(np.linalg.norm(specific)) * doubt_rad)

    def home(self) -> tuple[float, float, float] | None:
        """(lat_deg, lon_deg, alt_amsl_m) from HOME_POSITION, or None before it was received."""
        with self._lock:
            return self._home

    def home_signed(self) -> bool:
        """Whether the newest HOME_POSITION came with a MAVLink 2 signature (False before one came)."""
        with self._lock:
            return self._home_signed

    def ground_position(self) -> GroundPosition | None:
        """The autopilot's own position the last time it said the vehicle was on the ground in this run,
        with its EKF vouching for it (``_note_ground_position``); None if it never did."""
        with self._lock:
            return self._ground_position

    def gps_origin(self) -> tuple[float, float, float] | None:
        """(lat_deg, lon_deg, alt_amsl_m) of the autopilot's local NED origin from its latest
        GPS_GLOBAL_ORIGIN, or None before one was received (or since a detected autopilot reboot)."""
        with self._lock:
            return self._gps_origin

    def autopilot_position(self, now_unix_s: float | None = None) -> AutopilotPosition | None:
        """The autopilot's latest GLOBAL_POSITION_INT when at most ``POSITION_MAX_AGE_S`` old, with
        the EKF_STATUS_REPORT flags received within that age of it; None otherwise."""
        now_s = self._clock() if now_unix_s is None else now_unix_s
        with self._lock:
            offset = self._offset_usec()
            if self._position is None or offset is None:
                return None
            t_boot, lat, lon, vn, ve = self._position
            t_unix = int(t_boot + offset)
            if abs(now_s * 1e6 - t_unix) > POSITION_MAX_AGE_S * 1e6:
                return None
            flags = None
            if self._ekf_flags is not None and abs(self._ekf_flags[0] - t_boot) <= POSITION_MAX_AGE_S * 1e6:
                flags = self._ekf_flags[1]
        return AutopilotPosition(lat, lon, (vn, ve), t_unix, flags)

    def estimate_answered_since(self, since_unix_s: float) -> bool:
        """Both GLOBAL_POSITION_INT and EKF_STATUS_REPORT arrived at or after ``since_unix_s`` (receive
        time), whatever they said: the autopilot has told what it has, a position or none (F8: the
        restart's wait for the autopilot's estimate ends there)."""
        with self._lock:
            got = dict(self._answered_s)
        wanted = ("GLOBAL_POSITION_INT", "EKF_STATUS_REPORT")
        return all(got.get(m, -math.inf) >= since_unix_s for m in wanted)

    def flight_phase(self, now_unix_s: float | None = None) -> FlightPhase:
        """What the autopilot last said of arming and landing, each only while fresher than
        ``link_timeout_s`` (None otherwise), and when it last said the vehicle was on the ground."""
        now_s = self._clock() if now_unix_s is None else now_unix_s
        with self._lock:
            armed, landed, ground = self._armed, self._landed_state, self._last_on_ground_s

        def fresh(sample: tuple[float, Any] | None) -> Any:
            if sample is None or not 0.0 <= now_s - sample[0] <= self._link_timeout_s:
                return None
            return sample[1]

        return FlightPhase(fresh(armed), fresh(landed), ground)

    def ground_alt_amsl_m(self) -> float | None:
        """The autopilot's height of the ground at home above mean sea level, m: GLOBAL_POSITION_INT's
        ``alt - relative_alt`` once it carries a position (its EKF has an origin), else HOME_POSITION's
        altitude; None before either."""
        with self._lock:
            if self._ground_alt is not None:
                return self._ground_alt[1]
            return self._home[2] if self._home is not None else None

    def latest_imu(self) -> ImuSample | None:
        with self._lock:
            return self._imu

    @property
    def autopilot_kind(self) -> int | None:
        """HEARTBEAT.autopilot of the autopilot (``MAV_AUTOPILOT_PX4``, ...), None before its HEARTBEAT."""
        with self._lock:
            return self._autopilot_kind

    def param(self, name: str, since_unix_s: float = -math.inf) -> float | None:
        """The autopilot's parameter ``name`` as last answered (PARAM_VALUE) at or after ``since_unix_s``."""
        with self._lock:
            got = self._params.get(name)
        return got[0] if got is not None and got[1] >= since_unix_s else None

    def link_alive(self, now: float | None = None) -> bool:
        """True when the autopilot's HEARTBEAT was received within link_timeout_s of ``now``."""
        now_s = self._clock() if now is None else now
        with self._lock:
            last = self._last_heartbeat_s
        return last is not None and (now_s - last) <= self._link_timeout_s

    @property
    def autopilot_seen(self) -> bool:
        return self._autopilot_seen

    def snapshot(self, now: float | None = None) -> VehicleStateSnapshot:
        alive = self.link_alive(now)
        source = self.time_source
        with self._lock:
            offset = self._offset_usec()
            latest = None
            if self._attitude.t_usec and offset is not None:
                latest = int(self._attitude.t_usec[-1] + offset)
            return VehicleStateSnapshot(
                autopilot_seen=self._autopilot_seen,
                link_alive=alive,
                last_heartbeat_unix_s=self._last_heartbeat_s,
                time_source=source,
                boot_to_unix_offset_usec=None if offset is None else int(offset),
                home=self._home,
                attitude_samples=len(self._attitude),
                latest_attitude_time_unix_usec=latest,
                messages_used=self._used,
                messages_ignored=self._ignored,
            )


_HANDLERS: Final[dict[str, Callable[[VehicleStateTracker, Any, int], bool]]] = {
    "HEARTBEAT": VehicleStateTracker._on_heartbeat,
    "SYSTEM_TIME": VehicleStateTracker._on_system_time,
    "TIMESYNC": VehicleStateTracker._on_timesync,
    "ATTITUDE": VehicleStateTracker._on_attitude,
    "ALTITUDE": VehicleStateTracker._on_altitude,
    "GLOBAL_POSITION_INT": VehicleStateTracker._on_global_position_int,
    "EKF_STATUS_REPORT": VehicleStateTracker._on_ekf_status_report,
    "VFR_HUD": VehicleStateTracker._on_vfr_hud,
    "HOME_POSITION": VehicleStateTracker._on_home_position,
    "GPS_RAW_INT": VehicleStateTracker._on_gps_raw_int,
    "GPS_GLOBAL_ORIGIN": VehicleStateTracker._on_gps_global_origin,
    "EXTENDED_SYS_STATE": VehicleStateTracker._on_extended_sys_state,
    "HIGHRES_IMU": VehicleStateTracker._on_highres_imu,
    "PARAM_VALUE": VehicleStateTracker._on_param_value,
    "SCALED_IMU": VehicleStateTracker._on_scaled_imu,
    "SCALED_IMU2": VehicleStateTracker._on_scaled_imu,
}
