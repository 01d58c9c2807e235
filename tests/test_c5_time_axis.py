"""C5 time axis: admission of timestamps, late fixes fused at their own time, output at any time, and the
IMU-driven prediction it hands out.

The estimator is the real one; the clock and the acceleration source are fakes at their boundaries.
"""

from __future__ import annotations

import itertools
import math
import random
import threading

import numpy as np
import pytest
import structlog

from conftest import REPO_ROOT
from gps_denied_onboard.components.c1_vio.types import VoMotion
from gps_denied_onboard.components.c4_pose.types import PoseFix
from gps_denied_onboard.components.c5_estimator import FixReason, NavEstimator, Refusal, TimeAxis
from gps_denied_onboard.components.c5_estimator.protocol import ImuAcceleration
from gps_denied_onboard.config import ConfigError, EstimatorConfig, load_config
from gps_denied_onboard.constants import LogEvent, Provenance
from test_c5_estimator import LTP, S, _fix, _vo
from test_c5_estimator import T0_USEC as T0

FRAME_US = S // 3


class _Clock:
    def __init__(self, t_usec: int) -> None:
        self.t = t_usec

    def __call__(self) -> int:
        return self.t


class _ConstAccel:
    """Acceleration source answering a fixed NED acceleration (or None: no IMU)."""

    def __init__(self, accel_ned: np.ndarray | None) -> None:
        self.accel = accel_ned
        self.calls = 0

    def accel_ned_mean(self, t0_unix_usec: int, t1_unix_usec: int) -> ImuAcceleration | None:
        self.calls += 1
        return None if self.accel is None else ImuAcceleration(self.accel.copy())


def _axis(
    clock: _Clock, *, accel: _ConstAccel | None = None, max_delay_s: float = 5.0, **cfg: float
) -> TimeAxis:
    est = NavEstimator(EstimatorConfig(**cfg), LTP, accel_source=accel)
    return TimeAxis(
        est, max_delay_s=max_delay_s, max_frame_age_s=1.0, max_future_s=0.25, clock_unix_usec=clock
    )


def _flight(n_frames: int, vel_ne: np.ndarray) -> list[tuple[str, int, object]]:
    """Inputs of a straight flight at ``vel_ne`` m/s: VO every frame, a fix every frame, in time order."""
    start = np.array([0.0, 0.0, -120.0])
    out: list[tuple[str, int, object]] = []
    for k in range(1, n_frames + 1):
        t = T0 + k * FRAME_US
        out.append(("vo", t, _vo(vel_ne / 3.0, 0.3, 1 / 3)))
        truth = start + np.array([*(vel_ne * k / 3.0), 0.0])
        out.append(("fix", t, _fix(truth + np.array([0.4, -0.3, 0.0]) * ((-1) ** k), 2.0, t)))
    return out


def _apply(axis: TimeAxis, item: tuple[str, int, object]) -> None:
    kind, t, payload = item
    if kind == "vo":
        assert isinstance(payload, VoMotion)
        axis.fuse_vo(payload, t)
    else:
        assert isinstance(payload, PoseFix)
        axis.fuse_fix(payload)


# -- admission -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("ahead_s", [5.0, 3600.0])
def test_time_axis_refuses_future_frame_without_moving_the_clock(ahead_s: float) -> None:
    """A frame stamped 5 s or an hour ahead is refused as future, counted, and the next frame is fine."""
    clock = _Clock(T0)
    axis = _axis(clock)
    assert axis.admit_frame(T0 - 50_000).admitted
    bad = axis.admit_frame(T0 + round(ahead_s * S))
    assert not bad.admitted and bad.reason is Refusal.FUTURE
    assert bad.ahead_s == pytest.approx(ahead_s, abs=1e-6)
    clock.t += FRAME_US
    good = axis.admit_frame(clock.t - 50_000)
    assert good.admitted, good
    assert axis.stats().refused["future"] == 1 and axis.stats().frames_admitted == 2


