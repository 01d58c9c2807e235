"""The PX4 test double: which of the daemon's position messages PX4 would use, by the rules read in PX4's
source (DESIGN.md, "PX4"), checked on messages the daemon's own builders produce."""

from __future__ import annotations

import numpy as np
import pytest

from gps_denied_onboard.components.c5_estimator.types import EstimatorState
from gps_denied_onboard.components.c8_mavlink import messages as m
from gps_denied_onboard.components.c8_mavlink.messages import DIALECT as D
from gps_denied_onboard.constants import Provenance
from gps_denied_onboard.sitl.px4_rules import (
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


def test_px4_global_position_sensor_unused_when_flagged_unhealthy() -> None:
    """Dead reckoning and a too-large sigma set the UNHEALTHY flag; PX4 (double) does not use them."""
    for state in (_state(Provenance.DEAD_RECKONING), _state(sigma_m=80.0), _state(Provenance.NO_ESTIMATE)):
        fields = _gps_sensor_fields(state, sensor_id=1)
        assert fields["flags"] & D.GLOBAL_POSITION_UNHEALTHY
        assert global_position_sensor_rejection(fields, AGP0_ID1) == "GLOBAL_POSITION_UNHEALTHY flag set"


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
