"""The PX4 test double: which of the daemon's position messages PX4 would use, and what its EKF2 does
with a stream of them, by the rules measured on a real PX4 and read in its source (DESIGN.md, "What a
real PX4 does"), checked on messages the daemon's own builders produce."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gps_denied_onboard.components.c5_estimator.types import EstimatorState
from gps_denied_onboard.components.c8_mavlink import messages as m
from gps_denied_onboard.components.c8_mavlink.messages import DIALECT as D
from gps_denied_onboard.constants import Provenance
from gps_denied_onboard.sitl.px4_rules import (
    Origin,
    Px4AuxGlobalPosition,
    agp_instances_for,
    global_position_sensor_rejection,
    global_position_sensor_used,
    gps_input_used,
    px4_uses,
    vision_position_estimate_used,
)

T0_UNIX_USEC = 1_717_000_000_000_000
AGP0_ID1 = {"EKF2_AGP0_ID": 1, "EKF2_AGP0_CTRL": 1}


def _state(provenance: Provenance = Provenance.SATELLITE_ANCHORED, sigma_m: float = 4.0) -> EstimatorState:
    return EstimatorState(
        time_unix_usec=T0_UNIX_USEC,
        provenance=provenance,
        pos_ned_m=np.array([10.0, 20.0, -100.0]),
        vel_ned_m_s=np.zeros(3),
        cov_pos_ned_m2=np.diag([sigma_m**2, sigma_m**2, 25.0]),
        cov_vel_ned_m2_s2=np.diag([0.25, 0.25, 0.09]),
        lat_deg=50.45,
        lon_deg=30.52,
        alt_amsl_m=250.0,
        yaw_rad=None,
        last_fix_age_s=0.1,
        shared_sigma_m=1.0,
    )


def _gps_sensor_fields(state: EstimatorState, sensor_id: int) -> dict:
    """A GLOBAL_POSITION_SENSOR from the daemon's builder, encoded and decoded as PX4 would receive it."""
    tx = D.MAVLink(None, srcSystem=1, srcComponent=197)
    msg = m.global_position_sensor(
        tx, state, time_unix_usec=T0_UNIX_USEC, processing_time_usec=0, target_system=1, sensor_id=sensor_id
    )
    return D.MAVLink(None).decode(bytearray(msg.pack(tx))).to_dict()


def test_px4_gps_input_is_never_used() -> None:
    """PX4 has no GPS_INPUT handler: a valid 3D GPS_INPUT is unused under any parameters."""
    tx = D.MAVLink(None)
    fields = (
        D.MAVLink(None)
        .decode(bytearray(m.gps_input(tx, _state(), time_unix_usec=T0_UNIX_USEC).pack(tx)))
        .to_dict()
    )
    assert fields["fix_type"] == 3
    assert not gps_input_used(fields, {"EKF2_AGP0_ID": 0, "EKF2_AGP0_CTRL": 1, "EKF2_EV_CTRL": 15})
    assert not px4_uses("GPS_INPUT", fields, AGP0_ID1)


def test_px4_global_position_sensor_used_when_id_matches_enabled_agp() -> None:
    """A healthy GLOBAL_POSITION_SENSOR with id = EKF2_AGP0_ID and EKF2_AGP0_CTRL bit 0 is used."""
    fields = _gps_sensor_fields(_state(), sensor_id=1)
    assert fields["id"] == 1 and fields["flags"] == 0
    assert global_position_sensor_used(fields, AGP0_ID1)
    assert px4_uses("GLOBAL_POSITION_SENSOR", fields, AGP0_ID1)
    assert agp_instances_for(7, {"EKF2_AGP0_ID": 1, "EKF2_AGP2_ID": 7, "EKF2_AGP2_CTRL": 3}) == [2]