def test_time_axis_admits_small_clock_skew_ahead() -> None:
    """A frame 0.1 s ahead of the clock (camera/clock jitter) is inside the 0.25 s tolerance."""
    axis = _axis(_Clock(T0))
    assert axis.admit_frame(T0 + 100_000).admitted


def test_time_axis_subtracts_the_cameras_measured_lateness() -> None:
    """Once the camera's lateness is measured (``clock.CameraStampOffset``), every admitted frame's
    exposure is its stamp less it, and the admission says how much was taken off."""
    import random

    from gps_denied_onboard.clock import CameraStampOffset

    camera = CameraStampOffset(max_offset_s=0.3, prior_sigma_s=0.1)
    est = NavEstimator(EstimatorConfig(), LTP)
    axis = TimeAxis(
        est,
        max_delay_s=5.0,
        max_frame_age_s=1.0,
        max_future_s=0.25,
        clock_unix_usec=_Clock(T0),
        camera_offset=camera,
    )
    assert axis.admit_frame(T0 - 500_000).exposure_time_unix_usec == T0 - 500_000
    rng = random.Random(0)
    phases: dict[int, float] = {}

    def down(t_s: np.ndarray | float, ph: float) -> np.ndarray:
        return np.stack([0.2 * np.sin(1.5 * t_s + ph), 0.2 * np.cos(1.5 * t_s + ph)], axis=-1)

    for k in range(40):  # a camera 150 ms late, seen in tilts while world-down swings in the camera
        stamp = T0 - 30_000_000 + k * 500_000
        phases[stamp] = rng.uniform(0.0, 6.3)
        applied = camera.applied_s
        tilt = down(-0.15, phases[stamp]) - down(-applied, phases[stamp])
        camera.note((float(tilt[0]), float(tilt[1])), stamp - round(applied * 1e6), applied)
        camera.complete(lambda t, offs: down(offs, phases[t]), stamp + 100_000)
    late = axis.admit_frame(T0 - 100_000)
    assert late.admitted and late.stamp_offset_s == pytest.approx(0.15, abs=0.005)
    assert late.exposure_time_unix_usec == T0 - 100_000 - round(late.stamp_offset_s * 1e6)


def test_time_axis_refuses_out_of_order_and_repeated_frames() -> None:
    """A frame not after the previous admitted one is refused (VO needs dt > 0)."""
    axis = _axis(_Clock(T0))
    assert axis.admit_frame(T0 - 100_000).admitted
    assert axis.admit_frame(T0 - 100_000).reason is Refusal.OUT_OF_ORDER
    assert axis.admit_frame(T0 - 200_000).reason is Refusal.OUT_OF_ORDER
    assert axis.admit_frame(T0).admitted
    assert axis.stats().refused["out_of_order"] == 2


def test_time_axis_refuses_stale_frame() -> None:
    """A frame older than max_frame_age_s when admitted is refused as stale."""
    axis = _axis(_Clock(T0))
    assert axis.admit_frame(T0 - 1_500_000).reason is Refusal.STALE


def test_time_axis_refuses_future_measurement_and_keeps_accepting_correct_fixes() -> None:
    """The +5 s defect: a fix stamped 5 s ahead must not drag the filter forward; it is refused and the
    correct fixes after it keep being accepted."""
    clock = _Clock(T0)
    axis = _axis(clock)
    axis.initialise(np.array([0.0, 0.0, -120.0]), 30.0, T0)
    future = axis.fuse_fix(_fix(np.array([60.0, 0.0, -120.0]), 1.0, T0 + 5 * S))
    assert not future.accepted and future.reason == Refusal.FUTURE.value
    assert axis.head_unix_usec == T0
    for k in range(1, 20):
        clock.t = T0 + k * FRAME_US
        decision = axis.fuse_fix(_fix(np.array([0.5, -0.5, -120.0]), 2.0, clock.t))
        assert decision.accepted, (k, decision)
    st = axis.state_at()
    assert np.hypot(*(st.pos_ned_m[:2] - [0.5, -0.5])) < 1.0
    assert st.provenance is Provenance.SATELLITE_ANCHORED


