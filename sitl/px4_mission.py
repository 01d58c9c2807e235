"""The mission driver for PX4 (SITL with the SIH simulator, or the project's PX4 emulator).

What a ground station does to fly the GNSS-off mission on PX4, in PX4's own terms (:class:`Px4MissionDriver`,
the same steps and timeline as :class:`~gps_denied_onboard.sitl.mission.MissionDriver` for ArduPilot):

1. waits for PX4's HEARTBEAT; reads ``EKF2_AGP0_ID`` and ``EKF2_AGP0_CTRL`` and refuses, naming the values
   to set before boot, when they do not let EKF2 fuse the daemon's GLOBAL_POSITION_SENSOR (both are read
   when EKF2 starts: set at run time they do nothing until a reboot, measured);
2. asks for HIL_STATE_QUATERNION (SIH's truth) at 50 Hz and the rest the daemon and the driver read
   (``MAV_CMD_SET_MESSAGE_INTERVAL``), sets the cruise speed (``MPC_XY_CRUISE``) and the take-off height
   (``MIS_TAKEOFF_ALT``);
3. uploads NAV_TAKEOFF, the waypoints and NAV_LAND (mission protocol; PX4's mission has no home item),
   arms, and switches to AUTO.MISSION (``MAV_CMD_DO_SET_MODE`` with PX4's main and sub mode): PX4 takes
   off on its GNSS;
4. at the take-off height, once the daemon's GLOBAL_POSITION_SENSOR has been arriving for
   ``DAEMON_STREAM_SETTLE_S``, switches SIH's GNSS off (``SIM_GPS_USED`` = 0, at run time: measured to
   work; ``failure gps off`` does nothing in SIH);
5. switches it back on (its value before) when the mission reaches NAV_LAND, and waits for the disarm.

PX4 sends integer parameters byte-wise in PARAM_VALUE's float and expects PARAM_SET the same way
(MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE): :meth:`Px4MissionDriver.get_param` and
:meth:`Px4MissionDriver.set_param` follow the type PX4 reports.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

from gps_denied_onboard.components.c8_mavlink.px4_params import bytewise_to_value, value_to_bytewise
from gps_denied_onboard.sitl.mission import MissionDriver, MissionError, _pid, mavutil

#: PX4's custom_mode: main mode in bits 16-23, sub mode in bits 24-31 (px4_custom_mode.h).
PX4_MAIN_AUTO = 4
PX4_SUB_AUTO_MISSION = 4
PX4_SUB_AUTO_LAND = 6
#: Message rates asked for, Hz: the truth for rendering and scoring, the daemon's prediction inputs,
#: the rest for the driver and the daemon's start-up.
PX4_STREAM_RATES_HZ: dict[int, float] = {
    mavutil.mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION: 50.0,
    mavutil.mavlink.MAVLINK_MSG_ID_ATTITUDE: 50.0,
    mavutil.mavlink.MAVLINK_MSG_ID_HIGHRES_IMU: 50.0,
    mavutil.mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 10.0,
    mavutil.mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: 5.0,
    mavutil.mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 2.0,
    mavutil.mavlink.MAVLINK_MSG_ID_MISSION_CURRENT: 2.0,
    mavutil.mavlink.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
}
#: The daemon's GLOBAL_POSITION_SENSOR must have been arriving this long before the GNSS goes off, s
#: (PX4 fused the first message 0.3-1.0 s after it arrived: measured).
DAEMON_STREAM_SETTLE_S = 3.0
#: A gap longer than this in the daemon's stream restarts the settling, s.
DAEMON_STREAM_MAX_GAP_S = 0.5
#: SIH's GNSS switch, and the value that switches it off.
SIM_GPS_USED = "SIM_GPS_USED"


def px4_mode(main: int, sub: int = 0) -> int:
    """PX4's HEARTBEAT.custom_mode for a main and sub mode."""
    return (main << 16) | (sub << 24)


def _decoded(msg: Any) -> float:
    """PARAM_VALUE's value, integers decoded byte-wise as PX4 sends them."""
    return bytewise_to_value(float(msg.param_value), int(msg.param_type))


