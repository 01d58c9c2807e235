"""C5 estimator: convergence, gating, re-acquisition, provenance and honest covariance growth."""

from __future__ import annotations

import dataclasses
import math
import uuid

import numpy as np
import pytest
import structlog

from gps_denied_onboard.components.c1_vio.types import VoMotion
from gps_denied_onboard.components.c4_pose.types import PoseFix
from gps_denied_onboard.components.c5_estimator import FixReason, NavEstimator
from gps_denied_onboard.components.c5_estimator.protocol import ImuAcceleration
from gps_denied_onboard.components.c6_tiles.types import TileId
from gps_denied_onboard.config import EstimatorConfig
from gps_denied_onboard.constants import LogEvent, Provenance
from gps_denied_onboard.geo import LocalTangentPlane

LTP = LocalTangentPlane(17.59, 78.12, 500.0)
T0_USEC = 1_700_000_000_000_000
S = 1_000_000  # one second in microseconds


def _fix(
    pos_ned: np.ndarray, sigma_m: float, t_usec: int, *, yaw_rad: float = 0.3, shared_sigma_m: float = 0.0
) -> PoseFix:
    lat, lon, alt = LTP.to_geodetic(pos_ned)
    return PoseFix(
        frame_id=uuid.uuid4(),
        exposure_time_unix_usec=t_usec,
        pos_ned_m=np.asarray(pos_ned, dtype=np.float64),
        cov_ned_m2=np.eye(3) * sigma_m**2,
        lat_deg=float(lat),
        lon_deg=float(lon),
        alt_amsl_m=float(alt),
        yaw_rad=yaw_rad,
        yaw_sigma_rad=0.01,
        attitude_disagreement_rad=0.01,
        image_tilt_off_cam_rad=(0.01, 0.0),
        inlier_count=80,
        residual_px=0.8,
        tile_id=TileId.of(18, float(lat), float(lon)),
        shared_sigma_m=shared_sigma_m,
    )


def _vo(delta_ne: np.ndarray, sigma_m: float, dt_s: float) -> VoMotion:
    return VoMotion(
        uuid.uuid4(), uuid.uuid4(), dt_s, np.asarray(delta_ne, float), np.eye(2) * sigma_m**2, 200
    )


def _estimator(**cfg: float) -> NavEstimator:
    return NavEstimator(EstimatorConfig(**cfg), LTP)


def test_estimator_converges_on_constant_velocity_truth() -> None:
    """Noisy 5 m fixes at 2 Hz on a straight 10 m/s track: error shrinks and NEES stays consistent."""
    rng = np.random.default_rng(0)
    vel = np.array([8.0, 6.0, 0.0])
    start = np.array([100.0, -50.0, -120.0])
    est = _estimator(accel_noise_m_s2=1.5)  # a straight track: the tighter model fits it
    est.initialise(start + np.array([60.0, -40.0, 0.0]), 80.0, T0_USEC)
    errors, fix_errors, nees = [], [], []
    for k in range(1, 241):
        t = T0_USEC + k * S // 2
        truth = start + vel * (k / 2)
        measured = truth + rng.normal(0, 5.0, 3)
        decision = est.update_fix(_fix(measured, 5.0, t))
        assert decision.accepted, decision
        st = est.state()
        err = st.pos_ned_m[:2] - truth[:2]
        errors.append(float(np.linalg.norm(err)))
        fix_errors.append(float(np.linalg.norm(measured[:2] - truth[:2])))
        nees.append(float(err @ np.linalg.solve(st.cov_pos_ned_m2[:2, :2], err)))
    assert errors[0] < 20.0  # from 72 m of prior error
    assert np.mean(errors[-60:]) < 0.5 * np.mean(fix_errors[-60:])  # filtering beats single fixes
    assert 0.8 < np.mean(nees[40:]) < 4.0  # 2 dof
    assert np.linalg.norm(st.vel_ned_m_s[:2] - vel[:2]) < 1.5
    assert st.provenance is Provenance.SATELLITE_ANCHORED
    assert st.yaw_rad == pytest.approx(0.3)
    assert st.last_fix_age_s == 0.0


def _fly_with_common_bias(shared_sigma_m: float) -> list[float]:
    """Fixes at 3 Hz whose 1 m floor is one common 0.95 m offset plus small independent noise (the
    square flight's situation): the error of each output in units of its stated horizontal sigma."""
    rng = np.random.default_rng(3)
    bias = np.array([0.95 / np.sqrt(2), 0.95 / np.sqrt(2), 0.0])
    vel = np.array([10.0, 0.0, 0.0])
    est = _estimator()
    est.initialise(np.array([0.0, 0.0, -80.0]), 5.0, T0_USEC)
    ratios = []
    for k in range(1, 91):
        t = T0_USEC + k * S // 3
        truth = vel * (k / 3) + np.array([0.0, 0.0, -80.0])
        assert est.update_vo(_vo(vel[:2] / 3, 0.05, 1 / 3), time_unix_usec=t).accepted
        fix = _fix(truth + bias + rng.normal(0, 0.1, 3), 1.04, t, shared_sigma_m=shared_sigma_m)
        assert est.update_fix(fix).accepted
        st = est.state()
        ratios.append(float(np.linalg.norm(st.pos_ned_m[:2] - truth[:2])) / st.horiz_sigma_m)
    return ratios


