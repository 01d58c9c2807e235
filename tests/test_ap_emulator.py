"""The ArduPilot emulator's rules, over real UDP on loopback (the emulator in a thread of this process).

Each test drives the emulator as a companion computer and a ground station would and checks one
measured fact it must reproduce (sitl/ap_emulator.py; ../shared/DESIGN.md).
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil

from gps_denied_onboard.geo import gps_week_and_ms
from gps_denied_onboard.sitl.ap_emulator import (
    MODE_GUIDED,
    MODE_LAND,
    ArduPilotEmulator,
    EmulatorOptions,
    select_primary,
)

HOME = (17.5916, 78.1214, 400.0)


class Client:
    """A pymavlink peer of one emulator channel that keeps everything it receives."""

    def __init__(self, port: int, comp: int) -> None:
        self.conn = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{port}", source_system=1 if comp == 197 else 255, source_component=comp
        )
        self.msgs: list[Any] = []
        self.speed_accuracy = 0.5
        self.conn.mav.heartbeat_send(6, 8, 0, 0, 0)

    def pump(self, seconds: float, until: Callable[[Any], bool] | None = None) -> Any:
        end = time.time() + seconds
        while time.time() < end:
            m = self.conn.recv_match(blocking=True, timeout=0.05)
            if m is None:
                continue
            self.msgs.append(m)
            if until is not None and until(m):
                return m
        return None

    def gps_input(self, lat: float, lon: float, gps_id: int = 1, fix_type: int = 3) -> None:
        week, week_ms = gps_week_and_ms(int(time.time() * 1e6))
        self.conn.mav.gps_input_send(
            int(time.time() * 1e6),
            gps_id,
            0,
            week_ms,
            week,
            fix_type,
            round(lat * 1e7),
            round(lon * 1e7),
            400.0,
            1.0,
            1.0,
            0,
            0,
            0,
            self.speed_accuracy,
            0.5,
            0.5,
            10,
            0,
        )

    def command(self, cmd: int, *p: float) -> int | None:
        args = [*p, *([0.0] * (7 - len(p)))]
        self.conn.mav.command_long_send(1, 1, cmd, 0, *args)
        ack = self.pump(3.0, lambda m: m.get_type() == "COMMAND_ACK" and m.command == cmd)
        return None if ack is None else int(ack.result)

    def texts(self) -> list[str]:
        return [m.text for m in self.msgs if m.get_type() == "STATUSTEXT"]


@pytest.fixture
def emulator() -> Iterator[ArduPilotEmulator]:
    emu = ArduPilotEmulator(
        EmulatorOptions(
            *HOME,
            ports=(0, 0),
            params={"GPS2_TYPE": 14.0},
            ekf_origin_delay_s=0.2,
            ekf_using_gps_delay_s=0.5,
            quiet=True,
        )
    )
    t = threading.Thread(target=emu.run, daemon=True)
    t.start()
    yield emu
    emu.stop()
    t.join(3)
    emu.close()


def test_select_primary_keeps_current_and_switches_on_loss() -> None:
    assert select_primary(1, 0, [True, True]) == 0
    assert select_primary(1, 0, [False, True]) == 1
    assert select_primary(1, 1, [True, True]) == 1
    assert select_primary(0, 1, [False, True]) == 0


def test_gps2_bad_fix_blocks_arming_until_gps_input(emulator: ArduPilotEmulator) -> None:
    gcs = Client(emulator.ports[0], 190)
    gcs.pump(1.0)
    assert gcs.command(mavutil.mavlink.MAV_CMD_DO_SET_MODE, 1, MODE_GUIDED) == 0
    assert gcs.command(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavutil.mavlink.MAV_RESULT_FAILED
    gcs.pump(0.3)
    assert "PreArm: GPS 2: Bad fix" in gcs.texts()
    comp = Client(emulator.ports[1], 197)
    for _ in range(10):
        comp.gps_input(*HOME[:2])
        time.sleep(0.1)
    gcs.pump(0.3)
    assert "GPS 2: detected MAV" in gcs.texts()
    assert gcs.command(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavutil.mavlink.MAV_RESULT_ACCEPTED


def test_gps1_type_is_reboot_required(emulator: ArduPilotEmulator) -> None:
    gcs = Client(emulator.ports[0], 190)
    gcs.conn.mav.param_set_send(1, 1, b"GPS1_TYPE", 14.0, mavutil.mavlink.MAV_PARAM_TYPE_REAL32)
    pv = gcs.pump(2.0, lambda m: m.get_type() == "PARAM_VALUE")
    assert pv is not None and pv.param_value == 14.0  # stored and reported...
    comp = Client(emulator.ports[1], 197)
    for _ in range(5):
        comp.gps_input(*HOME[:2], gps_id=0)
        time.sleep(0.1)
    assert 0 not in emulator.mav_gps  # ...but not in effect: gps_id 0 finds no MAVLink instance
    gcs.command(mavutil.mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1)
    time.sleep(0.2)
    assert 0 in emulator.mav_gps


def _fly_on_gps2(emulator: ArduPilotEmulator, comp: Client, gcs: Client, offset_deg: float = 0.0) -> None:
    """Armed in GUIDED at 20 m with the simulated GNSS off, flying on GPS_INPUT (gps_id 1)."""
    stop = threading.Event()

    def feed() -> None:
        while not stop.is_set():
            lat, lon, _ = emulator._geodetic(emulator.pos_ned)
            comp.gps_input(lat + offset_deg, lon)
            time.sleep(0.1)

    t = threading.Thread(target=feed, daemon=True)
    t.start()
    comp._stop = stop  # type: ignore[attr-defined]
    time.sleep(1.0)
    assert gcs.command(mavutil.mavlink.MAV_CMD_DO_SET_MODE, 1, MODE_GUIDED) == 0
    assert gcs.command(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0, gcs.texts()
    assert gcs.command(mavutil.mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 20) == 0
    gcs.conn.mav.param_set_send(1, 1, b"SIM_GPS1_ENABLE", 0.0, mavutil.mavlink.MAV_PARAM_TYPE_REAL32)
    gcs.pump(2.0)
    assert emulator.primary == 1


def test_fused_position_follows_a_bias_and_the_vehicle_moves_by_it(emulator: ArduPilotEmulator) -> None:
    """EKF3 follows GPS_INPUT completely: a 10 m north bias moves the truth 10 m south of the target."""
    gcs, comp = Client(emulator.ports[0], 190), Client(emulator.ports[1], 197)
    _fly_on_gps2(emulator, comp, gcs)
    target = emulator.target_ned.copy()
    comp._stop.set()  # type: ignore[attr-defined]
    time.sleep(0.15)
    _fly_on_gps2_bias = 10.0 / 111_320.0
    stop = threading.Event()

    def feed() -> None:
        while not stop.is_set():
            lat, lon, _ = emulator._geodetic(emulator.pos_ned)
            comp.gps_input(lat + _fly_on_gps2_bias, lon)
            time.sleep(0.1)

    t = threading.Thread(target=feed, daemon=True)
    t.start()
    gcs.pump(8.0)
    stop.set()
    assert math.isclose(emulator.est_err_ne[0], 10.0, abs_tol=0.3), emulator.est_err_ne
    truth_north = emulator.pos_ned[0] - target[0]
    assert -10.6 < truth_north < -9.4, truth_north
    sim = [m for m in gcs.msgs if m.get_type() == "SIMSTATE"][-1]
    gp = [m for m in gcs.msgs if m.get_type() == "GLOBAL_POSITION_INT"][-1]
    assert math.isclose((gp.lat - sim.lat) / 1e7 * 111_320.0, 10.0, abs_tol=0.8)


def test_ekf_failsafe_land_at_7_8_s_and_latched(emulator: ArduPilotEmulator) -> None:
    gcs, comp = Client(emulator.ports[0], 190), Client(emulator.ports[1], 197)
    _fly_on_gps2(emulator, comp, gcs)
    comp._stop.set()  # type: ignore[attr-defined]
    t_stop = time.time()
    fs = gcs.pump(12.0, lambda m: m.get_type() == "STATUSTEXT" and "EKF Failsafe" in m.text)
    assert fs is not None and fs.text == "EKF Failsafe: changed to LAND Mode"
    assert 7.7 <= time.time() - t_stop <= 8.6
    stages = [e["stage"] for e in emulator.events if e["kind"] == "gps_loss"]
    assert stages == ["NO_FIX", "EKF_POSITION_LOST", "EKF_FAILSAFE_LAND"], stages
    for _ in range(20):  # the stream resumes: LAND stays
        lat, lon, _ = emulator._geodetic(emulator.pos_ned)
        comp.gps_input(lat, lon)
        time.sleep(0.1)
    assert emulator.mode == MODE_LAND


def test_broadcast_from_the_companion_reaches_the_other_channel(emulator: ArduPilotEmulator) -> None:
    gcs, comp = Client(emulator.ports[0], 190), Client(emulator.ports[1], 197)
    gcs.pump(0.3)
    comp.conn.mav.statustext_send(6, b"GDN: hello")
    m = gcs.pump(2.0, lambda m: m.get_type() == "STATUSTEXT" and m.get_srcComponent() == 197)
    assert m is not None and m.text == "GDN: hello"


def _emulator(**opts: Any) -> tuple[ArduPilotEmulator, threading.Thread]:
    emu = ArduPilotEmulator(
        EmulatorOptions(
            *HOME,
            ports=(0, 0),
            params=opts.pop("params", {"GPS2_TYPE": 14.0}),
            ekf_origin_delay_s=opts.pop("ekf_origin_delay_s", 0.2),
            ekf_using_gps_delay_s=0.5,
            quiet=True,
            **opts,
        )
    )
    t = threading.Thread(target=emu.run, daemon=True)
    t.start()
    return emu, t


def _stop(emu: ArduPilotEmulator, t: threading.Thread) -> None:
    emu.stop()
    t.join(3)
    emu.close()


def test_timesync_is_answered_with_boot_time_while_system_time_runs_behind(
    emulator: ArduPilotEmulator,
) -> None:
    """TIMESYNC: tc1 is the emulator's boot time when the request arrived (GCS_Common.cpp
    handle_timesync), ts1 echoed; SYSTEM_TIME's Unix time is 2.0 s behind the host (measured on SITL)."""
    comp = Client(emulator.ports[1], 197)
    sent = time.time()
    comp.conn.mav.timesync_send(0, 123_456_789)
    ans = comp.pump(2.0, lambda m: m.get_type() == "TIMESYNC" and m.ts1 == 123_456_789)
    assert ans is not None
    boot_s = sent - emulator.boot_unix_s
    assert ans.tc1 / 1e9 == pytest.approx(boot_s, abs=0.1)
    st = comp.pump(2.0, lambda m: m.get_type() == "SYSTEM_TIME")
    assert st is not None
    host_at_boot_ms = emulator.boot_unix_s + st.time_boot_ms / 1000.0
    assert st.time_unix_usec / 1e6 - host_at_boot_ms == pytest.approx(-2.0, abs=0.1)