@dataclass
class Px4MissionDriver(MissionDriver):
    """Flies the mission on PX4 (module docstring); ``stop()`` as the ArduPilot driver's."""

    sensor_id: int = 1
    _types: dict[str, int] = field(default_factory=dict, repr=False)
    _gnss_used: float = field(default=10.0, repr=False)

    # --- parameters (byte-wise integers) ----------------------------------------------------------
    def get_param(self, name: str, timeout_s: float = 3.0) -> float | None:
        for _ in range(3):
            sent = self.link.send(lambda mav: mav.param_request_read_send(*self._target(), name.encode(), -1))
            msg = self._wait(lambda m: _pid(m.param_id) == name, ["PARAM_VALUE"], timeout_s, since=sent)
            if msg is not None:
                self._types[name] = int(msg.param_type)
                return _decoded(msg)
        return None

    def set_param(self, name: str, value: float) -> None:
        if name not in self._types and self.get_param(name) is None:
            raise MissionError(f"PX4 has no parameter {name}")
        kind = self._types[name]
        for _ in range(3):
            self._check()
            sent = self.link.send(
                lambda mav: mav.param_set_send(
                    *self._target(), name.encode(), value_to_bytewise(value, kind), kind
                )
            )
            msg = self._wait(lambda m: _pid(m.param_id) == name, ["PARAM_VALUE"], 3.0, since=sent)
            if msg is not None and abs(_decoded(msg) - value) < 1e-3:
                self._event("param_set", name=name, value=value)
                return
        raise MissionError(f"PX4 did not confirm {name}={value:g} (no PARAM_VALUE with it)")

    def _gnss_on_message(self, mav: Any) -> None:
        kind = self._types.get(SIM_GPS_USED, mavutil.mavlink.MAV_PARAM_TYPE_INT32)
        mav.param_set_send(
            *self._target(), SIM_GPS_USED.encode(), value_to_bytewise(self._gnss_used, kind), kind
        )

    # --- the mission ----------------------------------------------------------------------------
    def prepare(self, timeout_s: float = 60.0) -> bool:
        """Wait for PX4 and check the parameters its EKF2 reads at boot (module docstring, step 1).
        Never reboots PX4: returns False."""
        hb = self._wait(lambda m: m.get_srcComponent() == 1, ["HEARTBEAT"], timeout_s)
        if hb is None:
            raise MissionError(f"no HEARTBEAT from the autopilot at {self.link.url} in {timeout_s:.0f} s")
        if int(hb.autopilot) != mavutil.mavlink.MAV_AUTOPILOT_PX4:
            raise MissionError(
                f"the autopilot at {self.link.url} is not PX4 (HEARTBEAT.autopilot {hb.autopilot})"
            )
        self._event("autopilot_heartbeat", system=self.link.ap_system, autopilot="PX4")
        agp_id, ctrl = self.get_param("EKF2_AGP0_ID"), self.get_param("EKF2_AGP0_CTRL")
        if agp_id is None or ctrl is None:
            raise MissionError(
                "PX4 has no EKF2_AGP0_ID/EKF2_AGP0_CTRL: GLOBAL_POSITION_SENSOR needs PX4 main after "
                "2026-02-27"
            )
        if int(agp_id) != self.sensor_id or not int(ctrl) & 1:
            raise MissionError(
                f"PX4's EKF2_AGP0_ID is {int(agp_id)} and EKF2_AGP0_CTRL {int(ctrl)}: EKF2 would not fuse "
                f"the daemon's GLOBAL_POSITION_SENSOR (id {self.sensor_id}). Both are read at boot: set "
                f"EKF2_AGP0_ID={self.sensor_id} and EKF2_AGP0_CTRL=1 and reboot PX4 (PX4 SITL: start it with "
                f"PX4_PARAM_EKF2_AGP0_ID={self.sensor_id} PX4_PARAM_EKF2_AGP0_CTRL=1 in its environment)"
            )
        used = self.get_param(SIM_GPS_USED)
        if used is None:
            raise MissionError(f"PX4 has no {SIM_GPS_USED}: the mission needs SIH's simulated GNSS")
        self._gnss_used = used if used > 0 else 10.0
        for msg_id, hz in PX4_STREAM_RATES_HZ.items():
            self.command(mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz, timeout_s=1.0)
        if used <= 0:
            self.set_param(SIM_GPS_USED, self._gnss_used)
        self.set_param("MPC_XY_CRUISE", float(self.plan.speed_m_s))
        self.set_param("MIS_TAKEOFF_ALT", float(self.plan.alt_rel_m))
        return False

    def wait_ready(self, timeout_s: float = 120.0) -> None:
        """PX4 has a global position and a home (its GNSS, before the flight)."""
        deadline = time.time() + timeout_s
        while time.time() < deadline:
            gp = self.link.last("GLOBAL_POSITION_INT")
            if gp is not None and (gp.lat, gp.lon) != (0, 0) and self.link.last("HOME_POSITION") is not None:
                self._event("ready", lat_deg=gp.lat / 1e7, lon_deg=gp.lon / 1e7)
                return
            self.command(
                mavutil.mavlink.MAV_CMD_REQUEST_MESSAGE, mavutil.mavlink.MAVLINK_MSG_ID_HOME_POSITION
            )
            self._sleep(0.5)
        raise MissionError(
            f"PX4 had no global position and home in {timeout_s:.0f} s; last texts: {self._texts()}"
        )

    def upload_mission(self) -> int:
        """NAV_TAKEOFF where the vehicle stands, the waypoints, NAV_LAND at the last one; returns the LAND
        item's seq."""
        gp = self.link.last("GLOBAL_POSITION_INT")
        here = (gp.lat / 1e7, gp.lon / 1e7) if gp is not None else self.plan.waypoints_lat_lon_deg[0]
        items: list[tuple[int, float, float, float]] = [
            (mavutil.mavlink.MAV_CMD_NAV_TAKEOFF, here[0], here[1], self.plan.alt_rel_m)
        ]
        for lat, lon in self.plan.waypoints_lat_lon_deg:
            items.append((mavutil.mavlink.MAV_CMD_NAV_WAYPOINT, lat, lon, self.plan.alt_rel_m))
        last = self.plan.waypoints_lat_lon_deg[-1]
        items.append((mavutil.mavlink.MAV_CMD_NAV_LAND, last[0], last[1], 0.0))
        return self._upload(items)

    def arm(self, timeout_s: float = 90.0) -> None:
        """Arm; PX4 refuses until its checks pass ("Preflight Fail: heading estimate not stable" early on)."""
        deadline = time.time() + timeout_s
        while time.time() < deadline:
            if (
                self.command(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
                == mavutil.mavlink.MAV_RESULT_ACCEPTED
            ):
                self._event("armed")
                return
            self._sleep(2.0)
        raise MissionError(f"PX4 refused to arm for {timeout_s:.0f} s: {self._texts()}")

    def _set_px4_mode(self, main: int, sub: int) -> None:
        for _ in range(5):
            res = self.command(
                mavutil.mavlink.MAV_CMD_DO_SET_MODE,
                mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                main,
                sub,
            )
            if res == mavutil.mavlink.MAV_RESULT_ACCEPTED:
                self._event("mode", main=main, sub=sub)
                return
            self._sleep(1.0)
        raise MissionError(f"PX4 refused mode {main}.{sub}; last texts: {self._texts()}")

    def _landed(self) -> bool:
        """Disarmed and on the ground by PX4's own landed state (EXTENDED_SYS_STATE); its relative
        altitude can read metres after the landing once the GNSS is back ("GPS Vertical Pos Drift too
        high", measured), so it decides only where PX4 sends no landed state."""
        if self.armed():
            return False
        ext = self.link.last("EXTENDED_SYS_STATE")
        if ext is not None:
            return int(ext.landed_state) == mavutil.mavlink.MAV_LANDED_STATE_ON_GROUND
        return self.rel_alt_m() <= 0.5

    def _daemon_streaming_for(self) -> float:
        """How long the daemon's GLOBAL_POSITION_SENSOR has been arriving without a gap, s."""
        times = [m.recv_time_unix_s for m in self.link.received[-200:] if m.type == "GLOBAL_POSITION_SENSOR"]
        if not times or time.time() - times[-1] > DAEMON_STREAM_MAX_GAP_S:
            return 0.0
        start = times[-1]
        for earlier in reversed(times[:-1]):
            if start - earlier > DAEMON_STREAM_MAX_GAP_S:
                break
            start = earlier
        return times[-1] - start

    def fly(self, *, gnss_off: bool = True, timeout_s: float = 600.0) -> dict[str, Any]:
        """The whole mission after :meth:`prepare` and :meth:`wait_ready`. Returns the timeline."""
        land_seq = self.upload_mission()
        self.arm()
        self._set_px4_mode(PX4_MAIN_AUTO, PX4_SUB_AUTO_MISSION)
        self._event("takeoff", alt_rel_m=self.plan.alt_rel_m)
        t_end = time.time() + timeout_s
        while self.rel_alt_m() < 0.95 * self.plan.alt_rel_m:
            if time.time() > t_end:
                raise MissionError(f"take-off did not reach the altitude: {self._texts()}")
            self._sleep(0.2)
        self._event("takeoff_done", rel_alt_m=round(self.rel_alt_m(), 1))
        while gnss_off and self._daemon_streaming_for() < DAEMON_STREAM_SETTLE_S:
            if time.time() > t_end:
                raise MissionError(
                    f"the daemon's GLOBAL_POSITION_SENSOR never settled: GNSS left on; {self._texts()}"
                )
            self._sleep(0.2)
        if gnss_off:
            self._gnss_off = True
            self.set_param(SIM_GPS_USED, 0)
            self._event("gnss_off")
        gnss_back = not gnss_off
        land_mode = px4_mode(PX4_MAIN_AUTO, PX4_SUB_AUTO_LAND)
        while not self._landed():
            if time.time() > t_end:
                raise MissionError(f"the mission did not finish in {timeout_s:.0f} s: {self._texts()}")
            cur = self.link.last("MISSION_CURRENT")
            hb = self._heartbeat()
            if not gnss_back and (
                (cur is not None and int(cur.seq) >= land_seq)
                or (hb is not None and hb.custom_mode == land_mode)
            ):
                self.set_param(SIM_GPS_USED, self._gnss_used)
                self._gnss_off = False
                self._event("gnss_on", rel_alt_m=round(self.rel_alt_m(), 1))
                gnss_back = True
            self._sleep(0.2)
        self._event("landed")
        self._done = True
        return {"log": self.log, "land_seq": land_seq}


def is_px4(heartbeat: Any) -> bool:
    """Whether a HEARTBEAT is PX4's."""
    return heartbeat is not None and int(heartbeat.autopilot) == mavutil.mavlink.MAV_AUTOPILOT_PX4