def test_an_error_every_fix_shares_is_not_averaged_away() -> None:
    """Treated as independent, fixes (with VO) sharing one 0.95 m offset take the stated sigma to about
    0.4 m and the output to 2.4 sigma off; carried as shared, it is never beyond 1.5 sigma."""
    assert max(_fly_with_common_bias(0.0)[-30:]) > 2.0
    honest = _fly_with_common_bias(1.0)
    assert max(honest) < 1.5


def test_the_shared_error_survives_a_checkpoint_and_resets_on_initialise() -> None:
    est = _estimator()
    est.initialise(np.array([0.0, 0.0, -80.0]), 5.0, T0_USEC)
    est.update_fix(_fix(np.array([1.0, 0.0, -80.0]), 1.0, T0_USEC + S, shared_sigma_m=2.0))
    after_fix = est.state().horiz_sigma_m
    cp = est.checkpoint()
    assert after_fix > 0.8 * 2.0  # the fix's common error is most of the stated sigma (gain ~0.96)
    est.initialise(np.array([0.0, 0.0, -80.0]), 0.5, T0_USEC + 2 * S)
    assert est.state().horiz_sigma_m == pytest.approx(0.5)
    est.restore(cp)
    assert est.state().horiz_sigma_m == pytest.approx(after_fix)
    bad = _fix(np.array([1.0, 0.0, -80.0]), 1.0, T0_USEC + 3 * S, shared_sigma_m=float("nan"))
    assert est.update_fix(bad).reason == FixReason.INVALID_MEASUREMENT


