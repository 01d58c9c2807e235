"""The simulated autopilot: plays ArduPilot's side of the MAVLink link over real UDP.

Sends what a flight controller sends a companion computer (HEARTBEAT, SYSTEM_TIME, ATTITUDE, HIGHRES_IMU,
ALTITUDE, VFR_HUD, HOME_POSITION) from the scenario's truth, answers TIMESYNC as ArduPilot does (``tc1``:
its boot time when the request arrived, GCS_Common.cpp ``handle_timesync``), and records everything the
daemon sends back with its receive time, for scoring. Its messages are stamped with its boot time, as
ArduPilot's are (ALTITUDE's ``time_usec`` too); its Unix time (SYSTEM_TIME) is off the host's by
``unix_offset_s``, as a real autopilot's is whenever nobody set it from GNSS.

The receive time is the kernel's, taken when the datagram reached the socket (``SO_TIMESTAMPNS``), not
when this process got round to reading it: a real autopilot has a processor of its own, while this one
shares two cores with the daemon and the frame renderer. Read times made the stream look stalled when the
harness was (measured: a 765 ms gap in what it read while the daemon's own record of its sends had none
over 118 ms). Where the kernel gives no stamp, the read time is used.

CPython 3.11's ``socket`` module does not export ``SO_TIMESTAMPNS``. On Linux x86-64 and arm64 its value is
35 (``asm-generic/socket.h``, ``SO_TIMESTAMPNS_OLD``, which is what ``SO_TIMESTAMPNS`` means where ``time_t``
is 64-bit), and the control message carries a ``struct timespec``: two 64-bit integers. Without the
constant every stamp silently fell back to the read time; ``tests/test_sitl_sim_autopilot.py`` checks
that it does not. Linux turns stamping on a moment after the first socket asks for it (deferred work), so
the first datagrams of a flight may still carry their read time.
"""

from __future__ import annotations

import errno
import math
import os
import socket
import struct
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil

from gps_denied_onboard.constants import MAV_COMPONENT_ID

MAV_CMD_REQUEST_MESSAGE = mavutil.mavlink.MAV_CMD_REQUEST_MESSAGE

#: ``SO_TIMESTAMPNS`` (and ``SCM_TIMESTAMPNS``): the socket module's where it has one, else Linux's value.
SO_TIMESTAMPNS: int | None = getattr(socket, "SO_TIMESTAMPNS", 35 if sys.platform == "linux" else None)


def send_home_position(
    mav: Any, lat_deg: float, lon_deg: float, alt_amsl_m: float, time_usec: int | None = None
) -> None:
    """HOME_POSITION at (lat, lon, alt AMSL), local frame at home, no approach vector; ``time_usec`` is
    sent when given (the field is a MAVLink 2 extension)."""
    args: list[Any] = [
        round(lat_deg * 1e7),
        round(lon_deg * 1e7),
        round(alt_amsl_m * 1000),
        0.0,
        0.0,
        0.0,
        [1.0, 0.0, 0.0, 0.0],
        0.0,
        0.0,
        0.0,
    ]
    if time_usec is not None:
        args.append(time_usec)
    mav.home_position_send(*args)


@dataclass
class ReceivedMessage:
    recv_time_unix_s: float
    type: str
    fields: dict[str, Any]