# -- delayed fusion --------------------------------------------------------------------------------------


def test_time_axis_late_fix_equals_in_order_fusion() -> None:
    """A fix that arrives after four later VO frames gives exactly the state of fusing it in order."""
    vel = np.array([12.0, 5.0])
    inputs = _flight(12, vel)
    clock = _Clock(T0 + 20 * S)  # every input is in the past: no future refusals
    in_order, late = _axis(clock), _axis(clock)
    for axis in (in_order, late):
        axis.initialise(np.array([0.0, 0.0, -120.0]), 10.0, T0)
    for item in inputs:
        _apply(in_order, item)
    # the fix path lags four frames behind VO
    vos = [i for i in inputs if i[0] == "vo"]
    fixes = [i for i in inputs if i[0] == "fix"]
    for k, vo in enumerate(vos):
        _apply(late, vo)
        if k >= 4:
            _apply(late, fixes[k - 4])
    for fix in fixes[-4:]:
        _apply(late, fix)
    a, b = in_order.state_at(T0 + 13 * FRAME_US), late.state_at(T0 + 13 * FRAME_US)
    np.testing.assert_allclose(b.pos_ned_m, a.pos_ned_m, atol=1e-9)
    np.testing.assert_allclose(b.cov_pos_ned_m2, a.cov_pos_ned_m2, atol=1e-9)
    assert late.stats().rewinds == len(fixes) - 1  # the last fix shares the newest VO's time: in order
    assert late.stats().max_rewind_s == pytest.approx(4 / 3, abs=1e-3)


def test_time_axis_arrival_order_does_not_matter_within_the_delay_bound() -> None:
    """Any arrival order of the same inputs (all within max_delay_s) ends in the same state."""
    inputs = _flight(15, np.array([8.0, -6.0]))
    clock = _Clock(T0 + 20 * S)
    reference = _axis(clock)
    reference.initialise(np.array([0.0, 0.0, -120.0]), 10.0, T0)
    for item in inputs:
        _apply(reference, item)
    want = reference.state_at(T0 + 16 * FRAME_US)
    rng = random.Random(3)
    for _ in range(5):
        shuffled = inputs[:]
        rng.shuffle(shuffled)
        axis = _axis(clock, max_delay_s=10.0)
        axis.initialise(np.array([0.0, 0.0, -120.0]), 10.0, T0)
        for item in shuffled:
            _apply(axis, item)
        got = axis.state_at(T0 + 16 * FRAME_US)
        np.testing.assert_allclose(got.pos_ned_m, want.pos_ned_m, atol=1e-8)
        np.testing.assert_allclose(got.vel_ned_m_s, want.vel_ned_m_s, atol=1e-8)


def test_time_axis_late_fix_at_exposure_time_has_no_flight_distance_bias() -> None:
    """At 15 m/s a 2 s-old exact fix fused at its exposure leaves < 1 m error; the same fix fused as if
    exposed at its arrival time (the defect) would be ~30 m off."""
    clock = _Clock(T0 + 20 * S)
    axis = _axis(clock)
    vel = np.array([15.0, 0.0])
    axis.initialise(np.array([0.0, 0.0, -120.0]), 40.0, T0)
    t_fix = T0 + 3 * FRAME_US
    for k in range(1, 10):  # 3 s of VO
        axis.fuse_vo(_vo(vel / 3.0, 0.2, 1 / 3), T0 + k * FRAME_US)
    truth_at_fix = np.array([15.0 * 1.0, 0.0, -120.0])
    decision = axis.fuse_fix(_fix(truth_at_fix, 0.5, t_fix))
    assert decision.accepted, decision
    head = axis.state_at(T0 + 9 * FRAME_US)
    assert abs(head.pos_ned_m[0] - 15.0 * 3.0) < 1.0, head.pos_ned_m
    naive = _axis(clock)
    naive.initialise(np.array([0.0, 0.0, -120.0]), 40.0, T0)
    for k in range(1, 10):
        naive.fuse_vo(_vo(vel / 3.0, 0.2, 1 / 3), T0 + k * FRAME_US)
    naive.fuse_fix(_fix(truth_at_fix, 0.5, T0 + 9 * FRAME_US))  # exposure replaced by arrival
    assert abs(naive.state_at(T0 + 9 * FRAME_US).pos_ned_m[0] - 45.0) > 25.0


