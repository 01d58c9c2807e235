"""C8 MAVLink: vehicle state tracking, message building, and the link over real UDP/TCP on 127.0.0.1."""

from __future__ import annotations

import errno
import math
import os
import re
import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import structlog

from gps_denied_onboard.components.c5_estimator.types import EstimatorState
from gps_denied_onboard.components.c8_mavlink import (
    MavlinkConfigError,
    MavlinkLink,
    TimeSource,
    VehicleStateTracker,
    load_signing_key,
)
from gps_denied_onboard.components.c8_mavlink import messages as m
from gps_denied_onboard.components.c8_mavlink.messages import DIALECT as D
from gps_denied_onboard.components.c8_mavlink.messages import mavutil
from gps_denied_onboard.components.c8_mavlink.vehicle_state import AHRS_SIGMA_PER_SWING
from gps_denied_onboard.config import ConfigError, MavlinkConfig, config_from_mapping
from gps_denied_onboard.constants import (
    GPS_INPUT_GPS_ID,
    SET_GPS_GLOBAL_ORIGIN_INTERVAL_S,
    FdrHealthState,
    FdrKind,
    LogEvent,
    Provenance,
)
from gps_denied_onboard.geo import LocalTangentPlane, gps_week_and_ms

T0_UNIX_USEC = 1_717_000_000_000_000  # 2024-05-29
BOOT0_MS = 100_000
KEY_HEX = "00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff"
#: The daemon's tangent plane in the link tests (map-cache centre at terrain height).
LTP = LocalTangentPlane(50.45, 30.52, 180.0)


class FakeClock:
    """Settable clock shared by the link and the tracker."""

    def __init__(self, t: float = T0_UNIX_USEC / 1e6) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _state(
    provenance: Provenance = Provenance.SATELLITE_ANCHORED,
    *,
    sigma_ne_m: tuple[float, float] = (3.0, 4.0),
    yaw_rad: float | None = 0.5,
    vel: tuple[float, float, float] = (5.0, -2.0, 0.5),
    lat_deg: float = 50.4501234,
) -> EstimatorState:
    return EstimatorState(
        time_unix_usec=T0_UNIX_USEC,
        provenance=provenance,
        pos_ned_m=np.array([10.0, 20.0, -100.0]),
        vel_ned_m_s=np.array(vel),
        cov_pos_ned_m2=np.diag([sigma_ne_m[0] ** 2, sigma_ne_m[1] ** 2, 25.0]),
        cov_vel_ned_m2_s2=np.diag([0.25, 0.16, 0.09]),
        lat_deg=lat_deg,
        lon_deg=30.5234567,
        alt_amsl_m=250.0,
        yaw_rad=yaw_rad,
        last_fix_age_s=0.2,
        shared_sigma_m=1.0,
    )


def _decoded(build: Callable[[Any], Any], src: tuple[int, int] = (1, 1)) -> Any:
    """Encode with one MAVLink instance and decode with another: a real received message."""
    tx = D.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
    return D.MAVLink(None).decode(bytearray(build(tx).pack(tx)))


def _ap_heartbeat(mav: Any) -> Any:
    return mav.heartbeat_encode(D.MAV_TYPE_QUADROTOR, D.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, D.MAV_STATE_ACTIVE)


def _tracker(clock: Callable[[], float] = time.time) -> VehicleStateTracker:
    return VehicleStateTracker(
        1, attitude_max_age_s=0.3, altitude_max_age_s=1.0, link_timeout_s=3.0, clock=clock
    )