@dataclass
class SimAutopilot:
    """Autopilot side of a UDP link to the daemon listening at ``daemon_port`` on loopback."""

    daemon_port: int
    system_id: int = 1
    boot_time_unix_s: float = field(default_factory=time.time)
    #: The autopilot's Unix clock minus the host's, s (SYSTEM_TIME.time_unix_usec).
    unix_offset_s: float = 0.0
    received: list[ReceivedMessage] = field(default_factory=list)
    timesync_answered: int = 0
    #: REQUEST_MESSAGEs answered with the message asked for (``_answer_request``).
    requests_answered: int = 0

    def __post_init__(self) -> None:
        self._conn = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{self.daemon_port}", source_system=self.system_id, source_component=1
        )
        self.mav = self._conn.mav
        self._alt_rel_m = 0.0  # height above home last sent (ALTITUDE), m
        self._home: tuple[float, float, float] | None = None  # the last HOME_POSITION sent
        self.kernel_stamps = SO_TIMESTAMPNS is not None
        if SO_TIMESTAMPNS is not None:
            self._conn.port.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)

    def _datagrams(self) -> Iterator[tuple[float, bytes]]:
        """Every datagram waiting on the socket, with the time it arrived (non-blocking)."""
        sock = self._conn.port
        while True:
            try:
                data, ancillary, _flags, _addr = sock.recvmsg(65535, 64)
            except OSError as exc:  # nothing waiting, or the daemon's port not open yet (ICMP refused)
                if exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED):
                    return
                raise
            stamp = time.time()
            for level, kind, payload in ancillary:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                    sec, nsec = struct.unpack("qq", payload[:16])
                    stamp = sec + nsec * 1e-9
            yield stamp, data

    def fileno(self) -> int:
        return int(self._conn.port.fileno())

    def _boot_ms(self, now_unix_s: float) -> int:
        return max(0, int((now_unix_s - self.boot_time_unix_s) * 1000))

    def send_heartbeat(self, *, armed: bool = True) -> None:
        armed_flag = mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0
        self.mav.heartbeat_send(
            mavutil.mavlink.MAV_TYPE_QUADROTOR,
            mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
            mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | armed_flag,
            4,
            mavutil.mavlink.MAV_STATE_ACTIVE if armed else mavutil.mavlink.MAV_STATE_STANDBY,
        )

    def send_extended_sys_state(self, landed_state: int) -> None:
        """EXTENDED_SYS_STATE: no VTOL, ``landed_state`` (MAV_LANDED_STATE)."""
        self.mav.extended_sys_state_send(mavutil.mavlink.MAV_VTOL_STATE_UNDEFINED, landed_state)

    def send_system_time(self, now_unix_s: float) -> None:
        self.mav.system_time_send(int((now_unix_s + self.unix_offset_s) * 1e6), self._boot_ms(now_unix_s))

    def send_attitude(
        self,
        now_unix_s: float,
        roll_rad: float,
        pitch_rad: float,
        yaw_rad: float,
        rates_rad_s: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> None:
        yaw = math.atan2(math.sin(yaw_rad), math.cos(yaw_rad))  # ArduPilot sends -pi..pi
        self.mav.attitude_send(self._boot_ms(now_unix_s), roll_rad, pitch_rad, yaw, *rates_rad_s)

    def send_highres_imu(
        self,
        now_unix_s: float,
        accel_body_m_s2: tuple[float, float, float],
        gyro_body_rad_s: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> None:
        """HIGHRES_IMU: specific force and rates in body FRD, time since boot (as ArduPilot stamps it)."""
        boot_usec = max(0, int((now_unix_s - self.boot_time_unix_s) * 1e6))
        self.mav.highres_imu_send(
            boot_usec,
            *accel_body_m_s2,
            *gyro_body_rad_s,
            0.0,
            0.0,
            0.0,  # magnetometer (not simulated)
            1013.25,
            0.0,
            0.0,
            20.0,
            0b111111,  # fields_updated: accelerometer and gyro only
        )

    def send_altitude(self, now_unix_s: float, alt_amsl_m: float, alt_rel_m: float, alt_agl_m: float) -> None:
        self._alt_rel_m = alt_rel_m
        self.mav.altitude_send(
            max(0, int((now_unix_s - self.boot_time_unix_s) * 1e6)),
            alt_amsl_m,
            alt_amsl_m,
            alt_rel_m,
            alt_rel_m,
            alt_amsl_m - alt_agl_m,
            alt_agl_m,
        )

    def send_vfr_hud(
        self, groundspeed_m_s: float, heading_deg: float, alt_amsl_m: float, climb_m_s: float
    ) -> None:
        self.mav.vfr_hud_send(
            groundspeed_m_s, groundspeed_m_s, int(heading_deg) % 360, 50, alt_amsl_m, climb_m_s
        )

    def send_ground_fix(
        self, now_unix_s: float, lat_deg: float, lon_deg: float, ground_amsl_m: float, h_acc_m: float
    ) -> None:
        """What an autopilot with GNSS sends while the vehicle stands on the ground, before the denial:
        EKF_STATUS_REPORT (its absolute horizontal position good), GPS_RAW_INT (a 3D fix stating
        ``h_acc_m``) and GLOBAL_POSITION_INT at (lat, lon) on the ground (relative_alt 0)."""
        m = mavutil.mavlink
        flags = (
            m.EKF_ATTITUDE
            | m.EKF_VELOCITY_HORIZ
            | m.EKF_VELOCITY_VERT
            | m.EKF_POS_HORIZ_REL
            | m.EKF_POS_HORIZ_ABS
            | m.EKF_POS_VERT_ABS
            | m.EKF_PRED_POS_HORIZ_REL
            | m.EKF_PRED_POS_HORIZ_ABS
        )
        self.mav.ekf_status_report_send(flags, 0.1, 0.1, 0.1, 0.1, 0.0)
        lat_e7, lon_e7, alt_mm = round(lat_deg * 1e7), round(lon_deg * 1e7), round(ground_amsl_m * 1000)
        eph = min(65534, round(h_acc_m * 100))
        t_usec = round(now_unix_s * 1e6)
        base = (t_usec, 3, lat_e7, lon_e7, alt_mm, eph, eph, 0, 0, 12)
        if m.WIRE_PROTOCOL_VERSION == "1.0":  # MAVLink 1 has no extension fields: no h_acc
            self.mav.gps_raw_int_send(*base)
        else:
            self.mav.gps_raw_int_send(*base, alt_mm, round(h_acc_m * 1000))
        self.mav.global_position_int_send(self._boot_ms(now_unix_s), lat_e7, lon_e7, alt_mm, 0, 0, 0, 0, 0)

    def send_home(self, lat_deg: float, lon_deg: float, alt_amsl_m: float) -> None:
        self._home = (lat_deg, lon_deg, alt_amsl_m)
        send_home_position(self.mav, lat_deg, lon_deg, alt_amsl_m)

    def poll(self, *, discard: bool = False) -> int:
        """Drain what the daemon sent (non-blocking); keeps only the daemon's own component.
        ``discard``: drop everything (a simulated link cut)."""
        n = 0
        for stamp, data in self._datagrams():
            for msg in self.mav.parse_buffer(data) or ():
                if discard or msg.get_type() == "BAD_DATA" or msg.get_srcComponent() != MAV_COMPONENT_ID:
                    continue
                n += 1
                self.received.append(ReceivedMessage(stamp, msg.get_type(), msg.to_dict()))
                if msg.get_type() == "TIMESYNC" and int(msg.tc1) == 0:
                    boot_ns = max(0, int((stamp - self.boot_time_unix_s) * 1e9))
                    self.mav.timesync_send(boot_ns, int(msg.ts1))
                    self.timesync_answered += 1
                elif msg.get_type() == "COMMAND_LONG" and int(msg.command) == MAV_CMD_REQUEST_MESSAGE:
                    self._answer_request(msg, stamp)
        return n

    def _answer_request(self, msg: Any, now_unix_s: float) -> None:
        """MAV_CMD_REQUEST_MESSAGE as ArduPilot answers it (GCS_Common.cpp
        ``handle_command_request_message``): the message now, if it is one it can send, and the ACK. This
        double has no EKF of its own (``sitl.ap_emulator`` models one): its GLOBAL_POSITION_INT says
        "no position" (lat/lon 0) with the height above home last sent, and its EKF_STATUS_REPORT flags
        attitude only, as an ArduPilot without an absolute position answers; HOME_POSITION is the home it
        last sent. Others, and HOME_POSITION before there is a home, are refused (MAV_RESULT_FAILED, as
        for a message ArduPilot cannot send)."""
        wanted = int(msg.param1)
        m = mavutil.mavlink
        result = m.MAV_RESULT_ACCEPTED
        if wanted == m.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            rel_mm = round(self._alt_rel_m * 1000)
            self.mav.global_position_int_send(self._boot_ms(now_unix_s), 0, 0, rel_mm, rel_mm, 0, 0, 0, 0)
        elif wanted == m.MAVLINK_MSG_ID_EKF_STATUS_REPORT:
            self.mav.ekf_status_report_send(m.EKF_ATTITUDE, 0.0, 0.0, 0.0, 0.0, 0.0)
        elif wanted == m.MAVLINK_MSG_ID_HOME_POSITION and self._home is not None:
            send_home_position(self.mav, *self._home)
        else:
            result = m.MAV_RESULT_FAILED
        self.mav.command_ack_send(MAV_CMD_REQUEST_MESSAGE, result)
        if result == m.MAV_RESULT_ACCEPTED:
            self.requests_answered += 1

    def of_type(self, *types: str) -> list[ReceivedMessage]:
        return [m for m in self.received if m.type in types]

    def close(self) -> None:
        self._conn.close()