def test_global_position_is_zero_until_the_ekf_has_an_origin() -> None:
    """Before the EKF origin GLOBAL_POSITION_INT's lat/lon/alt are 0 (measured: alt 0; the driver read a
    ground 520 m low from it), relative_alt is the barometer's; after it they are the position."""
    emu, t = _emulator(ekf_origin_delay_s=2.0)
    try:
        gcs = Client(emu.ports[0], 190)
        early = gcs.pump(1.0, lambda m: m.get_type() == "GLOBAL_POSITION_INT")
        assert early is not None and (early.lat, early.lon, early.alt) == (0, 0, 0)
        gcs.pump(2.5)
        late = gcs.pump(1.0, lambda m: m.get_type() == "GLOBAL_POSITION_INT")
        assert late is not None and late.alt == pytest.approx(HOME[2] * 1000, abs=50)
    finally:
        _stop(emu, t)


def test_arming_skipchk_replaces_arming_check_upstream() -> None:
    """Upstream 4.7 (PR #31568): ARMING_SKIPCHK (a mask of skipped checks) instead of ARMING_CHECK;
    bit 3 skips the GPS check, so GPS 2 without a fix no longer blocks arming."""
    emu, t = _emulator(arming_skipchk=True)
    try:
        assert "ARMING_CHECK" not in emu.params and emu.params["ARMING_SKIPCHK"] == 0
        assert any("GPS 2: Bad fix" in f for f in emu.prearm_failures(emu.now_s()))
        emu.params["ARMING_SKIPCHK"] = 8.0
        assert not any("GPS" in f for f in emu.prearm_failures(emu.now_s()))
    finally:
        _stop(emu, t)


