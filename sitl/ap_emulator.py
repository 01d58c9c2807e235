"""An ArduPilot copter EMULATOR for CI: a test double of the autopilot's MAVLink side, not the autopilot.

No ArduPilot binary ships with this project (and none is downloaded). CI flies the daemon against this
double; ``gdnav sitl run --autopilot URL`` flies it against a real ArduPilot SITL the same way
(docs/ardupilot.md, "ArduCopter SITL"). Nothing here is ArduPilot code, and no report may present what
it does as what ArduPilot does: it reproduces facts measured on copter SITL 4.7.0-dev through the rules
of :mod:`gps_denied_onboard.sitl.ardupilot_rules`, reused here, never restated.

Input: MAVLink 2 (ardupilotmega, system 1 component 1, UDP on loopback) on each ``--port``, one channel
each (like SERIAL0, SERIAL1), answering the last address that sent it a datagram: GPS_INPUT, TIMESYNC,
PARAM_*, COMMAND_LONG, SET_MODE, SET_POSITION_TARGET_GLOBAL_INT, the mission protocol.
Output: HEARTBEAT, SYSTEM_TIME, ATTITUDE, HIGHRES_IMU, GLOBAL_POSITION_INT, HOME_POSITION, GPS_RAW_INT,
GPS2_RAW, EKF_STATUS_REPORT, MISSION_CURRENT, SIMSTATE (the truth), STATUSTEXT, acks and replies;
broadcast messages are forwarded between channels, as ArduPilot does between its serial ports.

Rules, each from a measured fact: GPSn_TYPE=14 at boot, fix_type >= 3, time_week > 0; the 215/245 ms
health rule; "PreArm: GPS n: Bad fix"; NO_FIX 4 s, EKF position lost 7 s, LAND at 7.8 s (latched); EKF
origin 10 s and "using GPS" 28 s after the first 3D fix (shortened in CI); ``SIM_GPS1_ENABLE``;
``GPS_AUTO_SWITCH``; the fused position follows GPS_INPUT completely, bias included, lagged by
``GPSn_DELAY_MS``; the speed-accuracy glitch; TIMESYNC answered in boot time, SYSTEM_TIME off by
``system_time_offset_s``; ``ARMING_CHECK`` / ``ARMING_SKIPCHK``; ATTITUDE is the AHRS's estimate, off
the truth (SIMSTATE) by a tenth of each swing of the tilt, coming back over 6 s. The physics is a point
mass with a lagged tilt, speed and acceleration limits, flat ground, no wind.

Every rule and its source in full: docs/ardupilot.md, "The emulator and its rules in full".
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as apm

from gps_denied_onboard.geo import LocalTangentPlane
from gps_denied_onboard.sitl.ardupilot_rules import (
    GPS_TYPE_MAV,
    GpsHealthMonitor,
    GpsLossStage,
    GpsTypeParams,
    SpeedAccuracyGlitch,
    gps_input_rejection,
    gps_lag_s,
    gps_loss_stage,
    prearm_gps_failures,
)
from gps_denied_onboard.sitl.autopilot import send_home_position
from gps_denied_onboard.sitl.emulator_core import (
    PointMassVehicle,
    UdpEmulator,
    add_common_arguments,
    approach_velocity_ne,
    geodetic,
    parse_home,
    parse_params,
    send_global_position_int,
    send_highres_imu,
    serve,
)
from gps_denied_onboard.sitl.emulator_core import param_id as _param_id
from gps_denied_onboard.sitl.emulator_core import wrap_pi as _wrap_pi

#: Copter custom modes (ArduCopter ``Mode::Number``).
MODE_STABILIZE: Final[int] = 0
MODE_AUTO: Final[int] = 3
MODE_GUIDED: Final[int] = 4
MODE_LOITER: Final[int] = 5
MODE_LAND: Final[int] = 9
MODE_NAMES: Final[dict[int, str]] = {0: "STABILIZE", 3: "AUTO", 4: "GUIDED", 5: "LOITER", 9: "LAND"}
#: Modes ArduCopter arms in (AUTO needs AUTO_OPTIONS, not modelled).
ARMABLE_MODES: Final[frozenset[int]] = frozenset({MODE_STABILIZE, MODE_GUIDED, MODE_LOITER})
#: Modes that need a position estimate (the EKF failsafe acts in them).
POSITION_MODES: Final[frozenset[int]] = frozenset({MODE_AUTO, MODE_GUIDED, MODE_LOITER})
#: Measured start-up after the first GPS_INPUT: "EKF origin set at 10 s; EKF3 IMU0 is using GPS at 28 s".
EKF_ORIGIN_DELAY_S: Final[float] = 10.0
EKF_USING_GPS_DELAY_S: Final[float] = 28.0
#: Measured on SITL 4.7.0-dev: SYSTEM_TIME's Unix time 2.0 s behind the host (its clock stood still while
#: it waited for a client on SERIAL0).
SYSTEM_TIME_OFFSET_S: Final[float] = -2.0
#: The reported attitude's error (ATTITUDE minus SIMSTATE): each change of the true roll and pitch adds
#: AHRS_GAIN of it, and it decays with AHRS_DECAY_S. Measured on ArduPilot copter SITL 4.7.0-dev flying
#: autopilot_square on GPS_INPUT: 2.5-3.4 deg while roll and pitch swung through 30-50 deg, decaying over
#: 5-10 s once level.
AHRS_GAIN: Final[float] = 0.1
AHRS_DECAY_S: Final[float] = 6.0
#: Truth kept for the GPS lag, s.
TRUTH_HISTORY_S: Final[float] = 2.0
#: Measured: "GPS 1: detected MAV" 0.1 s after the first GPS_INPUT.
GPS_DETECTED_DELAY_S: Final[float] = 0.1
#: EKF_STATUS_REPORT flags.
EKF_FLAGS_POSITION_OK: Final[int] = (
    apm.EKF_ATTITUDE
    | apm.EKF_VELOCITY_HORIZ
    | apm.EKF_VELOCITY_VERT
    | apm.EKF_POS_HORIZ_REL
    | apm.EKF_POS_HORIZ_ABS
    | apm.EKF_POS_VERT_ABS
    | apm.EKF_PRED_POS_HORIZ_REL
    | apm.EKF_PRED_POS_HORIZ_ABS
)
EKF_FLAGS_NO_POSITION: Final[int] = (
    apm.EKF_ATTITUDE | apm.EKF_VELOCITY_VERT | apm.EKF_POS_VERT_ABS | apm.EKF_CONST_POS_MODE
)

#: Parameters this double knows, with ArduPilot's names, units and defaults (SITL copter).
DEFAULT_PARAMS: Final[dict[str, float]] = {
    "GPS1_TYPE": 1.0,  # 1 = auto (the simulated u-blox); 14 = MAVLink (GPS_INPUT); reboot-required
    "GPS2_TYPE": 0.0,  # 0 = none
    "GPS_AUTO_SWITCH": 1.0,  # 1 = use the best
    "SIM_GPS1_ENABLE": 1.0,  # the simulated GNSS of GPS1 on/off (this version's name)
    "FS_EKF_ACTION": 1.0,  # 1 = LAND
    "ARMING_CHECK": 1.0,  # 1 = all; otherwise a bitmask, bit 3 (8) = GPS lock
    "GPS1_DELAY_MS": 0.0,  # 0 = the backend's lag (0.2 s for MAVLink); reboot-required
    "GPS2_DELAY_MS": 0.0,
    "WPNAV_SPEED": 1000.0,  # cm/s
    "WPNAV_SPEED_UP": 250.0,  # cm/s
    "WPNAV_SPEED_DN": 150.0,  # cm/s
    "WPNAV_ACCEL": 250.0,  # cm/s/s
    "WPNAV_RADIUS": 200.0,  # cm
    "LAND_SPEED": 50.0,  # cm/s, below 10 m
    "LAND_SPEED_HIGH": 0.0,  # cm/s, above 10 m; 0 = WPNAV_SPEED_DN
}
#: Height above which LAND descends at LAND_SPEED_HIGH, m (ArduCopter LAND_START_ALT 10 m).
LAND_HIGH_ALT_M: Final[float] = 10.0


# ------------------------------------------------------------------------------------------------------
# GPS instances and the position source


@dataclass
class MavGpsInstance:
    """One ``GPSn_TYPE`` = 14 instance: what it has been told by GPS_INPUT."""

    index: int
    health: GpsHealthMonitor = field(default_factory=GpsHealthMonitor)
    last_accepted_s: float | None = None
    detected_s: float | None = None
    ne_m: tuple[float, float] | None = None  # the last accepted position, local NED at home
    true_ne_at_fix_m: tuple[float, float] | None = None  # the truth when it arrived
    alt_amsl_m: float = 0.0
    rejected: dict[str, int] = field(default_factory=dict)

    def has_3d_fix(self, now_s: float) -> bool:
        """3D fix until 4 s after the last accepted GPS_INPUT (measured NO_FIX at 4.0-4.2 s)."""
        return self.last_accepted_s is not None and gps_loss_stage(now_s - self.last_accepted_s) is (
            GpsLossStage.OK
        )


def select_primary(auto_switch: int, current: int, has_fix: Sequence[bool]) -> int:
    """The GPS instance the EKF uses. ``GPS_AUTO_SWITCH`` 0: GPS1 always; 1 ("use best"): an instance
    with a 3D fix, the current one kept while it has one (the measured switch from the simulated GNSS
    to GPS2 = GPS_INPUT happened when GPS1 lost its fix, and was seamless)."""
    if auto_switch == 0:
        return 0
    if has_fix[current]:
        return current
    return next((i for i, ok in enumerate(has_fix) if ok), current)


# ------------------------------------------------------------------------------------------------------
# The emulator


@dataclass
class EmulatorOptions:
    home_lat_deg: float
    home_lon_deg: float
    home_alt_amsl_m: float
    home_heading_deg: float = 0.0
    ports: tuple[int, ...] = (14555,)
    params: dict[str, float] = field(default_factory=dict)
    ekf_origin_delay_s: float = EKF_ORIGIN_DELAY_S
    ekf_using_gps_delay_s: float = EKF_USING_GPS_DELAY_S
    system_time_offset_s: float = SYSTEM_TIME_OFFSET_S
    #: Upstream 4.7's ARMING_SKIPCHK instead of ARMING_CHECK.
    arming_skipchk: bool = False
    events_path: Path | None = None
    quiet: bool = False


class ArduPilotEmulator(PointMassVehicle, UdpEmulator):
    """The double itself; :meth:`run` serves until :meth:`stop` or SIGTERM/SIGINT."""

    def __init__(self, opts: EmulatorOptions) -> None:
        super().__init__(apm, opts.ports, quiet=opts.quiet)
        self.opts = opts
        self.origin = LocalTangentPlane(opts.home_lat_deg, opts.home_lon_deg, opts.home_alt_amsl_m)
        self.params: dict[str, float] = {**DEFAULT_PARAMS, **opts.params}
        if opts.arming_skipchk:
            del self.params["ARMING_CHECK"]
            self.params["ARMING_SKIPCHK"] = 0.0  # a mask of the checks skipped: none
        self._boot()

    # --- state ----------------------------------------------------------------------------------
    def _boot(self) -> None:
        """Power-on (and MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN): GPSn_TYPE as stored take effect."""
        self.boot_unix_s = time.time()
        self.gps_types = GpsTypeParams(
            at_boot={0: int(self.params["GPS1_TYPE"]), 1: int(self.params["GPS2_TYPE"])}
        )
        self.mav_gps = {
            i: MavGpsInstance(i) for i, t in self.gps_types.in_effect.items() if t == GPS_TYPE_MAV
        }
        #: GPSn_DELAY_MS are reboot-required too: the lag in effect, per instance, s.
        self.gps_lag_s = {i: gps_lag_s(self.params[f"GPS{i + 1}_DELAY_MS"]) for i in (0, 1)}
        self.sacc_glitch = SpeedAccuracyGlitch()
        self.truth_history: list[tuple[float, float, float]] = []  # (now_s, north_m, east_m)
        self._reset_vehicle(self.opts.home_heading_deg)  # truth, NED at home (down = -height)
        self.ahrs_err_rad = np.zeros(2)  # reported minus true roll and pitch (the AHRS's own error)
        self.est_err_ne = np.zeros(2)  # EKF horizontal position minus truth
        self.armed = False
        self.mode = MODE_STABILIZE
        self.target_ned: np.ndarray | None = None
        self.landing = False
        self.landed_since_s: float | None = None
        self.primary = 0
        self.first_fix_s: float | None = None
        self.origin_set = False
        self.using_gps = False
        self.last_pos_source_s: float | None = None  # last time the EKF had a GPS position
        self.loss_stage = GpsLossStage.OK
        self.failsafe_latched = False
        self.home_set = False
        self.mission: list[Any] = []
        self.mission_current = 0
        self._upload: dict[str, Any] | None = None
        self.sim_gps_announced = False
        self._unhealthy: dict[int, bool] = {}
        self._last_prearm_text_s = -1e9
        self._event("boot", gps_types=self.gps_types.in_effect)

    # --- GPS ------------------------------------------------------------------------------------
    def _sim_gps_fix(self) -> bool:
        return self.gps_types.in_effect.get(0, 0) not in (0, GPS_TYPE_MAV) and bool(
            self.params["SIM_GPS1_ENABLE"]
        )

    def _has_fix(self, now: float) -> list[bool]:
        fixes = []
        for i in (0, 1):
            if i in self.mav_gps:
                fixes.append(self.mav_gps[i].has_3d_fix(now))
            else:
                fixes.append(i == 0 and self._sim_gps_fix())
        return fixes

    def _on_gps_input(self, msg: Any, now: float) -> None:
        fields = msg.to_dict()
        reason = gps_input_rejection(fields, self.gps_types.in_effect)
        inst = self.mav_gps.get(int(msg.gps_id))
        if reason is not None:
            if inst is not None:
                inst.rejected[reason.split(" ")[0]] = inst.rejected.get(reason.split(" ")[0], 0) + 1
            return
        assert inst is not None  # gps_input_rejection checked the type
        inst.health.on_message(time.time())
        self._check_health(inst)
        inst.last_accepted_s = now
        inst.ne_m = tuple(
            self.origin.to_ned(np.array([msg.lat / 1e7]), np.array([msg.lon / 1e7]), np.array([msg.alt]))[
                0, :2
            ]
        )  # type: ignore[assignment]
        # the EKF takes it as measured the lag before it arrived: the truth then is its reference
        inst.true_ne_at_fix_m = self._truth_ne_at(now - self.gps_lag_s[inst.index])
        inst.alt_amsl_m = float(msg.alt)
        has_sacc = not int(msg.ignore_flags) & apm.GPS_INPUT_IGNORE_FLAG_SPEED_ACCURACY
        if self.primary == inst.index and has_sacc:
            was = self.sacc_glitch.glitching
            if self.sacc_glitch.update(now, float(msg.speed_accuracy)) != was:
                self._text(2, "GPS Glitch or Compass error" if not was else "Glitch cleared")
                self._event("gps_glitch", glitching=not was, speed_accuracy_peak=self.sacc_glitch.peak_m_s)
        if inst.detected_s is None:
            inst.detected_s = now

    def _truth_ne_at(self, t_s: float) -> tuple[float, float]:
        """The true north/east at boot time ``t_s`` (the nearest kept sample at or before it)."""
        best = (float(self.pos_ned[0]), float(self.pos_ned[1]))
        for t, n, e in reversed(self.truth_history):
            best = (n, e)
            if t <= t_s:
                break
        return best

    def _check_health(self, inst: MavGpsInstance) -> None:
        healthy = inst.health.healthy or inst.health.messages < 2
        if self._unhealthy.get(inst.index, False) == (not healthy):
            return
        self._unhealthy[inst.index] = not healthy
        self._event(
            "gps_health",
            instance=inst.index + 1,
            healthy=healthy,
            mean_interval_ms=inst.health.mean_interval_ms,
            delayed=inst.health.delayed_count,
        )

    def _update_gps(self, now: float) -> None:
        for inst in self.mav_gps.values():
            if inst.detected_s is not None and now - inst.detected_s >= GPS_DETECTED_DELAY_S:
                self._text(6, f"GPS {inst.index + 1}: detected MAV")
                inst.detected_s = math.inf  # announced
            for _ in inst.health.advance_to(time.time()):
                self._check_health(inst)
        if not self.sim_gps_announced and self.gps_types.in_effect.get(0, 0) not in (0, GPS_TYPE_MAV):
            self.sim_gps_announced = True
            self._text(6, "GPS 1: detected u-blox (simulated GNSS)")
        fixes = self._has_fix(now)
        new_primary = select_primary(int(self.params["GPS_AUTO_SWITCH"]), self.primary, fixes)
        if new_primary != self.primary:
            self._event("gps_primary", instance=new_primary + 1)
            self.primary = new_primary
        # the newest position the EKF could use: a MAVLink instance's last accepted GPS_INPUT (the loss
        # timeouts run from it), the simulated GNSS now while it has a fix
        usable = range(2) if int(self.params["GPS_AUTO_SWITCH"]) else (0,)
        newest = [
            (self.mav_gps[i].last_accepted_s if i in self.mav_gps else (now if fixes[i] else None))
            for i in usable
        ]
        times = [t for t in newest if t is not None]
        if times and (self.last_pos_source_s is None or max(times) > self.last_pos_source_s):
            self.last_pos_source_s = max(times)
            if self.first_fix_s is None:
                self.first_fix_s = now
        # the fused position follows the source (bias included; see the module docstring)
        source = self.mav_gps.get(self.primary)
        if fixes[self.primary]:
            if source is not None and source.ne_m is not None and source.true_ne_at_fix_m is not None:
                moved = self.pos_ned[:2] - np.array(source.true_ne_at_fix_m)
                self.est_err_ne = np.array(source.ne_m) + moved - self.pos_ned[:2]
            elif source is None:
                self.est_err_ne = np.zeros(2)  # the simulated GNSS is the truth
        # EKF start-up and loss of the position source
        if self.first_fix_s is not None:
            if not self.origin_set and now - self.first_fix_s >= self.opts.ekf_origin_delay_s:
                self.origin_set = True
                self._text(6, "EKF3 IMU0 origin set")
                self._set_home()
            if not self.using_gps and now - self.first_fix_s >= self.opts.ekf_using_gps_delay_s:
                self.using_gps = True
                self._text(6, "EKF3 IMU0 is using GPS")
        if self.using_gps and self.last_pos_source_s is not None:
            stage = gps_loss_stage(now - self.last_pos_source_s)
            if stage != self.loss_stage:
                if stage > self.loss_stage:
                    self._event(
                        "gps_loss", stage=stage.name, silence_s=round(now - self.last_pos_source_s, 3)
                    )
                else:
                    self._event("gps_recovered", from_stage=self.loss_stage.name)
                self.loss_stage = stage
            if (
                stage is GpsLossStage.EKF_FAILSAFE_LAND
                and self.armed
                and self.mode in POSITION_MODES
                and not self.failsafe_latched
                and int(self.params["FS_EKF_ACTION"]) != 0
            ):
                self.failsafe_latched = True
                self._set_mode(MODE_LAND)
                self._text(2, "EKF Failsafe: changed to LAND Mode")
                self._event("ekf_failsafe", mode="LAND")

    @property
    def ekf_position_ok(self) -> bool:
        return self.using_gps and self.loss_stage < GpsLossStage.EKF_POSITION_LOST

    def _set_home(self) -> None:
        self.home_set = True
        self._send_home()

    # --- modes, arming, commands ----------------------------------------------------------------
    def _set_mode(self, mode: int) -> bool:
        if mode not in MODE_NAMES:
            return False
        if mode in POSITION_MODES and not self.ekf_position_ok:
            return False
        self.mode = mode
        self.landing = mode == MODE_LAND
        if mode in (MODE_GUIDED, MODE_LOITER):
            self.target_ned = (
                self._est_ned().copy() if self.target_ned is None or not self.armed else self.target_ned
            )
        if mode == MODE_AUTO:
            if self.mission_current < 1:
                self.mission_current = 1
            self._start_mission_item()
        self._event("mode", mode=MODE_NAMES[mode])
        return True

    def prearm_failures(self, now: float) -> list[str]:
        """What stops arming (the texts ArduPilot sends)."""
        if "ARMING_SKIPCHK" in self.params:
            gps_checked = not int(self.params["ARMING_SKIPCHK"]) & 8
        else:
            checks = int(self.params["ARMING_CHECK"])
            gps_checked = checks == 1 or bool(checks & 8)
        fails: list[str] = []
        if gps_checked:
            fails = prearm_gps_failures(
                self.gps_types.in_effect, [i for i, g in self.mav_gps.items() if g.has_3d_fix(now)]
            )
            for i, g in sorted(self.mav_gps.items()):
                if g.last_accepted_s is not None and not g.health.healthy:
                    fails.append(f"PreArm: GPS {i + 1}: not healthy")
        if not self.ekf_position_ok:
            fails.append("PreArm: Need Position Estimate")
        if self.mode not in ARMABLE_MODES:
            fails.append("Arm: Mode not armable")
        return fails

    def _arm(self, arm: bool, now: float) -> int:
        if not arm:
            if self.pos_ned[2] < -0.1 and self.armed:
                return int(mavutil.mavlink.MAV_RESULT_FAILED)
            self.armed = False
            self._event("disarmed")
            return int(mavutil.mavlink.MAV_RESULT_ACCEPTED)
        if self.armed:
            return int(mavutil.mavlink.MAV_RESULT_ACCEPTED)
        fails = self.prearm_failures(now)
        if fails:
            for t in fails:
                self._text(3, t)
            self._event("arm_refused", reasons=fails)
            return int(mavutil.mavlink.MAV_RESULT_FAILED)
        self.armed = True
        self.failsafe_latched = False
        self._set_home()
        self._event("armed")
        return int(mavutil.mavlink.MAV_RESULT_ACCEPTED)

    def _on_command_long(self, msg: Any, now: float) -> None:
        cmd = int(msg.command)
        m = mavutil.mavlink
        result = int(m.MAV_RESULT_UNSUPPORTED)
        if cmd == m.MAV_CMD_COMPONENT_ARM_DISARM:
            result = self._arm(msg.param1 > 0.5, now)
        elif cmd == m.MAV_CMD_DO_SET_MODE:
            result = int(m.MAV_RESULT_ACCEPTED if self._set_mode(int(msg.param2)) else m.MAV_RESULT_FAILED)
        elif cmd == m.MAV_CMD_NAV_TAKEOFF:
            if self.armed and self.mode == MODE_GUIDED and self.pos_ned[2] > -0.5:
                est = self._est_ned()
                self.target_ned = np.array([est[0], est[1], -float(msg.param7)])
                self._event("takeoff", alt_m=float(msg.param7))
                result = int(m.MAV_RESULT_ACCEPTED)
            else:
                result = int(m.MAV_RESULT_FAILED)
        elif cmd == m.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN:
            if self.armed:
                result = int(m.MAV_RESULT_FAILED)
            else:
                self._ack(cmd, int(m.MAV_RESULT_ACCEPTED))
                self._event("reboot")
                self._boot()
                return
        elif cmd == m.MAV_CMD_MISSION_START:
            result = int(m.MAV_RESULT_ACCEPTED if self._set_mode(MODE_AUTO) else m.MAV_RESULT_FAILED)
        elif cmd == m.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = int(m.MAV_RESULT_ACCEPTED)  # rates are fixed in this double (documented)
        elif cmd in (m.MAV_CMD_REQUEST_MESSAGE, m.MAV_CMD_GET_HOME_POSITION):
            wanted = int(msg.param1) if cmd == m.MAV_CMD_REQUEST_MESSAGE else m.MAVLINK_MSG_ID_HOME_POSITION
            if wanted == m.MAVLINK_MSG_ID_HOME_POSITION and self.home_set:
                result = int(m.MAV_RESULT_ACCEPTED)
                self._ack(cmd, result)
                self._send_home()
                return
            # ArduPilot answers REQUEST_MESSAGE with any message it can stream
            # (GCS_MAVLINK::handle_command_request_message -> try_send_message); the two the daemon asks
            # for after a restart (F8) are modelled.
            answers = {
                m.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: self._send_position,
                m.MAVLINK_MSG_ID_EKF_STATUS_REPORT: self._send_ekf,
            }
            if wanted in answers:
                self._ack(cmd, int(m.MAV_RESULT_ACCEPTED))
                answers[wanted]()
                return
            result = int(m.MAV_RESULT_FAILED)
        self._ack(cmd, result)

    def _ack(self, cmd: int, result: int) -> None:
        self._mav.command_ack_send(cmd, result)

    # --- parameters -----------------------------------------------------------------------------
    def _send_param(self, name: str) -> None:
        names = sorted(self.params)
        self._mav.param_value_send(
            name.encode(),
            float(self.params[name]),
            mavutil.mavlink.MAV_PARAM_TYPE_REAL32,
            len(names),
            names.index(name),
        )

    def _on_timesync(self, msg: Any, now: float) -> None:
        """A request (``tc1`` 0) is answered with the boot time it arrived, ``ts1`` echoed."""
        if int(msg.tc1) == 0:
            self._mav.timesync_send(int(now * 1e9), int(msg.ts1))

    def _on_param_set(self, msg: Any) -> None:
        name = _param_id(msg.param_id)
        if name not in self.params:
            self._event("param_unknown", name=name)
            return  # ArduPilot ignores an unknown name (no PARAM_VALUE)
        self.params[name] = float(msg.param_value)
        if name in ("GPS1_TYPE", "GPS2_TYPE"):
            # reboot-required: stored, reported, not in effect (GpsTypeParams)
            self.gps_types = self.gps_types.set(int(name[3]) - 1, int(msg.param_value))
        self._event("param_set", name=name, value=float(msg.param_value))
        self._send_param(name)

    def _on_param_read(self, msg: Any) -> None:
        names = sorted(self.params)
        name = _param_id(msg.param_id)
        if int(msg.param_index) >= 0 and int(msg.param_index) < len(names):
            name = names[int(msg.param_index)]
        if name in self.params:
            self._send_param(name)

    def _send_all_params(self) -> None:
        for name in sorted(self.params):
            self._send_param(name)

    def _on_guided_target(self, msg: Any) -> None:
        """SET_POSITION_TARGET_GLOBAL_INT in GUIDED: fly there (altitude relative to home)."""
        if self.mode != MODE_GUIDED or not self.armed:
            return
        ne = self.origin.to_ned(
            np.array([msg.lat_int / 1e7]),
            np.array([msg.lon_int / 1e7]),
            np.array([self.opts.home_alt_amsl_m]),
        )[0]
        self.target_ned = np.array([ne[0], ne[1], -float(msg.alt)])

    # --- mission protocol -----------------------------------------------------------------------
    def _mission_uploaded(self, items: list[Any]) -> None:
        """ArduPilot's mission: seq 0 is home, so the mission starts at 1."""
        self.mission = items
        self.mission_current = 1 if len(self.mission) > 1 else 0

    def _on_mission_request_list(self, msg: Any) -> None:
        self._mav.mission_count_send(msg.get_srcSystem(), msg.get_srcComponent(), len(self.mission), 0)

    def _on_mission_request_int(self, msg: Any) -> None:
        seq = int(msg.seq)
        if 0 <= seq < len(self.mission):
            it = self.mission[seq]
            self._mav.mission_item_int_send(
                msg.get_srcSystem(),
                msg.get_srcComponent(),
                seq,
                it.frame,
                it.command,
                int(seq == self.mission_current),
                it.autocontinue,
                it.param1,
                it.param2,
                it.param3,
                it.param4,
                it.x,
                it.y,
                it.z,
                0,
            )

    def _start_mission_item(self) -> None:
        if self.mission_current >= len(self.mission):
            self.target_ned = self._est_ned().copy()  # end of mission: hold
            return
        it = self.mission[self.mission_current]
        m = mavutil.mavlink
        est = self._est_ned()
        if int(it.command) == m.MAV_CMD_NAV_LAND:
            self.landing = True
            if it.x or it.y:
                ne = self.origin.to_ned(
                    np.array([it.x / 1e7]), np.array([it.y / 1e7]), np.array([self.opts.home_alt_amsl_m])
                )[0]
                self.target_ned = np.array([ne[0], ne[1], 0.0])
            else:
                self.target_ned = np.array([est[0], est[1], 0.0])
        elif int(it.command) == m.MAV_CMD_NAV_TAKEOFF:
            self.target_ned = np.array([est[0], est[1], -float(it.z)])
        elif int(it.command) == m.MAV_CMD_NAV_WAYPOINT:
            ne = self.origin.to_ned(
                np.array([it.x / 1e7]), np.array([it.y / 1e7]), np.array([self.opts.home_alt_amsl_m])
            )[0]
            self.target_ned = np.array([ne[0], ne[1], -float(it.z)])
        self._mav.mission_current_send(self.mission_current)

    def _advance_mission(self) -> None:
        self._mav.mission_item_reached_send(self.mission_current)
        self._event("mission_item_reached", seq=self.mission_current)
        self.mission_current += 1
        self._start_mission_item()

    # --- physics --------------------------------------------------------------------------------
    def _est_ned(self) -> np.ndarray:
        return np.array(
            [self.pos_ned[0] + self.est_err_ne[0], self.pos_ned[1] + self.est_err_ne[1], self.pos_ned[2]]
        )

    def _step(self, dt: float, now: float) -> None:
        p = self.params
        on_ground = self.on_ground
        want_v = np.zeros(3)
        if self.armed and self.target_ned is not None and (self.mode in POSITION_MODES or self.landing):
            est = self._est_ned()
            d_ne = self.target_ned[:2] - est[:2]
            dist = float(np.hypot(*d_ne))
            accel = max(p["WPNAV_ACCEL"] / 100.0, 0.5)
            want_v[:2] = approach_velocity_ne(d_ne, p["WPNAV_SPEED"] / 100.0, accel)
            height = -self.pos_ned[2]
            if self.landing:
                if height > LAND_HIGH_ALT_M:
                    want_v[2] = (p["LAND_SPEED_HIGH"] or p["WPNAV_SPEED_DN"]) / 100.0
                else:
                    want_v[2] = p["LAND_SPEED"] / 100.0
                if self.mode == MODE_LAND:
                    want_v[:2] = 0.0
            else:
                dz = self.target_ned[2] - self.pos_ned[2]  # + = descend
                rate = (p["WPNAV_SPEED_DN"] if dz > 0 else p["WPNAV_SPEED_UP"]) / 100.0
                want_v[2] = math.copysign(min(rate, 1.5 * abs(dz)), dz)
            self._turn_toward(d_ne, dt)
            # reached?
            if (
                self.mode == MODE_AUTO
                and not self.landing
                and dist < p["WPNAV_RADIUS"] / 100.0
                and abs(self.target_ned[2] - self.pos_ned[2]) < 1.0
            ):
                self._advance_mission()
        swing = self._integrate(want_v, dt, max(p["WPNAV_ACCEL"] / 100.0, 0.5), 2.5)
        self.truth_history.append((now, float(self.pos_ned[0]), float(self.pos_ned[1])))
        while self.truth_history and self.truth_history[0][0] < now - TRUTH_HISTORY_S:
            self.truth_history.pop(0)
        # the AHRS's error: driven by the tilt's changes, decaying once they stop (AHRS_GAIN)
        self.ahrs_err_rad = self.ahrs_err_rad * (1.0 - min(1.0, dt / AHRS_DECAY_S)) + AHRS_GAIN * swing
        # landing complete: disarm after 1 s on the ground (ArduCopter's land detector, simplified)
        if self.armed and self.landing and self.pos_ned[2] >= -1e-3:
            if self.landed_since_s is None:
                self.landed_since_s = now
            elif now - self.landed_since_s > 1.0:
                self.armed = False
                self.landing = False
                self._event("landed_disarmed", mission_current=self.mission_current)
        elif not on_ground:
            self.landed_since_s = None

    # --- telemetry ------------------------------------------------------------------------------
    def _geodetic(self, ned: np.ndarray) -> tuple[float, float, float]:
        return geodetic(self.origin, ned)

    def _send_home(self) -> None:
        o = self.opts
        send_home_position(
            self._mav, o.home_lat_deg, o.home_lon_deg, o.home_alt_amsl_m, int(time.time() * 1e6)
        )

    def _send_fast(self) -> None:
        self._mav.attitude_send(
            self._boot_ms(),
            self.roll_rad + float(self.ahrs_err_rad[0]),
            self.pitch_rad + float(self.ahrs_err_rad[1]),
            _wrap_pi(self.yaw_rad),
            0,
            0,
            0,
        )
        send_highres_imu(self._mav, int(self.now_s() * 1e6), self._specific_force_body())

    def _send_position(self) -> None:
        est = self._est_ned()
        here = self._geodetic(est) if self.origin_set else (0.0, 0.0, 0.0)
        send_global_position_int(self._mav, self._boot_ms(), here, -float(est[2]), self.vel_ned, self.yaw_rad)

    def _send_simstate(self) -> None:
        """SIMSTATE: the truth, at the physics rate (the scorer renders and scores against it)."""
        tl, tn, _ta = self._geodetic(self.pos_ned)
        self._mav.simstate_send(
            self.roll_rad,
            self.pitch_rad,
            _wrap_pi(self.yaw_rad),
            *(float(x) for x in self.accel_ned),
            0.0,
            0.0,
            0.0,
            round(tl * 1e7),
            round(tn * 1e7),
        )

    def _send_gps(self, now: float) -> None:
        tl, tn, ta = self._geodetic(self.pos_ned)
        for i in (0, 1):
            inst = self.mav_gps.get(i)
            if inst is not None:
                fix = 3 if inst.has_3d_fix(now) else (1 if inst.last_accepted_s is not None else 0)
                if inst.ne_m is not None:
                    lat, lon, _ = self._geodetic(np.array([inst.ne_m[0], inst.ne_m[1], 0.0]))
                else:
                    lat = lon = 0.0
                alt = inst.alt_amsl_m
            elif i == 0 and self.gps_types.in_effect.get(0, 0) != 0:
                fix = 3 if self._sim_gps_fix() else 1
                lat, lon, alt = (tl, tn, ta) if fix == 3 else (0.0, 0.0, 0.0)
            else:
                continue
            args = (
                int(time.time() * 1e6),
                fix,
                round(lat * 1e7),
                round(lon * 1e7),
                round(alt * 1000),
                100,
                100,
                0,
                0,
                10 if fix == 3 else 0,
            )
            if i == self.primary:
                self._mav.gps_raw_int_send(*args)
            if i == 1:
                self._mav.gps2_raw_send(*args, 0, 0)

    def _send_slow(self, now: float) -> None:
        base = mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.armed:
            base |= mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        self._mav.heartbeat_send(
            mavutil.mavlink.MAV_TYPE_QUADROTOR,
            mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
            base,
            self.mode,
            mavutil.mavlink.MAV_STATE_ACTIVE if self.armed else mavutil.mavlink.MAV_STATE_STANDBY,
        )
        self._mav.system_time_send(int((time.time() + self.opts.system_time_offset_s) * 1e6), self._boot_ms())
        if self.mission:
            self._mav.mission_current_send(self.mission_current)

    def _send_ekf(self) -> None:
        flags = EKF_FLAGS_POSITION_OK if self.ekf_position_ok else EKF_FLAGS_NO_POSITION
        if not self.using_gps and self.origin_set:
            flags |= apm.EKF_POS_HORIZ_REL
        self._mav.ekf_status_report_send(flags, 0.1, 0.1, 0.1, 0.1, 0.0)

    # --- the loop (emulator_core.UdpEmulator) --------------------------------------------------
    def _before_physics(self, now: float) -> None:
        self._update_gps(now)

    def _send_tick(self, k: int, now: float) -> None:
        self._send_fast()
        self._send_simstate()
        if k % 5 == 0:
            self._send_position()
        if k % 10 == 0:
            self._send_gps(now)
        if k % 25 == 0:
            self._send_ekf()
            self._upload_retry()
        if k % 50 == 0:
            self._send_slow(now)
        if k % 100 == 0 and self.home_set:
            self._send_home()

    def _write_events(self) -> None:
        if self.opts.events_path is None:
            return
        summary = {
            "source": "ArduPilot emulator (a test double of measured ArduPilot copter behaviour, not the "
            "autopilot)",
            "events": self.events,
            "gps_input_rejected": {i + 1: g.rejected for i, g in self.mav_gps.items()},
        }
        self.opts.events_path.write_text(json.dumps(summary, indent=1))