@pytest.mark.parametrize(
    ("params", "reason"),
    [
        ({"EKF2_AGP0_ID": 2, "EKF2_AGP0_CTRL": 1}, "no EKF2_AGP<i>_ID"),  # id mismatch
        ({"EKF2_AGP0_ID": 1, "EKF2_AGP0_CTRL": 0}, "no EKF2_AGP<i>_ID"),  # fusion disabled
        ({"EKF2_AGP0_ID": 1, "EKF2_AGP0_CTRL": 2}, "no EKF2_AGP<i>_ID"),  # another bit, not bit 0
        ({}, "no EKF2_AGP<i>_ID"),  # nothing configured
    ],
)
def test_px4_global_position_sensor_unused_without_matching_enabled_id(params: dict, reason: str) -> None:
    """The id must equal an EKF2_AGP<i>_ID whose EKF2_AGP<i>_CTRL has bit 0 set."""
    fields = _gps_sensor_fields(_state(), sensor_id=1)
    rejection = global_position_sensor_rejection(fields, params)
    assert rejection is not None and reason in rejection
    assert not global_position_sensor_used(fields, params)


def test_px4_reads_no_flags_so_the_daemon_never_sends_a_flagged_or_unbacked_message() -> None:
    """PX4 ignores GLOBAL_POSITION_UNHEALTHY (measured): a flagged message is routed like any other. So the
    daemon's builder refuses every state it cannot back (dead reckoning, a sigma above 50 m, no estimate,
    an unconfirmed start, a NaN altitude) and never sets the flag."""
    from dataclasses import replace

    flagged = {"id": 1, "flags": int(D.GLOBAL_POSITION_UNHEALTHY)}
    assert global_position_sensor_rejection(flagged, AGP0_ID1) is None
    assert _gps_sensor_fields(_state(), sensor_id=1)["flags"] == 0
    unbacked = {
        "dead reckoning": _state(Provenance.DEAD_RECKONING),
        "above 50 m": _state(sigma_m=80.0),
        "no estimate": _state(Provenance.NO_ESTIMATE),
        "confirmed the start": replace(_state(), map_confirmed=False),
        "altitude": replace(_state(), alt_amsl_m=float("nan")),
    }
    for reason, state in unbacked.items():
        with pytest.raises(ValueError, match=reason):
            _gps_sensor_fields(state, sensor_id=1)


def _msg(lat_deg: float, lon_deg: float, *, eph: float = 2.0, alt: float = 250.0, sensor_id: int = 1) -> dict:
    return {"id": sensor_id, "lat": round(lat_deg * 1e7), "lon": round(lon_deg * 1e7), "alt": alt, "eph": eph}


def test_px4_double_origin_comes_from_the_first_message_whatever_it_says() -> None:
    """Measured: the first message sets the origin, altitude included; eph = inf does not stop it, 0,0
    sets it there for good, and a NaN alt gives origin altitude 0 with no valid global altitude."""
    ekf = Px4AuxGlobalPosition(AGP0_ID1)
    ekf.receive(_msg(0.0, 0.0, eph=math.inf), 0.0)
    ekf.receive(_msg(50.45, 30.52), 1.0)
    assert ekf.origin == Origin(0.0, 0.0, 250.0, True)
    ekf = Px4AuxGlobalPosition(AGP0_ID1)
    ekf.receive(_msg(50.45, 30.52, alt=math.nan), 0.0)
    assert ekf.origin == Origin(50.45, 30.52, 0.0, False)


def test_px4_double_resets_to_an_unfusable_input_every_7_s_and_fails_safe_5_3_s_after_the_stream() -> None:
    """Measured: eph = inf is never fused, yet the position is reset to the message about every 7 s (to
    0,0 when it says 0,0); with no message, failsafe 5.3 s after the last update."""
    ekf = Px4AuxGlobalPosition(AGP0_ID1)
    assert ekf.receive(_msg(50.45, 30.52), 0.0) == "reset"
    outcomes = [ekf.receive(_msg(0.0, 0.0, eph=math.inf), 0.1 * k) for k in range(1, 80)]
    assert outcomes.index("reset") == 69 and outcomes.count("reset") == 1  # at 7.0 s
    assert ekf.global_position() == pytest.approx((0.0, 0.0), abs=1e-6)
    assert ekf.position_valid(7.9) and not ekf.failsafe(12.2) and ekf.failsafe(12.4)