def _speed_to(gcs: Client, emu: ArduPilotEmulator, north_m: float) -> None:
    lat, lon, _ = emu._geodetic(emu.pos_ned + np.array([north_m, 0.0, 0.0]))
    gcs.conn.mav.set_position_target_global_int_send(
        0, 1, 1, mavutil.mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 0b110111111000,
        round(lat * 1e7), round(lon * 1e7), 20.0, 0, 0, 0, 0, 0, 0, 0, 0,
    )  # fmt: skip


@pytest.mark.parametrize(("delay_ms", "lag_s"), [(0.0, 0.2), (10.0, 0.01)])
def test_the_ekf_runs_ahead_of_gps_input_by_speed_times_gps_delay(delay_ms: float, lag_s: float) -> None:
    """The EKF takes GPS_INPUT as measured GPS2_DELAY_MS (0.2 s when 0, GPS_Backend.h) before it arrived:
    fed the true position, its estimate runs ahead by the speed times that lag."""
    emu, t = _emulator(params={"GPS2_TYPE": 14.0, "GPS2_DELAY_MS": delay_ms})
    try:
        gcs, comp = Client(emu.ports[0], 190), Client(emu.ports[1], 197)
        _fly_on_gps2(emu, comp, gcs)
        _speed_to(gcs, emu, 400.0)
        gcs.pump(6.0)
        speed = float(math.hypot(*emu.vel_ned[:2]))
        assert speed > 5.0
        ahead = float(emu.est_err_ne @ (emu.vel_ned[:2] / speed))
        assert ahead == pytest.approx(speed * lag_s, abs=0.35), (ahead, speed)
        comp._stop.set()  # type: ignore[attr-defined]
    finally:
        _stop(emu, t)


def test_speed_accuracy_above_the_ekf_threshold_is_a_gps_glitch() -> None:
    """EKF3's filtered, peak-held speed accuracy above 1.5 m/s: "GPS Glitch or Compass error"; below
    1.0 m/s again (the peak decays over 10 s): "Glitch cleared"."""
    emu, t = _emulator()
    try:
        gcs, comp = Client(emu.ports[0], 190), Client(emu.ports[1], 197)
        _fly_on_gps2(emu, comp, gcs)
        comp.speed_accuracy = 2.5  # type: ignore[attr-defined]
        hit = gcs.pump(5.0, lambda m: m.get_type() == "STATUSTEXT" and "GPS Glitch" in m.text)
        assert hit is not None and hit.text == "GPS Glitch or Compass error"
        comp.speed_accuracy = 0.3  # type: ignore[attr-defined]
        cleared = gcs.pump(20.0, lambda m: m.get_type() == "STATUSTEXT" and "Glitch cleared" in m.text)
        assert cleared is not None
        comp._stop.set()  # type: ignore[attr-defined]
    finally:
        _stop(emu, t)