def test_estimator_gate_rejects_far_fix_and_accepts_consistent_one() -> None:
    """With ~5 m sigma, a fix 200 m away is gated (and logged); a fix 4 m away is fused."""
    est = _estimator()
    est.initialise(np.array([0.0, 0.0, -100.0]), 5.0, T0_USEC, vel_sigma_m_s=0.5)
    with structlog.testing.capture_logs() as logs:
        far = est.update_fix(_fix(np.array([200.0, 0.0, -100.0]), 3.0, T0_USEC + S // 3))
    assert not far.accepted and far.reason == FixReason.GATED and far.nis > 13.8
    assert any(e["event"] == LogEvent.ESTIMATOR_FIX_REJECTED and e["nis"] == far.nis for e in logs)
    assert np.linalg.norm(est.state().pos_ned_m[:2]) < 1.0  # not teleported
    near = est.update_fix(_fix(np.array([3.0, -2.5, -100.0]), 3.0, T0_USEC + 2 * S // 3))
    assert near.accepted and near.reason == FixReason.ACCEPTED and near.nis < 13.8
    assert est.state().pos_ned_m[0] > 1.0


def test_estimator_reacquires_after_long_gap() -> None:
    """After a 30 s gap (sigma > reacquire_sigma_m) a fix far outside the gate is accepted."""
    est = _estimator(accel_noise_m_s2=1.5)
    est.initialise(np.array([0.0, 0.0, -100.0]), 5.0, T0_USEC)
    t = T0_USEC + 30 * S
    est.predict_to(t)
    assert est.state().horiz_sigma_m > 150.0
    far = np.array([1500.0, 300.0, -100.0])
    decision = est.update_fix(_fix(far, 4.0, t))
    assert decision.accepted and decision.reason == FixReason.ACCEPTED_REACQUIRE
    assert decision.nis > 13.8  # the gate alone would have refused it
    st = est.state()
    assert np.linalg.norm(st.pos_ned_m[:2] - far[:2]) < 5.0
    assert st.horiz_sigma_m < 5.0
    # The same situation with re-acquisition disabled keeps the gate.
    strict = _estimator(accel_noise_m_s2=1.5, reacquire_sigma_m=1e6)
    strict.initialise(np.array([0.0, 0.0, -100.0]), 5.0, T0_USEC)
    assert strict.update_fix(_fix(far, 4.0, t)).reason == FixReason.GATED


def test_estimator_reacquire_refuses_enormous_fix_sigma() -> None:
    """A re-acquisition fix whose own sigma is above reacquire_sigma_m is refused."""
    est = _estimator()
    est.initialise(np.array([0.0, 0.0, -100.0]), 5.0, T0_USEC)
    decision = est.update_fix(_fix(np.array([1500.0, 0.0, -100.0]), 400.0, T0_USEC + 30 * S))
    assert not decision.accepted and decision.reason == FixReason.FIX_SIGMA_TOO_LARGE


def test_estimator_rejects_invalid_and_uninitialised_fixes() -> None:
    """NaN positions / non-PD covariances are refused; nothing is fused before initialise."""
    est = _estimator()
    assert est.update_fix(_fix(np.zeros(3), 3.0, T0_USEC)).reason == FixReason.NOT_INITIALISED
    est.initialise(np.zeros(3), 5.0, T0_USEC)
    bad = _fix(np.array([np.nan, 0.0, 0.0]), 3.0, T0_USEC + S)
    assert est.update_fix(bad).reason == FixReason.INVALID_MEASUREMENT
    neg = _fix(np.zeros(3), 3.0, T0_USEC + S)
    neg = PoseFix(**{**neg.__dict__, "cov_ned_m2": -np.eye(3)})
    assert est.update_fix(neg).reason == FixReason.INVALID_MEASUREMENT


def test_estimator_provenance_transitions() -> None:
    """no_estimate -> dead_reckoning -> satellite_anchored -> visual_propagated -> dead_reckoning ->
    no_estimate, each change logged with from/to."""
    est = _estimator(anchored_window_s=2.0)
    assert est.state(T0_USEC).provenance is Provenance.NO_ESTIMATE
    with structlog.testing.capture_logs() as logs:
        est.initialise(np.array([0.0, 0.0, -100.0]), 20.0, T0_USEC, vel_sigma_m_s=2.0)
        assert est.state().provenance is Provenance.DEAD_RECKONING
        est.update_fix(_fix(np.array([1.0, 1.0, -100.0]), 3.0, T0_USEC + S))
        assert est.state().provenance is Provenance.SATELLITE_ANCHORED
        t = T0_USEC + S
        for _ in range(15):  # 5 s of VO only, 3 Hz, the vehicle hovering
            t += S // 3
            assert est.update_vo(_vo(np.zeros(2), 0.5, 1 / 3), time_unix_usec=t).accepted
        assert est.state().provenance is Provenance.VISUAL_PROPAGATED
        assert est.state(t + 3 * S).provenance is Provenance.DEAD_RECKONING
        assert est.state(t + 600 * S).provenance is Provenance.NO_ESTIMATE
    changes = [(e["from"], e["to"]) for e in logs if e["event"] == LogEvent.PROVENANCE_CHANGED]
    assert changes == [
        ("no_estimate", "dead_reckoning"),
        ("dead_reckoning", "satellite_anchored"),
        ("satellite_anchored", "visual_propagated"),
        ("visual_propagated", "dead_reckoning"),
        ("dead_reckoning", "no_estimate"),
    ]


def test_estimator_sigma_grows_monotonically_without_fixes() -> None:
    """Pure prediction: the horizontal sigma increases at every step, and state() does not mutate."""
    est = _estimator()
    est.initialise(np.zeros(3), 3.0, T0_USEC, vel_sigma_m_s=1.0)
    before = est.state()
    sigmas = [est.state(T0_USEC + k * S // 2).horiz_sigma_m for k in range(0, 60)]
    assert np.all(np.diff(sigmas) > 0)
    after = est.state()
    assert after.time_unix_usec == before.time_unix_usec
    assert after.horiz_sigma_m == before.horiz_sigma_m
    stepped = []
    for k in range(1, 60):
        est.predict_to(T0_USEC + k * S // 2)
        stepped.append(est.state().horiz_sigma_m)
    assert np.all(np.diff(stepped) > 0)
    assert stepped[-1] == pytest.approx(sigmas[-1], rel=1e-9)


def test_estimator_vo_slows_sigma_growth() -> None:
    """After a fix, 30 s of VO keeps the sigma well below pure prediction, yet still growing."""
    fused, blind = _estimator(), _estimator()
    for est in (fused, blind):
        est.initialise(np.array([0.0, 0.0, -100.0]), 5.0, T0_USEC)
    vel = np.array([10.0, 0.0])
    t = T0_USEC
    vo_sigmas = []
    for _ in range(90):
        t += S // 3
        assert fused.update_vo(_vo(vel / 3, 0.6, 1 / 3), time_unix_usec=t).accepted
        blind.predict_to(t)
        vo_sigmas.append(fused.state().horiz_sigma_m)
    assert fused.state().horiz_sigma_m < 0.5 * blind.state().horiz_sigma_m
    assert np.all(np.diff(vo_sigmas[10:]) > 0)  # VO bounds velocity, not position
    assert fused.state().vel_ned_m_s[0] == pytest.approx(10.0, abs=0.5)


def test_estimator_vo_gate_rejects_blunder() -> None:
    """A VO velocity 60 m/s off a well-known velocity is gated, not fused."""
    est = _estimator()
    est.initialise(np.zeros(3), 5.0, T0_USEC, vel_sigma_m_s=0.5)
    decision = est.update_vo(_vo(np.array([20.0, 0.0]), 0.3, 1 / 3), time_unix_usec=T0_USEC + S // 3)
    assert not decision.accepted and decision.reason == FixReason.GATED
    assert abs(est.state().vel_ned_m_s[0]) < 0.1


def test_estimator_ignores_time_going_backwards() -> None:
    """predict_to an earlier time is logged and leaves the state unchanged."""
    est = _estimator()
    est.initialise(np.zeros(3), 5.0, T0_USEC)
    est.predict_to(T0_USEC + 2 * S)
    before = est.state()
    with structlog.testing.capture_logs() as logs:
        est.predict_to(T0_USEC + S)
    after = est.state()
    assert after.time_unix_usec == T0_USEC + 2 * S
    assert np.array_equal(after.cov_pos_ned_m2, before.cov_pos_ned_m2)
    assert any(e["event"] == LogEvent.ESTIMATOR_TIME_BACKWARDS for e in logs)


def test_estimator_refuses_fix_behind_its_time() -> None:
    """A fix older than the filter's time is refused (behind_filter): only the time axis may rewind."""
    est = _estimator()
    est.initialise(np.zeros(3), 5.0, T0_USEC)
    est.predict_to(T0_USEC + 5 * S)
    assert est.update_fix(_fix(np.zeros(3), 3.0, T0_USEC + 2 * S)).reason == FixReason.BEHIND_FILTER
    assert est.time_unix_usec == T0_USEC + 5 * S


def test_estimator_altitude_update_sets_down() -> None:
    """AGL 120 m over ground at 520 m AMSL (origin 500 m) -> d near -140 m and geodetic alt near 640 m."""
    est = _estimator()
    est.initialise(np.zeros(3), 30.0, T0_USEC)
    for _ in range(5):
        assert est.update_altitude(120.0, 520.0, 1.0).accepted
    st = est.state()
    assert st.pos_ned_m[2] == pytest.approx(-140.0, abs=1.0)
    assert st.alt_amsl_m == pytest.approx(640.0, abs=1.0)
    assert st.vert_sigma_m < 1.0
    assert math.isfinite(st.lat_deg) and math.isfinite(st.lon_deg)


def test_estimator_consecutive_gated_fixes_inflate_covariance() -> None:
    """Three fixes in a row that disagree with the state grow its stated sigma to the disagreement and
    the next consistent fix is accepted; a single rejected fix leaves the sigma alone."""
    from gps_denied_onboard.components.c5_estimator.ekf import CONSECUTIVE_GATED_INFLATE

    est = _estimator()
    start = np.array([0.0, 0.0, -120.0])
    est.initialise(start, 1.0, T0_USEC)
    moved = start + np.array([40.0, 0.0, 0.0])
    decisions = []
    for k in range(1, CONSECUTIVE_GATED_INFLATE + 2):
        t = T0_USEC + k * S // 10
        decisions.append(est.update_fix(_fix(moved, 1.0, t)))
        if k == 1:
            assert est.state(t).horiz_sigma_m < 3.0
    gated = [d.accepted for d in decisions[:CONSECUTIVE_GATED_INFLATE]]
    assert gated == [False] * CONSECUTIVE_GATED_INFLATE
    assert decisions[-1].accepted
    assert np.linalg.norm(est.state(T0_USEC + S // 2).pos_ned_m[:2] - moved[:2]) < 5.0


def test_estimator_consecutive_gated_fixes_stay_rejected_while_vo_fused() -> None:
    """With fixes having anchored the state and visual odometry corroborating it, a run of fixes 40 m off
    (a look-alike area) is rejected every time and the stated sigma does not absorb them."""
    est = _estimator()
    start = np.array([0.0, 0.0, -120.0])
    est.initialise(start, 1.0, T0_USEC)
    assert est.update_fix(_fix(start, 1.0, T0_USEC + S // 10)).accepted
    decisions = []
    for k in range(1, 9):
        t = T0_USEC + k * S // 3
        est.update_vo(_vo(np.zeros(2), 0.05, 1 / 3), time_unix_usec=t)
        decisions.append(est.update_fix(_fix(start + np.array([40.0, 0.0, 0.0]), 1.0, t)))
    assert not any(d.accepted for d in decisions)
    assert est.state(T0_USEC + 3 * S).horiz_sigma_m < 5.0


def test_estimator_provenance_switches_on_first_frame_without_fix() -> None:
    """Frame k: VO + an accepted fix (anchored). Frame k+1: VO while its fix is still being computed
    stays anchored; the moment its fix attempt gives no fix, visual_propagated."""
    est = _estimator()
    start = np.array([0.0, 0.0, -120.0])
    est.initialise(start, 5.0, T0_USEC)
    t1, t2 = T0_USEC + S // 3, T0_USEC + 2 * S // 3
    est.update_vo(_vo(np.zeros(2), 0.1, 1 / 3), time_unix_usec=t1)
    assert est.update_fix(_fix(start, 1.0, t1)).accepted
    assert est.state(t1).provenance is Provenance.SATELLITE_ANCHORED
    est.update_vo(_vo(np.zeros(2), 0.1, 1 / 3), time_unix_usec=t2)
    assert est.state(t2).provenance is Provenance.SATELLITE_ANCHORED
    est.note_no_fix(t2)
    assert est.state(t2).provenance is Provenance.VISUAL_PROPAGATED


def _fly_north_from_a_prior(est: NavEstimator, prior_off_ne: np.ndarray, fix_off_ne, n: int) -> list:
    """Initialise ``prior_off_ne`` (m) from the truth at a stated 30 m, then fly north at 12 m/s with VO
    every 1/3 s and a fix each frame at the truth plus ``fix_off_ne(k)``; returns (k, decision, state)."""
    est.initialise(np.array([*prior_off_ne, -120.0]), 30.0, T0_USEC)
    out = []
    for k in range(1, n + 1):
        t = T0_USEC + k * S // 3
        est.update_vo(_vo(np.array([4.0, 0.0]), 0.3, 1 / 3), time_unix_usec=t)
        truth = np.array([4.0 * k, 0.0, -120.0])
        decision = est.update_fix(_fix(truth + np.array([*fix_off_ne(k), 0.0]), 1.5, t))
        out.append((k, decision, est.state(t), truth))
    return out


def test_a_start_prior_far_beyond_its_sigma_is_given_up_for_the_fixes_that_contradict_it() -> None:
    """Configured 150 m from the truth at a stated 30 m, with VO running: the right fixes are gated. From
    the second that agrees with the first, the output states the disagreement (never fix-quality at 30 m
    while 150 m off); once 5 of them span 200 m of ground the prior is given up and the next fix
    re-anchors the state. Measured before in SITL: 792 of 807 GPS_INPUT beyond 3 sigma, all flight."""
    from gps_denied_onboard.components.c5_estimator.ekf import PRIOR_CONTRADICTED_FIXES

    est = _estimator(prior_conflict_span_m=200.0)
    flight = _fly_north_from_a_prior(est, np.array([150.0, 0.0]), lambda k: (0.0, 0.0), 90)
    for k, _, state, truth in flight:
        err = float(np.linalg.norm(state.pos_ned_m[:2] - truth[:2]))
        assert err <= 3.0 * state.horiz_sigma_m or k == 1, (k, err, state.horiz_sigma_m)
    accepted = [k for k, d, _, _ in flight if d.accepted]
    # the run must span 200 m at 4 m a frame: frame 51 at the earliest, and at least 5 fixes
    assert accepted and 51 <= accepted[0] <= 53 and accepted[0] > PRIOR_CONTRADICTED_FIXES, accepted[:3]
    assert accepted == list(range(accepted[0], 91))
    _, _, last, truth = flight[-1]
    assert np.linalg.norm(last.pos_ned_m[:2] - truth[:2]) < 2.0 and last.horiz_sigma_m < 3.0


def test_fixes_that_do_not_agree_with_each_other_never_move_an_unconfirmed_prior() -> None:
    """Gated fixes scattered 150-300 m around in every direction (blunders, not a place) neither widen
    the output nor re-anchor the state: only a run that agrees with itself can contradict the prior."""
    rng = np.random.default_rng(3)
    offsets = [
        rng.uniform(150.0, 300.0) * np.array([math.cos(a), math.sin(a)]) for a in rng.uniform(0, 6.3, 90)
    ]
    est = _estimator()
    flight = _fly_north_from_a_prior(est, np.array([0.0, 0.0]), lambda k: offsets[k - 1], 90)
    assert not any(d.accepted for _, d, _, _ in flight)
    assert all(state.shared_sigma_m == 0.0 for _, _, state, _ in flight)
    _, _, last, truth = flight[-1]
    assert np.linalg.norm(last.pos_ned_m[:2] - truth[:2]) < 5.0


def test_a_confirmed_state_keeps_refusing_a_look_alike_however_long() -> None:
    """The prior was right and a fix confirmed it; then 60 fixes 70 m east over 240 m of ground (the
    wrong-tile trap): all gated, and the output does not take them up (the trap rule, unchanged)."""
    est = _estimator()
    flight = _fly_north_from_a_prior(
        est, np.array([0.0, 0.0]), lambda k: (0.0, 70.0) if k > 1 else (0.0, 0.0), 61
    )
    assert flight[0][1].accepted
    assert not any(d.accepted for _, d, _, _ in flight[1:])
    assert flight[-1][2].horiz_sigma_m < 10.0 and flight[-1][2].shared_sigma_m < 3.0


def test_a_prior_contradicted_while_hovering_is_stated_but_not_given_up() -> None:
    """Hovering 150 m from a prior at a stated 30 m: the consistent fixes never span 200 m of ground, so
    the state is not moved onto them, but what leaves states the disagreement."""
    est = _estimator()
    est.initialise(np.array([150.0, 0.0, -120.0]), 30.0, T0_USEC)
    for k in range(1, 40):
        t = T0_USEC + k * S // 3
        est.update_vo(_vo(np.zeros(2), 0.3, 1 / 3), time_unix_usec=t)
        assert not est.update_fix(_fix(np.array([0.0, 0.0, -120.0]), 1.5, t)).accepted
    state = est.state(T0_USEC + 13 * S)
    assert state.pos_ned_m[0] > 100.0 and state.horiz_sigma_m >= 150.0


def test_a_start_prior_is_unconfirmed_until_a_map_fix_is_fused() -> None:
    """Issue 37: the state a start prior gives is a claim (``map_confirmed`` False, so never a 3D fix)
    until an accepted fix; a gated one does not confirm it; a rewind to before the fix takes it back; a
    resumed 3D estimate (the previous run's own output) starts confirmed."""
    est = _estimator()
    est.initialise(np.array([0.0, 0.0, -100.0]), 5.0, T0_USEC, vel_sigma_m_s=0.5)
    assert not est.state().map_confirmed
    cp = est.checkpoint()
    assert not est.update_fix(_fix(np.array([200.0, 0.0, -100.0]), 3.0, T0_USEC + S // 3)).accepted
    assert not est.state().map_confirmed
    assert est.update_fix(_fix(np.array([3.0, -2.5, -100.0]), 3.0, T0_USEC + 2 * S // 3)).accepted
    assert est.state().map_confirmed and est.state(T0_USEC + 10 * S).map_confirmed
    est.restore(cp)
    assert not est.state().map_confirmed
    est.initialise(np.array([0.0, 0.0, -100.0]), 30.0, T0_USEC + S, map_confirmed=True)
    assert est.state().map_confirmed


class _HoverImu:
    """The autopilot's IMU of a hovering vehicle: no acceleration."""

    def accel_ned_mean(self, t0_unix_usec: int, t1_unix_usec: int) -> ImuAcceleration:
        return ImuAcceleration(np.zeros(3))


class _TiltedImu:
    """The IMU of a hovering vehicle rotated with an attitude that may be off: it reads no acceleration,
    stating ``tilt_bound`` of doubt, while the truth accelerates north by what the wrong tilt hid."""

    def __init__(self, tilt_bound_m_s2: float) -> None:
        self.tilt_bound_m_s2 = tilt_bound_m_s2

    def accel_ned_mean(self, t0_unix_usec: int, t1_unix_usec: int) -> ImuAcceleration:
        return ImuAcceleration(np.zeros(3), self.tilt_bound_m_s2)


def _imu_alone_ratios(bound_m_s2: float, hidden_m_s2: float, held_s: float = 5.0) -> list[float]:
    """VO measured the motion once, then the IMU alone carries the state of a vehicle whose wrong tilt
    hid ``hidden_m_s2`` of acceleration, the IMU stating ``bound_m_s2``: at each 0.1 s the larger of the
    velocity's and the position's error over their stated sigmas."""
    est = NavEstimator(EstimatorConfig(), LTP, accel_source=_TiltedImu(bound_m_s2))
    est.initialise(np.zeros(3), 0.5, T0_USEC - S // 3, vel_sigma_m_s=0.1)
    assert est.update_vo(_vo(np.zeros(2), 0.05, 1 / 3), time_unix_usec=T0_USEC).accepted
    ratios = []
    for k in range(1, int(held_s * 10) + 1):
        t_s = k / 10
        st = est.state(T0_USEC + k * S // 10)
        vel_err, pos_err = hidden_m_s2 * t_s, 0.5 * hidden_m_s2 * t_s**2
        ratios.append(
            max(
                vel_err / math.sqrt(float(st.cov_vel_ned_m2_s2[0, 0])),
                pos_err / math.sqrt(float(st.cov_pos_ned_m2[0, 0])),
            )
        )
    return ratios


@pytest.mark.parametrize("bound_m_s2", [0.3, 0.5, 0.9])
def test_the_imu_alone_states_what_its_attitudes_doubt_can_put_into_it(bound_m_s2: float) -> None:
    """VO and the fixes are gone (a landing: no texture, no map match below 20 m) and the IMU carries the
    state, the autopilot's tilt off after its manoeuvres within the bound its swing sets, the error held
    for the whole stretch (up to the tilt error's hold time). A bias at the bound's sigma (a bias
    anywhere within it) stays within 1 stated sigma of velocity and position, one at the whole bound
    within sqrt(3) of them: never beyond 3. With the IMU's own noise alone the bound's error ends beyond
    1.3 of its sigmas, and the further the larger the tilt (a few degrees in the ArduPilot emulator's
    landing flare: 5.5-10 m off at a stated 1.9-2.9 m)."""
    sigma_m_s2 = bound_m_s2 / math.sqrt(3.0)
    assert max(_imu_alone_ratios(bound_m_s2, sigma_m_s2)) <= 1.0
    assert max(_imu_alone_ratios(bound_m_s2, bound_m_s2)) <= math.sqrt(3.0) + 1e-9
    assert _imu_alone_ratios(0.0, bound_m_s2)[-1] > 1.3


def test_the_tilt_doubt_adds_little_between_the_frames_vo_measures() -> None:
    """The same doubt while VO measures every frame (3 Hz): the bias has a third of a second to act
    before the next VO, and the stated speed sigma stays within a quarter of the IMU's own."""
    sigmas = {}
    for tilt in (0.0, 0.9):
        est = NavEstimator(EstimatorConfig(), LTP, accel_source=_TiltedImu(tilt))
        est.initialise(np.zeros(3), 0.5, T0_USEC, vel_sigma_m_s=0.1)
        for k in range(1, 31):
            assert est.update_vo(_vo(np.zeros(2), 0.3, 1 / 3), time_unix_usec=T0_USEC + k * S // 3).accepted
        sigmas[tilt] = math.sqrt(float(est.state(T0_USEC + 30 * S // 3 + S // 4).cov_vel_ned_m2_s2[0, 0]))
    assert sigmas[0.9] <= 1.25 * sigmas[0.0], sigmas


def test_vo_noisier_than_it_states_is_weighed_as_it_shows_not_fused_on_one_side() -> None:
    """A hovering vehicle whose VO alternates +0.6 and -0.7 m east a frame (3 Hz) stating 0.15 m (a PX4
    SIH landing at 30 m AGL over weak texture), the IMU keeping the velocity known. Gated on one side and
    fused on the other, such VO carried the state 17 m off in 10 s at a stated 1.5 m. Once its
    innovations show it noisier than it states, its covariance is scaled by what they show: both sides
    are fused and the state stays within 3 sigma of the truth."""
    est = NavEstimator(EstimatorConfig(), LTP, accel_source=_HoverImu())
    est.initialise(np.zeros(3), 1.0, T0_USEC, vel_sigma_m_s=0.3)
    accepted, ratios = [], []
    for k in range(1, 31):
        east = 0.6 if k % 2 else -0.7
        decision = est.update_vo(_vo(np.array([0.0, east]), 0.15, 1 / 3), time_unix_usec=T0_USEC + k * S // 3)
        st = est.state()
        accepted.append(decision.accepted)
        ratios.append(abs(float(st.pos_ned_m[1])) / float(np.sqrt(st.cov_pos_ned_m2[1, 1])))
    assert all(accepted[4:]), accepted
    assert max(ratios) <= 3.0, ratios


def test_one_vo_blunder_among_consistent_updates_is_still_gated() -> None:
    """The noise factor is a median over the newest updates: one blunder among consistent ones leaves
    it at 1, and the blunder is gated as before."""
    est = _estimator()
    est.initialise(np.zeros(3), 5.0, T0_USEC, vel_sigma_m_s=0.5)
    for k in range(1, 8):
        assert est.update_vo(_vo(np.zeros(2), 0.3, 1 / 3), time_unix_usec=T0_USEC + k * S // 3).accepted
    decision = est.update_vo(_vo(np.array([6.0, 0.0]), 0.3, 1 / 3), time_unix_usec=T0_USEC + 8 * S // 3)
    assert not decision.accepted and decision.reason == FixReason.GATED


def _fly_wrong_vo_right_fixes(*, slope_apart: bool) -> tuple[float, float]:
    """Hovering at 80 m while VO, de-rotated with a drifting tilt, says 1 m east a frame at 10 Hz
    (stating 0.3 m), and fixes at 3 Hz are right within 0.5 m but state 8 m for a slope they might be on
    (g11 on a real PX4 beside two busy loops): the largest error, m, over 2 s, and the largest in units
    of the stated horizontal sigma from the first fix."""
    rng = np.random.default_rng(7)
    est = _estimator()
    est.initialise(np.array([0.0, 0.0, -80.0]), 1.0, T0_USEC)
    worst_m, worst_ratio = 0.0, 0.0
    for k in range(1, 21):
        t = T0_USEC + k * S // 10
        est.update_vo(_vo(np.array([0.0, 1.0]), 0.3, 0.1), time_unix_usec=t)
        if k % 3 == 0:
            slope_m = 8.0
            fix = _fix(np.array([0.0, 0.0, -80.0]) + rng.normal(0, 0.3, 3), 0.5, t)
            cov = np.array(fix.cov_ned_m2)
            cov[:2, :2] += np.eye(2) * slope_m**2
            fix = dataclasses.replace(
                fix, cov_ned_m2=cov, shared_sigma_m=slope_m, slope_sigma_m=slope_m if slope_apart else 0.0
            )
            assert est.update_fix(fix).accepted
        st = est.state()
        err = float(np.hypot(*st.pos_ned_m[:2]))
        worst_m = max(worst_m, err)
        if k >= 3:  # from the first fix (before it, VO's own doubt is the pipeline's to state)
            worst_ratio = max(worst_ratio, err / st.horiz_sigma_m)
    return worst_m, worst_ratio


def test_a_slope_the_fixes_might_share_does_not_make_them_too_weak_to_hold_the_estimate() -> None:
    """Weighed with the slope's 8 m as their own noise, right fixes let wrong VO carry the estimate
    18 m off in 2 s; weighed by their own error, with the slope stated in the output, they hold it
    within the 3.3 m VO runs between two of them, and the output never claims less than its error."""
    weak_m, weak_ratio = _fly_wrong_vo_right_fixes(slope_apart=False)
    held_m, held_ratio = _fly_wrong_vo_right_fixes(slope_apart=True)
    assert weak_m > 9.0 and weak_ratio > 3.0  # a confident lie: 18 m off at a stated 2 m
    assert held_m < 4.0
    assert held_ratio < 1.0


def test_vo_that_keeps_saying_another_velocity_puts_the_velocity_in_doubt_not_the_vo() -> None:
    """Anchored at 12 m/s north, then VO says 12 m/s south frame after frame (a reversal the state did
    not follow): the first two are gated as blunders; the third puts the velocity in doubt by what VO
    says and the position by what that moved it over the gated frames, so VO is fused again and the
    stated accuracy covers where the vehicle is if VO was right, rather than holding a velocity the
    camera keeps contradicting."""
    from gps_denied_onboard.components.c5_estimator.ekf import CONSECUTIVE_GATED_INFLATE

    est = _estimator()
    est.initialise(np.array([0.0, 0.0, -100.0]), 1.0, T0_USEC)
    t = T0_USEC
    for k in range(1, 31):  # 10 s north at 12 m/s, VO and a fix every frame
        t = T0_USEC + k * S // 3
        est.update_vo(_vo(np.array([4.0, 0.0]), 0.05, 1 / 3), time_unix_usec=t)
        est.update_fix(_fix(np.array([4.0 * k, 0.0, -100.0]), 1.0, t))
    before = est.state(t)
    assert before.speed_sigma_m_s < 1.0
    decisions = []
    for k in range(1, CONSECUTIVE_GATED_INFLATE + 2):
        south = _vo(np.array([-4.0, 0.0]), 0.05, 1 / 3)
        decisions.append(est.update_vo(south, time_unix_usec=t + k * S // 3))
    assert [d.accepted for d in decisions[:CONSECUTIVE_GATED_INFLATE]] == [False] * CONSECUTIVE_GATED_INFLATE
    assert decisions[-1].accepted  # the velocity in doubt, VO is heard again
    t_end = t + (CONSECUTIVE_GATED_INFLATE + 1) * S // 3
    after = est.state(t_end)
    assert after.vel_ned_m_s[0] < 0.0  # going south, as VO says
    # had the vehicle reversed at the first contradicting frame, the state is this far off: covered
    truth_n = 4.0 * 30 - 12.0 * (t_end - t - S // 3) / S
    assert abs(after.pos_ned_m[0] - truth_n) < 3.0 * after.horiz_sigma_m, (after.pos_ned_m, truth_n)


def test_vo_that_says_another_thing_each_frame_stays_gated() -> None:
    """Anchored at 12 m/s north, then VO frame after frame wrong by a different 12-50 m/s each time (a
    camera whose lateness is not yet measured, de-rotated with the wrong attitude through a turn): each
    is gated, none agrees with the one before, and the state keeps its velocity and its 3D-worthy speed
    sigma instead of taking the blunders' size as its doubt."""
    est = _estimator()
    est.initialise(np.array([0.0, 0.0, -100.0]), 1.0, T0_USEC)
    t = T0_USEC
    for k in range(1, 31):
        t = T0_USEC + k * S // 3
        est.update_vo(_vo(np.array([4.0, 0.0]), 0.05, 1 / 3), time_unix_usec=t)
        est.update_fix(_fix(np.array([4.0 * k, 0.0, -100.0]), 1.0, t))
    unheard = _estimator()
    unheard.restore(est.checkpoint())
    wrong_m_s = [(-12.0, 30.0), (40.0, -20.0), (12.0, 50.0), (-30.0, -10.0), (16.0, 24.0), (4.0, -40.0)]
    for k, (dn, de) in enumerate(wrong_m_s, start=1):
        vo = _vo(np.array([(12.0 + dn) / 3, de / 3]), 0.05, 1 / 3)
        assert not est.update_vo(vo, time_unix_usec=t + k * S // 3).accepted
        assert len(est.checkpoint().vo_gated_run) == 1
    t_end = t + len(wrong_m_s) * S // 3
    after, predicted = est.state(t_end), unheard.state(t_end)
    # what the prediction alone states over those 2 s, no more: the blunders put nothing in doubt
    assert after.speed_sigma_m_s == pytest.approx(predicted.speed_sigma_m_s)
    assert after.horiz_sigma_m == pytest.approx(predicted.horiz_sigma_m)
    assert after.speed_sigma_m_s < 5.0
    assert abs(after.vel_ned_m_s[0] - 12.0) < 1.0


def test_vo_back_after_a_dead_reckoned_stretch_does_not_vouch_for_the_position() -> None:
    """Anchored at 12 m/s north, then 3 s without VO in which the vehicle in truth stood still (the state
    dead-reckons on north, 36 m wrong at a sigma of a few metres), then VO again at 12 m/s north, which
    agrees with the state's velocity: fixes 36 m behind are gated at first; after three the state takes
    their disagreement into its sigma and the next fix re-anchors it. VO fused throughout since the last
    fix (the look-alike case, test_a_confirmed_state_keeps_refusing_a_look_alike_however_long) keeps
    refusing them."""
    from gps_denied_onboard.components.c5_estimator.ekf import CONSECUTIVE_GATED_INFLATE

    est = _estimator()
    est.initialise(np.array([0.0, 0.0, -100.0]), 1.0, T0_USEC)
    for k in range(1, 31):  # 10 s north at 12 m/s
        t = T0_USEC + k * S // 3
        est.update_vo(_vo(np.array([4.0, 0.0]), 0.05, 1 / 3), time_unix_usec=t)
        est.update_fix(_fix(np.array([4.0 * k, 0.0, -100.0]), 1.0, t))
    t_dr = T0_USEC + 10 * S
    decisions = []
    for k in range(1, CONSECUTIVE_GATED_INFLATE + 3):
        t = t_dr + 3 * S + k * S // 3
        truth_n = 120.0 + 4.0 * k  # stood still for the 3 s, then north again
        est.update_vo(_vo(np.array([4.0, 0.0]), 0.05, 1 / 3), time_unix_usec=t)
        decisions.append(est.update_fix(_fix(np.array([truth_n, 0.0, -100.0]), 1.0, t)))
    assert [d.accepted for d in decisions[:CONSECUTIVE_GATED_INFLATE]] == [False] * CONSECUTIVE_GATED_INFLATE
    assert decisions[CONSECUTIVE_GATED_INFLATE].accepted
    end = est.state(t)
    assert abs(end.pos_ned_m[0] - truth_n) < 3.0 * end.horiz_sigma_m and abs(end.pos_ned_m[0] - truth_n) < 5.0
