"""The PX4 emulator's protocol and rules over real UDP on loopback (the emulator in a thread of this process).

Each test drives the emulator as a companion computer and a ground station would and checks one fact
measured on PX4 SITL with SIH that it must reproduce (sitl/px4_emulator.py; docs/px4.md, "The PX4 emulator
(CI)"). The emulator is a test double, not PX4.
"""

from __future__ import annotations

import os
import struct
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil

from gps_denied_onboard.sitl.px4_emulator import HEADING_SETTLE_S, Px4Emulator, Px4EmulatorOptions
from gps_denied_onboard.sitl.px4_mission import (
    PX4_MAIN_AUTO,
    PX4_SUB_AUTO_LAND,
    PX4_SUB_AUTO_MISSION,
    px4_mode,
)
from gps_denied_onboard.sitl.px4_rules import POSITION_TIMEOUT_S
from test_ap_emulator import Client

HOME = (17.5916, 78.1214, 400.0)
AGP = {"EKF2_AGP0_ID": 1.0, "EKF2_AGP0_CTRL": 1.0}
M = mavutil.mavlink


def _as_int(value: float) -> int:
    return int(struct.unpack("<i", struct.pack("<f", value))[0])


def _as_float(value: int) -> float:
    return float(struct.unpack("<f", struct.pack("<i", value))[0])


def _start(params: dict[str, float]) -> Px4Emulator:
    emu = Px4Emulator(Px4EmulatorOptions(*HOME, ports=(0,), params=params, quiet=True))
    threading.Thread(target=emu.run, daemon=True).start()
    return emu


@pytest.fixture
def emulators() -> Iterator[list[Px4Emulator]]:
    started: list[Px4Emulator] = []
    yield started
    for emu in started:
        emu.stop()
    time.sleep(0.1)
    for emu in started:
        emu.close()


def _param(gcs: Client, name: str) -> Any:
    gcs.conn.mav.param_request_read_send(1, 1, name.encode(), -1)
    return gcs.pump(2.0, lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == name)


def _set_int(gcs: Client, name: str, value: int) -> Any:
    gcs.conn.mav.param_set_send(1, 1, name.encode(), _as_float(value), M.MAV_PARAM_TYPE_INT32)
    return gcs.pump(2.0, lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == name)


def _sensor(gcs: Client, lat_deg: float, lon_deg: float, sensor_id: int = 1, eph: float = 2.0) -> None:
    gcs.conn.mav.global_position_sensor_send(
        1, 1, sensor_id, 0, 0, 0, 0, round(lat_deg * 1e7), round(lon_deg * 1e7), float("nan"), 440.0, eph, 5.0
    )


def _of(gcs: Client, mtype: str, since: int = 0) -> list[Any]:
    return [m for m in gcs.msgs[since:] if m.get_type() == mtype]


def test_heartbeat_is_px4s_and_integer_parameters_are_bytewise(emulators: list[Px4Emulator]) -> None:
    """HEARTBEAT autopilot 12, type 2, custom mode enabled, custom_mode main << 16 | sub << 24; integer
    parameters travel byte-wise in the float (INT32), floats as REAL32; PARAM_SET is read the same way."""
    emu = _start({**AGP})
    emulators.append(emu)
    gcs = Client(emu.ports[0], 190)
    hb = gcs.pump(2.0, lambda m: m.get_type() == "HEARTBEAT")
    assert hb is not None and hb.autopilot == M.MAV_AUTOPILOT_PX4 and hb.type == M.MAV_TYPE_QUADROTOR
    assert hb.base_mode & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert hb.custom_mode == px4_mode(PX4_MAIN_AUTO, 3)  # AUTO.LOITER
    agp_id = _param(gcs, "EKF2_AGP0_ID")
    assert agp_id.param_type == M.MAV_PARAM_TYPE_INT32 and agp_id.param_value != 1.0
    assert _as_int(agp_id.param_value) == 1
    cruise = _param(gcs, "MPC_XY_CRUISE")
    assert cruise.param_type == M.MAV_PARAM_TYPE_REAL32 and cruise.param_value == pytest.approx(5.0)
    assert _as_int(_param(gcs, "SIM_GPS_USED").param_value) == 10
    assert _as_int(_set_int(gcs, "SIM_GPS_USED", 0).param_value) == 0
    mark = len(gcs.msgs)
    gcs.pump(0.5)
    assert {m.fix_type for m in _of(gcs, "GPS_RAW_INT", mark)} == {0}  # SIH's GNSS off at once