def _h(fn: Callable[..., None], with_now: bool = False) -> Callable[[ArduPilotEmulator, Any, float], None]:
    if with_now:
        return fn
    return lambda self, msg, now: fn(self, msg)


ArduPilotEmulator._handlers = {
    "GPS_INPUT": _h(ArduPilotEmulator._on_gps_input, True),
    "TIMESYNC": _h(ArduPilotEmulator._on_timesync, True),
    "COMMAND_LONG": _h(ArduPilotEmulator._on_command_long, True),
    "SET_MODE": lambda self, msg, now: self._ack(
        mavutil.mavlink.MAV_CMD_DO_SET_MODE,
        int(
            mavutil.mavlink.MAV_RESULT_ACCEPTED
            if self._set_mode(int(msg.custom_mode))
            else mavutil.mavlink.MAV_RESULT_FAILED
        ),
    ),
    "PARAM_SET": _h(ArduPilotEmulator._on_param_set),
    "PARAM_REQUEST_READ": _h(ArduPilotEmulator._on_param_read),
    "PARAM_REQUEST_LIST": lambda self, msg, now: self._send_all_params(),
    "MISSION_COUNT": _h(ArduPilotEmulator._on_mission_count),
    "MISSION_ITEM_INT": _h(ArduPilotEmulator._on_mission_item),
    "MISSION_REQUEST_LIST": _h(ArduPilotEmulator._on_mission_request_list),
    "MISSION_REQUEST_INT": _h(ArduPilotEmulator._on_mission_request_int),
    "SET_POSITION_TARGET_GLOBAL_INT": lambda self, msg, now: self._on_guided_target(msg),
}