def _pump(link: MavlinkLink, until: Callable[[], bool], timeout_s: float = 2.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        link.poll()
        if until():
            return True
        time.sleep(0.005)
    return until()


def _recv_all(conn: Any, msg_type: str, wait_s: float = 0.3) -> list[Any]:
    out = []
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        msg = conn.recv_match(type=msg_type, blocking=True, timeout=0.05)
        if msg is not None:
            out.append(msg)
    return out


@pytest.fixture
def udp_pair() -> Iterator[tuple[MavlinkLink, Any, FakeClock, int]]:
    """A MavlinkLink on udpin:127.0.0.1:PORT and a pymavlink "autopilot" (sysid 1, comp 1) sending to it."""
    port = _free_udp_port()
    clock = FakeClock()
    tracker = _tracker(clock)
    link = MavlinkLink(
        MavlinkConfig(
            url=f"udpin:127.0.0.1:{port}",
            outputs=("gps_input", "global_position_sensor", "vision_position_estimate"),
        ),
        tracker,
        clock=clock,
        ltp=LTP,
    )
    link.open()
    ap = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    try:
        yield link, ap, clock, port
    finally:
        ap.close()
        link.close()


# --- vehicle state -----------------------------------------------------------------------------------


def test_tracker_interpolates_attitude_over_udp_with_yaw_wrap(udp_pair: tuple) -> None:
    """ATTITUDE over UDP, time-mapped by its receive time (the test autopilot answers no TIMESYNC); yaw
    interpolates across +-pi the short way."""
    link, ap, clock, _ = udp_pair
    ap.mav.send(_ap_heartbeat(ap.mav))
    ap.mav.system_time_send(T0_UNIX_USEC, BOOT0_MS)
    ap.mav.attitude_send(BOOT0_MS, 0.1, -0.05, 3.1, 0, 0, 0)
    tr = link.tracker
    assert _pump(link, lambda: tr.snapshot().attitude_samples == 1)
    clock.t += 0.1  # received as they were sent, 100 ms apart
    ap.mav.attitude_send(BOOT0_MS + 100, 0.2, -0.15, -3.1, 0, 0, 0)
    assert _pump(link, lambda: tr.snapshot().attitude_samples == 2)
    assert tr.time_source is TimeSource.RECEIVE_TIME
    mid = tr.attitude_at(T0_UNIX_USEC + 50_000)
    assert mid is not None
    assert mid.roll_rad == pytest.approx(0.15, abs=1e-6)
    assert mid.pitch_rad == pytest.approx(-0.10, abs=1e-6)
    assert abs(abs(mid.yaw_rad) - math.pi) < 1e-3  # through +-pi, not through 0
    quarter = tr.attitude_at(T0_UNIX_USEC + 25_000)
    assert quarter is not None and quarter.yaw_rad == pytest.approx(
        3.1 + 0.25 * (2 * math.pi - 6.2), abs=1e-5
    )
    # extrapolation beyond the newest sample is clamped at 50 ms, then held
    late = tr.attitude_at(T0_UNIX_USEC + 100_000 + 200_000)
    assert late is not None and late.roll_rad == pytest.approx(0.25, abs=1e-6)
    # nearest sample older than attitude_max_age_s (0.3 s): invalid
    assert tr.attitude_at(T0_UNIX_USEC + 100_000 + 301_000) is None
    assert tr.attitude_at(T0_UNIX_USEC - 301_000) is None


def test_tracker_never_maps_by_the_autopilots_unix_time() -> None:
    """Without TIMESYNC, boot time maps to the daemon's clock by receive times, and the state says so; a
    SYSTEM_TIME whose Unix time is 5 s off (an autopilot clock nobody set) moves nothing (issue 26:
    SITL's ran 2.0 s behind and every frame was refused as stale)."""
    tr = _tracker()
    assert tr.time_source is TimeSource.NONE and tr.attitude_at(T0_UNIX_USEC) is None
    recv_s = T0_UNIX_USEC / 1e6
    tr.handle(_decoded(lambda mav: mav.attitude_encode(BOOT0_MS, 0.0, 0.0, 1.0, 0, 0, 0)), recv_s)
    tr.handle(_decoded(lambda mav: mav.attitude_encode(BOOT0_MS + 20, 0.0, 0.0, 1.2, 0, 0, 0)), recv_s + 0.02)
    assert tr.time_source is TimeSource.RECEIVE_TIME
    att = tr.attitude_at(T0_UNIX_USEC + 10_000)
    assert att is not None and att.yaw_rad == pytest.approx(1.1, abs=1e-3)
    tr.handle(_decoded(lambda mav: mav.system_time_encode(T0_UNIX_USEC - 5_000_000, BOOT0_MS)), recv_s + 0.03)
    assert tr.time_source is TimeSource.RECEIVE_TIME
    att = tr.attitude_at(T0_UNIX_USEC + 10_000)
    assert att is not None and att.yaw_rad == pytest.approx(1.1, abs=1e-3)
    assert tr.attitude_at(T0_UNIX_USEC - 4_990_000) is None


def test_link_maps_the_autopilot_clock_with_timesync_over_udp(udp_pair: tuple) -> None:
    """The link asks the autopilot for TIMESYNC; the answer (tc1: its boot time when the request arrived,
    as ArduPilot's ``handle_timesync`` does) maps its boot time onto the daemon's clock even though its
    SYSTEM_TIME says the Unix time is 2 s earlier and its messages arrive 80 ms late. The link also
    answers the autopilot's own TIMESYNC request."""
    link, ap, clock, _ = udp_pair
    offset_usec = T0_UNIX_USEC - BOOT0_MS * 1000  # the truth: daemon clock minus boot time

    def boot_usec() -> int:
        return int(clock.t * 1e6 - offset_usec)

    ap.mav.send(_ap_heartbeat(ap.mav))
    assert _pump(link, lambda: link.tracker.autopilot_seen)
    answered = 0
    for _ in range(6):
        clock.t += 0.3
        link.poll()
        for req in _recv_all(ap, "TIMESYNC", wait_s=0.1):
            if req.tc1 == 0:
                ap.mav.timesync_send(boot_usec() * 1000, req.ts1)
                answered += 1
        clock.t += 0.002
        ap.mav.system_time_send(int(clock.t * 1e6) - 2_000_000, boot_usec() // 1000)
        ap.mav.attitude_send(boot_usec() // 1000 - 80, 0.1, 0.0, 0.0, 0, 0, 0)  # stamped 80 ms earlier
        _pump(link, lambda: False, timeout_s=0.05)
    tr = link.tracker
    assert answered >= 3
    assert tr.time_source is TimeSource.TIMESYNC
    assert tr.snapshot().boot_to_unix_offset_usec == pytest.approx(offset_usec, abs=3_000)
    # its own request is answered with our time, ts1 echoed
    ap.mav.timesync_send(0, 777)
    _pump(link, lambda: False, timeout_s=0.2)
    answers = [m for m in _recv_all(ap, "TIMESYNC", wait_s=0.3) if m.ts1 == 777]
    assert answers and answers[0].tc1 == pytest.approx(clock.t * 1e9, abs=1e6)


def test_tracker_altitude_priority_and_staleness() -> None:
    """ALTITUDE.altitude_relative first, then GLOBAL_POSITION_INT.relative_alt, then VFR_HUD - home."""
    tr = _tracker()
    recv_s = T0_UNIX_USEC / 1e6
    tr.handle(_decoded(lambda mav: mav.system_time_encode(T0_UNIX_USEC, BOOT0_MS)), recv_s)
    q = [1.0, 0.0, 0.0, 0.0]
    home = _decoded(lambda mav: mav.home_position_encode(504501234, 305234567, 180_000, 0, 0, 0, q, 0, 0, 0))
    tr.handle(home, recv_s)
    assert tr.home() == pytest.approx((50.4501234, 30.5234567, 180.0))
    # VFR_HUD only: AMSL minus home altitude (receive time)
    tr.handle(_decoded(lambda mav: mav.vfr_hud_encode(10, 10, 90, 50, 300.0, 0)), recv_s)
    assert tr.alt_agl_at(T0_UNIX_USEC) == pytest.approx(120.0)
    tr.handle(
        _decoded(lambda mav: mav.global_position_int_encode(BOOT0_MS, 0, 0, 0, 110_000, 0, 0, 0, 0)), recv_s
    )
    assert tr.alt_agl_at(T0_UNIX_USEC) == pytest.approx(110.0)
    tr.handle(_decoded(lambda mav: mav.altitude_encode(BOOT0_MS * 1000, 0, 0, 0, 100.0, 0, 0)), recv_s)
    assert tr.alt_agl_at(T0_UNIX_USEC) == pytest.approx(100.0)
    # ALTITUDE goes stale (no newer sample), GLOBAL_POSITION_INT continues
    tr.handle(
        _decoded(lambda mav: mav.global_position_int_encode(BOOT0_MS + 2000, 0, 0, 0, 111_000, 0, 0, 0, 0)),
        recv_s + 2.0,
    )
    assert tr.alt_agl_at(T0_UNIX_USEC + 2_000_000) == pytest.approx(111.0)
    assert tr.alt_agl_at(T0_UNIX_USEC + 3_500_000) is None  # every source older than 1 s


def test_tracker_autopilot_position_with_its_ekf_flags_and_staleness() -> None:
    """GLOBAL_POSITION_INT lat/lon/velocity with EKF_STATUS_REPORT's flags beside it (F8 restart);
    older than 2 s it is gone; (0, 0), what an autopilot without a position sends, is never one."""
    tr = _tracker()
    recv_s = T0_UNIX_USEC / 1e6
    tr.handle(_decoded(lambda mav: mav.system_time_encode(T0_UNIX_USEC, BOOT0_MS)), recv_s)
    tr.handle(
        _decoded(lambda mav: mav.global_position_int_encode(BOOT0_MS, 0, 0, 0, 110_000, 0, 0, 0, 0)), recv_s
    )
    assert tr.autopilot_position(recv_s) is None
    gpi = _decoded(
        lambda mav: mav.global_position_int_encode(
            BOOT0_MS, 504501234, 305234567, 0, 110_000, 1250, -300, 0, 0
        )
    )
    tr.handle(gpi, recv_s)
    ap = tr.autopilot_position(recv_s + 0.5)
    assert ap is not None
    assert (ap.lat_deg, ap.lon_deg) == pytest.approx((50.4501234, 30.5234567))
    assert ap.vel_ne_m_s == pytest.approx((12.5, -3.0))
    assert ap.time_unix_usec == pytest.approx(T0_UNIX_USEC, abs=1000)
    assert ap.ekf_flags is None and not ap.horizontal_position_valid
    good = D.EKF_ATTITUDE | D.EKF_VELOCITY_HORIZ | D.EKF_POS_HORIZ_ABS
    tr.handle(_decoded(lambda mav: mav.ekf_status_report_encode(good, 0.1, 0.1, 0.1, 0.1, 0.0)), recv_s)
    ap = tr.autopilot_position(recv_s + 0.5)
    assert ap is not None and ap.horizontal_position_valid
    lost = good | D.EKF_CONST_POS_MODE
    tr.handle(_decoded(lambda mav: mav.ekf_status_report_encode(lost, 0.1, 0.1, 0.1, 0.1, 0.0)), recv_s)
    assert not tr.autopilot_position(recv_s + 0.5).horizontal_position_valid  # type: ignore[union-attr]
    assert tr.autopilot_position(recv_s + 2.5) is None


def test_tracker_knows_when_the_autopilot_answered_even_without_a_position() -> None:
    """An autopilot without a position still answers (lat/lon 0, attitude-only flags): once both
    GLOBAL_POSITION_INT and EKF_STATUS_REPORT arrived after the request, the restart's wait is over,
    while ``autopilot_position`` stays None."""
    tr = _tracker()
    recv_s = T0_UNIX_USEC / 1e6
    tr.handle(_decoded(lambda mav: mav.system_time_encode(T0_UNIX_USEC, BOOT0_MS)), recv_s)
    asked_s = recv_s + 1.0
    no_pos = _decoded(lambda mav: mav.global_position_int_encode(BOOT0_MS, 0, 0, 0, 110_000, 0, 0, 0, 0))
    tr.handle(no_pos, recv_s)  # before the request: not an answer to it
    attitude_only = _decoded(lambda mav: mav.ekf_status_report_encode(D.EKF_ATTITUDE, 0, 0, 0, 0, 0))
    tr.handle(attitude_only, asked_s + 0.05)
    assert not tr.estimate_answered_since(asked_s)
    tr.handle(no_pos, asked_s + 0.06)
    assert tr.estimate_answered_since(asked_s)
    assert not tr.estimate_answered_since(asked_s + 0.1)
    assert tr.autopilot_position(asked_s + 0.1) is None


def test_link_asks_the_autopilot_for_its_estimate_over_udp(udp_pair: tuple) -> None:
    """``request_autopilot_estimate``: MAV_CMD_REQUEST_MESSAGE to the autopilot (sysid 1, comp 1) for
    GPS_RAW_INT, GLOBAL_POSITION_INT, EKF_STATUS_REPORT and HOME_POSITION, received by a real pymavlink
    endpoint."""
    link, ap, _clock, _ = udp_pair
    ap.mav.send(_ap_heartbeat(ap.mav))
    assert _pump(link, lambda: link.tracker.autopilot_seen)
    assert link.request_autopilot_estimate()
    got = _recv_all(ap, "COMMAND_LONG", wait_s=0.5)
    wanted = {
        D.MAVLINK_MSG_ID_GPS_RAW_INT,
        D.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
        D.MAVLINK_MSG_ID_EKF_STATUS_REPORT,
        D.MAVLINK_MSG_ID_HOME_POSITION,
    }
    # (The link's periodic GPS_GLOBAL_ORIGIN request may be among them.)
    requests = [m for m in got if m.command == D.MAV_CMD_REQUEST_MESSAGE and int(m.param1) in wanted]
    assert sorted(int(m.param1) for m in requests) == sorted(wanted)
    assert all((m.target_system, m.target_component) == (1, 1) for m in requests)


def test_tracker_acceleration_is_imu_rotated_by_attitude_minus_gravity() -> None:
    """HIGHRES_IMU specific force (body FRD) rotated with ATTITUDE at each sample's time plus gravity is
    the NED acceleration the prediction uses; stale IMU or no attitude gives None, never a guess."""
    tr = _tracker()
    recv_s = T0_UNIX_USEC / 1e6
    tr.handle(_decoded(lambda mav: mav.system_time_encode(T0_UNIX_USEC, BOOT0_MS)), recv_s)
    yaw = math.pi / 2  # nose east
    for k in range(0, 6):  # 50 Hz for 100 ms
        t_ms = BOOT0_MS + 20 * k
        tr.handle(_decoded(lambda mav, t=t_ms: mav.attitude_encode(t, 0.0, 0.0, yaw, 0, 0, 0)), recv_s)
        # 2 m/s^2 forward (= east) and the -g an accelerometer at rest reads on body z
        imu = (2.0, 0.0, -9.80665, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0)
        tr.handle(_decoded(lambda mav, t=t_ms, v=imu: mav.highres_imu_encode(t * 1000, *v)), recv_s)
    t0 = T0_UNIX_USEC
    accel = tr.accel_ned_mean(t0, t0 + 100_000)
    assert accel is not None
    np.testing.assert_allclose(accel.mean_ned_m_s2, [0.0, 2.0, 0.0], atol=1e-4)
    assert accel.tilt_bound_m_s2 == 0.0  # the attitude has not swung: nothing in doubt
    assert tr.accel_ned_mean(t0 + 400_000, t0 + 500_000) is None  # 300 ms past the last sample
    no_att = _tracker()
    no_att.handle(_decoded(lambda mav: mav.system_time_encode(T0_UNIX_USEC, BOOT0_MS)), recv_s)
    rest = (0.0, 0.0, -9.8, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0)
    no_att.handle(_decoded(lambda mav: mav.highres_imu_encode(BOOT0_MS * 1000, *rest)), recv_s)
    assert no_att.accel_ned_mean(t0 - 10_000, t0 + 10_000) is None


def test_tracker_acceleration_after_a_manoeuvre_carries_the_attitudes_doubt() -> None:
    """After roll swung through 30 deg, the autopilot's roll and pitch may be off by
    ``AHRS_SIGMA_PER_SWING`` of that (``ahrs_doubt_rad``), and so is the rotation that puts the IMU's
    specific force into NED: the acceleration's tilt bound is the specific force's magnitude times it."""
    tr = _tracker()
    recv_s = T0_UNIX_USEC / 1e6
    tr.handle(_decoded(lambda mav: mav.system_time_encode(T0_UNIX_USEC, BOOT0_MS)), recv_s)
    rest = (0.0, 0.0, -9.80665, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0)
    for k in range(0, 51):  # 1 s at 50 Hz: a roll from 0 to 30 deg and level again
        t_ms = BOOT0_MS + 20 * k
        roll = math.radians(30.0) * math.sin(math.pi * k / 50)
        at_s = recv_s + 0.02 * k
        tr.handle(_decoded(lambda mav, t=t_ms, r=roll: mav.attitude_encode(t, r, 0.0, 0.0, 0, 0, 0)), at_s)
        tr.handle(_decoded(lambda mav, t=t_ms: mav.highres_imu_encode(t * 1000, *rest)), at_s)
    t1 = T0_UNIX_USEC + 1_000_000
    accel = tr.accel_ned_mean(t1 - 100_000, t1)
    doubt = tr.ahrs_doubt_rad(t1)
    assert accel is not None and doubt is not None
    assert doubt == pytest.approx(AHRS_SIGMA_PER_SWING * math.radians(30.0), rel=1e-3)
    # |the interval's mean specific force| is g within the last 0.1 s's rolling (under 1 %)
    assert accel.tilt_bound_m_s2 == pytest.approx(9.80665 * doubt, rel=0.01)


def test_tracker_ignores_gcs_and_companion_heartbeats_over_udp(udp_pair: tuple) -> None:
    """Heartbeats from a GCS, another companion, or sysid 1 with MAV_AUTOPILOT_INVALID do not count."""
    link, ap, _clock, port = udp_pair
    gcs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
    comp = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=191)
    fake = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    try:
        gcs.mav.heartbeat_send(D.MAV_TYPE_GCS, D.MAV_AUTOPILOT_INVALID, 0, 0, D.MAV_STATE_ACTIVE)
        comp.mav.heartbeat_send(D.MAV_TYPE_QUADROTOR, D.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4)  # wrong comp
        fake.mav.heartbeat_send(D.MAV_TYPE_ONBOARD_CONTROLLER, D.MAV_AUTOPILOT_INVALID, 0, 0, 4)
        tr = link.tracker
        assert _pump(link, lambda: tr.snapshot().messages_ignored >= 3)
        assert not tr.autopilot_seen and not tr.link_alive()
        ap.mav.send(_ap_heartbeat(ap.mav))
        assert _pump(link, lambda: tr.autopilot_seen)
        assert tr.link_alive()
    finally:
        for c in (gcs, comp, fake):
            c.close()


# --- messages ----------------------------------------------------------------------------------------


def test_fix_type_policy_by_provenance_and_sigma() -> None:
    """3D while anchored/VIO and sigma <= limit; no fix for dead reckoning or large sigma; 0 for none."""
    assert m.fix_type_for(Provenance.SATELLITE_ANCHORED, 4.0) == 3
    assert m.fix_type_for(Provenance.VISUAL_PROPAGATED, m.FIX_3D_MAX_HORIZ_SIGMA_M) == 3
    assert m.fix_type_for(Provenance.VISUAL_PROPAGATED, m.FIX_3D_MAX_HORIZ_SIGMA_M + 0.1) == 1
    assert m.fix_type_for(Provenance.DEAD_RECKONING, 4.0) == 1
    assert m.fix_type_for(Provenance.NO_ESTIMATE, 4.0) == 0
    assert m.fix_type_for(Provenance.SATELLITE_ANCHORED, math.nan) == 0
    mav = D.MAVLink(None)
    nan_pos = m.gps_input(mav, _state(lat_deg=math.nan), time_unix_usec=T0_UNIX_USEC)
    assert nan_pos.fix_type == 0 and nan_pos.lat == 0


def test_gps_input_is_no_fix_while_its_speed_is_not_known_to_arducopters_limit() -> None:
    """A position good for 3D with the 10 m/s speed sigma of a just-started velocity is sent as no fix
    (ArduPilot would latch "GPS Glitch" for ~15 s on that speed accuracy); at 1.5 m/s it is 3D again.
    GLOBAL_POSITION_SENSOR carries no velocity: its validity stays the position's."""
    from dataclasses import replace

    mav = D.MAVLink(None)
    unknown = replace(_state(), cov_vel_ned_m2_s2=np.diag([100.0, 100.0, 4.0]))
    known = replace(_state(), cov_vel_ned_m2_s2=np.diag([m.FIX_3D_MAX_SPEED_SIGMA_M_S**2] * 2 + [1.0]))
    slow = m.gps_input(mav, unknown, time_unix_usec=T0_UNIX_USEC)
    assert (slow.fix_type, slow.speed_accuracy) == (1, pytest.approx(10.0))
    assert m.gps_input(mav, known, time_unix_usec=T0_UNIX_USEC).fix_type == 3
    gps = m.global_position_sensor(
        mav, unknown, time_unix_usec=T0_UNIX_USEC, processing_time_usec=0, target_system=1, sensor_id=1
    )
    assert gps.flags & D.GLOBAL_POSITION_UNHEALTHY == 0


def test_the_3d_stream_enters_at_the_speed_bound_settles_once_and_keeps_to_the_wider_bound() -> None:
    """The speed's sigma saw-tooths across 1.5 m/s at the camera rate (measured: one 3D message, then
    three of fix 1, on naip_cross_date; 14 s without 3D and a failsafe in a square flight). The gate:
    enters 3D only at 1.5 m/s, holds the stream's first 3D back until the states qualify for
    FIX_3D_SETTLE_S in a row, keeps 3D up to FIX_3D_KEEP_SPEED_SIGMA_M_S, and then needs 1.5 m/s again;
    it never sends 3D where the wider bound would not."""
    from dataclasses import replace

    def at(speed_sigma: float) -> EstimatorState:
        return replace(_state(), cov_vel_ned_m2_s2=np.diag([speed_sigma**2, speed_sigma**2, 1.0]))

    good, mid, worse = at(1.0), at(2.0), at(m.FIX_3D_KEEP_SPEED_SIGMA_M_S + 1.0)
    speeds = [mid, good, mid, mid, good, good, good, good, good, good, mid, worse, mid, good]
    gate = m.Fix3dGate()
    sent = []
    for k, state in enumerate(speeds):
        s = replace(state, time_unix_usec=T0_UNIX_USEC + k * 100_000)  # 10 Hz
        sent.append(gate.fix_type(s))
        assert sent[-1] <= m.gps_input_fix_type(s, max_speed_sigma_m_s=m.FIX_3D_KEEP_SPEED_SIGMA_M_S)
    settle_msgs = math.ceil(m.FIX_3D_SETTLE_S / 0.1)  # 4 messages held back
    assert sent == [1, 1, 1, 1] + [1] * settle_msgs + [3, 3] + [3, 1, 1, 3], sent
    assert m.Fix3dGate(0.0).fix_type(good) == 3
    assert m.Fix3dGate(0.0).fix_type(mid) == 1  # entering needs the 1.5 m/s
    kept = m.Fix3dGate(0.0)
    assert kept.fix_type(good) == 3
    assert kept.fix_type(replace(mid, provenance=Provenance.DEAD_RECKONING)) == 1  # only the speed widens
    assert m.Fix3dGate().fix_type(replace(good, provenance=Provenance.NO_ESTIMATE)) == 0
    with pytest.raises(ValueError, match="settle_s"):
        m.Fix3dGate(-1.0)


def test_gps_input_accuracy_dop_and_ignore_flags() -> None:
    """Accuracy fields are the state's sigmas, hdop tracks them, ignore_flags only for unknowns."""
    mav = D.MAVLink(None)
    msg = m.gps_input(mav, _state(), time_unix_usec=T0_UNIX_USEC)
    assert msg.ignore_flags == 0
    assert msg.horiz_accuracy == pytest.approx(4.0) and msg.vert_accuracy == pytest.approx(5.0)
    assert msg.speed_accuracy == pytest.approx(0.5)
    assert msg.hdop == pytest.approx(4.0 / m.NOMINAL_UERE_M) and msg.vdop == pytest.approx(1.0)
    assert msg.yaw == round(math.degrees(0.5) * 100)
    assert m.gps_input(mav, _state(yaw_rad=0.0), time_unix_usec=T0_UNIX_USEC).yaw == 36000
    assert m.gps_input(mav, _state(yaw_rad=None), time_unix_usec=T0_UNIX_USEC).yaw == 0
    no_vd = m.gps_input(mav, _state(vel=(1.0, 2.0, math.nan)), time_unix_usec=T0_UNIX_USEC)
    assert no_vd.ignore_flags == D.GPS_INPUT_IGNORE_FLAG_VEL_VERT and no_vd.vd == 0.0
    worse = m.gps_input(mav, _state(sigma_ne_m=(30.0, 40.0)), time_unix_usec=T0_UNIX_USEC)
    assert worse.hdop == pytest.approx(8.0) and worse.hdop > msg.hdop
    with pytest.raises(ValueError, match="GPS epoch"):
        m.gps_input(mav, _state(), time_unix_usec=1_000_000)


def test_vision_position_estimate_covariance_and_reset_counter() -> None:
    """VISION_POSITION_ESTIMATE carries NED position, the 21-element upper triangle and reset_counter."""
    tx = D.MAVLink(None, srcSystem=1, srcComponent=197)
    msg = m.vision_position_estimate(tx, _state(), time_usec=T0_UNIX_USEC, reset_counter=3)
    rx = D.MAVLink(None).decode(bytearray(msg.pack(tx)))
    assert (rx.x, rx.y, rx.z) == pytest.approx((10.0, 20.0, -100.0))
    cov = list(rx.covariance)
    assert len(cov) == 21 and rx.reset_counter == 3
    assert cov[0] == pytest.approx(9.0) and cov[6] == pytest.approx(16.0) and cov[11] == pytest.approx(25.0)
    assert cov[1] == 0.0 and cov[20] == pytest.approx(math.pi**2, rel=1e-6)


def test_statustext_truncates_to_50_ascii_bytes() -> None:
    """Long or non-ASCII text is cut to 50 bytes without breaking the message."""
    tx = D.MAVLink(None)
    msg = m.statustext(tx, D.MAV_SEVERITY_WARNING, "é" + "x" * 80 + "\n")
    rx = D.MAVLink(None).decode(bytearray(msg.pack(tx)))
    assert rx.text == "?" + "x" * 49 and rx.severity == D.MAV_SEVERITY_WARNING
    with pytest.raises(ValueError, match="severity"):
        m.statustext(tx, 9, "bad")


# --- link --------------------------------------------------------------------------------------------


def test_link_outputs_decode_on_autopilot_side(udp_pair: tuple) -> None:
    """GPS_INPUT, GLOBAL_POSITION_SENSOR, VISION_POSITION_ESTIMATE, NAMED_VALUEs, HEARTBEAT decode sanely."""
    link, ap, _clock, _ = udp_pair
    ap.mav.send(_ap_heartbeat(ap.mav))
    assert _pump(link, lambda: link.tracker.autopilot_seen)
    state = _state()
    t_usec = T0_UNIX_USEC + 40_000
    assert link.send_estimate(state, time_unix_usec=t_usec) == 3
    n = link.send_status_values(
        provenance=state.provenance,
        inliers=87,
        residual_px=1.25,
        horiz_sigma_m=state.horiz_sigma_m,
        frame_drops=2,
        fdr_health=FdrHealthState.DEGRADED,
        integrity_refused=4,
    )
    assert n == 7
    assert link.send_heartbeat(D.MAV_STATE_ACTIVE)

    got = _recv_all(ap, None, 0.4)
    by_type = {x.get_type(): x for x in got}
    gps = by_type.get("GPS_INPUT")
    assert gps is not None and gps.get_srcComponent() == 197 and gps.get_srcSystem() == 1
    assert gps.lat == 504501234 and gps.lon == 305234567
    assert gps.lat / 1e7 == pytest.approx(state.lat_deg, abs=1e-7)
    assert gps.alt == pytest.approx(250.0)
    assert gps.horiz_accuracy == pytest.approx(state.horiz_sigma_m)
    assert gps.vert_accuracy == pytest.approx(state.vert_sigma_m)
    assert gps.speed_accuracy == pytest.approx(state.speed_sigma_m_s)
    assert (gps.vn, gps.ve, gps.vd) == pytest.approx((5.0, -2.0, 0.5))
    week, week_ms = gps_week_and_ms(t_usec)
    assert gps.time_week == week > 0 and gps.time_week_ms == week_ms and gps.time_usec == t_usec
    assert gps.gps_id == GPS_INPUT_GPS_ID == 0 and gps.fix_type == 3 and gps.satellites_visible > 0

    gps_sensor = by_type.get("GLOBAL_POSITION_SENSOR")
    assert gps_sensor is not None and gps_sensor.lat == 504501234
    assert gps_sensor.eph == pytest.approx(4.0) and gps_sensor.epv == pytest.approx(5.0)
    assert gps_sensor.source == D.GLOBAL_POSITION_SRC_VISION and gps_sensor.flags == 0
    vpe = by_type.get("VISION_POSITION_ESTIMATE")
    assert vpe is not None and vpe.x == pytest.approx(10.0)

    values = {x.name: x.value for x in got if x.get_type().startswith("NAMED_VALUE")}
    assert values["GDN_PROV"] == Provenance.SATELLITE_ANCHORED.code == 3
    assert values["GDN_INL"] == 87 and values["GDN_DROP"] == 2
    assert values["GDN_FDR"] == FdrHealthState.DEGRADED.code == 1
    assert values["GDN_IREF"] == 4
    assert values["GDN_RES"] == pytest.approx(1.25) and values["GDN_HSIG"] == pytest.approx(4.0)

    hb = [x for x in got if x.get_type() == "HEARTBEAT" and x.get_srcComponent() == 197]
    assert hb, "no heartbeat from component 197"
    assert hb[0].type == D.MAV_TYPE_ONBOARD_CONTROLLER and hb[0].autopilot == D.MAV_AUTOPILOT_INVALID
    assert link.stats().send_errors == 0


def test_link_no_estimate_is_gps_input_fix_zero_and_nothing_else(udp_pair: tuple) -> None:
    """no_estimate: GPS_INPUT says fix 0 (ArduPilot honours it); GLOBAL_POSITION_SENSOR and
    VISION_POSITION_ESTIMATE, which have no "do not use" their receivers honour, are not sent, counted."""
    link, ap, _clock, _ = udp_pair
    ap.mav.send(_ap_heartbeat(ap.mav))
    assert _pump(link, lambda: link.tracker.autopilot_seen)
    assert link.send_estimate(_state(Provenance.NO_ESTIMATE), time_unix_usec=T0_UNIX_USEC) == 1
    got = _recv_all(ap, ["GPS_INPUT", "GLOBAL_POSITION_SENSOR", "VISION_POSITION_ESTIMATE"], 0.3)
    assert [x.get_type() for x in got] == ["GPS_INPUT"] and got[0].fix_type == 0
    assert link.stats().positions_withheld == 2


def test_statustext_rate_limited_and_coalesced(udp_pair: tuple) -> None:
    """Transitions inside the interval are coalesced; the latest is sent once the interval allows."""
    link, ap, clock, _ = udp_pair
    ap.mav.send(_ap_heartbeat(ap.mav))
    assert _pump(link, lambda: link.tracker.autopilot_seen)
    link.notify_provenance(Provenance.SATELLITE_ANCHORED, Provenance.VISUAL_PROPAGATED, "GDN: vio only")
    clock.t += 0.2
    link.notify_provenance(Provenance.VISUAL_PROPAGATED, Provenance.NO_ESTIMATE, "GDN: lost")
    clock.t += 0.2
    link.notify_provenance(Provenance.NO_ESTIMATE, Provenance.SATELLITE_ANCHORED, "GDN: anchored again")
    link.poll()
    first = _recv_all(ap, "STATUSTEXT", 0.3)
    assert [x.text for x in first] == ["GDN: vio only"]
    assert first[0].severity == D.MAV_SEVERITY_WARNING
    clock.t += 0.61  # 1.01 s after the first
    link.poll()
    second = _recv_all(ap, "STATUSTEXT", 0.3)
    assert [x.text for x in second] == ["GDN: anchored again (+1)"]
    assert second[0].severity == D.MAV_SEVERITY_INFO
    clock.t += 5.0
    link.poll()
    assert _recv_all(ap, "STATUSTEXT", 0.2) == []  # nothing pending, nothing repeated
    link.notify_provenance(Provenance.SATELLITE_ANCHORED, Provenance.NO_ESTIMATE, "GDN: lost")
    third = _recv_all(ap, "STATUSTEXT", 0.3)
    assert [(x.text, x.severity) for x in third] == [("GDN: lost", D.MAV_SEVERITY_CRITICAL)]
    stats = link.stats()
    assert stats.statustext_sent == 3 and stats.statustext_coalesced == 1


def _key_file(tmp_path: Path, content: bytes, mode: int, name: str = "mavlink.key") -> Path:
    p = tmp_path / name
    p.write_bytes(content)
    os.chmod(p, mode)
    return p


def test_signing_key_file_permissions_and_format_are_checked(tmp_path: Path) -> None:
    """A group/world-readable key file, a wrong length, or a missing file is refused at open()."""
    assert load_signing_key(_key_file(tmp_path, KEY_HEX.encode() + b"\n", 0o600)) == bytes.fromhex(KEY_HEX)
    assert load_signing_key(_key_file(tmp_path, bytes(range(32)), 0o400)) == bytes(range(32))
    cases = [
        (_key_file(tmp_path, KEY_HEX.encode(), 0o644, "world.key"), "mode 0644"),
        (_key_file(tmp_path, KEY_HEX.encode(), 0o640, "group.key"), "mode 0640"),
        (_key_file(tmp_path, b"short", 0o600, "short.key"), "32 raw bytes or 64 hex"),
        (_key_file(tmp_path, b"z" * 64, 0o600, "nothex.key"), "not hex"),
        (tmp_path / "missing.key", "cannot be read"),
    ]
    for path, match in cases:
        cfg = MavlinkConfig(url=f"udpin:127.0.0.1:{_free_udp_port()}", signing_key_file=str(path))
        link = MavlinkLink(cfg, _tracker())
        with pytest.raises(MavlinkConfigError, match=match):
            link.open()
        assert not link.connected


def test_signing_outgoing_verified_by_keyed_receiver(tmp_path: Path) -> None:
    """With a key, outputs are signed and verify on the keyed side; unsigned ones are rejected there,
    and the signed link ignores an unsigned autopilot."""
    key = bytes.fromhex(KEY_HEX)
    key_path = _key_file(tmp_path, KEY_HEX.encode(), 0o600)
    for signed in (True, False):
        port = _free_udp_port()
        cfg = MavlinkConfig(url=f"udpin:127.0.0.1:{port}", signing_key_file=str(key_path) if signed else None)
        link = MavlinkLink(cfg, _tracker())
        link.open()
        ap = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
        try:
            ap.setup_signing(key, sign_outgoing=True)
            ap.mav.send(_ap_heartbeat(ap.mav))
            tracker = link.tracker
            assert _pump(link, lambda: tracker.autopilot_seen)  # noqa: B023 - called within the iteration
            link.send_estimate(_state(), time_unix_usec=T0_UNIX_USEC)
            gps = ap.recv_match(type="GPS_INPUT", blocking=True, timeout=0.5 if not signed else 1.0)
            if signed:
                assert gps is not None and gps.get_signed() and gps.lat == 504501234
            else:
                assert gps is None and ap.mav.signing.goodsig_count == 0  # rejected: "Invalid signature"
        finally:
            ap.close()
            link.close()
    # the signed link refuses an unsigned autopilot
    port = _free_udp_port()
    link = MavlinkLink(
        MavlinkConfig(url=f"udpin:127.0.0.1:{port}", signing_key_file=str(key_path)), _tracker()
    )
    link.open()
    ap = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    try:
        ap.mav.send(_ap_heartbeat(ap.mav))
        assert not _pump(link, lambda: link.tracker.autopilot_seen, timeout_s=0.3)
        assert link.stats().bad_packets >= 1
    finally:
        ap.close()
        link.close()


def test_link_heartbeat_loss_and_recovery_with_fake_clock(udp_pair: tuple) -> None:
    """No autopilot heartbeat for link_timeout_s -> not alive, link_lost logged once; resumes after."""
    link, ap, clock, port = udp_pair
    ap.mav.send(_ap_heartbeat(ap.mav))
    assert _pump(link, lambda: link.tracker.link_alive())
    ap.close()
    with structlog.testing.capture_logs() as logs:
        clock.t += 2.9
        link.poll()
        assert link.tracker.link_alive()
        clock.t += 0.2  # 3.1 s > link_timeout_s = 3 s
        link.poll()
        assert not link.tracker.link_alive()
        clock.t += 5.0
        link.poll()
        ap2 = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
        try:
            ap2.mav.send(_ap_heartbeat(ap2.mav))
            assert _pump(link, lambda: link.tracker.link_alive())
        finally:
            ap2.close()
    events = [e["event"] for e in logs]
    assert events.count(LogEvent.MAVLINK_LINK_LOST) == 1
    assert events.count(LogEvent.MAVLINK_LINK_RESTORED) == 1


def test_link_tcp_transport_loss_reconnects_with_backoff() -> None:
    """TCP: no server at open -> down; server appears -> connects; peer close -> down, then reconnects."""
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind(("127.0.0.1", 0))
    port = server.getsockname()[1]
    server.close()  # nothing listening yet
    clock = FakeClock()
    link = MavlinkLink(MavlinkConfig(url=f"tcp:127.0.0.1:{port}"), _tracker(clock), clock=clock)
    with structlog.testing.capture_logs() as logs:
        link.open()
        assert not link.connected and link.fileno() is None
        assert link.send_heartbeat() is False  # dropped, not raised
        server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        server.bind(("127.0.0.1", port))
        server.listen(1)
        server.settimeout(2.0)
        try:
            link.poll()
            assert not link.connected  # backoff (0.5 s +- 20 %) not yet elapsed
            clock.t += 0.61
            link.poll()
            assert link.connected and isinstance(link.fileno(), int)
            peer, _ = server.accept()
            tx = D.MAVLink(None, srcSystem=1, srcComponent=1)
            peer.sendall(_ap_heartbeat(tx).pack(tx))
            assert _pump(link, lambda: link.tracker.autopilot_seen)
            peer.close()  # transport loss
            assert _pump(link, lambda: not link.connected)
            clock.t += 0.61
            link.poll()
            assert link.connected and link.stats().reconnects == 2
            peer2, _ = server.accept()
            peer2.close()
        finally:
            server.close()
            link.close()
    assert [e["event"] for e in logs].count(LogEvent.MAVLINK_LINK_LOST) >= 1


def test_link_sends_never_raise_when_closed() -> None:
    """Sends on a link that is not open are dropped and counted, never raised."""
    link = MavlinkLink(MavlinkConfig(url="udpout:127.0.0.1:9"), _tracker())
    assert link.send_estimate(_state(), time_unix_usec=T0_UNIX_USEC) == 0
    status = {
        "inliers": 1,
        "residual_px": 1.0,
        "horiz_sigma_m": 1.0,
        "frame_drops": 0,
        "fdr_health": FdrHealthState.OK,
    }
    assert link.send_status_values(provenance=Provenance.SATELLITE_ANCHORED, **status) == 0
    link.notify_provenance(None, Provenance.SATELLITE_ANCHORED)
    assert link.poll() == 0
    assert link.stats().sends_dropped_link_down > 0


def test_link_rejects_unknown_url_scheme() -> None:
    """An unsupported connection string is a MavlinkConfigError naming the URL."""
    link = MavlinkLink(MavlinkConfig(url="http://127.0.0.1:80"), _tracker())
    with pytest.raises(MavlinkConfigError, match=re.escape("http://127.0.0.1:80")):
        link.open()


def test_named_values_without_residual_send_nan() -> None:
    """A frame with no match has no residual: GDN_RES goes out as NaN instead of failing the send."""
    import math as _math

    from pymavlink.dialects.v20 import common

    from gps_denied_onboard.components.c8_mavlink.messages import named_values
    from gps_denied_onboard.constants import NV_RESIDUAL_PX, Provenance

    mav = common.MAVLink(None, srcSystem=1, srcComponent=197)
    msgs = named_values(mav, time_boot_ms=1, provenance=Provenance.VISUAL_PROPAGATED, inliers=16,
                        residual_px=None, horiz_sigma_m=2.0, frame_drops=0, fdr_health=FdrHealthState.OK)
    res = [m for m in msgs if m.get_type() == "NAMED_VALUE_FLOAT" and m.name == NV_RESIDUAL_PX]
    assert len(res) == 1 and _math.isnan(res[0].value)


def _reuseaddr_udp_socket() -> socket.socket:
    """A UDP socket set up the way pymavlink's udpin sets up its own (SO_REUSEADDR)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    return s


def test_link_open_refuses_udpin_port_bound_by_another_socket() -> None:
    """open() on a udpin port another socket holds (even with SO_REUSEADDR) raises MavlinkConfigError
    naming the port, and binds nothing."""
    with _reuseaddr_udp_socket() as other:
        other.bind(("127.0.0.1", 0))
        port = other.getsockname()[1]
        link = MavlinkLink(MavlinkConfig(url=f"udpin:127.0.0.1:{port}"), _tracker())
        with pytest.raises(MavlinkConfigError, match=rf"UDP port {port} on 127\.0\.0\.1 is already bound"):
            link.open()
        assert not link.connected


def test_link_udpin_port_cannot_be_shared_after_open() -> None:
    """Once a link listens on a udpin port, a second link is refused and a later SO_REUSEADDR bind (another
    pymavlink program) fails instead of silently taking the autopilot's datagrams."""
    port = _free_udp_port()
    first = MavlinkLink(MavlinkConfig(url=f"udpin:127.0.0.1:{port}"), _tracker())
    first.open()
    try:
        assert first.connected
        second = MavlinkLink(MavlinkConfig(url=f"udp:127.0.0.1:{port}"), _tracker())
        with pytest.raises(MavlinkConfigError, match="already bound"):
            second.open()
        with _reuseaddr_udp_socket() as late, pytest.raises(OSError) as err:
            late.bind(("127.0.0.1", port))
        assert err.value.errno == errno.EADDRINUSE
    finally:
        first.close()


# --- shared local frame, reset_counter, sensor id ----------------------------------------------------


def _state_at(
    t_usec: int,
    pos_ned_m: tuple[float, float, float],
    *,
    provenance: Provenance = Provenance.SATELLITE_ANCHORED,
    vel: tuple[float, float, float] = (5.0, 0.0, 0.0),
    sigma_m: float = 3.0,
) -> EstimatorState:
    return EstimatorState(
        time_unix_usec=t_usec,
        provenance=provenance,
        pos_ned_m=np.array(pos_ned_m, dtype=np.float64),
        vel_ned_m_s=np.array(vel, dtype=np.float64),
        cov_pos_ned_m2=np.diag([sigma_m**2, sigma_m**2, 4.0]),
        cov_vel_ned_m2_s2=np.diag([0.25, 0.25, 0.09]),
        lat_deg=50.45,
        lon_deg=30.52,
        alt_amsl_m=280.0,
        yaw_rad=None,
        last_fix_age_s=0.1,
        shared_sigma_m=1.0,
    )


def _ap_origin(mav: Any, lat_deg: float, lon_deg: float, alt_amsl_m: float) -> Any:
    return mav.gps_global_origin_encode(
        round(lat_deg * 1e7), round(lon_deg * 1e7), round(alt_amsl_m * 1000), T0_UNIX_USEC
    )


def _seen(link: MavlinkLink, ap: Any) -> None:
    ap.mav.send(_ap_heartbeat(ap.mav))
    assert _pump(link, lambda: link.tracker.link_alive())


def test_link_offers_origin_when_autopilot_seen_and_repeats_until_reported(udp_pair: tuple) -> None:
    """SET_GPS_GLOBAL_ORIGIN (the ltp origin) and a GPS_GLOBAL_ORIGIN request go out once the autopilot is
    seen, every 10 s until it reports an origin, then stop; no VISION_POSITION_ESTIMATE before the offer."""
    link, ap, clock, _ = udp_pair
    state = _state_at(T0_UNIX_USEC, (10.0, 20.0, -100.0))
    assert link.send_estimate(state, time_unix_usec=T0_UNIX_USEC) == 2  # GPS_INPUT + GPS sensor only
    assert link.stats().vision_withheld == 1 and link.stats().global_origin_sent == 0

    _seen(link, ap)
    got = _recv_all(ap, ["SET_GPS_GLOBAL_ORIGIN", "COMMAND_LONG", "VISION_POSITION_ESTIMATE"], 0.3)
    origin = [x for x in got if x.get_type() == "SET_GPS_GLOBAL_ORIGIN"]
    assert len(origin) == 1 and origin[0].get_srcComponent() == 197
    assert origin[0].target_system == 1
    assert origin[0].latitude == 504500000 and origin[0].longitude == 305200000
    assert origin[0].altitude == 180_000 and origin[0].time_usec == int(clock.t * 1e6)
    request = [x for x in got if x.get_type() == "COMMAND_LONG"]
    assert request and request[0].command == D.MAV_CMD_REQUEST_MESSAGE
    assert request[0].param1 == D.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN and request[0].target_component == 1
    assert not [x for x in got if x.get_type() == "VISION_POSITION_ESTIMATE"]  # the one before was withheld

    clock.t += SET_GPS_GLOBAL_ORIGIN_INTERVAL_S / 2
    _seen(link, ap)
    assert _recv_all(ap, "SET_GPS_GLOBAL_ORIGIN", 0.2) == []  # not due yet
    clock.t += SET_GPS_GLOBAL_ORIGIN_INTERVAL_S / 2
    _seen(link, ap)
    assert len(_recv_all(ap, "SET_GPS_GLOBAL_ORIGIN", 0.3)) == 1
    assert link.stats().global_origin_sent == 2

    ap.mav.send(_ap_origin(ap.mav, 50.45, 30.52, 180.0))  # the autopilot adopted ours
    assert _pump(link, lambda: link.tracker.gps_origin() is not None)
    clock.t += 3 * SET_GPS_GLOBAL_ORIGIN_INTERVAL_S
    _seen(link, ap)
    assert link.send_estimate(state, time_unix_usec=T0_UNIX_USEC) == 3
    got = _recv_all(ap, ["SET_GPS_GLOBAL_ORIGIN", "VISION_POSITION_ESTIMATE"], 0.3)
    assert [x.get_type() for x in got] == ["VISION_POSITION_ESTIMATE"]
    assert (got[0].x, got[0].y, got[0].z) == pytest.approx((10.0, 20.0, -100.0), abs=1e-4)


def test_link_vision_position_is_state_ned_in_the_shared_frame(udp_pair: tuple) -> None:
    """After the offer, VISION_POSITION_ESTIMATE x/y/z are the state's NED position in the ltp, unchanged."""
    link, ap, _clock, _ = udp_pair
    _seen(link, ap)
    state = _state_at(T0_UNIX_USEC, (123.25, -456.5, -80.0))
    link.send_estimate(state, time_unix_usec=T0_UNIX_USEC + 1000)
    vpe = _recv_all(ap, "VISION_POSITION_ESTIMATE", 0.3)
    assert len(vpe) == 1 and vpe[0].usec == T0_UNIX_USEC + 1000
    assert (vpe[0].x, vpe[0].y, vpe[0].z) == pytest.approx((123.25, -456.5, -80.0), abs=1e-4)


def test_link_vision_position_reexpressed_at_autopilot_origin(udp_pair: tuple) -> None:
    """An autopilot that reports another origin gets positions in its own NED frame (and no
    SET_GPS_GLOBAL_ORIGIN); the switch from our frame to its frame bumps reset_counter."""
    link, ap, clock, _ = udp_pair
    _seen(link, ap)
    state = _state_at(T0_UNIX_USEC, (10.0, 20.0, -100.0))
    link.send_estimate(state, time_unix_usec=T0_UNIX_USEC)
    first = _recv_all(ap, "VISION_POSITION_ESTIMATE", 0.3)
    assert len(first) == 1 and first[0].x == pytest.approx(10.0, abs=1e-4)

    # The autopilot's origin lies 100 m north, 50 m west and 20 m above ours.
    lat, lon, alt = LTP.to_geodetic(np.array([100.0, -50.0, -20.0]))
    ap.mav.send(_ap_origin(ap.mav, float(lat), float(lon), float(alt)))
    assert _pump(link, lambda: link.tracker.gps_origin() is not None)
    clock.t += 2 * SET_GPS_GLOBAL_ORIGIN_INTERVAL_S
    _seen(link, ap)
    later = _state_at(T0_UNIX_USEC + 100_000, (10.5, 20.0, -100.0))
    link.send_estimate(later, time_unix_usec=T0_UNIX_USEC + 100_000)
    got = _recv_all(ap, ["VISION_POSITION_ESTIMATE", "SET_GPS_GLOBAL_ORIGIN"], 0.3)
    assert [x.get_type() for x in got] == ["VISION_POSITION_ESTIMATE"]
    vpe = got[0]
    # 1e-7 deg and 1 mm rounding of the reported origin: about 1 cm.
    assert (vpe.x, vpe.y, vpe.z) == pytest.approx((10.5 - 100.0, 20.0 + 50.0, -100.0 + 20.0), abs=0.02)
    assert vpe.reset_counter == (first[0].reset_counter + 1) & 0xFF


def test_link_vision_reset_counter_bumps_on_reinit_and_jump_not_on_motion(udp_pair: tuple) -> None:
    """reset_counter: unchanged over ordinary motion and a 1.7-sigma correction; +1 on a jump beyond
    3 sigma; +1 when an estimate follows no_estimate."""
    link, ap, _clock, _ = udp_pair
    _seen(link, ap)
    t, north = T0_UNIX_USEC, 0.0
    plan: list[tuple[float, Provenance]] = []
    for _ in range(5):  # 5 m/s at 10 Hz: 0.5 m per send, as predicted by the velocity
        north += 0.5
        plan.append((north, Provenance.VISUAL_PROPAGATED))
    north += 0.5 + 5.0  # an ordinary fix moves it 5 m (< 3 * 3 m)
    plan.append((north, Provenance.SATELLITE_ANCHORED))
    north += 0.5 + 20.0  # a re-acquisition lands 20 m away (> 3 * 3 m)
    plan.append((north, Provenance.SATELLITE_ANCHORED))
    north += 0.5
    plan.append((north, Provenance.SATELLITE_ANCHORED))
    plan.append((north, Provenance.NO_ESTIMATE))
    plan.append((north + 300.0, Provenance.SATELLITE_ANCHORED))  # re-initialised elsewhere
    for n, provenance in plan:
        t += 100_000
        link.send_estimate(_state_at(t, (n, 0.0, -50.0), provenance=provenance), time_unix_usec=t)
    vpe = _recv_all(ap, "VISION_POSITION_ESTIMATE", 0.4)
    counters = [x.reset_counter for x in vpe]
    c = counters[0]
    assert counters == [c] * 6 + [c + 1, c + 1, c + 2]
    assert [x.x for x in vpe][-1] == pytest.approx(north + 300.0)


def test_vision_position_jumped_rule() -> None:
    """The jump rule: beyond 3 previous sigma (horizontal or vertical) after the velocity's prediction,
    with a 0.5 m floor; non-finite input is not a jump."""
    prev = _state_at(T0_UNIX_USEC, (0.0, 0.0, -50.0), sigma_m=2.0)
    dt = 200_000  # 0.2 s at 5 m/s north: predicted 1 m north
    assert not m.vision_position_jumped(prev, _state_at(T0_UNIX_USEC + dt, (1.0 + 5.9, 0.0, -50.0)))
    assert m.vision_position_jumped(prev, _state_at(T0_UNIX_USEC + dt, (1.0 + 6.1, 0.0, -50.0)))
    assert m.vision_position_jumped(prev, _state_at(T0_UNIX_USEC + dt, (1.0, 0.0, -50.0 + 6.1)))  # sigma_d 2
    tiny = _state_at(T0_UNIX_USEC, (0.0, 0.0, -50.0), sigma_m=0.01)
    assert not m.vision_position_jumped(tiny, _state_at(T0_UNIX_USEC + dt, (1.4, 0.0, -50.0)))
    nan = _state_at(T0_UNIX_USEC + dt, (math.nan, 0.0, -50.0))
    assert not m.vision_position_jumped(prev, nan)


def test_link_global_position_sensor_carries_configured_id() -> None:
    """GLOBAL_POSITION_SENSOR.id is mavlink.global_position_sensor_id (so it can match EKF2_AGP0_ID), and
    GPS_INPUT.gps_id is mavlink.gps_input_gps_id."""
    port = _free_udp_port()
    cfg = MavlinkConfig(
        url=f"udpin:127.0.0.1:{port}",
        outputs=("global_position_sensor", "gps_input"),
        global_position_sensor_id=7,
        gps_input_gps_id=1,
    )
    link = MavlinkLink(cfg, _tracker())
    link.open()
    ap = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    try:
        ap.mav.send(_ap_heartbeat(ap.mav))
        assert _pump(link, lambda: link.tracker.autopilot_seen)
        assert link.send_estimate(_state(), time_unix_usec=T0_UNIX_USEC) == 2
        got = {x.get_type(): x for x in _recv_all(ap, ["GLOBAL_POSITION_SENSOR", "GPS_INPUT"], 0.3)}
        sensor = got["GLOBAL_POSITION_SENSOR"]
        assert sensor.id == 7 and sensor.target_system == 1 and sensor.flags == 0
        assert got["GPS_INPUT"].gps_id == 1  # GPS2_TYPE=14 for the in-flight switch
    finally:
        ap.close()
        link.close()
    assert MavlinkConfig().global_position_sensor_id == 1
    with pytest.raises(ConfigError, match="global_position_sensor_id"):
        config_from_mapping({"mavlink": {"global_position_sensor_id": 256}})
    with pytest.raises(ConfigError, match="gps_input_gps_id"):
        config_from_mapping({"mavlink": {"gps_input_gps_id": 2}})


def test_link_refuses_vision_output_without_local_frame() -> None:
    """vision_position_estimate without the daemon's ltp cannot say which frame it is in: refused."""
    cfg = MavlinkConfig(url="udpout:127.0.0.1:9", outputs=("vision_position_estimate",))
    with pytest.raises(MavlinkConfigError, match="ltp"):
        MavlinkLink(cfg, _tracker())


def test_tracker_gps_global_origin_from_autopilot_only() -> None:
    """GPS_GLOBAL_ORIGIN from the autopilot is kept (degE7, mm); another system's is ignored."""
    tracker = _tracker()
    now = T0_UNIX_USEC / 1e6
    assert tracker.gps_origin() is None
    assert not tracker.handle(_decoded(lambda mav: _ap_origin(mav, 1.0, 2.0, 3.0), src=(2, 1)), now)
    assert tracker.handle(_decoded(lambda mav: _ap_origin(mav, 50.4512345, 30.5212345, 201.5)), now)
    origin = tracker.gps_origin()
    assert origin == pytest.approx((50.4512345, 30.5212345, 201.5))


def test_named_values_carry_fdr_health_code() -> None:
    """GDN_FDR goes out as a NAMED_VALUE_INT with the recorder's health code; decoded by pymavlink."""
    from pymavlink.dialects.v20 import common

    from gps_denied_onboard.components.c8_mavlink.messages import named_values
    from gps_denied_onboard.constants import NV_FDR_HEALTH

    for health, code in ((FdrHealthState.OK, 0), (FdrHealthState.DEGRADED, 1), (FdrHealthState.FAILING, 2)):
        tx = common.MAVLink(None, srcSystem=1, srcComponent=197)
        msgs = named_values(tx, time_boot_ms=5, provenance=Provenance.DEAD_RECKONING, inliers=0,
                            residual_px=None, horiz_sigma_m=9.0, frame_drops=0, fdr_health=health)
        rx = common.MAVLink(None)
        decoded = [rx.decode(bytearray(m.pack(tx))) for m in msgs]
        fdr = [m for m in decoded if m.get_type() == "NAMED_VALUE_INT" and m.name == NV_FDR_HEALTH]
        assert len(fdr) == 1 and fdr[0].value == code and fdr[0].time_boot_ms == 5


def test_tracker_down_curve_in_the_camera_from_the_attitude() -> None:
    """World-down in the camera around an instant: pitching up at 10 deg/s moves it along the camera's
    y axis (image down = body backward) by 0.175 rad/s, rolling along its x axis; no attitude: None."""
    recv_s = T0_UNIX_USEC / 1e6
    offsets = np.array([-0.1, 0.0, 0.1])
    for roll_rate, pitch_rate, axis in ((0.0, 10.0, 1), (10.0, 0.0, 0)):
        tr = _tracker()
        for k in range(16):  # 50 Hz for 300 ms
            t_ms = BOOT0_MS + 20 * k
            roll, pitch = math.radians(roll_rate * 0.02 * k), math.radians(pitch_rate * 0.02 * k)
            tr.handle(
                _decoded(lambda mav, t=t_ms, r=roll, p=pitch: mav.attitude_encode(t, r, p, 0.3, 0, 0, 0)),
                recv_s + 0.02 * k,
            )
        curve = tr.down_cam_curve(T0_UNIX_USEC + 150_000, offsets)
        assert curve is not None and curve.shape == (3, 2)
        rate = (curve[2] - curve[0]) / 0.2
        assert abs(rate[axis]) == pytest.approx(math.radians(10.0), rel=0.02), rate
        assert abs(rate[1 - axis]) < 1e-3, rate
    assert _tracker().down_cam_curve(T0_UNIX_USEC, offsets) is None


def test_tracker_ground_altitude_waits_for_the_ekf_origin() -> None:
    """Before the EKF has an origin ArduPilot's GLOBAL_POSITION_INT carries no position and alt 0: the
    ground is HOME_POSITION's altitude then, and alt - relative_alt once it carries one."""
    tr = _tracker()
    recv_s = T0_UNIX_USEC / 1e6
    assert tr.ground_alt_amsl_m() is None
    lat, lon = 504501234, 305234567
    no_origin = _decoded(lambda mav: mav.global_position_int_encode(BOOT0_MS, 0, 0, 0, 80_000, 0, 0, 0, 0))
    tr.handle(no_origin, recv_s)
    assert tr.ground_alt_amsl_m() is None  # alt 0 before the origin is no ground at -80 m
    q = [1.0, 0.0, 0.0, 0.0]
    home = _decoded(lambda mav: mav.home_position_encode(lat, lon, 520_000, 0, 0, 0, q, 0, 0, 0))
    tr.handle(home, recv_s)
    assert tr.ground_alt_amsl_m() == pytest.approx(520.0)
    origin = _decoded(
        lambda mav: mav.global_position_int_encode(BOOT0_MS, lat, lon, 601_000, 80_000, 0, 0, 0, 0)
    )
    tr.handle(origin, recv_s)
    assert tr.ground_alt_amsl_m() == pytest.approx(521.0)


def test_gps_input_without_a_trusted_altitude_flags_it_ignored() -> None:
    """``alt_trusted=False`` (the ground altitude disagrees with the autopilot's): the altitude, VDOP and
    vertical accuracy are flagged as ignored and sent as 0; the horizontal fix is unchanged."""
    mav = D.MAVLink(None)
    ok = m.gps_input(mav, _state(), time_unix_usec=T0_UNIX_USEC)
    off = m.gps_input(mav, _state(), time_unix_usec=T0_UNIX_USEC, alt_trusted=False)
    alt_flags = (
        D.GPS_INPUT_IGNORE_FLAG_ALT | D.GPS_INPUT_IGNORE_FLAG_VDOP | D.GPS_INPUT_IGNORE_FLAG_VERTICAL_ACCURACY
    )
    assert ok.ignore_flags & alt_flags == 0 and ok.alt == pytest.approx(250.0)
    assert off.ignore_flags & alt_flags == alt_flags and off.alt == 0.0 and off.vert_accuracy == 0.0
    assert (off.lat, off.lon, off.fix_type) == (ok.lat, ok.lon, ok.fix_type)


def test_tracker_ahrs_doubt_grows_with_the_autopilots_manoeuvres() -> None:
    """Level flight: no doubt of the autopilot's tilt beyond its own; a 3 deg step: a tenth of it; after
    roll and pitch swung by 20 and 10 deg within the window, a tenth of the swing (the AHRS error
    measured on ArduPilot SITL); no samples: None."""
    recv_s = T0_UNIX_USEC / 1e6
    tr = _tracker()
    for k in range(50):  # 1 s level at 50 Hz
        t_ms = BOOT0_MS + 20 * k
        level = _decoded(lambda mav, t=t_ms: mav.attitude_encode(t, 0.0, 0.0, 0.3, 0, 0, 0))
        tr.handle(level, recv_s + 0.02 * k)
    assert tr.ahrs_doubt_rad(T0_UNIX_USEC + 980_000) == pytest.approx(0.0)
    step = _tracker()
    for k in range(60):
        t_ms, r = BOOT0_MS + 20 * k, math.radians(3.0) if k >= 50 else 0.0
        msg = _decoded(lambda mav, t=t_ms, r=r: mav.attitude_encode(t, r, 0.0, 0.3, 0, 0, 0))
        step.handle(msg, recv_s + 0.02 * k)
    assert step.ahrs_doubt_rad(T0_UNIX_USEC + 1_180_000) == pytest.approx(0.1 * math.radians(3.0))
    roll, pitch = math.radians(20.0), math.radians(-10.0)
    for k in range(50, 60):
        t_ms = BOOT0_MS + 20 * k
        tr.handle(
            _decoded(lambda mav, t=t_ms: mav.attitude_encode(t, roll, pitch, 0.3, 0, 0, 0)), recv_s + 0.02 * k
        )
    doubt = tr.ahrs_doubt_rad(T0_UNIX_USEC + 1_180_000)
    assert doubt == pytest.approx(0.1 * math.hypot(roll, pitch), rel=1e-6)
    assert _tracker().ahrs_doubt_rad(T0_UNIX_USEC) is None


def test_a_state_no_map_fix_has_confirmed_is_never_a_3d_fix() -> None:
    """Issue 37: a start prior (configured, HOME_POSITION) stating 5 m is a claim until a map fix
    confirms it: GPS_INPUT says no fix (1), GLOBAL_POSITION_SENSOR is not built, the 3D stream never
    enters; the same state confirmed is 3D."""
    from dataclasses import replace

    mav = D.MAVLink(None)
    claim = replace(_state(Provenance.VISUAL_PROPAGATED), map_confirmed=False)
    assert m.gps_input(mav, claim, time_unix_usec=T0_UNIX_USEC).fix_type == 1
    assert m.gps_input(mav, replace(claim, map_confirmed=True), time_unix_usec=T0_UNIX_USEC).fix_type == 3
    assert m.withheld_reason(claim) == "no map fix has confirmed the start"
    with pytest.raises(ValueError, match="confirmed the start"):
        m.global_position_sensor(
            mav, claim, time_unix_usec=T0_UNIX_USEC, processing_time_usec=0, target_system=1, sensor_id=1
        )
    gate = m.Fix3dGate(settle_s=0.0)
    assert all(
        gate.fix_type(replace(claim, time_unix_usec=T0_UNIX_USEC + k * 100_000)) == 1 for k in range(20)
    )


def test_link_sends_no_vision_position_for_a_state_no_map_fix_has_confirmed(udp_pair: tuple) -> None:
    """VISION_POSITION_ESTIMATE has no fix_type to say "not to be trusted": an unconfirmed start prior
    is not sent at all, and the confirmed state is."""
    from dataclasses import replace

    link, ap, _clock, _ = udp_pair
    _seen(link, ap)
    state = _state_at(T0_UNIX_USEC, (123.25, -456.5, -80.0))
    link.send_estimate(replace(state, map_confirmed=False), time_unix_usec=T0_UNIX_USEC + 1000)
    assert _recv_all(ap, "VISION_POSITION_ESTIMATE", 0.3) == []
    link.send_estimate(state, time_unix_usec=T0_UNIX_USEC + 2000)
    assert len(_recv_all(ap, "VISION_POSITION_ESTIMATE", 0.3)) == 1


def _ground_fix(tr: VehicleStateTracker, recv_s: float, lat_e7: int, lon_e7: int, h_acc_mm: int) -> None:
    """What an autopilot with GNSS streams on the ground: EKF status, GPS_RAW_INT, GLOBAL_POSITION_INT."""
    good = D.EKF_ATTITUDE | D.EKF_VELOCITY_HORIZ | D.EKF_POS_HORIZ_ABS
    tr.handle(_decoded(lambda mav: mav.ekf_status_report_encode(good, 0.1, 0.1, 0.1, 0.1, 0.0)), recv_s)
    raw = _decoded(
        lambda mav: mav.gps_raw_int_encode(
            0, 3, lat_e7, lon_e7, 400_000, 100, 100, 0, 0, 12, 400_000, h_acc_mm
        )
    )
    tr.handle(raw, recv_s)
    gpi = _decoded(
        lambda mav: mav.global_position_int_encode(BOOT0_MS, lat_e7, lon_e7, 400_000, 0, 0, 0, 0, 0)
    )
    tr.handle(
        gpi,
        recv_s,
    )


def test_tracker_keeps_the_autopilots_position_on_the_ground_with_its_stated_accuracy() -> None:
    """Issue 37: the autopilot's own position while the vehicle stands on the ground (disarmed or
    landed ON_GROUND), its EKF vouching for it, with GPS_RAW_INT.h_acc as its sigma, is kept for the
    run: the start points' witness. In the air it is not taken as a ground position."""
    tr = _tracker()
    recv_s = T0_UNIX_USEC / 1e6
    tr.handle(_decoded(lambda mav: mav.system_time_encode(T0_UNIX_USEC, BOOT0_MS)), recv_s)
    _ground_fix(tr, recv_s, 504501234, 305234567, 2500)
    assert tr.ground_position() is None  # nothing said it stands on the ground
    tr.handle(_decoded(lambda mav: mav.extended_sys_state_encode(0, D.MAV_LANDED_STATE_ON_GROUND)), recv_s)
    _ground_fix(tr, recv_s + 0.5, 504501234, 305234567, 2500)
    ground = tr.ground_position()
    assert ground is not None
    assert (ground.lat_deg, ground.lon_deg, ground.sigma_m) == pytest.approx((50.4501234, 30.5234567, 2.5))
    tr.handle(_decoded(lambda mav: mav.extended_sys_state_encode(0, D.MAV_LANDED_STATE_IN_AIR)), recv_s + 1)
    _ground_fix(tr, recv_s + 1.5, 504600000, 305234567, 2500)
    assert tr.ground_position() == ground  # in the air: the ground position stays the last one


def test_tracker_says_whether_home_came_signed() -> None:
    """An unsigned HOME_POSITION is a claim anyone on the link could have made (``home_signed``)."""
    tr = _tracker()
    home = _decoded(
        lambda mav: mav.home_position_encode(504501234, 305234567, 180_000, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0)
    )
    assert not home.get_signed()
    tr.handle(home, T0_UNIX_USEC / 1e6)
    assert tr.home() is not None and not tr.home_signed()
    home._signed = True  # as pymavlink marks a message whose signature it verified
    tr.handle(home, T0_UNIX_USEC / 1e6)
    assert tr.home_signed()


def test_px4_never_gets_an_origin_or_a_position_from_a_daemon_without_a_backed_fix(
    recording_fdr: Any,
) -> None:
    """Issue 34: PX4 takes its origin from the first GLOBAL_POSITION_SENSOR whatever it says, and resets
    to messages it does not fuse (the double, ``sitl/px4_rules.py``, measured rules). Over UDP, the real
    link: no estimate, an unconfirmed start, dead reckoning and a NaN altitude send nothing (the double
    keeps no origin, nothing at 0,0 arrives); the first backed state sets the origin where it is, with its
    altitude; dead reckoning after it stops the stream, so PX4 fails safe instead of following it."""
    from dataclasses import replace

    from gps_denied_onboard.sitl.px4_rules import Origin, Px4AuxGlobalPosition

    port = _free_udp_port()
    fdr = recording_fdr
    link = MavlinkLink(
        MavlinkConfig(url=f"udpin:127.0.0.1:{port}", outputs=("global_position_sensor",)), _tracker()
    )
    link.open()
    link.attach(fdr, None)
    ap = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    px4 = Px4AuxGlobalPosition({"EKF2_AGP0_ID": 1, "EKF2_AGP0_CTRL": 1})
    received: list[Any] = []

    def feed(states: list[EstimatorState]) -> None:
        for k, state in enumerate(states):
            link.send_estimate(state, time_unix_usec=T0_UNIX_USEC + k * 100_000)
        for msg in _recv_all(ap, "GLOBAL_POSITION_SENSOR", 0.3):
            received.append(msg)
            px4.receive(msg.to_dict(), time.monotonic())

    try:
        ap.mav.send(_ap_heartbeat(ap.mav))
        assert _pump(link, lambda: link.tracker.autopilot_seen)
        good = _state(Provenance.SATELLITE_ANCHORED)
        unbacked = (
            [EstimatorState.no_estimate(T0_UNIX_USEC)] * 5
            + [replace(good, map_confirmed=False)] * 5
            + [_state(Provenance.DEAD_RECKONING)] * 5
            + [replace(good, alt_amsl_m=math.nan)] * 5
        )
        feed(unbacked)
        assert received == [] and px4.origin is None and px4.global_position() is None
        assert link.stats().positions_withheld == 20
        feed([good] * 5)
        assert len(received) == 5 and all(msg.flags == 0 and math.isfinite(msg.alt) for msg in received)
        near = {"abs": 1e-7}
        assert px4.origin == Origin(
            pytest.approx(good.lat_deg, **near), pytest.approx(good.lon_deg, **near), good.alt_amsl_m, True
        )
        assert px4.global_position() == pytest.approx((good.lat_deg, good.lon_deg), abs=1e-7)
        feed([_state(Provenance.DEAD_RECKONING)] * 5)
        assert len(received) == 5
        assert px4.failsafe(time.monotonic() + 5.3)
        events = [r["event"] for kind, r in fdr.records if kind == FdrKind.LINK_EVENT]
        assert events.count("output_withheld") == 5 and events.count("output_resumed") == 1
    finally:
        ap.close()
        link.close()


def test_px4_parameters_are_read_back_byte_wise_and_a_wrong_one_named_with_the_fix() -> None:
    """PX4 answers PARAM_REQUEST_READ with integers byte-wise in PARAM_VALUE's float; the link asks, the
    tracker decodes, and ``px4_agp_problems`` names each wrong value with the value to set and the reboot
    (the id and CTRL are read at boot). Preflight's reader does the same over real UDP."""
    import struct

    from gps_denied_onboard.cli_preflight import _read_px4_params
    from gps_denied_onboard.components.c8_mavlink.px4_params import PX4_AGP_PARAMS, px4_agp_problems
    from gps_denied_onboard.config import Config

    port = _free_udp_port()
    cfg = MavlinkConfig(url=f"udpin:127.0.0.1:{port}", outputs=("global_position_sensor",))
    link = MavlinkLink(cfg, _tracker())
    link.open()
    px4 = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    px4_params = {"EKF2_AGP0_ID": (0, D.MAV_PARAM_TYPE_INT32), "EKF2_AGP0_CTRL": (0, D.MAV_PARAM_TYPE_INT32)}
    px4_params["EKF2_AGP0_DELAY"] = (200.0, D.MAV_PARAM_TYPE_REAL32)
    try:
        px4.mav.heartbeat_send(D.MAV_TYPE_QUADROTOR, D.MAV_AUTOPILOT_PX4, 0, 0, D.MAV_STATE_STANDBY)
        assert _pump(link, lambda: link.tracker.autopilot_kind == D.MAV_AUTOPILOT_PX4)
        assert link.request_params(PX4_AGP_PARAMS)
        for _ in PX4_AGP_PARAMS:
            ask = px4.recv_match(type="PARAM_REQUEST_READ", blocking=True, timeout=2.0)
            assert ask is not None and ask.target_system == 1 and ask.target_component == 1
            name = ask.param_id if isinstance(ask.param_id, str) else ask.param_id.decode()
            value, kind = px4_params[name]
            if kind != D.MAV_PARAM_TYPE_REAL32:  # PX4's byte-wise encoding of an integer
                value = struct.unpack("<f", struct.pack("<i", int(value)))[0]
            wire = value
            px4.mav.param_value_send(name.encode(), wire, kind, len(px4_params), 0)
        assert _pump(link, lambda: link.tracker.param("EKF2_AGP0_DELAY") is not None)
        values = {name: link.tracker.param(name) for name in PX4_AGP_PARAMS}
        assert values == {"EKF2_AGP0_ID": 0.0, "EKF2_AGP0_CTRL": 0.0, "EKF2_AGP0_DELAY": 200.0}
        problems = px4_agp_problems(values, sensor_id=1)
        assert [p.detail.split(":")[0] for p in problems] == [
            "EKF2_AGP0_ID is 0",
            "EKF2_AGP0_CTRL is 0",
            "EKF2_AGP0_DELAY is 200 ms",
        ]
        assert "set it to 1" in problems[0].detail and "reboot PX4" in problems[0].detail
        assert problems[0].blocks_output and not problems[2].blocks_output
        assert all(len(p.statustext.encode()) <= m.STATUSTEXT_MAX_BYTES for p in problems)
        good = {"EKF2_AGP0_ID": 1, "EKF2_AGP0_CTRL": 1, "EKF2_AGP0_DELAY": 0.0}
        assert px4_agp_problems(good, sensor_id=1) == []
        unread = px4_agp_problems({}, sensor_id=1)
        assert len(unread) == 1 and "did not answer" in unread[0].detail and not unread[0].blocks_output
        config = Config(mavlink=cfg)
        assert _read_px4_params(config, link, link.tracker, time.monotonic() + 0.3) == values
    finally:
        px4.close()
        link.close()