def test_agp_parameters_are_read_at_boot_only(emulators: list[Px4Emulator]) -> None:
    """EKF2_AGP0_ID set at run time changes PARAM_VALUE, not the estimator: messages with the boot id are
    still fused, the first one setting the origin."""
    emu = _start({**AGP, "SIM_GPS_USED": 0.0})
    emulators.append(emu)
    gcs = Client(emu.ports[0], 190)
    assert _as_int(_set_int(gcs, "EKF2_AGP0_ID", 2).param_value) == 2
    for _ in range(10):
        _sensor(gcs, HOME[0], HOME[1], sensor_id=1)
        gcs.pump(0.1)
    assert emu.ekf_origin() is not None and emu.agp_outcomes.get("fused", 0) >= 5, emu.agp_outcomes
    assert gcs.pump(1.0, lambda m: m.get_type() == "GLOBAL_POSITION_INT") is not None


def test_a_first_unknown_id_takes_a_free_slot_and_binds_the_link(emulators: list[Px4Emulator]) -> None:
    """A first message with an id no EKF2_AGP<i>_ID holds takes the free instance 1, saved in
    EKF2_AGP1_ID (PARAM_VALUE), and binds the link to it: the configured id 1 is then never fused."""
    emu = _start({**AGP, "SIM_GPS_USED": 0.0})
    emulators.append(emu)
    gcs = Client(emu.ports[0], 190)
    for sensor_id in (2, 1, 1, 1, 1):
        _sensor(gcs, HOME[0], HOME[1], sensor_id=sensor_id)
        gcs.pump(0.1)
    assert _as_int(_param(gcs, "EKF2_AGP1_ID").param_value) == 2
    assert emu.agp_outcomes == {"ignored": 5} and emu.ekf_origin() is None


def test_no_gnss_and_no_message_means_no_origin_and_gps_input_is_ignored(
    emulators: list[Px4Emulator],
) -> None:
    """With SIH's GNSS off from boot and no GLOBAL_POSITION_SENSOR, EKF2 has no origin: no
    GLOBAL_POSITION_INT, GPS_GLOBAL_ORIGIN refused; GPS_INPUT, for which PX4 has no handler, changes
    nothing."""
    emu = _start({**AGP, "SIM_GPS_USED": 0.0})
    emulators.append(emu)
    gcs = Client(emu.ports[0], 190)
    for _ in range(15):
        gcs.gps_input(HOME[0], HOME[1])
        gcs.pump(0.1)
    assert gcs.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN) == M.MAV_RESULT_DENIED
    gcs.pump(0.5)
    assert _of(gcs, "GLOBAL_POSITION_INT") == [] and _of(gcs, "GPS_GLOBAL_ORIGIN") == []
    assert len(_of(gcs, "ATTITUDE")) > 50  # it streams: only the position is missing
    assert emu.ekf_origin() is None and emu.unhandled.get("GPS_INPUT", 0) == 15


def test_hil_state_quaternion_streams_only_when_asked_with_time_usec_0(emulators: list[Px4Emulator]) -> None:
    """SIH's truth, HIL_STATE_QUATERNION, is not streamed until MAV_CMD_SET_MESSAGE_INTERVAL asks for it
    (ACK 0); then at the rate asked, time_usec 0, lat/lon degE7, alt mm AMSL, a unit quaternion."""
    emu = _start({**AGP})
    emulators.append(emu)
    gcs = Client(emu.ports[0], 190)
    gcs.pump(0.5)
    assert _of(gcs, "HIL_STATE_QUATERNION") == []
    assert gcs.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_HIL_STATE_QUATERNION, 20_000) == 0
    mark = len(gcs.msgs)
    gcs.pump(1.0)
    hil = _of(gcs, "HIL_STATE_QUATERNION", mark)
    assert 40 <= len(hil) <= 60, len(hil)
    assert {m.time_usec for m in hil} == {0}
    assert hil[-1].lat == round(HOME[0] * 1e7) and hil[-1].alt == round(HOME[2] * 1000)
    assert sum(q * q for q in hil[-1].attitude_quaternion) == pytest.approx(1.0)


