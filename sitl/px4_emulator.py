"""A PX4 multicopter EMULATOR for CI: a test double of PX4's MAVLink side (SITL with SIH), not PX4.

No PX4 binary is available in CI. CI flies ``gdnav sitl run --autopilot URL`` against this double
(``gdnav sitl emulate --px4``); the same command flies a real PX4 SITL (docs/px4.md). Nothing here is
PX4 code and no report may present what it does as what PX4 does. Each rule names its source: "measured"
is PX4 main of 2026-03-02 run as SITL with SIH on these machines (../shared/DESIGN.md, "What a real PX4
does with an external position", and the issue-34 measurements); "source" names the PX4 file the fact was
read in; "assumption" is neither, and says so.

What EKF2 does with GLOBAL_POSITION_SENSOR is ``px4_rules.Px4AuxGlobalPosition``, reused here, never
restated. The vehicle is ``emulator_core.PointMassVehicle``, the ArduPilot emulator's.

Speaks MAVLink 2 (common dialect) as system 1 component 1, on each ``--port`` (UDP on loopback, one channel
each, answering the last address that sent it a datagram):

- out, streamed by default (measured on the onboard link): HEARTBEAT, ATTITUDE (50 Hz here, 100 measured),
  HIGHRES_IMU 50 Hz, GLOBAL_POSITION_INT 10 Hz (only while EKF2 has a valid global position), HOME_POSITION,
  EXTENDED_SYS_STATE, MISSION_CURRENT, SYSTEM_TIME, TIMESYNC requests 10 Hz, GPS_RAW_INT, STATUSTEXT;
  HIL_STATE_QUATERNION (SIH's truth) only once asked for (MAV_CMD_SET_MESSAGE_INTERVAL), with time_usec 0;
  GPS_GLOBAL_ORIGIN once the origin is set;
- in: GLOBAL_POSITION_SENSOR, TIMESYNC, PARAM_REQUEST_READ / PARAM_REQUEST_LIST / PARAM_SET (integers
  byte-wise), COMMAND_LONG (arm/disarm, DO_SET_MODE, SET_MESSAGE_INTERVAL, REQUEST_MESSAGE), the mission
  upload protocol. GPS_INPUT has no handler (it is counted as unhandled, nothing else).

The rules in full, each with its source: docs/px4.md, "The PX4 emulator (CI)".
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mav

from gps_denied_onboard.components.c8_mavlink.px4_params import bytewise_to_value, value_to_bytewise
from gps_denied_onboard.geo import LocalTangentPlane
from gps_denied_onboard.sitl.autopilot import send_home_position
from gps_denied_onboard.sitl.emulator_core import (
    GRAVITY_M_S2,
    PointMassVehicle,
    UdpEmulator,
    add_common_arguments,
    approach_velocity_ne,
    geodetic,
    param_id,
    parse_home,
    parse_params,
    send_global_position_int,
    send_highres_imu,
    serve,
    wrap_pi,
)
from gps_denied_onboard.sitl.px4_mission import (
    PX4_MAIN_AUTO,
    PX4_SUB_AUTO_LAND,
    PX4_SUB_AUTO_MISSION,
    px4_mode,
)
from gps_denied_onboard.sitl.px4_rules import POSITION_TIMEOUT_S, Px4AuxGlobalPosition

#: PX4's other sub modes of AUTO used here (source: ``src/modules/commander/px4_custom_mode.h``).
PX4_SUB_AUTO_TAKEOFF: Final[int] = 2
PX4_SUB_AUTO_LOITER: Final[int] = 3
INT32: Final[int] = mav.MAV_PARAM_TYPE_INT32
REAL32: Final[int] = mav.MAV_PARAM_TYPE_REAL32
#: Parameters this double knows: PX4's names, types and defaults. Sources: EKF2_AGP{i}_* in
#: ``src/modules/ekf2/params_aux_global_position.yaml`` (4 instances; DELAY ms, reboot-required);
#: SIM_GPS_USED in ``src/modules/simulation/sensor_gps_sim/parameters.c``; MPC_* in
#: ``src/modules/mc_pos_control/multicopter_*_params.c``; MIS_TAKEOFF_ALT, NAV_ACC_RAD, NAV_MC_ALT_RAD in
#: ``src/modules/navigator``; COM_DISARM_LAND in ``src/modules/commander``.
DEFAULT_PARAMS: Final[dict[str, tuple[float, int]]] = {
    **{f"EKF2_AGP{i}_ID": (0.0, INT32) for i in range(4)},
    **{f"EKF2_AGP{i}_CTRL": (0.0, INT32) for i in range(4)},
    "EKF2_AGP0_DELAY": (0.0, REAL32),
    "SIM_GPS_USED": (10.0, INT32),
    "MPC_XY_CRUISE": (5.0, REAL32),
    "MPC_ACC_HOR": (3.0, REAL32),
    "MPC_Z_V_AUTO_UP": (3.0, REAL32),
    "MPC_Z_V_AUTO_DN": (1.5, REAL32),
    "MPC_ACC_DOWN_MAX": (3.0, REAL32),
    "MPC_LAND_SPEED": (0.7, REAL32),
    "MPC_LAND_ALT1": (10.0, REAL32),
    "MPC_LAND_ALT2": (5.0, REAL32),
    "MIS_TAKEOFF_ALT": (2.5, REAL32),
    "NAV_ACC_RAD": (10.0, REAL32),
    "NAV_MC_ALT_RAD": (0.8, REAL32),
    "COM_DISARM_LAND": (2.0, REAL32),
}
#: SIH's GNSS has a 3D fix while SIM_GPS_USED is at least this (source:
#: ``src/modules/simulation/sensor_gps_sim/SensorGpsSim.cpp``); set at run time it takes effect at once
#: (measured).
SIM_GPS_MIN_SATS_FOR_FIX: Final[int] = 4
#: PX4 SITL's boot clock against the host's: its mean rate, and the amplitude and period of its swing
#: (``Px4Emulator.boot_s``).
BOOT_CLOCK_RATE: Final[float] = 0.985
BOOT_CLOCK_SWING: Final[float] = 0.004
BOOT_CLOCK_SWING_PERIOD_S: Final[float] = 23.0
#: Arming is refused this long after boot: "Preflight Fail: heading estimate not stable" (measured that
#: PX4 refused early after boot; the duration is an assumption).
HEADING_SETTLE_S: Final[float] = 3.0
#: EKF2's position with GNSS: the truth plus a first-order Gauss-Markov error of this sigma and time
#: constant (an assumption: measured only "truth plus a little noise").
GNSS_NOISE_SIGMA_M: Final[float] = 0.2
GNSS_NOISE_TAU_S: Final[float] = 5.0
#: Height at which the land detector says "Takeoff detected", m (an assumption).
TAKEOFF_DETECT_HEIGHT_M: Final[float] = 1.0
#: EXTENDED_SYS_STATE.landed_state values (MAV_LANDED_STATE).
LANDED_ON_GROUND, LANDED_IN_AIR, LANDED_TAKEOFF, LANDED_LANDING = 1, 2, 3, 4
M = mav
#: Default rates of the onboard link, Hz (measured counts; ATTITUDE is capped at the physics rate here,
#: GPS_RAW_INT's rate is an assumption: PX4 sends it on each GNSS update, source
#: ``src/modules/mavlink/mavlink_main.cpp``). HIL_STATE_QUATERNION is off until asked for (measured).
DEFAULT_RATES_HZ: Final[dict[int, float]] = {
    M.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    M.MAVLINK_MSG_ID_ATTITUDE: 50.0,
    M.MAVLINK_MSG_ID_HIGHRES_IMU: 50.0,
    M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 10.0,
    M.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 5.0,
    M.MAVLINK_MSG_ID_MISSION_CURRENT: 1.0,
    M.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
    M.MAVLINK_MSG_ID_TIMESYNC: 10.0,
    M.MAVLINK_MSG_ID_GPS_RAW_INT: 5.0,
    M.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN: 1.0,
    M.MAVLINK_MSG_ID_HIL_STATE_QUATERNION: 0.0,
}


#: The UDP port when none is given (clear of PX4 SITL's 14540/14550/14580/18570).
DEFAULT_PORT: Final[int] = 14560


@dataclass
class Px4EmulatorOptions:
    home_lat_deg: float
    home_lon_deg: float
    home_alt_amsl_m: float
    home_heading_deg: float = 0.0
    ports: tuple[int, ...] = (DEFAULT_PORT,)
    #: Parameters as stored before boot (PX4 SITL: ``PX4_PARAM_<NAME>=value`` in its environment).
    params: dict[str, float] = field(default_factory=dict)
    events_path: Path | None = None
    quiet: bool = False
    seed: int = 0


class Px4Emulator(PointMassVehicle, UdpEmulator):
    """The double (module docstring); :meth:`run` serves until :meth:`stop` or SIGTERM/SIGINT."""

    def __init__(self, opts: Px4EmulatorOptions) -> None:
        super().__init__(mav, opts.ports, quiet=opts.quiet)
        self.opts = opts
        self.home_ltp = LocalTangentPlane(opts.home_lat_deg, opts.home_lon_deg, opts.home_alt_amsl_m)
        unknown = sorted(set(opts.params) - set(DEFAULT_PARAMS))
        if unknown:
            raise ValueError(f"unknown parameter(s) {unknown}; known: {', '.join(sorted(DEFAULT_PARAMS))}")
        self.params: dict[str, float] = {n: v for n, (v, _t) in DEFAULT_PARAMS.items()}
        self.params.update(opts.params)
        self._rng = np.random.default_rng(opts.seed)
        self._boot()

    # --- state ----------------------------------------------------------------------------------
    def _boot(self) -> None:
        """Power-on: EKF2 reads its EKF2_AGP{i}_ID/CTRL now (Px4AuxGlobalPosition)."""
        self.boot_unix_s = time.time()
        self.agp = Px4AuxGlobalPosition({n: v for n, v in self.params.items() if n.startswith("EKF2_AGP")})
        self._reset_vehicle(self.opts.home_heading_deg)
        self.est_err_ne = np.zeros(2)  # EKF2's horizontal position minus the truth
        self._gnss_noise_ne = np.zeros(2)
        self.last_gnss_s: float | None = None  # the last tick EKF2 fused SIH's GNSS
        self.gnss_origin: tuple[float, float, float] | None = None
        self._agp_ref_ne = np.zeros(2)  # the truth where the vehicle-fixed frame of the AGP double is pinned
        self.agp_received = 0
        self.agp_received_at_0_0 = 0
        self.agp_outcomes: dict[str, int] = {}
        self.armed = False
        self.main_mode, self.sub_mode = PX4_MAIN_AUTO, PX4_SUB_AUTO_LOITER
        self.home: tuple[float, float, float] | None = None
        self.origin_announced = False
        self.failsafe = False
        self.had_position = False
        self.target_ned: np.ndarray | None = None
        self.mission: list[Any] = []
        self.mission_current = 0
        self.mission_active = False
        self.landing = False
        self.takeoff_detected = False
        self.landed_since_s: float | None = None
        self.rates_hz = dict(DEFAULT_RATES_HZ)
        self._next_due: dict[int, float] = {}
        self._upload = None
        self._event("boot", params={n: self.params[n] for n in sorted(self.params)})

    def gnss_fix(self) -> bool:
        """SIH's GNSS has a 3D fix (SIM_GPS_USED, source)."""
        return int(self.params["SIM_GPS_USED"]) >= SIM_GPS_MIN_SATS_FOR_FIX

    def ekf_origin(self) -> tuple[float, float, float] | None:
        """EKF2's global origin: from the first GNSS fix, else from the first GLOBAL_POSITION_SENSOR the
        AGP double took (Px4AuxGlobalPosition.origin); None without either (measured: no origin without
        GNSS and without a fused message)."""
        if self.gnss_origin is not None:
            return self.gnss_origin
        o = self.agp.origin
        return None if o is None else (o.lat_deg, o.lon_deg, o.alt_amsl_m)

    def position_valid(self, now: float) -> bool:
        """EKF2 has a valid global position: an origin, and GNSS fused or the AGP double's position valid
        within POSITION_TIMEOUT_S (measured 5.3 s for GLOBAL_POSITION_SENSOR; applying the same timeout
        to the GNSS is an assumption)."""
        if self.ekf_origin() is None:
            return False
        gnss = self.last_gnss_s is not None and now - self.last_gnss_s < POSITION_TIMEOUT_S
        return gnss or self.agp.position_valid(now)

    def _truth_ne(self) -> np.ndarray:
        return np.array(self.pos_ned[:2], dtype=float)

    def _est_ned(self) -> np.ndarray:
        return np.array([*(self.pos_ned[:2] + self.est_err_ne), self.pos_ned[2]])

    def _geodetic(self, ned: np.ndarray) -> tuple[float, float, float]:
        return geodetic(self.home_ltp, ned)

    # --- EKF2 -----------------------------------------------------------------------------------
    def _on_global_position_sensor(self, msg: Any, now: float) -> None:
        """GLOBAL_POSITION_SENSOR, stamped on arrival, time fields and flags not read (measured, source):
        Px4AuxGlobalPosition decides. EKF2 predicts with its IMU between messages; this double's IMU is
        the truth, so each message is handed to the double in a frame that moves with the vehicle (the
        truth's displacement since the origin was set is taken off), where its rules apply as they are:
        a position it holds is then the estimate's error, and the vehicle flies on what it is told."""
        fields = msg.to_dict()
        self.agp_received += 1
        if (int(fields["lat"]), int(fields["lon"])) == (0, 0):
            self.agp_received_at_0_0 += 1
        truth = self._truth_ne()
        if self.agp.origin is None:
            self._agp_ref_ne = truth  # the first message is taken as it is: it sets the origin
        ne = self.home_ltp.to_ned(fields["lat"] / 1e7, fields["lon"] / 1e7, self.opts.home_alt_amsl_m)
        shifted = ne[:2] - (truth - self._agp_ref_ne)
        lat, lon, _ = self._geodetic(np.array([shifted[0], shifted[1], 0.0]))
        had_origin = self.agp.origin is not None
        outcome = self.agp.receive({**fields, "lat": round(lat * 1e7), "lon": round(lon * 1e7)}, now)
        self.agp_outcomes[outcome] = self.agp_outcomes.get(outcome, 0) + 1
        o = self.agp.origin
        if not had_origin and o is not None:  # the message as sent: the shift is 0 for the first one
            self._event("agp_origin", lat_deg=o.lat_deg, lon_deg=o.lon_deg, alt_amsl_m=o.alt_amsl_m)
        if outcome == "reset":
            self._event("agp_reset", resets=self.agp.resets)
        if outcome == "ignored" and self.agp.ignored == 1:
            self._event("agp_ignored", id=int(fields["id"]), params=self.agp.params)

    def _update_estimate(self, now: float, dt: float) -> None:
        """EKF2's horizontal position: with GNSS, the truth plus a little noise; without it, what the AGP
        double holds (module docstring of :meth:`_on_global_position_sensor`); with neither, the error of
        the last one held (dead reckoning)."""
        if self.gnss_fix():
            a = min(1.0, dt / GNSS_NOISE_TAU_S)
            kick = self._rng.normal(0.0, GNSS_NOISE_SIGMA_M * math.sqrt(2.0 * a), 2)
            self._gnss_noise_ne = (1.0 - a) * self._gnss_noise_ne + kick
            self.est_err_ne = self._gnss_noise_ne.copy()
            self.last_gnss_s = now
            if self.gnss_origin is None:
                o = self.opts
                self.gnss_origin = (o.home_lat_deg, o.home_lon_deg, o.home_alt_amsl_m)
                self._event("gnss_origin")
            return
        pos = self.agp.global_position() if self.agp.position_valid(now) else None
        if pos is not None:
            ne = self.home_ltp.to_ned(pos[0], pos[1], self.opts.home_alt_amsl_m)
            self.est_err_ne = ne[:2] - self._agp_ref_ne

    def _before_physics(self, now: float) -> None:
        self._update_estimate(now, 1.0 / 50.0)
        valid = self.position_valid(now)
        if valid and self.home is None and self.on_ground:
            self._set_home()
        if valid and not self.origin_announced:
            self.origin_announced = True
            self._send_origin()
        if valid:
            self.had_position = True
        elif self.armed and not self.on_ground and self.had_position and not self.failsafe:
            # measured: failsafe (descend) 5.3 s after the last message, "Failsafe activated"
            self.failsafe = True
            self._text(mav.MAV_SEVERITY_CRITICAL, "Failsafe activated")
            self._event("failsafe", action="descend", agp=self._agp_summary())
            self.main_mode, self.sub_mode = PX4_MAIN_AUTO, PX4_SUB_AUTO_LAND  # DESCEND's custom mode
            self.landing = True
            self.mission_active = False
            self.target_ned = None

    def _set_home(self) -> None:
        """Home: where EKF2 puts the vehicle, when its position is first valid on the ground and at arming
        (source: ``src/modules/commander/HomePosition.cpp``)."""
        lat, lon, _ = self._geodetic(self._est_ned())
        self.home = (lat, lon, self.opts.home_alt_amsl_m)
        self._event("home", lat_deg=lat, lon_deg=lon)

    # --- modes, arming, commands ----------------------------------------------------------------
    def _arm(self, arm: bool, now: float) -> int:
        if not arm:
            if not self.on_ground:
                return int(mav.MAV_RESULT_DENIED)
            self._disarm("external command")
            return int(mav.MAV_RESULT_ACCEPTED)
        if self.armed:
            return int(mav.MAV_RESULT_ACCEPTED)
        reason = None
        if now < HEADING_SETTLE_S:
            reason = "Preflight Fail: heading estimate not stable"  # measured, early after boot
        elif not self.position_valid(now):
            # source: mission mode needs a global position (ModeUtil/mode_requirements.cpp); the text is
            # an assumption
            reason = "Preflight Fail: no global position"
        if reason is not None:
            self._text(mav.MAV_SEVERITY_CRITICAL, reason)
            self._event("arm_refused", reason=reason)
            return int(mav.MAV_RESULT_TEMPORARILY_REJECTED)  # source: Commander.cpp
        self.armed = True
        self.failsafe = False
        self.takeoff_detected = False
        self._set_home()
        self._text(mav.MAV_SEVERITY_INFO, "Armed by external command")  # measured
        self._event("armed")
        return int(mav.MAV_RESULT_ACCEPTED)

    def _disarm(self, why: str) -> None:
        self.armed = False
        self.landing = False
        self.mission_active = False
        self._text(mav.MAV_SEVERITY_INFO, f"Disarmed by {why}")  # measured: "Disarmed by landing"
        self._event("disarmed", why=why)

    def _set_mode(self, main: int, sub: int, now: float) -> int:
        """DO_SET_MODE to AUTO.{MISSION,LOITER,LAND}; the first two need a valid global position (source:
        ``ModeUtil/mode_requirements.cpp``). AUTO.MISSION starts the mission (texts measured)."""
        if main != PX4_MAIN_AUTO or sub not in (PX4_SUB_AUTO_MISSION, PX4_SUB_AUTO_LOITER, PX4_SUB_AUTO_LAND):
            return int(mav.MAV_RESULT_DENIED)
        if sub != PX4_SUB_AUTO_LAND and not self.position_valid(now):
            return int(mav.MAV_RESULT_DENIED)
        self.main_mode, self.sub_mode = main, sub
        self.mission_active = sub == PX4_SUB_AUTO_MISSION
        self.landing = sub == PX4_SUB_AUTO_LAND
        est = self._est_ned()
        self.target_ned = est.copy() if sub == PX4_SUB_AUTO_LOITER else None
        if self.mission_active:
            self._text(mav.MAV_SEVERITY_INFO, "Executing Mission")
            if self.on_ground and self.mission:
                first = self.mission[0]
                if int(first.command) == mav.MAV_CMD_NAV_TAKEOFF:
                    self._text(mav.MAV_SEVERITY_INFO, f"Climb to {float(first.z):.1f} meters above home")
            self._start_item()
        self._event("mode", main=main, sub=sub)
        return int(mav.MAV_RESULT_ACCEPTED)

    def _on_command_long(self, msg: Any, now: float) -> None:
        cmd = int(msg.command)
        result = int(mav.MAV_RESULT_UNSUPPORTED)
        if cmd == mav.MAV_CMD_COMPONENT_ARM_DISARM:
            result = self._arm(msg.param1 > 0.5, now)
        elif cmd == mav.MAV_CMD_DO_SET_MODE:
            result = self._set_mode(round(msg.param2), round(msg.param3), now)
        elif cmd == mav.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = self._set_interval(round(msg.param1), float(msg.param2))
        elif cmd == mav.MAV_CMD_REQUEST_MESSAGE:
            # source: mavlink_receiver.cpp handle_request_message_command: ACCEPTED once sent, else DENIED
            sent = self._send_message(round(msg.param1), now)
            result = int(mav.MAV_RESULT_ACCEPTED if sent else mav.MAV_RESULT_DENIED)
        self._mav.command_ack_send(cmd, result)

    def _set_interval(self, msg_id: int, interval_us: float) -> int:
        """MAV_CMD_SET_MESSAGE_INTERVAL: -1 stops the stream, 0 gives its default, else that interval
        (ACK 0, measured); a message this double cannot send is FAILED."""
        if msg_id not in DEFAULT_RATES_HZ:
            return int(mav.MAV_RESULT_FAILED)
        if interval_us < 0:
            self.rates_hz[msg_id] = 0.0
        elif interval_us == 0:
            self.rates_hz[msg_id] = DEFAULT_RATES_HZ[msg_id]
        else:
            self.rates_hz[msg_id] = 1e6 / interval_us
        self._next_due.pop(msg_id, None)
        return int(mav.MAV_RESULT_ACCEPTED)

    # --- parameters (integers byte-wise: measured) -----------------------------------------------
    def _param_value(self, name: str) -> float:
        if name.startswith("EKF2_AGP"):
            return float(self.agp.params.get(name, self.params[name]))  # a bound id slot is saved there
        return self.params[name]

    def _send_param(self, name: str) -> None:
        names = sorted(self.params)
        kind = DEFAULT_PARAMS[name][1]
        wire = value_to_bytewise(self._param_value(name), kind)
        self._mav.param_value_send(name.encode(), wire, kind, len(names), names.index(name))

    def _on_param_read(self, msg: Any, now: float) -> None:
        names = sorted(self.params)
        name = param_id(msg.param_id)
        if 0 <= int(msg.param_index) < len(names):
            name = names[int(msg.param_index)]
        if name in self.params:
            self._send_param(name)

    def _on_param_list(self, msg: Any, now: float) -> None:
        for name in sorted(self.params):
            self._send_param(name)

    def _on_param_set(self, msg: Any, now: float) -> None:
        """PARAM_SET, integers byte-wise (measured). EKF2_AGP{i}_ID/CTRL are saved and used from the next
        boot (Px4AuxGlobalPosition.set_param); SIM_GPS_USED takes effect at once (measured)."""
        name = param_id(msg.param_id)
        if name not in self.params:
            self._event("param_unknown", name=name)
            return
        value = float(msg.param_value)
        # the float's bytes are the integer's, whatever param_type says
        value = bytewise_to_value(value, DEFAULT_PARAMS[name][1])
        self.params[name] = value
        if name.startswith("EKF2_AGP"):
            self.agp.set_param(name, value)
        self._event("param_set", name=name, value=value)
        self._send_param(name)

    # --- the mission ----------------------------------------------------------------------------
    def _mission_uploaded(self, items: list[Any]) -> None:
        """PX4's mission has no home item: seq 0 is the first real item (measured)."""
        self.mission = items
        self.mission_current = 0

    def _item_ned(self, it: Any, alt_rel_m: float) -> np.ndarray:
        ne = self.home_ltp.to_ned(it.x / 1e7, it.y / 1e7, self.opts.home_alt_amsl_m)
        return np.array([ne[0], ne[1], -alt_rel_m])

    def _start_item(self) -> None:
        if self.mission_current >= len(self.mission):
            self.target_ned = self._est_ned()
            return
        it = self.mission[self.mission_current]
        est = self._est_ned()
        if int(it.command) == mav.MAV_CMD_NAV_TAKEOFF:
            self.target_ned = np.array([est[0], est[1], -float(it.z)])
        elif int(it.command) == mav.MAV_CMD_NAV_LAND:
            self.target_ned = self._item_ned(it, -float(est[2]))  # there at its height, then down
        else:
            self.target_ned = self._item_ned(it, float(it.z))
        self._mav.mission_current_send(self.mission_current, len(self.mission), 0, 0)

    def _advance(self) -> None:
        self._mav.mission_item_reached_send(self.mission_current)
        self._event("mission_item_reached", seq=self.mission_current)
        self.mission_current += 1
        self._start_item()

    # --- physics --------------------------------------------------------------------------------
    def _descent_rate(self) -> float:
        """Landing descent (source: ``mc_pos_control``): MPC_Z_V_AUTO_DN above MPC_LAND_ALT1, MPC_LAND_SPEED
        below MPC_LAND_ALT2, linear between."""
        p, h = self.params, -float(self.pos_ned[2])
        hi, lo = p["MPC_LAND_ALT1"], p["MPC_LAND_ALT2"]
        if h >= hi:
            return p["MPC_Z_V_AUTO_DN"]
        if h <= lo:
            return p["MPC_LAND_SPEED"]
        w = (h - lo) / max(hi - lo, 1e-6)
        return p["MPC_LAND_SPEED"] + w * (p["MPC_Z_V_AUTO_DN"] - p["MPC_LAND_SPEED"])

    def _step(self, dt: float, now: float) -> None:
        p = self.params
        want_v = np.zeros(3)
        if self.armed and (self.target_ned is not None or self.landing):
            est = self._est_ned()
            d_ne = np.zeros(2) if self.target_ned is None else self.target_ned[:2] - est[:2]
            dist = float(np.hypot(*d_ne))
            want_v[:2] = approach_velocity_ne(d_ne, p["MPC_XY_CRUISE"], p["MPC_ACC_HOR"])
            if self.landing or (self._current_is_land() and dist < p["NAV_ACC_RAD"]):
                want_v[2] = self._descent_rate()
                self.landing = True
            elif self.target_ned is not None:
                dz = float(self.target_ned[2] - self.pos_ned[2])  # + = descend
                rate = p["MPC_Z_V_AUTO_DN"] if dz > 0 else p["MPC_Z_V_AUTO_UP"]
                want_v[2] = math.copysign(min(rate, 1.5 * abs(dz)), dz)
            self._turn_toward(d_ne, dt)
            if (
                self.mission_active
                and not self.landing
                and self.target_ned is not None
                and self.mission_current < len(self.mission)
                and dist < max(p["NAV_ACC_RAD"], 0.5)
                and abs(self.target_ned[2] - self.pos_ned[2]) < p["NAV_MC_ALT_RAD"]
            ):
                self._advance()
        self._integrate(want_v, dt, p["MPC_ACC_HOR"], p["MPC_ACC_DOWN_MAX"])
        self._land_detector(now)

    def _current_is_land(self) -> bool:
        return (
            self.mission_active
            and self.mission_current < len(self.mission)
            and int(self.mission[self.mission_current].command) == mav.MAV_CMD_NAV_LAND
        )

    def _land_detector(self, now: float) -> None:
        """Texts measured; disarm COM_DISARM_LAND s after landing (source: commander's parameter)."""
        if not self.armed:
            return
        height = -float(self.pos_ned[2])
        if not self.takeoff_detected and height > TAKEOFF_DETECT_HEIGHT_M:
            self.takeoff_detected = True
            self._text(mav.MAV_SEVERITY_INFO, "Takeoff detected")
        if not (self.takeoff_detected and self.landing and self.on_ground):
            return
        if self.landed_since_s is None:
            self.landed_since_s = now
            self._text(mav.MAV_SEVERITY_INFO, "Landing detected")
            if self._current_is_land():
                self._text(mav.MAV_SEVERITY_INFO, "Mission finished, landed")
        elif now - self.landed_since_s >= self.params["COM_DISARM_LAND"]:
            self.landed_since_s = None
            self._event("landed_disarmed", mission_current=self.mission_current, failsafe=self.failsafe)
            self._disarm("landing")

    # --- telemetry ------------------------------------------------------------------------------
    def _landed_state(self) -> int:
        """EXTENDED_SYS_STATE.landed_state from the land detector's view."""
        if not self.armed or (self.on_ground and (self.landing or self.target_ned is None)):
            return LANDED_ON_GROUND
        if not self.takeoff_detected:
            return LANDED_TAKEOFF
        return LANDED_LANDING if self.landing else LANDED_IN_AIR

    def _send_heartbeat(self) -> None:
        """autopilot 12 (PX4), type 2 (quadrotor), custom mode enabled, armed flag; custom_mode =
        main << 16 | sub << 24 (measured)."""
        base = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.armed:
            base |= mav.MAV_MODE_FLAG_SAFETY_ARMED
        state = mav.MAV_STATE_ACTIVE if self.armed else mav.MAV_STATE_STANDBY
        if self.failsafe:
            state = mav.MAV_STATE_CRITICAL
        self._mav.heartbeat_send(
            mav.MAV_TYPE_QUADROTOR,
            mav.MAV_AUTOPILOT_PX4,
            base,
            px4_mode(self.main_mode, self.sub_mode),
            state,
        )

    def _send_attitude(self) -> None:
        """ATTITUDE: the truth (nothing was measured of PX4's attitude error in SIH)."""
        self._mav.attitude_send(
            self._boot_ms(), self.roll_rad, self.pitch_rad, wrap_pi(self.yaw_rad), 0, 0, 0
        )

    def _send_imu(self) -> None:
        send_highres_imu(self._mav, int(self.boot_s() * 1e6), self._specific_force_body())

    def _send_global_position(self, now: float) -> bool:
        """GLOBAL_POSITION_INT only while EKF2 has a valid global position (measured)."""
        if not self.position_valid(now):
            return False
        est = self._est_ned()
        send_global_position_int(
            self._mav, self._boot_ms(), self._geodetic(est), -float(est[2]), self.vel_ned, self.yaw_rad
        )
        return True

    def _send_home(self) -> bool:
        if self.home is None:
            return False
        send_home_position(self._mav, *self.home, int(time.time() * 1e6))
        return True

    def _send_origin(self) -> bool:
        """GPS_GLOBAL_ORIGIN once EKF2 has an origin (source: streams/GPS_GLOBAL_ORIGIN.hpp; measured: not
        answered without one)."""
        origin = self.ekf_origin()
        if origin is None:
            return False
        lat, lon, alt = origin
        self._mav.gps_global_origin_send(
            round(lat * 1e7), round(lon * 1e7), round(alt * 1000), int(time.time() * 1e6)
        )
        return True

    def _send_hil_state(self) -> None:
        """HIL_STATE_QUATERNION: SIH's truth; time_usec 0, lat/lon degE7, alt mm AMSL, quaternion w,x,y,z
        (measured)."""
        lat, lon, alt = self._geodetic(self.pos_ned)
        cr, sr = math.cos(self.roll_rad / 2), math.sin(self.roll_rad / 2)
        cp, sp = math.cos(self.pitch_rad / 2), math.sin(self.pitch_rad / 2)
        cy, sy = math.cos(self.yaw_rad / 2), math.sin(self.yaw_rad / 2)
        q = [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
        f_mg = self._specific_force_body() / GRAVITY_M_S2 * 1000.0
        v = self.vel_ned * 100.0
        self._mav.hil_state_quaternion_send(
            0, q, 0.0, 0.0, 0.0, round(lat * 1e7), round(lon * 1e7), round(alt * 1000),
            *(int(np.clip(x, -32768, 32767)) for x in v), 0, 0,
            *(int(np.clip(x, -32768, 32767)) for x in f_mg),
        )  # fmt: skip

    def _send_gps_raw(self) -> None:
        """GPS_RAW_INT: SIH's GNSS, fix 3 with SIM_GPS_USED satellites, else fix 0 (source:
        SensorGpsSim.cpp)."""
        fix = self.gnss_fix()
        lat, lon, alt = self._geodetic(self.pos_ned) if fix else (0.0, 0.0, 0.0)
        self._mav.gps_raw_int_send(
            int(time.time() * 1e6),
            3 if fix else 0,
            round(lat * 1e7),
            round(lon * 1e7),
            round(alt * 1000),
            70 if fix else 65535,
            100 if fix else 65535,
            round(float(np.hypot(*self.vel_ned[:2])) * 100),
            65535,
            int(self.params["SIM_GPS_USED"]) if fix else 0,
        )

    def _send_message(self, msg_id: int, now: float) -> bool:
        """Send one message of ``msg_id`` now; False when this double has none to send."""
        m = mav
        if msg_id == m.MAVLINK_MSG_ID_HEARTBEAT:
            self._send_heartbeat()
        elif msg_id == m.MAVLINK_MSG_ID_ATTITUDE:
            self._send_attitude()
        elif msg_id == m.MAVLINK_MSG_ID_HIGHRES_IMU:
            self._send_imu()
        elif msg_id == m.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            return self._send_global_position(now)
        elif msg_id == m.MAVLINK_MSG_ID_HOME_POSITION:
            return self._send_home()
        elif msg_id == m.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
            return self._send_origin()
        elif msg_id == m.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            self._mav.extended_sys_state_send(0, self._landed_state())
        elif msg_id == m.MAVLINK_MSG_ID_MISSION_CURRENT:
            if not self.mission:
                return False
            self._mav.mission_current_send(self.mission_current, len(self.mission), 0, 0)
        elif msg_id == m.MAVLINK_MSG_ID_SYSTEM_TIME:
            self._mav.system_time_send(int(time.time() * 1e6), self._boot_ms())  # the host's clock: measured
        elif msg_id == m.MAVLINK_MSG_ID_TIMESYNC:
            self._mav.timesync_send(0, int(self.boot_s() * 1e9))  # PX4's own request, boot time ns (measured)
        elif msg_id == m.MAVLINK_MSG_ID_GPS_RAW_INT:
            self._send_gps_raw()
        elif msg_id == m.MAVLINK_MSG_ID_HIL_STATE_QUATERNION:
            self._send_hil_state()
        else:
            return False
        return True

    def _on_timesync(self, msg: Any, now: float) -> None:
        """A request (``tc1`` 0) is answered with PX4's boot time in ns, ``ts1`` echoed (measured)."""
        if int(msg.tc1) == 0:
            self._mav.timesync_send(int(self.boot_s() * 1e9), int(msg.ts1))

    def boot_s(self) -> float:
        """PX4 SITL's boot clock runs slower than its host, unevenly: SIH steps the simulation in
        lockstep, behind the wall clock when the machine is busy (measured on PX4 main's SITL against
        the host: 0.984-0.986 of its rate over 15 s nearly idle, 0.979 over 60 s with two busy loops,
        losing 0.07-0.4 s per 10 s). Here it runs at ``BOOT_CLOCK_RATE`` with a swing of
        ``BOOT_CLOCK_SWING`` over ``BOOT_CLOCK_SWING_PERIOD_S`` (the swing's shape is an assumption);
        the vehicle itself moves with the host's clock, as the daemon sees it through the camera."""
        t = self.now_s()
        w = 2.0 * math.pi / BOOT_CLOCK_SWING_PERIOD_S
        return BOOT_CLOCK_RATE * t + BOOT_CLOCK_SWING * (1.0 - math.cos(w * t)) / w

    def _send_tick(self, k: int, now: float) -> None:
        wall = time.time()
        # ATTITUDE first: the relay times HIL_STATE_QUATERNION (time_usec 0) by the ATTITUDE before it
        order = sorted(self.rates_hz, key=lambda i: i != mav.MAVLINK_MSG_ID_ATTITUDE)
        for msg_id in order:
            hz = self.rates_hz[msg_id]
            if hz <= 0:
                continue
            due = self._next_due.get(msg_id, wall)
            if wall + 1e-4 < due:
                continue
            self._next_due[msg_id] = max(due + 1.0 / hz, wall)
            if msg_id == mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
                continue  # sent when it changes, not as a stream (source)
            self._send_message(msg_id, now)
        if k % 25 == 0:
            self._upload_retry()

    # --- events ---------------------------------------------------------------------------------
    def _agp_summary(self) -> dict[str, Any]:
        o = self.agp.origin
        return {
            "received": self.agp_received,
            "received_at_0_0": self.agp_received_at_0_0,
            "outcomes": dict(self.agp_outcomes),
            "origin": None
            if o is None
            else {"lat_deg": o.lat_deg, "lon_deg": o.lon_deg, "alt_amsl_m": o.alt_amsl_m},
        }

    def summary(self) -> dict[str, Any]:
        """What the events file holds."""
        origin = self.ekf_origin()
        return {
            "source": "PX4 emulator (a test double of measured PX4 behaviour, not the autopilot)",
            "events": self.events,
            "global_position_sensor": self._agp_summary(),
            "ekf_origin": None if origin is None else list(origin),
            "unhandled": dict(self.unhandled),
            "params": {n: self._param_value(n) for n in sorted(self.params)},
        }

    def _write_events(self) -> None:
        if self.opts.events_path is not None:
            self.opts.events_path.write_text(json.dumps(self.summary(), indent=1))


Px4Emulator._handlers = {
    "GLOBAL_POSITION_SENSOR": Px4Emulator._on_global_position_sensor,
    "TIMESYNC": Px4Emulator._on_timesync,
    "COMMAND_LONG": Px4Emulator._on_command_long,
    "PARAM_SET": Px4Emulator._on_param_set,
    "PARAM_REQUEST_READ": Px4Emulator._on_param_read,
    "PARAM_REQUEST_LIST": Px4Emulator._on_param_list,
    "MISSION_COUNT": lambda self, msg, now: self._on_mission_count(msg),
    "MISSION_ITEM_INT": lambda self, msg, now: self._on_mission_item(msg),
}

DESCRIPTION = (
    "PX4 multicopter EMULATOR (a test double of measured PX4 SITL/SIH behaviour, not PX4): MAVLink over "
    "UDP on loopback, one channel per --port."
)


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The PX4 emulator's own options, beside ``emulator_core.add_common_arguments``."""
    ap.add_argument("--seed", type=int, default=0, help="PX4 emulator: the seed of its GNSS noise")


def run_from_args(args: argparse.Namespace) -> int:
    """Serve until SIGTERM/SIGINT or ``--duration``; 2 on a bad argument."""
    try:
        lat, lon, alt, hdg = parse_home(args.home)
        params = parse_params(args.param, DEFAULT_PARAMS)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    emu = Px4Emulator(
        Px4EmulatorOptions(
            lat,
            lon,
            alt,
            hdg,
            ports=tuple(args.port or [DEFAULT_PORT]),
            params=params,
            events_path=args.events,
            quiet=args.quiet,
            seed=args.seed,
        )
    )
    return serve(emu, args.duration, autopilot="px4")


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m gps_denied_onboard.sitl.px4_emulator", description=DESCRIPTION
    )
    add_common_arguments(ap)
    add_arguments(ap)
    return run_from_args(ap.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
