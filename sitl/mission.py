"""The link to an external autopilot (ArduPilot SITL, or the project's emulator) and the mission driver.

:class:`AutopilotRelay` holds one MAVLink connection to the autopilot (any pymavlink URL:
``tcp:127.0.0.1:5762``, ``udpin:127.0.0.1:14550``, ``udpout:127.0.0.1:14555``) and one UDP link to the
daemon, and forwards every message both ways at once, on its own thread: the daemon talks to the
autopilot through it as through a serial port. It records what the daemon sent (with receive times,
for scoring), the autopilot's true pose (SIMSTATE, else SIM_STATE, else its own GLOBAL_POSITION_INT +
ATTITUDE) and its state, and cuts the link in the scenario's ``link_drops`` windows.

:class:`MissionDriver` flies the GNSS-off mission a ground station would: set the parameters, wait for
the EKF and for GPS 2 (GPS_INPUT) to have a 3D fix, upload the waypoints (AUTO), arm in GUIDED, take
off, switch the simulated GNSS off (``SIM_GPS1_ENABLE=0``; GPS 2 = GPS_INPUT, ``GPS2_TYPE=14`` from boot,
``GPS_AUTO_SWITCH=1``: the measured working in-flight switch), fly the waypoints in AUTO, switch the
GNSS back on at the last waypoint, land, and wait for the disarm.
"""

from __future__ import annotations

import bisect
import contextlib
import math
import os
import select
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil

from gps_denied_onboard.clock import AutopilotClock
from gps_denied_onboard.constants import MAV_COMPONENT_ID
from gps_denied_onboard.sitl.autopilot import ReceivedMessage

#: Copter custom modes used by the driver.
MODE_AUTO = 3
MODE_GUIDED = 4
MODE_LAND = 9
#: Message rates asked for with MAV_CMD_SET_MESSAGE_INTERVAL, Hz: the truth (SIMSTATE, SIM_STATE) for
#: rendering and scoring, ATTITUDE/HIGHRES_IMU for the daemon's prediction, the rest for the driver.
STREAM_RATES_HZ: dict[int, float] = {
    mavutil.mavlink.MAVLINK_MSG_ID_SIMSTATE: 50.0,
    mavutil.mavlink.MAVLINK_MSG_ID_SIM_STATE: 50.0,
    mavutil.mavlink.MAVLINK_MSG_ID_ATTITUDE: 50.0,
    mavutil.mavlink.MAVLINK_MSG_ID_HIGHRES_IMU: 50.0,
    mavutil.mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 10.0,
    mavutil.mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: 5.0,
    mavutil.mavlink.MAVLINK_MSG_ID_GPS2_RAW: 5.0,
    mavutil.mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT: 2.0,
    mavutil.mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
    mavutil.mavlink.MAVLINK_MSG_ID_MISSION_CURRENT: 2.0,
    mavutil.mavlink.MAVLINK_MSG_ID_HOME_POSITION: 0.5,  # the daemon's starting prior on the ground
}
#: The autopilot's true pose, by preference: ArduPilot SITL's SIMSTATE, SIM_STATE, PX4 SIH's
#: HIL_STATE_QUATERNION (streamed on the onboard link when asked for: measured on PX4 main of 2026-03-02).
TRUTH_TYPES: tuple[str, ...] = ("SIMSTATE", "SIM_STATE", "HIL_STATE_QUATERNION")
#: ARMING_CHECK: every check (bits 1..18) but bit 3, "GPS lock".
ARMING_CHECK_ALL_BUT_GPS = (1 << 19) - 2 - 8
#: ARMING_SKIPCHK (upstream 4.7, PR #31568, which replaced ARMING_CHECK): a mask of the checks skipped.
ARMING_SKIPCHK_GPS = 8
#: GPS2_DELAY_MS for GPS_INPUT: the daemon propagates each estimate to its send time, so the lag the EKF
#: must allow for is the link's (ms on a serial or loopback link). 0 would mean the MAVLink backend's
#: default of 200 ms (GPS_Backend.h ``get_lag``), with which EKF3 put the position a speed x 0.2 s ahead.
GPS_INPUT_DELAY_MS = 10
#: Reboot-required parameters the mission needs (GPS2_TYPE = 14: GPS 2 is GPS_INPUT).
BOOT_PARAMS: dict[str, float] = {"GPS2_TYPE": 14, "GPS2_DELAY_MS": GPS_INPUT_DELAY_MS}
#: The relay's TIMESYNC requests, s.
TIMESYNC_INTERVAL_S = 1.0
#: This driver's MAVLink identity: a ground station.
GCS_SYSTEM_ID = 255
GCS_COMPONENT_ID = 190


