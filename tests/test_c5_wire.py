"""The estimator's state between the vision worker and the navigator core (``c5_estimator/wire.py``): a
filter restored from the wire predicts exactly what the original does, and a malformed message is refused
with the field that is wrong."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from gps_denied_onboard.components.c5_estimator.ekf import NavEstimator, PriorConflict
from gps_denied_onboard.components.c5_estimator.protocol import ImuAcceleration
from gps_denied_onboard.components.c5_estimator.wire import (
    WireError,
    pack,
    state_from_wire,
    state_to_wire,
    unpack,
)
from gps_denied_onboard.config import EstimatorConfig
from gps_denied_onboard.geo import LocalTangentPlane
from test_c5_estimator import LTP, S, _fix, _vo
from test_c5_estimator import T0_USEC as T0


class _Accel:
    """A constant NED acceleration (the autopilot's IMU, as the tracker gives it)."""

    def accel_ned_mean(self, t0: int, t1: int) -> ImuAcceleration:
        return ImuAcceleration(np.array([0.3, -0.2, 0.0]), 0.1)


def _flown() -> NavEstimator:
    """A filter that has fused fixes and VO, then heard VO say another velocity twice (a gated run under
    way)."""
    est = NavEstimator(EstimatorConfig(), LTP, accel_source=_Accel())
    est.initialise(np.zeros(3), 30.0, T0)
    for k in range(1, 6):
        t = T0 + k * S // 3
        est.update_vo(_vo(np.array([3.0, 1.0]), 0.3, 1 / 3), time_unix_usec=t)
        est.update_fix(_fix(np.array([3.0 * k, 1.0 * k, 0.0]), 2.0, t, shared_sigma_m=0.5))
    for k in range(6, 8):
        assert not est.update_vo(
            _vo(np.array([-3.0, 1.0]), 0.05, 1 / 3), time_unix_usec=T0 + k * S // 3
        ).accepted
    assert len(est.checkpoint().vo_gated_run) == 2
    return est


def test_a_restored_filter_predicts_exactly_what_the_original_does() -> None:
    est = _flown()
    message = unpack(pack({"kind": "estimate", "state": state_to_wire(est.checkpoint(), LTP)}))
    wire = state_from_wire(message["state"])
    assert wire.ltp == LTP
    core = NavEstimator(EstimatorConfig(), wire.ltp, accel_source=_Accel())
    core.restore(wire.checkpoint)
    t_head = est.time_unix_usec
    assert t_head is not None and core.time_unix_usec == t_head
    for dt_usec in (0, 100_000, 2 * S, 9 * S):
        a, b = est.state(t_head + dt_usec), core.state(t_head + dt_usec)
        assert a.provenance is b.provenance
        assert (a.lat_deg, a.lon_deg, a.alt_amsl_m) == (b.lat_deg, b.lon_deg, b.alt_amsl_m)
        np.testing.assert_array_equal(a.cov_pos_ned_m2, b.cov_pos_ned_m2)
        np.testing.assert_array_equal(a.vel_ned_m_s, b.vel_ned_m_s)
        assert a.shared_sigma_m == b.shared_sigma_m and a.map_confirmed == b.map_confirmed
    # the prediction grows the stated sigma: a core predicting on alone states more and more
    assert core.state(t_head + 9 * S).horiz_sigma_m > core.state(t_head).horiz_sigma_m


def test_every_field_of_the_checkpoint_survives_the_wire() -> None:
    cp = _flown().checkpoint()
    back = state_from_wire(unpack(pack({"kind": "x", "state": state_to_wire(cp, LTP)}))["state"]).checkpoint
    for field in dataclasses.fields(cp):
        a, b = getattr(back, field.name), getattr(cp, field.name)
        if isinstance(b, np.ndarray):
            np.testing.assert_array_equal(a, b)
        else:
            assert a == b, field.name


def _good() -> dict[str, object]:
    return state_to_wire(_flown().checkpoint(), LocalTangentPlane(17.59, 78.12, 500.0))


@pytest.mark.parametrize(
    ("field", "value", "named"),
    [
        ("p", [1.0] * 35, "p"),
        ("p", [math.nan] * 36, "p"),
        ("x", [0.0, 0.0, math.inf, 0.0, 0.0, 0.0], "x"),
        ("x", "north", "x"),
        ("t", 1.5, "t"),
        ("gated", -1, "gated"),
        ("shared", -0.1, "shared"),
        ("yaw", math.nan, "yaw"),
        ("ltp", [math.nan, 0.0, 0.0], "ltp"),
        ("anchor", 1.5e18, "anchor"),
        ("vo_gated_run", [[0.0, 1.0, 2.0]], "vo_gated_run"),
        ("vo_gated_run", [[0.0, 1.0, 2.0, 0.0, 2.0, math.nan]], "vo_gated_run"),
    ],
)
def test_a_malformed_state_is_refused_naming_the_field(field: str, value: object, named: str) -> None:
    fields = {**_good(), field: value}
    with pytest.raises(WireError, match=named):
        state_from_wire(fields)


def test_times_are_mapped_from_the_senders_clock_onto_the_receivers() -> None:
    """Two processes' clocks count the host's monotonic time from anchors that differ by what the wall
    clock slewed or stepped between their starts: the receiver's times are the sender's plus that."""
    cp = _flown().checkpoint()
    sender, receiver = 1_700_000_000_000_000_000, 1_700_000_000_250_000_000  # anchors 0.25 s apart
    fields = state_to_wire(cp, LocalTangentPlane(17.59, 78.12, 500.0), clock_anchor_ns=sender)
    mapped = state_from_wire(fields, clock_anchor_ns=receiver).checkpoint
    assert cp.time_usec is not None and cp.last_fix_usec is not None and cp.last_vo_usec is not None
    assert mapped.time_usec == cp.time_usec + 250_000
    assert mapped.last_fix_usec == cp.last_fix_usec + 250_000
    assert mapped.last_vo_usec == cp.last_vo_usec + 250_000
    assert mapped.last_no_fix_usec == (None if cp.last_no_fix_usec is None else cp.last_no_fix_usec + 250_000)
    # with either anchor unknown the times are taken as they are
    assert state_from_wire(fields).checkpoint.time_usec == cp.time_usec
    unsaid = state_to_wire(cp, LocalTangentPlane(17.59, 78.12, 500.0))
    assert state_from_wire(unsaid, clock_anchor_ns=receiver).checkpoint.time_usec == cp.time_usec


def test_a_missing_field_and_an_asymmetric_covariance_are_refused() -> None:
    fields = _good()
    del fields["last_vo"]
    with pytest.raises(WireError, match="last_vo"):
        state_from_wire(fields)
    p = np.eye(6)
    p[0, 1] = 5.0
    with pytest.raises(WireError, match="symmetric"):
        state_from_wire({**_good(), "p": p.reshape(-1).tolist()})


@pytest.mark.parametrize("data", [b"", b"\xc1", pack([1, 2]), pack({"kind": 3}), pack({"state": {}})])
def test_a_message_that_is_not_a_kinded_map_is_refused(data: bytes) -> None:
    with pytest.raises(WireError):
        unpack(data)


def test_a_prior_conflict_under_way_survives_the_wire() -> None:
    conflict = PriorConflict(
        np.array([1.0, 2.0]), np.array([40.0, -3.0]), np.eye(2) * 4.0, np.array([[9.0, 1.0], [1.0, 8.0]]), 2
    )
    cp = dataclasses.replace(_flown().checkpoint(), prior_conflict=conflict)
    back = state_from_wire(state_to_wire(cp, LTP)).checkpoint.prior_conflict
    assert back is not None and back.count == 2
    for name in ("first_pos_ne", "innov_ne", "fix_cov_ne", "p_ne"):
        np.testing.assert_array_equal(getattr(back, name), getattr(conflict, name))