def test_time_axis_refuses_fix_older_than_the_delay_bound() -> None:
    """A fix more than max_delay_s behind the newest input is refused as too late; the state is unchanged."""
    clock = _Clock(T0 + 20 * S)
    axis = _axis(clock, max_delay_s=2.0)
    axis.initialise(np.array([0.0, 0.0, -120.0]), 10.0, T0)
    for k in range(1, 13):  # 4 s of VO
        axis.fuse_vo(_vo(np.zeros(2), 0.3, 1 / 3), T0 + k * FRAME_US)
    before = axis.state_at()
    decision = axis.fuse_fix(_fix(np.array([3.0, 0.0, -120.0]), 1.0, T0 + FRAME_US))
    assert not decision.accepted and decision.reason == Refusal.TOO_LATE.value
    np.testing.assert_array_equal(axis.state_at().pos_ned_m, before.pos_ned_m)
    assert axis.stats().refused["too_late"] == 1


def test_time_axis_refuses_fix_from_before_initialisation() -> None:
    """Nothing exposed before the (re)initialisation can be fused: there is no state to rewind to."""
    axis = _axis(_Clock(T0 + 20 * S))
    axis.initialise(np.array([0.0, 0.0, -120.0]), 10.0, T0)
    decision = axis.fuse_fix(_fix(np.zeros(3), 1.0, T0 - FRAME_US))
    assert decision.reason == Refusal.TOO_LATE.value


def test_time_axis_measurement_before_initialisation_is_not_fused() -> None:
    """Before initialise() every measurement is refused as not initialised and the output is no_estimate."""
    axis = _axis(_Clock(T0))
    assert axis.fuse_vo(_vo(np.zeros(2), 0.3, 1 / 3), T0).reason == FixReason.NOT_INITIALISED
    assert axis.state_at().provenance is Provenance.NO_ESTIMATE


def test_time_axis_replay_does_not_log_replayed_events_twice() -> None:
    """A rewind re-applies later inputs silently: a gated fix is logged once, not once per replay."""
    clock = _Clock(T0 + 20 * S)
    axis = _axis(clock)
    axis.initialise(np.array([0.0, 0.0, -120.0]), 2.0, T0)
    with structlog.testing.capture_logs() as logs:
        axis.fuse_vo(_vo(np.zeros(2), 0.3, 1 / 3), T0 + FRAME_US)
        axis.fuse_fix(_fix(np.array([300.0, 0.0, -120.0]), 1.0, T0 + 2 * FRAME_US))  # far: gated
        axis.fuse_vo(_vo(np.zeros(2), 0.3, 1 / 3), T0 + 3 * FRAME_US)
        for k in (1, 2):  # two late fixes before the gated one: two rewinds replaying it
            axis.fuse_fix(_fix(np.array([0.2, 0.1, -120.0]), 1.0, T0 + k * FRAME_US - 1000))
    gated = [e for e in logs if e["event"] == LogEvent.ESTIMATOR_FIX_REJECTED]
    assert len(gated) == 1, gated
    assert axis.stats().rewinds == 2