class MissionError(RuntimeError):
    """The autopilot did not do what the mission needs (the message says what and what it said)."""


class MissionStopped(MissionError):
    """``MissionDriver.stop()`` was called (the runner got SIGTERM or Ctrl-C): the driver's thread ends."""


@dataclass(frozen=True)
class TruePose:
    t_unix_s: float
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float | None
    roll_rad: float
    pitch_rad: float
    yaw_rad: float


@dataclass
class AutopilotRelay:
    """See the module docstring. ``link_down(t_unix_s)`` says when the daemon's link is cut."""

    url: str
    daemon_port: int
    link_down: Callable[[float], bool] = lambda _t: False
    received: list[ReceivedMessage] = field(default_factory=list)  # from the daemon
    statustext: list[tuple[float, str]] = field(default_factory=list)  # from the autopilot
    truth_source: str | None = None

    def __post_init__(self) -> None:
        self.ap = mavutil.mavlink_connection(
            self.url, source_system=GCS_SYSTEM_ID, source_component=GCS_COMPONENT_ID, autoreconnect=True
        )
        self.daemon = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{self.daemon_port}",
            source_system=GCS_SYSTEM_ID,
            source_component=GCS_COMPONENT_ID,
        )
        self.truth: list[TruePose] = []
        #: Per truth sample: its receive time minus the sample time it was given, s (how far the
        #: autopilot's boot-time mapping puts it before it arrived).
        self.truth_stamp_lead_s: list[float] = []
        #: The autopilot's GLOBAL_POSITION_INT: (host time, lat_deg, lon_deg).
        self.autopilot_track: list[tuple[float, float, float]] = []
        self.latest: dict[str, Any] = {}
        self.ap_system: int | None = None
        self._cond = threading.Condition()
        self._write_lock = threading.Lock()
        self._stop = threading.Event()
        self._waits_interrupted = False
        self._att: Any = None
        #: The autopilot's boot time on this host's clock (the frames are stamped on it).
        self.clock = AutopilotClock()
        self._events: list[tuple[float, Any]] = []
        self._thread = threading.Thread(target=self._run, name="autopilot_relay", daemon=True)
        self._thread.start()
        self._hb = threading.Thread(target=self._heartbeat, name="gcs_heartbeat", daemon=True)
        self._hb.start()

    # --- the relay thread -----------------------------------------------------------------------
    def _fds(self) -> list[Any]:
        fds = []
        for c in (self.ap, self.daemon):
            with contextlib.suppress(Exception):
                fds.append(c.port.fileno())
        return fds

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                select.select(self._fds(), [], [], 0.01)
            except (OSError, ValueError):
                time.sleep(0.01)
            self._drain_autopilot()
            self._drain_daemon()

    def _drain_autopilot(self) -> None:
        while True:
            try:
                msg = self.ap.recv_msg()
            except (OSError, ConnectionError):
                return
            if msg is None:
                return
            now = time.time()
            mtype = msg.get_type()
            if mtype == "BAD_DATA":
                continue
            src = msg.get_srcSystem()
            if mtype == "HEARTBEAT" and msg.get_srcComponent() == 1 and self.ap_system is None:
                self.ap_system = src
            if src != (self.ap_system or src) or msg.get_srcComponent() == MAV_COMPONENT_ID:
                continue
            if not self.link_down(now):
                with contextlib.suppress(OSError):
                    self.daemon.write(msg.get_msgbuf())
            self._note(msg, mtype, now)

    def _sample_time(self, now: float) -> float:
        """When a SIMSTATE/SIM_STATE sample was taken (they carry no time), on this host's clock: the boot
        time of the ATTITUDE just before it, mapped with the relay's TIMESYNC (``clock.AutopilotClock``).
        The receive time would carry every stall of this process into the truth's timeline; the
        autopilot's own Unix time (SYSTEM_TIME) is not this host's (SITL's ran 2.0 s behind)."""
        offset = self.clock.offset_usec(now * 1e6)
        if self._att is None or offset is None:
            return now
        return min(now, self._att.time_boot_ms / 1000.0 + offset / 1e6)

    def _note(self, msg: Any, mtype: str, now: float) -> None:
        boot_ms = getattr(msg, "time_boot_ms", None)
        if boot_ms is not None and boot_ms > 0:
            self.clock.note_stamp(int(boot_ms) * 1000, int(now * 1e6))
        if mtype == "TIMESYNC" and int(msg.tc1) != 0:
            self.clock.answer(int(msg.tc1), int(msg.ts1), int(now * 1e6))
        if mtype in TRUTH_TYPES:
            received = now
            now = self._sample_time(now)
            self.truth_stamp_lead_s.append(received - now)
            if self.truth and now <= self.truth[-1].t_unix_s:
                return
            if mtype == "SIMSTATE":
                pose = TruePose(now, msg.lat / 1e7, msg.lng / 1e7, None, msg.roll, msg.pitch, msg.yaw)
            elif mtype == "SIM_STATE":
                pose = TruePose(now, msg.lat, msg.lon, float(msg.alt), msg.roll, msg.pitch, msg.yaw)
            else:  # PX4 SIH's HIL_STATE_QUATERNION (its time_usec is 0: measured)
                roll, pitch, yaw = _euler_from_quaternion(msg.attitude_quaternion)
                pose = TruePose(now, msg.lat / 1e7, msg.lon / 1e7, msg.alt / 1000.0, roll, pitch, yaw)
            if self.truth_source in (None, mtype):
                self.truth_source = mtype
                self.truth.append(pose)
        elif mtype == "ATTITUDE":
            self._att = msg
        if mtype == "GLOBAL_POSITION_INT" and (msg.lat, msg.lon) != (0, 0):
            # the autopilot's own estimate, on this host's clock, to score against the truth
            offset = self.clock.offset_usec(now * 1e6)
            t = msg.time_boot_ms / 1000.0 + offset / 1e6 if offset is not None else now
            self.autopilot_track.append((min(t, now), msg.lat / 1e7, msg.lon / 1e7))
        elif mtype == "GLOBAL_POSITION_INT" and self.truth_source in (None, "GLOBAL_POSITION_INT"):
            if (
                self._att is not None
                and not any(k in self.latest for k in TRUTH_TYPES)
                and (now - self.latest.get("_first_t", now) > 3.0)
            ):
                self.truth_source = "GLOBAL_POSITION_INT"
                self.truth.append(
                    TruePose(
                        now,
                        msg.lat / 1e7,
                        msg.lon / 1e7,
                        msg.alt / 1000.0,
                        self._att.roll,
                        self._att.pitch,
                        self._att.yaw,
                    )
                )
        elif mtype == "STATUSTEXT":
            self.statustext.append((now, str(msg.text)))
        with self._cond:
            self.latest.setdefault("_first_t", now)
            self.latest[mtype] = msg
            self.latest.setdefault("_seq", 0)
            self.latest["_seq"] += 1
            self._events.append((now, msg))
            self._cond.notify_all()

    def _drain_daemon(self) -> None:
        while True:
            try:
                msg = self.daemon.recv_msg()
            except OSError:
                return
            if msg is None:
                return
            now = time.time()
            if msg.get_type() == "BAD_DATA" or self.link_down(now):
                continue
            if msg.get_srcComponent() == MAV_COMPONENT_ID:
                self.received.append(ReceivedMessage(now, msg.get_type(), msg.to_dict()))
            with self._write_lock, contextlib.suppress(OSError):
                self.ap.write(msg.get_msgbuf())

    def _heartbeat(self) -> None:
        while not self._stop.is_set():
            self.send(
                lambda mav: mav.heartbeat_send(
                    mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0
                )
            )
            self.send(self._timesync_request)
            self._stop.wait(TIMESYNC_INTERVAL_S)

    def _timesync_request(self, mav: Any) -> None:
        mav.timesync_send(0, self.clock.request(int(time.time() * 1e6)))

    # --- the driver's side ----------------------------------------------------------------------
    def send(self, fn: Callable[[Any], None]) -> int:
        """Send one message of this ground station's: ``fn(mav)`` calls a ``*_send`` of pymavlink's.

        Returns how many messages had been received when it was sent: :meth:`wait` from there sees the
        reply even when it arrives before the wait begins (the emulator answers within a millisecond,
        and a COMMAND_ACK missed that way read as a refused take-off)."""
        with self._cond:
            mark = len(self._events)
        with self._write_lock, contextlib.suppress(OSError):
            fn(self.ap.mav)
        return mark

    def wait(
        self, pred: Callable[[Any], bool], types: Sequence[str], timeout_s: float, *, since: int | None = None
    ) -> Any:
        """The first message of ``types`` received after ``since`` (a :meth:`send`'s return; default: now)
        for which ``pred`` holds, or None at the timeout or once :meth:`interrupt_waits` was called."""
        deadline = time.time() + timeout_s
        with self._cond:
            start = len(self._events) if since is None else since
            while not self._waits_interrupted:
                for _, msg in self._events[start:]:
                    if msg.get_type() in types and pred(msg):
                        return msg
                start = len(self._events)
                left = deadline - time.time()
                if left <= 0:
                    return None
                self._cond.wait(min(left, 0.2))
            return None

    def interrupt_waits(self) -> None:
        """End every :meth:`wait`, now and later, with None (the mission is being stopped)."""
        with self._cond:
            self._waits_interrupted = True
            self._cond.notify_all()

    def last(self, mtype: str) -> Any:
        with self._cond:
            return self.latest.get(mtype)

    def truth_at(self, t_unix_s: float) -> TruePose | None:
        """The true pose at ``t_unix_s``, interpolated between the samples (None before the first)."""
        truth = self.truth
        if not truth:
            return None
        times = [p.t_unix_s for p in truth]
        i = bisect.bisect_left(times, t_unix_s)
        if i == 0:
            return truth[0]
        if i >= len(truth):
            return truth[-1]
        a, b = truth[i - 1], truth[i]
        w = (t_unix_s - a.t_unix_s) / max(b.t_unix_s - a.t_unix_s, 1e-9)

        def lerp(x: float, y: float) -> float:
            return x + w * (y - x)

        def alerp(x: float, y: float) -> float:
            return x + w * math.atan2(math.sin(y - x), math.cos(y - x))

        alt = None if a.alt_amsl_m is None or b.alt_amsl_m is None else lerp(a.alt_amsl_m, b.alt_amsl_m)
        return TruePose(
            t_unix_s,
            lerp(a.lat_deg, b.lat_deg),
            lerp(a.lon_deg, b.lon_deg),
            alt,
            lerp(a.roll_rad, b.roll_rad),
            lerp(a.pitch_rad, b.pitch_rad),
            alerp(a.yaw_rad, b.yaw_rad),
        )

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self._hb.join(2.0)
        self.ap.close()
        self.daemon.close()


