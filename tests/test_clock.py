"""The daemon's clock (monotonic, anchored to Unix time once) and the time axis on it: a step of the host's
wall clock, forward or back, is detected and counted, and neither refuses correct frames nor stops
correct fixes from being accepted (issue 9: the daemon's "now" was the wall clock).

The monotonic and wall clocks are fakes at the clock's boundary; the estimator and time axis are real.
"""

from __future__ import annotations

import numpy as np
import pytest

from gps_denied_onboard.clock import CLOCK_STEP_MIN_S, EPOCH_HISTORY_S, DaemonClock
from gps_denied_onboard.components.c5_estimator import FixReason, NavEstimator, Refusal, TimeAxis
from gps_denied_onboard.config import EstimatorConfig
from test_c5_estimator import LTP, S, _fix, _vo
from test_c5_estimator import T0_USEC as T0

FRAME_US = S // 3
#: Camera latency: exposure to admission, µs.
LATENCY_US = 40_000


class _HostClocks:
    """A host's CLOCK_MONOTONIC and CLOCK_REALTIME, in ns; ``step_wall`` is what NTP or ``date -s`` does."""

    def __init__(self, unix_usec: int) -> None:
        self.mono_ns = 5_000_000_000
        self.wall_ns = unix_usec * 1000

    def monotonic_ns(self) -> int:
        return self.mono_ns

    def time_ns(self) -> int:
        return self.wall_ns

    def advance(self, usec: int) -> None:
        self.mono_ns += usec * 1000
        self.wall_ns += usec * 1000

    def step_wall(self, seconds: float) -> None:
        self.wall_ns += round(seconds * 1e9)

    def wall_usec(self) -> int:
        return self.wall_ns // 1000


def _clock(host: _HostClocks) -> DaemonClock:
    return DaemonClock(monotonic_ns=host.monotonic_ns, wall_ns=host.time_ns)


def test_clock_is_anchored_once_and_never_follows_the_wall_clock() -> None:
    """Now starts at the wall clock's Unix time and then moves only with the monotonic clock."""
    host = _HostClocks(T0)
    clock = _clock(host)
    assert clock.now_unix_usec() == T0
    host.advance(S)
    host.step_wall(-30.0)
    assert clock.now_unix_usec() == T0 + S
    host.step_wall(+3600.0)
    host.advance(S)
    assert clock.now_unix_usec() == T0 + 2 * S
    assert clock.now_unix_s() == pytest.approx((T0 + 2 * S) / 1e6)


@pytest.mark.parametrize("step_s", [-30.0, -0.5, 0.5, 3600.0])
def test_clock_maps_a_host_wall_stamp_through_a_step(step_s: float) -> None:
    """A stamp taken with the host's wall clock after a step maps to the same daemon time as without it."""
    host = _HostClocks(T0)
    clock = _clock(host)
    host.advance(2 * S)
    before = clock.from_wall_usec(host.wall_usec() - LATENCY_US)
    host.step_wall(step_s)
    assert clock.from_wall_usec(host.wall_usec() - LATENCY_US) == before == T0 + 2 * S - LATENCY_US
    assert clock.wall_offset_usec() == round(step_s * S)


def test_clock_detects_each_step_once_and_ignores_slew() -> None:
    """A step beyond CLOCK_STEP_MIN_S is reported once with its size; NTP-like slewing is not a step."""
    host = _HostClocks(T0)
    clock = _clock(host)
    assert clock.check_step() is None
    host.advance(S)
    host.step_wall(CLOCK_STEP_MIN_S / 4)  # slew-sized
    assert clock.check_step() is None
    host.step_wall(-30.0)
    step = clock.check_step()
    assert step is not None and step.step_s == pytest.approx(-30.0, abs=CLOCK_STEP_MIN_S)
    assert clock.check_step() is None, "one step reported twice"
    host.step_wall(+45.0)
    step = clock.check_step()
    assert step is not None and step.step_s == pytest.approx(45.0, abs=1e-6)
    assert step.wall_offset_s == pytest.approx(15.0 + CLOCK_STEP_MIN_S / 4, abs=1e-6)
    assert clock.steps == 2