def test_px4_double_follows_a_slow_bias_and_rejects_a_step() -> None:
    """Measured: a 20 m bias ramped at 0.5 m/s is followed completely; a 20 m step is rejected, the
    position lost ~5 s later (failsafe), and reset to the input at ~7 s."""
    lat0, lon0 = 50.45, 30.52
    dlat_per_m = 1.0 / 111_200.0
    ekf = Px4AuxGlobalPosition(AGP0_ID1)
    t = 0.0
    for _ in range(50):
        ekf.receive(_msg(lat0, lon0, eph=1.0), t)
        t += 0.1
    for k in range(400):  # 20 m at 0.5 m/s, then held, 10 Hz
        ekf.receive(_msg(lat0 + min(0.05 * (k + 1), 20.0) * dlat_per_m, lon0, eph=1.0), t)
        t += 0.1
    lat, _lon = ekf.global_position()
    assert (lat - lat0) / dlat_per_m == pytest.approx(20.0, abs=0.5)
    assert ekf.rejected == 0
    step = _msg(lat0 + 40.0 * dlat_per_m, lon0, eph=1.0)
    assert [ekf.receive(step, t + 0.1 * k) for k in range(1, 61)] == ["rejected"] * 60
    assert ekf.failsafe(t + 6.0)
    assert "reset" in [ekf.receive(step, t + 0.1 * k) for k in range(61, 80)]


def test_px4_double_binds_a_link_to_the_slot_of_a_first_unknown_id_until_reboot() -> None:
    """Measured: a first message whose id no EKF2_AGP<i>_ID holds takes a free slot, saves it, and binds
    the link: messages with the configured id are then never fused. EKF2_AGP0_ID set at run time does
    nothing until a reboot."""
    ekf = Px4AuxGlobalPosition(AGP0_ID1)
    assert ekf.receive(_msg(50.45, 30.52, sensor_id=9), 0.0) == "ignored"  # slot 1 taken, CTRL 0
    assert ekf.params["EKF2_AGP1_ID"] == 9
    assert all(ekf.receive(_msg(50.45, 30.52), 0.1 * k) == "ignored" for k in range(1, 20))
    ekf.reboot()
    assert ekf.receive(_msg(50.45, 30.52), 3.0) == "reset" and ekf.receive(_msg(50.45, 30.52), 3.1) == "fused"
    late = Px4AuxGlobalPosition({"EKF2_AGP0_ID": 0, "EKF2_AGP0_CTRL": 0})
    late.set_param("EKF2_AGP0_ID", 1)
    late.set_param("EKF2_AGP0_CTRL", 1)
    assert late.receive(_msg(50.45, 30.52), 0.0) == "ignored"
    late.reboot()
    assert late.receive(_msg(50.45, 30.52), 1.0) == "reset"


def test_px4_global_position_sensor_missing_fields_raise() -> None:
    """A field dict without id/flags is a caller bug, reported by name."""
    with pytest.raises(ValueError, match="'id'"):
        global_position_sensor_rejection({"flags": 0}, AGP0_ID1)


def test_px4_vision_position_estimate_needs_ev_ctrl_bit0() -> None:
    """VISION_POSITION_ESTIMATE is used only with EKF2_EV_CTRL bit 0 set."""
    assert vision_position_estimate_used({"EKF2_EV_CTRL": 1})
    assert vision_position_estimate_used({"EKF2_EV_CTRL": 15})
    assert not vision_position_estimate_used({"EKF2_EV_CTRL": 14})
    assert not vision_position_estimate_used({})
    assert px4_uses("VISION_POSITION_ESTIMATE", {}, {"EKF2_EV_CTRL": 1})
    assert not px4_uses("HEARTBEAT", {}, {"EKF2_EV_CTRL": 1})