def test_time_axis_is_safe_under_concurrent_callers() -> None:
    """VO, fixes and output from three threads at once end in the state of in-order fusion."""
    inputs = _flight(30, np.array([10.0, 2.0]))
    clock = _Clock(T0 + 60 * S)
    reference = _axis(clock, max_delay_s=30.0)
    reference.initialise(np.array([0.0, 0.0, -120.0]), 10.0, T0)
    for item in inputs:
        _apply(reference, item)
    axis = _axis(clock, max_delay_s=30.0)
    axis.initialise(np.array([0.0, 0.0, -120.0]), 10.0, T0)
    errors: list[BaseException] = []

    def run(items: list[tuple[str, int, object]]) -> None:
        try:
            for item in items:
                _apply(axis, item)
        except BaseException as exc:  # surfaced by the assertion below
            errors.append(exc)

    def read() -> None:
        try:
            for _ in range(300):
                st = axis.state_at()
                assert np.all(np.isfinite(st.pos_ned_m))
        except BaseException as exc:
            errors.append(exc)

    threads = [
        threading.Thread(target=run, args=([i for i in inputs if i[0] == "vo"],)),
        threading.Thread(target=run, args=([i for i in inputs if i[0] == "fix"],)),
        threading.Thread(target=read),
    ]
    for th in threads:
        th.start()
    for th in threads:
        th.join(10.0)
    assert not errors, errors
    t_end = T0 + 31 * FRAME_US
    np.testing.assert_allclose(axis.state_at(t_end).pos_ned_m, reference.state_at(t_end).pos_ned_m, atol=1e-8)


# -- output and prediction -------------------------------------------------------------------------------


def test_time_axis_output_at_now_propagates_without_moving_the_filter() -> None:
    """state_at() answers at the clock's now (sigma grows with time); the head stays at the last input."""
    clock = _Clock(T0)
    axis = _axis(clock)
    axis.initialise(np.array([0.0, 0.0, -120.0]), 3.0, T0)
    sigmas = []
    for k in range(1, 6):
        clock.t = T0 + k * 100_000
        st = axis.state_at()
        assert st.time_unix_usec == clock.t
        sigmas.append(st.horiz_sigma_m)
    assert all(b > a for a, b in itertools.pairwise(sigmas))
    assert axis.head_unix_usec == T0


def test_time_axis_output_before_the_newest_input_is_not_retrodicted() -> None:
    """Asked for a time before the newest input, the axis answers that input's estimate, stamped with it."""
    clock = _Clock(T0)
    axis = _axis(clock)
    axis.initialise(np.array([0.0, 0.0, -120.0]), 3.0, T0 + 200_000)
    assert axis.state_at().time_unix_usec == T0 + 200_000


def _turn_error_and_nees(accel: _ConstAccel | None, seconds: float = 1.0) -> tuple[float, float]:
    """Predict ``seconds`` of a 15 deg/s, 12 m/s turn from an exactly known state; (error m, NEES)."""
    omega, speed = math.radians(15.0), 12.0
    est = NavEstimator(EstimatorConfig(), LTP, accel_source=accel)
    est.initialise(np.array([0.0, 0.0, -120.0]), 0.05, T0, vel_sigma_m_s=0.05)
    est._kf.x[3:6, 0] = [speed, 0.0, 0.0]  # the known velocity (north)
    dt = seconds
    theta = omega * dt
    truth = np.array([speed / omega * math.sin(theta), speed / omega * (1 - math.cos(theta))])
    st = est.state(T0 + round(dt * S))
    err = st.pos_ned_m[:2] - truth
    nees = float(err @ np.linalg.solve(st.cov_pos_ned_m2[:2, :2], err))
    return float(np.hypot(*err)), nees


def test_prediction_with_imu_follows_a_turn_and_stays_honest() -> None:
    """In a 15 deg/s turn the constant-velocity prediction is off by ~1.5 m; with the IMU's (mean)
    centripetal acceleration it is within 0.2 m, and its stated covariance covers the error."""
    centripetal = np.array([0.0, 12.0 * math.radians(15.0), 0.0])  # toward the turn centre (east)
    cv_err, _ = _turn_error_and_nees(_ConstAccel(None))
    imu_err, imu_nees = _turn_error_and_nees(_ConstAccel(centripetal))
    assert cv_err > 1.0
    assert imu_err < 0.2
    assert imu_nees < 9.21  # chi-square 2 dof, 99 %