@pytest.mark.parametrize("step_s", [-30.0, 30.0, -2.0, 3600.0])
def test_clock_maps_a_backlogged_frame_with_the_offset_of_its_own_epoch(step_s: float) -> None:
    """Frames exposed before a step but read after it (a backlog in the stream) keep their true times, as
    do the frames after the step; once the backlog horizon has passed only the current offset is used."""
    host = _HostClocks(T0)
    clock = _clock(host)
    host.advance(S)
    before = [host.wall_usec() - LATENCY_US - k * FRAME_US for k in (2, 1, 0)]
    true_before = [T0 + S - LATENCY_US - k * FRAME_US for k in (2, 1, 0)]
    host.step_wall(step_s)
    assert clock.check_step() is not None
    host.advance(FRAME_US)
    after = host.wall_usec() - LATENCY_US
    assert [clock.from_wall_usec(stamp) for stamp in before] == true_before
    assert clock.from_wall_usec(after) == T0 + S + FRAME_US - LATENCY_US
    host.advance(round(EPOCH_HISTORY_S * S) + S)
    assert clock.from_wall_usec(before[-1]) == true_before[-1] - round(step_s * S)


def test_clock_history_does_not_explain_away_a_lying_stamp() -> None:
    """A frame stamped 5 s in the future right after a backwards step is not mapped to a fresh time."""
    host = _HostClocks(T0)
    clock = _clock(host)
    host.advance(S)
    host.step_wall(-30.0)
    clock.check_step()
    t = clock.from_wall_usec(host.wall_usec() + 5 * S)
    assert abs(t - clock.now_unix_usec()) > 4 * S


def _axis(clock: DaemonClock) -> TimeAxis:
    est = NavEstimator(EstimatorConfig(), LTP)
    return TimeAxis(est, max_delay_s=5.0, max_frame_age_s=1.0, max_future_s=0.25, clock=clock)


def _fly_through_step(axis: TimeAxis, host: _HostClocks, step_s: float) -> list[tuple[bool, str | None]]:
    """A straight 10 m/s flight, frames stamped with the host's wall clock, VO and an exact fix per
    frame; the wall clock steps by ``step_s`` after frame 10. Returns (admitted, fix reason) per frame."""
    start = np.array([0.0, 0.0, -120.0])
    vel_ne = np.array([10.0, 0.0])
    axis.initialise(start, 2.0, host.wall_usec())
    out = []
    for k in range(1, 31):
        host.advance(FRAME_US)
        if k == 11:
            host.step_wall(step_s)
        exposure_stamp = host.wall_usec() - LATENCY_US
        adm = axis.admit_frame(exposure_stamp)
        reason = None
        if adm.admitted:
            t = adm.exposure_time_unix_usec
            axis.fuse_vo(_vo(vel_ne / 3.0, 0.3, 1 / 3), t)
            truth = start + np.array([*(vel_ne * (t - T0) / S), 0.0])
            reason = axis.fuse_fix(_fix(truth, 2.0, t)).reason
        out.append((adm.admitted, reason))
    return out


@pytest.mark.parametrize("step_s", [-30.0, -2.0, 2.0, 3600.0])
def test_time_axis_on_the_daemon_clock_keeps_accepting_correct_fixes_through_a_wall_step(
    step_s: float,
) -> None:
    """Through a host clock step back or forward, every frame stamped by the host is admitted at its true
    time and every correct fix is accepted; nothing is refused."""
    host = _HostClocks(T0)
    axis = _axis(_clock(host))
    results = _fly_through_step(axis, host, step_s)
    assert all(admitted for admitted, _ in results), results
    assert all(reason == FixReason.ACCEPTED for _, reason in results), results
    assert sum(axis.stats().refused.values()) == 0
    state = axis.state_at()
    assert state.time_unix_usec == T0 + 30 * FRAME_US


def test_time_axis_on_the_wall_clock_refuses_every_frame_after_a_backwards_step() -> None:
    """The defect the daemon clock removes: with the wall clock as "now", the host stepping back 30 s
    makes every later frame out of order (a 30 s outage), and a forward step refuses them as stale."""
    host = _HostClocks(T0)
    est = NavEstimator(EstimatorConfig(), LTP)
    axis = TimeAxis(
        est, max_delay_s=5.0, max_frame_age_s=1.0, max_future_s=0.25, clock_unix_usec=host.wall_usec
    )
    results = _fly_through_step(axis, host, -30.0)
    assert [a for a, _ in results[:10]] == [True] * 10
    assert not any(a for a, _ in results[10:]), results
    assert axis.stats().refused[Refusal.OUT_OF_ORDER.value] == 20