DESCRIPTION = (
    "ArduPilot copter EMULATOR (a test double of measured behaviour, not ArduPilot): MAVLink over UDP on "
    "loopback, one channel per --port."
)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m gps_denied_onboard.sitl.ap_emulator", description=DESCRIPTION
    )
    add_arguments(ap)
    return run_from_args(ap.parse_args(argv))


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The emulator's command line (``gdnav sitl emulate`` and ``python -m``)."""
    add_common_arguments(ap)
    ap.add_argument("--ekf-origin-delay-s", type=float, default=EKF_ORIGIN_DELAY_S)
    ap.add_argument("--ekf-using-gps-delay-s", type=float, default=EKF_USING_GPS_DELAY_S)
    ap.add_argument(
        "--system-time-offset-s",
        type=float,
        default=SYSTEM_TIME_OFFSET_S,
        help="SYSTEM_TIME's Unix time minus the host's, s (measured on SITL: -2.0)",
    )
    ap.add_argument(
        "--arming-skipchk", action="store_true", help="upstream 4.7's ARMING_SKIPCHK instead of ARMING_CHECK"
    )


def run_from_args(args: argparse.Namespace) -> int:
    """Serve until SIGTERM/SIGINT or ``--duration``; 2 on a bad argument."""
    try:
        lat, lon, alt, hdg = parse_home(args.home)
        params = parse_params(args.param, {*DEFAULT_PARAMS, "ARMING_SKIPCHK"})
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    emu = ArduPilotEmulator(
        EmulatorOptions(
            lat,
            lon,
            alt,
            hdg,
            ports=tuple(args.port or [14555]),
            params=params,
            ekf_origin_delay_s=args.ekf_origin_delay_s,
            ekf_using_gps_delay_s=args.ekf_using_gps_delay_s,
            system_time_offset_s=args.system_time_offset_s,
            arming_skipchk=args.arming_skipchk,
            events_path=args.events,
            quiet=args.quiet,
        )
    )
    return serve(emu, args.duration)


if __name__ == "__main__":
    sys.exit(main())