def test_prediction_without_imu_stays_honest_through_an_unmeasured_turn() -> None:
    """The soak's finding: 5 s without IMU or VO (a link drop) in a 15 deg/s, 12 m/s turn. The
    constant-velocity prediction is ~38 m off; with the default noise its stated covariance must still
    cover that (NEES below the 99.9 % chi-square bound, 13.8), so the first fix after the drop is not
    gated and nothing confident is said in between."""
    err, nees = _turn_error_and_nees(_ConstAccel(None), seconds=5.0)
    assert err > 30.0
    assert nees < 13.8, (err, nees)


def test_vo_over_an_unmeasured_gap_does_not_claim_the_end_velocity() -> None:
    """The soak's second finding: VO across a 2 s gap without IMU measures the mean velocity of a turn,
    3 m/s off the end velocity. Its covariance must say so (velocity NEES below 13.8), where the
    frame-rate covariance alone claimed 0.1 m/s."""
    est = NavEstimator(EstimatorConfig(), LTP, accel_source=_ConstAccel(None))
    est.initialise(np.zeros(3), 0.5, T0, vel_sigma_m_s=0.5)
    est._kf.x[3:6, 0] = [12.0, 0.0, 0.0]
    end_vel = np.array([12.0 * math.cos(math.radians(30)), 12.0 * math.sin(math.radians(30))])
    mean_vel = np.array([12.0 * math.sin(math.radians(30)) / math.radians(30), 0.0])
    mean_vel[1] = 12.0 * (1 - math.cos(math.radians(30))) / math.radians(30)
    assert np.hypot(*(mean_vel - end_vel)) > 3.0
    assert est.update_vo(_vo(mean_vel * 2.0, 0.2, 2.0), time_unix_usec=T0 + 2 * S).accepted
    st = est.state()
    err = st.vel_ned_m_s[:2] - end_vel
    assert float(err @ np.linalg.solve(st.cov_vel_ned_m2_s2[:2, :2], err)) < 13.8


def test_prediction_without_imu_uses_the_larger_noise() -> None:
    """With no IMU answer the prediction covariance grows with accel_noise_m_s2, not the IMU's."""
    with_imu = NavEstimator(EstimatorConfig(), LTP, accel_source=_ConstAccel(np.zeros(3)))
    without = NavEstimator(EstimatorConfig(), LTP, accel_source=_ConstAccel(None))
    for est in (with_imu, without):
        est.initialise(np.zeros(3), 0.1, T0, vel_sigma_m_s=0.1)
    assert without.state(T0 + 2 * S).horiz_sigma_m > 1.5 * with_imu.state(T0 + 2 * S).horiz_sigma_m


def test_vo_velocity_is_moved_to_the_end_of_its_interval_with_the_imu() -> None:
    """VO measures the interval's mean velocity; with a known acceleration the filter gets the end
    velocity (mean + a dt / 2), so a steady 2 m/s^2 acceleration is not lagged by half a frame."""
    accel = _ConstAccel(np.array([2.0, 0.0, 0.0]))
    est = NavEstimator(EstimatorConfig(), LTP, accel_source=accel)
    est.initialise(np.zeros(3), 1.0, T0, vel_sigma_m_s=20.0)
    v = 0.0
    t = T0
    for _ in range(30):
        t += FRAME_US
        v_mean = v + 2.0 * (1 / 3) / 2
        v += 2.0 / 3
        assert est.update_vo(_vo(np.array([v_mean / 3.0, 0.0]), 0.05, 1 / 3), time_unix_usec=t).accepted
    assert est.state().vel_ned_m_s[0] == pytest.approx(v, abs=0.05)