def test_timesync_answers_in_boot_time_and_px4_asks_at_10_hz(emulators: list[Px4Emulator]) -> None:
    """A TIMESYNC request is answered with PX4's boot time in ns, ts1 echoed; PX4 sends its own requests
    at 10 Hz."""
    emu = _start({**AGP})
    emulators.append(emu)
    gcs = Client(emu.ports[0], 190)
    gcs.pump(1.0)
    gcs.conn.mav.timesync_send(0, 123456789)
    answer = gcs.pump(1.0, lambda m: m.get_type() == "TIMESYNC" and m.ts1 == 123456789)
    assert answer is not None and abs(answer.tc1 / 1e9 - emu.now_s()) < 0.5
    requests = [m for m in _of(gcs, "TIMESYNC") if m.tc1 == 0]
    assert 7 <= len(requests) <= 13, len(requests)


def test_failsafe_5_3_s_after_the_last_fused_message_with_the_gnss_off(emulators: list[Px4Emulator]) -> None:
    """Take-off in AUTO.MISSION on the GNSS (mission protocol, arm, DO_SET_MODE), GLOBAL_POSITION_SENSOR
    fused, SIM_GPS_USED = 0, then the messages stop: "Failsafe activated" and a descent 5.3 s after the
    last one (measured), and GLOBAL_POSITION_INT stops with the position."""
    emu = _start({**AGP, "MPC_Z_V_AUTO_UP": 5.0})
    emulators.append(emu)
    gcs = Client(emu.ports[0], 190)
    gcs.conn.mav.mission_count_send(1, 1, 1, 0)
    req = gcs.pump(2.0, lambda m: m.get_type() == "MISSION_REQUEST_INT")
    assert req is not None and req.seq == 0  # no home item: seq 0 is the first real item
    gcs.conn.mav.mission_item_int_send(
        1, 1, 0, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, M.MAV_CMD_NAV_TAKEOFF, 0, 1, 0, 0, 0, 0,
        round(HOME[0] * 1e7), round(HOME[1] * 1e7), 4.0, 0,
    )  # fmt: skip
    ack = gcs.pump(2.0, lambda m: m.get_type() == "MISSION_ACK")
    assert ack is not None and ack.type == M.MAV_MISSION_ACCEPTED
    if emu.now_s() < HEADING_SETTLE_S:
        assert gcs.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) != M.MAV_RESULT_ACCEPTED
        assert "Preflight Fail: heading estimate not stable" in gcs.texts()
        gcs.pump(HEADING_SETTLE_S - emu.now_s() + 0.2)
    assert gcs.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
    assert gcs.command(M.MAV_CMD_DO_SET_MODE, 1, PX4_MAIN_AUTO, PX4_SUB_AUTO_MISSION) == M.MAV_RESULT_ACCEPTED
    assert gcs.pump(10.0, lambda m: m.get_type() == "GLOBAL_POSITION_INT" and m.relative_alt > 3500)
    for i in range(30):  # 3 s at 10 Hz where the vehicle is, the GNSS off after 1 s
        lat, lon, _alt = emu._geodetic(emu.pos_ned)
        _sensor(gcs, lat, lon)
        if i == 10:
            assert _as_int(_set_int(gcs, "SIM_GPS_USED", 0).param_value) == 0
        gcs.pump(0.1)
    t_last = time.time()
    assert emu.agp_outcomes.get("fused", 0) >= 20, emu.agp_outcomes
    text = gcs.pump(8.0, lambda m: m.get_type() == "STATUSTEXT" and m.text == "Failsafe activated")
    assert text is not None, gcs.texts()
    assert POSITION_TIMEOUT_S - 0.3 <= time.time() - t_last <= POSITION_TIMEOUT_S + 0.5
    mark = len(gcs.msgs)
    gcs.pump(1.5)
    assert _of(gcs, "GLOBAL_POSITION_INT", mark) == []
    assert _of(gcs, "HEARTBEAT", mark)[-1].custom_mode == px4_mode(PX4_MAIN_AUTO, PX4_SUB_AUTO_LAND)
    assert emu.vel_ned[2] > 0.5  # descending