@dataclass(frozen=True)
class MissionPlan:
    """What to fly: waypoints (lat, lon) at ``alt_rel_m`` above home, at ``speed_m_s``."""

    waypoints_lat_lon_deg: tuple[tuple[float, float], ...]
    alt_rel_m: float
    speed_m_s: float
    climb_m_s: float = 5.0
    descent_m_s: float = 3.0
    land_high_m_s: float = 5.0


@dataclass
class MissionDriver:
    """Flies the mission (module docstring). ``stop()``, from any thread, ends it at once: every wait and
    sleep of the driver's raises ``MissionStopped`` within a few milliseconds, and a GNSS the driver
    switched off is switched back on, so the vehicle is not left flying blind without the daemon."""

    link: AutopilotRelay
    plan: MissionPlan
    say: Callable[[str], None] = print
    log: list[dict[str, Any]] = field(default_factory=list)
    _stopped: threading.Event = field(default_factory=threading.Event, repr=False)
    _gnss_off: bool = field(default=False, repr=False)
    _done: bool = field(default=False, repr=False)

    def stop(self) -> None:
        """End the mission now (see the class docstring); idempotent."""
        if self._stopped.is_set():
            return
        self._stopped.set()
        self.link.interrupt_waits()
        if self._done:
            return
        if self._gnss_off:  # one message, not waited on: the caller is stopping
            self.link.send(self._gnss_on_message)
        self._event("stopped", gnss_restored=self._gnss_off)

    def _gnss_on_message(self, mav: Any) -> None:
        """Send the one message that switches the simulated GNSS back on (``stop``)."""
        mav.param_set_send(*self._target(), b"SIM_GPS1_ENABLE", 1.0, mavutil.mavlink.MAV_PARAM_TYPE_REAL32)

    def _check(self) -> None:
        if self._stopped.is_set():
            raise MissionStopped("the mission was stopped")

    def _sleep(self, seconds: float) -> None:
        """``time.sleep`` that ends at once, raising ``MissionStopped``, when the driver is stopped."""
        if self._stopped.wait(seconds):
            self._check()

    def _wait(
        self, pred: Callable[[Any], bool], types: Sequence[str], timeout_s: float, *, since: int | None = None
    ) -> Any:
        """``AutopilotRelay.wait``, ended by ``stop()`` (``MissionStopped``)."""
        self._check()
        msg = self.link.wait(pred, types, timeout_s, since=since)
        self._check()
        return msg

    def _event(self, kind: str, **data: Any) -> None:
        self.log.append({"t_unix_s": round(time.time(), 3), "kind": kind, **data})
        self.say(f"mission: {kind} {data if data else ''}".rstrip())

    def _target(self) -> tuple[int, int]:
        return self.link.ap_system or 1, 1

    # --- parameters -----------------------------------------------------------------------------
    def get_param(self, name: str, timeout_s: float = 3.0) -> float | None:
        for _ in range(3):
            sent = self.link.send(lambda mav: mav.param_request_read_send(*self._target(), name.encode(), -1))
            msg = self._wait(lambda m: _pid(m.param_id) == name, ["PARAM_VALUE"], timeout_s, since=sent)
            if msg is not None:
                return float(msg.param_value)
        return None

    def set_param(self, name: str, value: float) -> None:
        for _ in range(3):
            self._check()  # never a parameter after stop() (it may have just restored the GNSS)
            sent = self.link.send(
                lambda mav: mav.param_set_send(
                    *self._target(), name.encode(), float(value), mavutil.mavlink.MAV_PARAM_TYPE_REAL32
                )
            )
            msg = self._wait(lambda m: _pid(m.param_id) == name, ["PARAM_VALUE"], 3.0, since=sent)
            if msg is not None and abs(float(msg.param_value) - value) < 1e-3:
                self._event("param_set", name=name, value=value)
                return
        raise MissionError(
            f"the autopilot did not confirm {name}={value:g} (no PARAM_VALUE): this ArduPilot version may "
            f"not have {name}"
        )

    # --- commands -------------------------------------------------------------------------------
    def command(self, cmd: int, *params: float, timeout_s: float = 3.0) -> int | None:
        p = [*params, *([0.0] * (7 - len(params)))]
        sent = self.link.send(lambda mav: mav.command_long_send(*self._target(), cmd, 0, *p))
        msg = self._wait(lambda m: int(m.command) == cmd, ["COMMAND_ACK"], timeout_s, since=sent)
        return None if msg is None else int(msg.result)

    def set_mode(self, mode: int) -> None:
        for _ in range(5):
            res = self.command(
                mavutil.mavlink.MAV_CMD_DO_SET_MODE, mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode
            )
            if res == mavutil.mavlink.MAV_RESULT_ACCEPTED:
                self._event("mode", mode=mode)
                return
            self._sleep(1.0)
        raise MissionError(f"the autopilot refused mode {mode}; last texts: {self._texts()}")

    def _texts(self, n: int = 6) -> list[str]:
        return [t for _, t in self.link.statustext[-n:]]

    def _heartbeat(self) -> Any:
        return self.link.last("HEARTBEAT")

    def armed(self) -> bool:
        hb = self._heartbeat()
        return hb is not None and bool(hb.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    def rel_alt_m(self) -> float:
        gp = self.link.last("GLOBAL_POSITION_INT")
        return 0.0 if gp is None else gp.relative_alt / 1000.0

    # --- the mission ----------------------------------------------------------------------------
    def prepare(self, timeout_s: float = 60.0) -> bool:
        """Wait for the autopilot; make sure GPS2_TYPE=14 is in effect (a reboot when it had to be set).
        Returns True when it rebooted."""
        if self._wait(lambda m: True, ["HEARTBEAT"], timeout_s) is None:
            raise MissionError(f"no HEARTBEAT from the autopilot at {self.link.url} in {timeout_s:.0f} s")
        self._event("autopilot_heartbeat", system=self.link.ap_system)
        stale = self._boot_params_to_set()
        rebooted = False
        if stale:
            # reboot-required (measured for GPSn_TYPE): set, then reboot, before anything relies on it
            for name in stale:
                self.set_param(name, BOOT_PARAMS[name])
            self._event("reboot", why=f"{', '.join(stale)} reboot-required")
            self.command(mavutil.mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1)
            self._sleep(2.0)
            if self._wait(lambda m: True, ["HEARTBEAT"], timeout_s) is None:
                raise MissionError("the autopilot did not come back after the reboot")
            rebooted = True
            # a SITL started with --wipe wipes them again on the reboot (a literal -w does not: SITL drops it
            # when it reboots): read them back
            still = self._boot_params_to_set()
            if still:
                raise MissionError(
                    f"{', '.join(still)} did not survive the reboot (a SITL started with --wipe wipes its "
                    "parameters again on every boot; a literal -w is dropped on reboot, so it cannot: start "
                    "it without --wipe, or set them with --defaults)"
                )
        # what the daemon and the scorer need, at rates a real ArduPilot does not stream by default
        for msg_id, hz in STREAM_RATES_HZ.items():
            self.command(mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz, timeout_s=1.0)
        for name, value in (
            ("GPS_AUTO_SWITCH", 1),
            ("SIM_GPS1_ENABLE", 1),
            ("WPNAV_SPEED", round(self.plan.speed_m_s * 100)),
            ("WPNAV_SPEED_UP", round(self.plan.climb_m_s * 100)),
            ("WPNAV_SPEED_DN", round(self.plan.descent_m_s * 100)),
            ("LAND_SPEED_HIGH", round(self.plan.land_high_m_s * 100)),
            ("LAND_SPEED", 150),
        ):
            self.set_param(name, value)
        return rebooted

    def _boot_params_to_set(self) -> list[str]:
        """The reboot-required parameters whose stored value is not what the mission needs."""
        stale = []
        for name, value in BOOT_PARAMS.items():
            have = self.get_param(name)
            if have is None:
                raise MissionError(f"the autopilot has no {name} parameter (ArduPilot 4.5+ is needed)")
            if round(have) != round(value):
                stale.append(name)
        return stale

    def ground_alt_amsl_m(self, timeout_s: float = 60.0) -> float:
        """The ground's height at home, AMSL, m, once the EKF has an origin: HOME_POSITION's altitude,
        checked against GLOBAL_POSITION_INT (alt - relative_alt). Before the origin exists
        GLOBAL_POSITION_INT's alt is 0 (measured), which read as a ground 520 m low."""
        deadline = time.time() + timeout_s
        while time.time() < deadline:
            home = self.link.last("HOME_POSITION")
            gp = self.link.last("GLOBAL_POSITION_INT")
            if home is not None and gp is not None and (gp.lat, gp.lon, gp.alt) != (0, 0, 0):
                home_alt = home.altitude / 1000.0
                gp_ground = (gp.alt - gp.relative_alt) / 1000.0
                if abs(home_alt - gp_ground) > 5.0:
                    raise MissionError(
                        "the autopilot's ground altitude disagrees with itself: HOME_POSITION "
                        f"{home_alt:.1f} m, GLOBAL_POSITION_INT alt - relative_alt {gp_ground:.1f} m AMSL"
                    )
                self._event("ground_alt", home_m=home_alt, global_position_m=gp_ground)
                return home_alt
            if home is None:
                self.command(
                    mavutil.mavlink.MAV_CMD_REQUEST_MESSAGE,
                    mavutil.mavlink.MAVLINK_MSG_ID_HOME_POSITION,
                    timeout_s=1.0,
                )
            self._sleep(0.5)
        raise MissionError(
            f"no EKF origin in {timeout_s:.0f} s (HOME_POSITION and a GLOBAL_POSITION_INT with a position): "
            f"the ground altitude is unknown; last texts: {self._texts()}"
        )

    def wait_ready(self, timeout_s: float = 120.0) -> None:
        """EKF position ok and GPS 2 (the daemon's GPS_INPUT) with a 3D fix."""
        deadline = time.time() + timeout_s
        while time.time() < deadline:
            ekf = self.link.last("EKF_STATUS_REPORT")
            gps2 = self.link.last("GPS2_RAW")
            ok_ekf = (
                ekf is not None
                and (ekf.flags & mavutil.mavlink.EKF_POS_HORIZ_ABS)
                and not (ekf.flags & mavutil.mavlink.EKF_CONST_POS_MODE)
            )
            if ok_ekf:
                self.command(
                    mavutil.mavlink.MAV_CMD_REQUEST_MESSAGE, mavutil.mavlink.MAVLINK_MSG_ID_HOME_POSITION
                )
                self._event("ready", ekf_flags=int(ekf.flags), gps2_fix=getattr(gps2, "fix_type", None))
                return
            self._sleep(0.5)
        raise MissionError(
            f"not ready in {timeout_s:.0f} s (EKF position and GPS 2 3D fix): EKF "
            f"{getattr(self.link.last('EKF_STATUS_REPORT'), 'flags', None)}, GPS2 fix "
            f"{getattr(self.link.last('GPS2_RAW'), 'fix_type', None)}; last texts: {self._texts()}"
        )

    def upload_mission(self) -> int:
        """Home (seq 0, replaced by the autopilot), the waypoints, then LAND at the last one. Returns
        the LAND item's seq."""
        items: list[tuple[int, float, float, float]] = [(mavutil.mavlink.MAV_CMD_NAV_WAYPOINT, 0, 0, 0)]
        for lat, lon in self.plan.waypoints_lat_lon_deg:
            items.append((mavutil.mavlink.MAV_CMD_NAV_WAYPOINT, lat, lon, self.plan.alt_rel_m))
        items.append((mavutil.mavlink.MAV_CMD_NAV_LAND, 0, 0, 0))
        return self._upload(items)

    def _upload(self, items: Sequence[tuple[int, float, float, float]]) -> int:
        """Upload ``items`` (command, lat, lon, alt above home) with the mission protocol; returns the last
        item's seq. The yaw of NAV_TAKEOFF and NAV_LAND is NaN: the autopilot keeps its heading."""
        sys_id, comp = self._target()
        for _attempt in range(3):
            mark = self.link.send(lambda mav: mav.mission_count_send(sys_id, comp, len(items), 0))
            sent = -1
            while True:
                msg = self._wait(
                    lambda m: True, ["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"], 5.0, since=mark
                )
                if msg is None:
                    break
                if msg.get_type() == "MISSION_ACK":
                    if int(msg.type) == mavutil.mavlink.MAV_MISSION_ACCEPTED and sent == len(items) - 1:
                        self._event("mission_uploaded", items=len(items))
                        return len(items) - 1
                    break
                seq = int(msg.seq)
                if not 0 <= seq < len(items):
                    break
                cmd, lat, lon, alt = items[seq]
                mark = self.link.send(
                    lambda mav, seq=seq, cmd=cmd, lat=lat, lon=lon, alt=alt: mav.mission_item_int_send(  # type: ignore[misc]
                        sys_id,
                        comp,
                        seq,
                        mavutil.mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                        cmd,
                        0,
                        1,
                        0,
                        0,
                        0,
                        math.nan if cmd in _KEEP_YAW_COMMANDS else 0,
                        round(lat * 1e7),
                        round(lon * 1e7),
                        alt,
                        0,
                    )
                )
                sent = max(sent, seq)
        raise MissionError(f"mission upload failed; last texts: {self._texts()}")

    def gps2_fix(self) -> bool:
        gps2 = self.link.last("GPS2_RAW")
        return gps2 is not None and int(gps2.fix_type) >= 3

    def arm(self, timeout_s: float = 60.0) -> None:
        """Arm. On the ground the daemon has no visual fix (the camera sees a few centimetres of ground),
        so GPS 2 (GPS_INPUT) has none and ArduPilot refuses: "PreArm: GPS 2: Bad fix" (measured). Then,
        with GPS 1 (the real GNSS) primary with a 3D fix, the GPS pre-arm check is skipped for the arming
        only (ARMING_CHECK without bit 3, "GPS lock") and restored at once; the GNSS is switched off
        later only once GPS 2 has a 3D fix in the air (:meth:`fly`)."""
        deadline = time.time() + timeout_s
        skipped: tuple[str, float] | None = None  # the parameter changed and its value before
        while time.time() < deadline:
            n_texts = len(self.link.statustext)
            res = self.command(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
            if res == mavutil.mavlink.MAV_RESULT_ACCEPTED:
                self._event("armed", gps2_prearm_skipped=skipped)
                if skipped is not None:
                    self.set_param(*skipped)  # restored at once
                return
            self._sleep(0.5)
            texts = [t for _, t in self.link.statustext[n_texts:]]
            gps1 = self.link.last("GPS_RAW_INT")
            only_gps2 = texts and all("GPS 2" in t for t in texts if "PreArm" in t or "Arm:" in t)
            if only_gps2 and skipped is None and gps1 is not None and int(gps1.fix_type) >= 3:
                skipped = self._skip_gps_arming_check()
                continue
            self._sleep(1.5)
        raise MissionError(f"the autopilot refused to arm for {timeout_s:.0f} s: {self._texts()}")

    def _skip_gps_arming_check(self) -> tuple[str, float]:
        """Skip the GPS pre-arm check through whichever parameter this ArduPilot has: ARMING_SKIPCHK
        (upstream 4.7, a mask of the checks skipped) or ARMING_CHECK (a mask of the checks done).
        Returns the parameter and the value to restore."""
        skip = self.get_param("ARMING_SKIPCHK")
        if skip is not None:
            self.set_param("ARMING_SKIPCHK", int(skip) | ARMING_SKIPCHK_GPS)
            return "ARMING_SKIPCHK", skip
        check = self.get_param("ARMING_CHECK")
        if check is None:
            raise MissionError("the autopilot has neither ARMING_SKIPCHK nor ARMING_CHECK")
        self.set_param("ARMING_CHECK", ARMING_CHECK_ALL_BUT_GPS)
        return "ARMING_CHECK", check

    def fly(self, *, gnss_off: bool = True, timeout_s: float = 600.0) -> dict[str, Any]:
        """The whole mission after :meth:`prepare` and :meth:`wait_ready`. Returns the timeline."""
        land_seq = self.upload_mission()
        self.set_mode(MODE_GUIDED)
        self.arm()
        if self.command(mavutil.mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, self.plan.alt_rel_m) != (
            mavutil.mavlink.MAV_RESULT_ACCEPTED
        ):
            raise MissionError(f"take-off refused: {self._texts()}")
        self._event("takeoff", alt_rel_m=self.plan.alt_rel_m)
        t_end = time.time() + timeout_s
        while self.rel_alt_m() < 0.95 * self.plan.alt_rel_m:
            if time.time() > t_end:
                raise MissionError("take-off did not reach the altitude")
            self._sleep(0.2)
        self._event("takeoff_done", rel_alt_m=round(self.rel_alt_m(), 1))
        while gnss_off and not self.gps2_fix():
            if time.time() > t_end:
                raise MissionError(f"GPS 2 (GPS_INPUT) never had a 3D fix: GNSS left on; {self._texts()}")
            self._sleep(0.2)
        if gnss_off:
            self._gnss_off = True  # from the request on: stop() switches it back on
            self.set_param("SIM_GPS1_ENABLE", 0)
            self._event("gnss_off")
        self.set_mode(MODE_AUTO)
        gnss_back = not gnss_off
        while self.armed() or self.rel_alt_m() > 0.5:
            if time.time() > t_end:
                raise MissionError(f"the mission did not finish in {timeout_s:.0f} s: {self._texts()}")
            cur = self.link.last("MISSION_CURRENT")
            hb = self._heartbeat()
            if not gnss_back and (
                (cur is not None and int(cur.seq) >= land_seq)
                or (hb is not None and hb.custom_mode == MODE_LAND)
            ):
                self.set_param("SIM_GPS1_ENABLE", 1)
                self._gnss_off = False
                self._event("gnss_on", rel_alt_m=round(self.rel_alt_m(), 1))
                gnss_back = True
            self._sleep(0.2)
        self._event("landed")
        self._done = True
        return {"log": self.log, "land_seq": land_seq}


_KEEP_YAW_COMMANDS = (mavutil.mavlink.MAV_CMD_NAV_LAND, mavutil.mavlink.MAV_CMD_NAV_TAKEOFF)


def _euler_from_quaternion(q: Sequence[float]) -> tuple[float, float, float]:
    """Roll, pitch, yaw (rad, ZYX) of a unit quaternion (w, x, y, z), body to NED."""
    w, x, y, z = (float(v) for v in q)
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def _pid(raw: Any) -> str:
    s = raw.decode("ascii", "replace") if isinstance(raw, bytes) else str(raw)
    return s.split("\x00", 1)[0]
