"""C5 input journal: units recorded on one time axis and played back on another give the same states bit
for bit, even with IMU answers that change between the first fusion and a rewind; a replay that leaves
the recorded order is stopped, never answered with made-up data.

The estimator and the time axis are the real ones; the clock and the IMU are fakes at their boundaries.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from gps_denied_onboard.components.c5_estimator import NavEstimator, TimeAxis
from gps_denied_onboard.components.c5_estimator.journal import (
    UNIT_FIX,
    UNIT_TRACK,
    RecordingJournal,
    ReplayDivergence,
    ReplayJournal,
)
from gps_denied_onboard.components.c5_estimator.protocol import ImuAcceleration
from gps_denied_onboard.config import EstimatorConfig
from test_c5_estimator import LTP, _fix, _vo
from test_c5_estimator import T0_USEC as T0
from test_c5_time_axis import FRAME_US, _Clock


class _DriftingImu:
    """An IMU whose answer for the same interval changes over time (samples arriving late): each call
    answers a slightly different acceleration, as a live tracker may."""

    def __init__(self) -> None:
        self.calls = 0

    def accel_ned_mean(self, t0_unix_usec: int, t1_unix_usec: int) -> ImuAcceleration | None:
        self.calls += 1
        if self.calls % 7 == 0:
            return None  # stale now and then
        return ImuAcceleration(np.array([0.3 + 0.01 * self.calls, -0.2, 0.0]), 0.05 * (self.calls % 3))


def _run(axis: TimeAxis, clock: _Clock | None, script: list[tuple[str, int, Any]]) -> list[tuple[float, ...]]:
    """The daemon's interleaving: track units in frame order, fix units for older frames in between."""
    states = []
    for kind, t, payload in script:
        if clock is not None:
            clock.t = t + 50_000
        with axis.unit(kind, t) as unit:
            if kind == UNIT_TRACK:
                if not axis.is_initialised:
                    axis.initialise(np.array([0.0, 0.0, -120.0]), 30.0, t)
                    unit["initialised"] = True
                axis.fuse_vo(payload, t)
                s = axis.state_at(t)
                states.append((*s.pos_ned_m, *s.vel_ned_m_s, float(s.cov_pos_ned_m2[0, 0])))
            else:
                axis.fuse_fix(payload)
    return states


def _script() -> list[tuple[str, int, Any]]:
    out: list[tuple[str, int, Any]] = []
    vel = np.array([12.0, 3.0])
    for k in range(1, 16):
        t = T0 + k * FRAME_US
        out.append((UNIT_TRACK, t, _vo(vel / 3.0, 0.3, 1 / 3)))
        if k >= 3 and k % 2 == 1:  # the fix for frame k-2 arrives now: the axis rewinds
            tf = T0 + (k - 2) * FRAME_US
            truth = np.array([*(vel * (k - 2) / 3.0), -120.0])
            out.append((UNIT_FIX, tf, _fix(truth, 2.0, tf)))
    return out


def _axis(journal: Any, clock: Any) -> TimeAxis:
    est = NavEstimator(EstimatorConfig(), LTP, accel_source=journal)
    return TimeAxis(est, max_delay_s=5.0, max_frame_age_s=1.0, clock_unix_usec=clock, journal=journal)


def test_journal_playback_reproduces_every_state_exactly() -> None:
    """Recorded with an IMU whose answers drift between calls (so a rewind sees other values than the
    first fusion did), played back on a fresh axis: every tracked state is equal, bit for bit."""
    records: list[dict[str, Any]] = []
    clock = _Clock(T0)
    imu = _DriftingImu()
    recorded = _run(_axis(RecordingJournal(imu, records.append), clock), clock, _script())
    assert any(r["unit"] == UNIT_FIX for r in records) and sum(len(r["accel"]) for r in records) > 20
    assert any(a[2] is None for r in records for a in r["accel"])
    assert (
        records[0]["initialised"] is True
        and records[0]["clock_unix_usec"] == records[0]["time_unix_usec"] + 50_000
    )
    replay = ReplayJournal(records)
    replayed = _run(_axis(replay, replay.clock_unix_usec), None, _script())
    assert replayed == recorded
    assert replay.units_replayed == len(records)


def test_journal_playback_without_the_imu_answers_differs() -> None:
    """The same script on an axis with the live IMU again (not the recorded answers) does not reproduce
    the recording: the recorded answers are what makes the replay exact."""
    records: list[dict[str, Any]] = []
    clock = _Clock(T0)
    recorded = _run(_axis(RecordingJournal(_DriftingImu(), records.append), clock), clock, _script())
    clock2 = _Clock(T0)
    imu2 = _DriftingImu()
    imu2.calls = 3  # a live source answers whatever it has now
    again = _run(_axis(RecordingJournal(imu2, lambda r: None), clock2), clock2, _script())
    assert again != recorded


def test_journal_playback_refuses_another_order() -> None:
    """A replay that performs a unit the recording does not have next (another kind or time) is stopped
    with ReplayDivergence naming the unit."""
    records: list[dict[str, Any]] = []
    clock = _Clock(T0)
    _run(_axis(RecordingJournal(_DriftingImu(), records.append), clock), clock, _script())
    swapped = _script()
    i = next(k for k, item in enumerate(swapped) if item[0] == UNIT_FIX)
    swapped[i], swapped[i + 1] = swapped[i + 1], swapped[i]
    replay = ReplayJournal(records)
    with pytest.raises(ReplayDivergence, match=r"unit \d+: recorded fix"):
        _run(_axis(replay, replay.clock_unix_usec), None, swapped)


def test_journal_playback_refuses_an_unrecorded_imu_question() -> None:
    """An IMU question outside any unit, or beyond a unit's recorded answers, is refused, never answered."""
    replay = ReplayJournal([])
    with pytest.raises(ReplayDivergence, match="outside a unit"):
        replay.accel_ned_mean(T0, T0 + 1)
    replay = ReplayJournal(
        [{"n": 1, "unit": UNIT_TRACK, "time_unix_usec": T0, "clock_unix_usec": T0, "accel": []}]
    )
    replay.begin(UNIT_TRACK, T0, 0)
    with pytest.raises(ReplayDivergence, match="beyond the recorded answers"):
        replay.accel_ned_mean(T0, T0 + 1)


def test_journal_records_the_tilt_doubt_and_replays_a_recording_made_before_it_with_none() -> None:
    """Each answer is recorded with its tilt doubt and served back with it; an answer recorded before
    the doubt existed (``[t0, t1, mean]``) is served with a doubt of 0, as that code predicted."""
    records: list[dict[str, Any]] = []
    journal = RecordingJournal(_DriftingImu(), records.append)
    journal.begin(UNIT_TRACK, T0, T0)
    journal.accel_ned_mean(T0, T0 + 1)
    journal.emit(journal.end({}) or {})
    entry = records[0]["accel"][0]
    assert len(entry) == 4 and entry[3] == pytest.approx(0.05)
    old = {"n": 1, "unit": UNIT_TRACK, "time_unix_usec": T0, "clock_unix_usec": T0}
    replay = ReplayJournal([{**old, "accel": [entry]}, {**old, "n": 2, "accel": [entry[:3]]}])
    replay.begin(UNIT_TRACK, T0, 0)
    assert replay.accel_ned_mean(T0, T0 + 1) == (pytest.approx(entry[2]), pytest.approx(0.05))
    replay.end({})
    replay.begin(UNIT_TRACK, T0, 0)
    served = replay.accel_ned_mean(T0, T0 + 1)
    assert served is not None and served.tilt_bound_m_s2 == 0.0