def test_a_slow_matchers_late_fixes_anchor_the_output_until_the_window_ends() -> None:
    """Fixes that land 1.7 s after their exposure (XFeat + LighterGlue on a 2-core CPU), each attempt on
    the newest frame when the previous one is done: the output stays anchored from one fix to the next,
    stops being anchored once the newest fix's exposure is older than ``anchored_window_s``, and at once
    when an attempt gives no fix. A 1 s window never labelled such a flight anchored."""
    clock = _Clock(T0)
    axis = _axis(clock, anchored_window_s=4.0)
    start = np.array([0.0, 0.0, -120.0])
    axis.initialise(start, 30.0, T0)
    latency, exposure, last_fix = int(1.7 * S), T0, T0

    def vo_until(t_usec: int) -> None:  # VO at 10 Hz
        while clock.t < t_usec:
            clock.t += S // 10
            assert axis.fuse_vo(_vo(np.zeros(2), 0.05, 0.1), clock.t).accepted

    for _ in range(4):
        vo_until(exposure + latency)  # while the matcher works
        assert axis.fuse_fix(_fix(start, 2.0, exposure)).accepted
        for dt in (0, S // 2, latency - S // 10):  # until the next fix lands
            assert axis.state_at(clock.t + dt).provenance is Provenance.SATELLITE_ANCHORED
        last_fix, exposure = exposure, clock.t  # the next attempt takes the newest frame
    vo_until(last_fix + 4 * S)  # the matcher has gone quiet: no fix, no failed attempt
    assert axis.state_at().provenance is Provenance.SATELLITE_ANCHORED
    vo_until(clock.t + S // 10)
    assert axis.state_at().provenance is Provenance.VISUAL_PROPAGATED
    axis.fuse_fix(_fix(start, 2.0, clock.t))
    assert axis.state_at().provenance is Provenance.SATELLITE_ANCHORED
    vo_until(clock.t + S // 10)
    axis.note_no_fix(clock.t)  # the next frame's attempt gave no fix
    assert axis.state_at().provenance is Provenance.VISUAL_PROPAGATED

    with pytest.raises(ConfigError, match="anchored_window_s"):
        load_config(REPO_ROOT / "config" / "sitl.yaml", ["estimator.anchored_window_s=0"])


def test_a_raised_position_sigma_widens_the_state_and_survives_a_rewind() -> None:
    """The attitude check found the state leaning on a wrong tilt: its position sigma relative to the map
    (what the gates compare a fix with, not only what the output states) is at least the raised one and
    the position is not moved; only later accepted fixes bring it down; a fix from before the raise that
    arrives late rewinds the axis and the raise is replayed on top."""
    inputs = _flight(9, np.array([12.0, 5.0]))
    clock = _Clock(T0 + 20 * S)
    t_raise = T0 + 5 * FRAME_US
    held = inputs[7]  # frame 4's fix
    in_order, late = _axis(clock), _axis(clock)
    for axis in (in_order, late):
        axis.initialise(np.array([0.0, 0.0, -120.0]), 10.0, T0)
    for item in inputs[:10]:
        _apply(in_order, item)
        if item is not held:
            _apply(late, item)
    before = in_order.state_at(t_raise)
    assert before.horiz_sigma_m < 8.0
    in_order.raise_position_sigma(8.0, t_raise)
    after = in_order.state_at(t_raise)
    np.testing.assert_allclose(after.pos_ned_m, before.pos_ned_m, atol=1e-9)
    assert after.shared_sigma_m == pytest.approx(before.shared_sigma_m)
    assert np.sqrt(np.linalg.eigvalsh(after.map_frame_cov_ne_m2)) == pytest.approx([8.0, 8.0], rel=1e-6)
    late.raise_position_sigma(8.0, t_raise)
    _apply(late, held)
    np.testing.assert_allclose(late.state_at(t_raise).cov_pos_ned_m2, after.cov_pos_ned_m2, atol=1e-9)
    in_order.raise_position_sigma(2.0, t_raise)  # a smaller raise never narrows it
    np.testing.assert_allclose(in_order.state_at(t_raise).cov_pos_ned_m2, after.cov_pos_ned_m2, atol=1e-9)
    for axis in (in_order, late):
        for item in inputs[10:]:  # frames 6-9: VO, then the frame's fix
            _apply(axis, item)
        assert axis.state_at(inputs[-1][1]).horiz_sigma_m < 3.0


def test_an_untrusted_imu_is_left_out_of_the_prediction_and_a_rewind_keeps_it_out() -> None:
    """The autopilot's attitude was found 3 deg off: its IMU, rotated with it, reports 0.5 m/s^2 of
    gravity as horizontal acceleration. Untrusted, the prediction is the constant-velocity one with its
    larger noise; a late fix from before the switch rewinds the axis and the switch is replayed."""
    clock = _Clock(T0 + 20 * S)
    leaked = _ConstAccel(np.array([0.5, 0.0, 0.0]))
    with_imu, without = _axis(clock, accel=leaked), _axis(clock, accel=None)
    for axis in (with_imu, without):
        axis.initialise(np.array([0.0, 0.0, -120.0]), 3.0, T0)
    with_imu.set_imu_trusted(False, T0)
    t = T0 + 5 * S
    np.testing.assert_allclose(with_imu.state_at(t).pos_ned_m, without.state_at(t).pos_ned_m, atol=1e-9)
    np.testing.assert_allclose(
        with_imu.state_at(t).cov_pos_ned_m2, without.state_at(t).cov_pos_ned_m2, atol=1e-9
    )
    with_imu.fuse_fix(_fix(np.array([0.0, 0.0, -120.0]), 2.0, T0 + S))
    without.fuse_fix(_fix(np.array([0.0, 0.0, -120.0]), 2.0, T0 + S))
    with_imu.fuse_fix(_fix(np.array([0.0, 0.0, -120.0]), 2.0, T0 + S // 2))  # late: rewinds past nothing
    without.fuse_fix(_fix(np.array([0.0, 0.0, -120.0]), 2.0, T0 + S // 2))
    np.testing.assert_allclose(with_imu.state_at(t).pos_ned_m, without.state_at(t).pos_ned_m, atol=1e-9)
    with_imu.set_imu_trusted(True, T0 + 2 * S)
    gained = with_imu.state_at(t).pos_ned_m[0] - without.state_at(t).pos_ned_m[0]
    assert gained == pytest.approx(0.5 * 0.5 * 3.0**2, rel=0.05)  # 3 s of 0.5 m/s^2 after the switch


def test_an_imu_switch_the_axis_cannot_take_says_so() -> None:
    """Before the axis is initialised the switch is refused and the caller is told, so it says it
    again instead of believing the IMU is out of the prediction."""
    clock = _Clock(T0 + 20 * S)
    axis = _axis(clock, accel=_ConstAccel(np.array([0.5, 0.0, 0.0])))
    assert axis.set_imu_trusted(False, T0) is False
    assert axis.raise_position_sigma(8.0, T0) is False
    axis.initialise(np.array([0.0, 0.0, -120.0]), 3.0, T0)
    assert axis.set_imu_trusted(False, T0 + S) is True
    assert axis.raise_position_sigma(8.0, T0 + S) is True
    assert axis.set_imu_trusted(True, T0 - S) is True  # too late for its time: placed at the head


def test_a_position_sigma_or_imu_switch_too_late_for_its_time_holds_from_the_head() -> None:
    """A slow matcher's fix shows the attitude off after the axis has moved past its exposure by more than
    the delay it takes: the error the estimate carries and the IMU switch still reach the output, from
    the head on, never lost with the late fix."""
    clock = _Clock(T0 + 60 * S)
    axis = _axis(clock, accel=_ConstAccel(np.array([0.5, 0.0, 0.0])), max_delay_s=5.0)
    axis.initialise(np.array([0.0, 0.0, -120.0]), 3.0, T0)
    assert axis.set_imu_trusted(True, T0 + 20 * S) is True  # moves the head to T0 + 20 s
    late = T0 + 10 * S  # 10 s behind the head, the axis keeps 5
    assert axis.raise_position_sigma(8.0, late) is True
    assert np.sqrt(np.linalg.eigvalsh(axis.state_at(T0 + 20 * S).map_frame_cov_ne_m2)).min() >= 8.0
    before = axis.state_at(T0 + 25 * S).pos_ned_m[0]
    assert axis.set_imu_trusted(False, late) is True
    without_imu = axis.state_at(T0 + 25 * S).pos_ned_m[0]
    assert before - without_imu == pytest.approx(0.5 * 0.5 * 5.0**2, rel=0.05)  # 5 s of leaked gravity gone
