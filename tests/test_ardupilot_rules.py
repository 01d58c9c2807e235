"""The ArduPilot GPS_INPUT test double: acceptance, health, loss-of-stream timeouts and the stream verdict,
each against the measured facts it reproduces (DESIGN.md, "What a real ArduPilot does with GPS_INPUT")."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gps_denied_onboard.sitl.ardupilot_rules import (
    GPS_TYPE_MAV,
    GpsHealthMonitor,
    GpsLossStage,
    GpsTypeParams,
    evaluate_gps_stream,
    gps_input_accepted,
    gps_input_rejection,
    gps_loss_stage,
    prearm_gps_failures,
)

GPS1_MAV = {0: GPS_TYPE_MAV}
GPS2_MAV = {0: 1, 1: GPS_TYPE_MAV}  # simulated u-blox on GPS1, GPS_INPUT on GPS2


def fields(gps_id: int = 0, fix_type: int = 3, time_week: int = 2350) -> dict[str, int]:
    return {"gps_id": gps_id, "fix_type": fix_type, "time_week": time_week, "time_week_ms": 1000}


def steady(start_s: float, stop_s: float, interval_ms: float) -> list[float]:
    """Times from start_s up to and including stop_s at a fixed interval, exact to the microsecond."""
    n = round((stop_s - start_s) * 1000 / interval_ms)
    return [round(start_s + k * interval_ms / 1000, 6) for k in range(n + 1)]


def feed(times_s: list[float]) -> GpsHealthMonitor:
    monitor = GpsHealthMonitor()
    for t in times_s:
        monitor.on_message(t)
    return monitor


def with_gap(gap_s: float, *, after_s: float = 10.0) -> list[float]:
    """10 Hz for 10 s, silence of gap_s, 10 Hz for 10 s more."""
    before = steady(0.0, after_s, 100)
    return before + steady(after_s + gap_s, after_s + gap_s + 10.0, 100)


# --- acceptance ---------------------------------------------------------------------------------------


def test_acceptance_3d_fix_on_gps1_accepted() -> None:
    """fix_type 3, time_week > 0, gps_id 0 with GPS1_TYPE=14 is used."""
    assert gps_input_accepted(fields(), GPS1_MAV)
    assert gps_input_rejection(fields(fix_type=6), GPS1_MAV) is None


def test_acceptance_fix_type_2_rejected() -> None:
    """A 2D fix is not used."""
    assert not gps_input_accepted(fields(fix_type=2), GPS1_MAV)
    assert "fix_type 2" in (gps_input_rejection(fields(fix_type=2), GPS1_MAV) or "")


def test_acceptance_time_week_0_rejected() -> None:
    """time_week 0 is not used even with a 3D fix."""
    assert not gps_input_accepted(fields(time_week=0), GPS1_MAV)
    assert "time_week 0" in (gps_input_rejection(fields(time_week=0), GPS1_MAV) or "")


def test_acceptance_gps_id_1_with_only_gps1_mav_rejected() -> None:
    """gps_id 1 is ignored when only GPS1_TYPE is 14."""
    assert not gps_input_accepted(fields(gps_id=1), GPS1_MAV)
    assert "gps_id 1" in (gps_input_rejection(fields(gps_id=1), GPS1_MAV) or "")


def test_acceptance_gps2_mav_takes_gps_id_1_only() -> None:
    """With GPS2_TYPE=14 (GPS1 a real receiver) gps_id 1 is used and gps_id 0 ignored."""
    assert gps_input_accepted(fields(gps_id=1), GPS2_MAV)
    assert not gps_input_accepted(fields(gps_id=0), GPS2_MAV)


def test_acceptance_out_of_range_gps_id_rejected() -> None:
    """Ids beyond the two receivers are ignored even when both are MAVLink GPSs."""
    both = {0: GPS_TYPE_MAV, 1: GPS_TYPE_MAV}
    assert not gps_input_accepted(fields(gps_id=2), both)
    assert not gps_input_accepted(fields(gps_id=127), both)


def test_acceptance_missing_field_raises() -> None:
    """A message without fix_type is an error naming the field, not a silent rejection."""
    with pytest.raises(ValueError, match="fix_type"):
        gps_input_accepted({"gps_id": 0, "time_week": 2350}, GPS1_MAV)


def test_params_gps_type_set_in_flight_not_in_effect_until_reboot() -> None:
    """GPS1_TYPE is reboot-required: setting it in flight changes nothing until a reboot."""
    params = GpsTypeParams(at_boot={0: 1}).set(0, GPS_TYPE_MAV)
    assert not gps_input_accepted(fields(gps_id=0), params.in_effect)
    assert gps_input_accepted(fields(gps_id=0), params.reboot().in_effect)


def test_params_instance_out_of_range_raises() -> None:
    """There is no GPS3_TYPE."""
    with pytest.raises(ValueError, match="instance 2"):
        GpsTypeParams(at_boot=GPS1_MAV).set(2, GPS_TYPE_MAV)


def test_prearm_gps2_without_gps_input_bad_fix() -> None:
    """GPS 2 as a MAVLink GPS must have had an accepted GPS_INPUT before arming."""
    assert prearm_gps_failures(GPS2_MAV, instances_with_fix=()) == ["PreArm: GPS 2: Bad fix"]
    assert prearm_gps_failures(GPS2_MAV, instances_with_fix={1}) == []


# --- health -------------------------------------------------------------------------------------------


def test_health_steady_10hz_healthy() -> None:
    """10 Hz without jitter is healthy, with a 100 ms mean."""
    monitor = feed(steady(0.0, 30.0, 100))
    assert monitor.healthy
    assert monitor.mean_interval_ms == pytest.approx(100.0)
    verdict = evaluate_gps_stream(steady(0.0, 30.0, 100), [True] * 301)
    assert not verdict.health_tripped and verdict.healthy_at_end


def test_health_steady_5hz_healthy() -> None:
    """Exactly 5 Hz (200 ms) is the slowest healthy rate."""
    assert feed(steady(0.0, 30.0, 200)).healthy


def test_health_exactly_3hz_unhealthy_permanently() -> None:
    """3 Hz is 'not healthy' from its first interval on (333 ms mean) and never recovers."""
    times = [round(k / 3, 6) for k in range(90)]
    verdict = evaluate_gps_stream(times, [True] * len(times))
    assert verdict.unhealthy_spans_s == ((times[1], times[-1]),)
    assert not verdict.healthy_at_end


def test_health_jittery_5hz_two_consecutive_late_intervals_unhealthy_once() -> None:
    """5 Hz whose jitter gives two consecutive intervals > 245 ms trips once, then recovers."""
    intervals_ms = [200.0] * 20 + [250.0, 250.0] + [150.0, 200.0, 150.0] + [200.0] * 20
    times = [0.0, *np.round(np.cumsum(intervals_ms) / 1000.0, 6).tolist()]
    verdict = evaluate_gps_stream(times, [True] * len(times))
    assert len(verdict.unhealthy_spans_s) == 1
    start_s, end_s = verdict.unhealthy_spans_s[0]
    assert start_s == pytest.approx(times[22])  # the second 250 ms interval
    assert end_s == pytest.approx(times[23])  # the next on-time interval resets the counter
    assert verdict.healthy_at_end


def test_health_single_late_interval_at_10hz_stays_healthy() -> None:
    """One 300 ms interval is a delayed frame but not two in a row."""
    times = steady(0.0, 5.0, 100) + steady(5.3, 10.0, 100)
    assert not evaluate_gps_stream(times, [True] * len(times)).health_tripped


def test_health_interval_245ms_is_not_delayed() -> None:
    """Boundary: 245 ms is on time (the rule is > 245 ms), even twice in a row."""
    monitor = feed([*steady(0.0, 5.0, 100), 5.245, 5.49])
    assert monitor.delayed_count == 0
    assert monitor.healthy


def test_health_two_intervals_246ms_unhealthy() -> None:
    """Boundary: two consecutive 246 ms intervals make the GPS unhealthy."""
    monitor = feed([*steady(0.0, 5.0, 100), 5.246])
    assert monitor.delayed_count == 1 and monitor.healthy
    monitor.on_message(5.492)
    assert monitor.delayed_count == 2 and not monitor.healthy


def test_health_mean_214ms_healthy_215ms_unhealthy() -> None:
    """Boundary: a steady 214 ms stream is healthy, a steady 215 ms stream is not (mean < 215 ms)."""
    assert feed(steady(0.0, 30.0, 214)).healthy
    monitor = feed(steady(0.0, 30.0, 215))
    assert monitor.delayed_count == 0
    assert monitor.mean_interval_ms == 215.0
    assert not monitor.healthy


def test_health_mean_is_filtered_0_98_0_02() -> None:
    """At 5 Hz one 1 s hiccup lifts the filtered mean to 216 ms (unhealthy); it decays back under 215 ms."""
    monitor = feed([*steady(0.0, 10.0, 200), 11.0])
    assert monitor.mean_interval_ms == pytest.approx(0.98 * 200 + 0.02 * 1000)
    assert monitor.delayed_count == 1
    assert not monitor.healthy
    monitor.on_message(11.2)
    assert not monitor.healthy  # 200 + 16 * 0.98
    for t in (11.4, 11.6, 11.8):
        monitor.on_message(t)
    assert monitor.mean_interval_ms == pytest.approx(200 + 16 * 0.98**4)
    assert monitor.healthy


def test_health_intervals_of_2s_or_more_not_averaged() -> None:
    """A 3 s interval counts as delayed but leaves the filtered mean alone."""
    monitor = feed([*steady(0.0, 5.0, 100), 8.0])
    assert monitor.mean_interval_ms == pytest.approx(100.0)
    assert monitor.delayed_count == 1


def test_health_two_timeouts_of_silence_unhealthy() -> None:
    """Each 4 s of silence counts as a delayed frame: after 8 s the GPS is unhealthy."""
    monitor = feed(steady(0.0, 5.0, 100))
    assert monitor.advance_to(9.0) == []  # exactly 4 s of silence is not yet a timeout
    assert monitor.advance_to(9.05) == [9.0]
    assert monitor.delayed_count == 1 and monitor.healthy
    assert monitor.advance_to(13.05) == [13.0]
    assert not monitor.healthy


def test_health_timeout_restarts_the_interval() -> None:
    """After a timeout the next interval is measured from the timeout, not from the last message."""
    monitor = feed(steady(0.0, 5.0, 100))
    monitor.on_message(9.1)  # timeout at 9.0, then a 100 ms interval
    assert monitor.last_interval_ms == pytest.approx(100.0)
    assert monitor.delayed_count == 0


def test_health_message_going_backwards_raises() -> None:
    """Times must not go backwards."""
    monitor = feed([1.0, 1.1])
    with pytest.raises(ValueError, match="earlier"):
        monitor.on_message(1.05)


# --- loss of the stream -------------------------------------------------------------------------------


def test_loss_stage_thresholds() -> None:
    """NO_FIX after 4.0 s, EKF position lost after 7.0 s, failsafe LAND after 7.8 s (strictly after)."""
    assert gps_loss_stage(4.0) is GpsLossStage.OK
    assert gps_loss_stage(4.001) is GpsLossStage.NO_FIX
    assert gps_loss_stage(7.0) is GpsLossStage.NO_FIX
    assert gps_loss_stage(7.001) is GpsLossStage.EKF_POSITION_LOST
    assert gps_loss_stage(7.8) is GpsLossStage.EKF_POSITION_LOST
    assert gps_loss_stage(7.801) is GpsLossStage.EKF_FAILSAFE_LAND


def test_stream_gap_4_1s_no_fix_without_failsafe() -> None:
    """A 4.1 s gap reports NO_FIX from 4.0 s into it until the stream resumes, and nothing worse."""
    verdict = evaluate_gps_stream(with_gap(4.1), [True] * len(with_gap(4.1)))
    assert len(verdict.no_fix) == 1
    outage = verdict.no_fix[0]
    assert (outage.last_accepted_s, outage.start_s, outage.end_s) == pytest.approx((10.0, 14.0, 14.1))
    assert verdict.ekf_position_lost == ()
    assert verdict.ekf_failsafe_land_s is None


def test_stream_gap_6s_no_fix_without_failsafe() -> None:
    """A 6 s gap: NO_FIX, the EKF keeps its position, no failsafe."""
    times = with_gap(6.0)
    verdict = evaluate_gps_stream(times, [True] * len(times))
    assert len(verdict.no_fix) == 1
    assert verdict.ekf_position_lost == ()
    assert verdict.ekf_failsafe_land_s is None
    assert not verdict.in_land_at(times[-1])


def test_stream_gap_7_5s_ekf_position_lost_without_failsafe() -> None:
    """A 7.5 s gap loses the EKF position at 7.0 s but ends before the failsafe."""
    times = with_gap(7.5)
    verdict = evaluate_gps_stream(times, [True] * len(times))
    assert [o.start_s for o in verdict.ekf_position_lost] == pytest.approx([17.0])
    assert verdict.ekf_failsafe_land_s is None


def test_stream_gap_8_5s_failsafe_latched_after_resume() -> None:
    """An 8.5 s gap: failsafe to LAND at 7.8 s, still LAND after the stream is back and healthy."""
    times = with_gap(8.5)
    verdict = evaluate_gps_stream(times, [True] * len(times))
    assert verdict.ekf_failsafe_land_s == pytest.approx(17.8)
    assert verdict.no_fix[0].end_s == pytest.approx(18.5)  # the stream resumed...
    assert verdict.healthy_at_end
    assert verdict.in_land_at(times[-1])  # ...and the vehicle stayed in LAND
    assert not verdict.in_land_at(17.7)


def test_stream_two_long_gaps_failsafe_time_is_the_first() -> None:
    """The failsafe latches at the first long gap; a second one reports outages but not a new failsafe."""
    times = with_gap(8.5) + steady(40.0, 45.0, 100)  # second gap: 28.5 s -> 40.0 s
    verdict = evaluate_gps_stream(times, [True] * len(times))
    assert verdict.ekf_failsafe_land_s == pytest.approx(17.8)
    assert [o.last_accepted_s for o in verdict.ekf_position_lost] == pytest.approx([10.0, 28.5])


def test_stream_rejected_messages_count_as_absent() -> None:
    """10 Hz all along, but 5 s of fix_type 2 in the middle: NO_FIX as if nothing had arrived."""
    times = steady(0.0, 20.0, 100)
    msgs = [fields(fix_type=2 if 10.0 < t < 15.05 else 3) for t in times]
    accepted = [gps_input_accepted(m, GPS1_MAV) for m in msgs]
    verdict = evaluate_gps_stream(times, accepted)
    assert verdict.messages == len(times) and verdict.accepted == len(times) - 50
    assert len(verdict.no_fix) == 1
    assert (verdict.no_fix[0].last_accepted_s, verdict.no_fix[0].end_s) == pytest.approx((10.0, 15.1))
    assert verdict.ekf_failsafe_land_s is None


def test_stream_wrong_gps_id_all_along_never_has_a_fix() -> None:
    """gps_id 1 with only GPS1_TYPE=14: nothing accepted, so no fix, no health, no outage to report."""
    times = steady(0.0, 10.0, 100)
    accepted = [gps_input_accepted(fields(gps_id=1), GPS1_MAV) for _ in times]
    verdict = evaluate_gps_stream(times, accepted, end_s=20.0)
    assert verdict.accepted == 0 and verdict.first_accepted_s is None
    assert verdict.no_fix == () and verdict.ekf_failsafe_land_s is None
    assert not verdict.healthy_at_end
    assert prearm_gps_failures(GPS1_MAV, instances_with_fix=()) == ["PreArm: GPS 1: Bad fix"]


def test_stream_trailing_silence_judged_with_end_s() -> None:
    """A stream that stops 9 s before the end of the flight: open outages and a failsafe."""
    times = steady(0.0, 10.0, 100)
    verdict = evaluate_gps_stream(times, [True] * len(times), end_s=19.0)
    assert [(o.start_s, o.end_s) for o in verdict.no_fix] == [(pytest.approx(14.0), None)]
    assert verdict.ekf_failsafe_land_s == pytest.approx(17.8)
    assert verdict.unhealthy_spans_s == ((pytest.approx(18.0), 19.0),)  # two timeouts of silence
    assert evaluate_gps_stream(times, [True] * len(times)).ekf_failsafe_land_s is None


def test_stream_interval_statistics_over_accepted_messages() -> None:
    """Interval stats are over consecutive accepted messages, in ms."""
    times = [0.0, 0.1, 0.2, 0.3, 0.8, 0.9]
    verdict = evaluate_gps_stream(times, [True, True, False, True, True, True])
    stats = verdict.interval_ms
    assert stats is not None
    assert stats.n == 4
    assert stats.mean_ms == pytest.approx(np.mean([100, 200, 500, 100]))
    assert stats.p50_ms == pytest.approx(150.0)
    assert stats.max_ms == pytest.approx(500.0)
    assert stats.p99_ms == pytest.approx(np.percentile([100, 200, 500, 100], 99))


def test_stream_to_dict_is_json() -> None:
    """The verdict serialises to JSON with the rules it was judged by and a test-double label."""
    times = with_gap(8.5)
    out = json.loads(json.dumps(evaluate_gps_stream(times, [True] * len(times)).to_dict()))
    assert out["ekf_failsafe_land_s"] == pytest.approx(17.8)
    assert out["no_fix"][0]["end_s"] == pytest.approx(18.5)
    assert out["rules"]["health_delayed_interval_ms"] == 245.0
    assert "not the autopilot" in out["source"]
    assert set(out["interval_ms"]) == {"n", "mean_ms", "p50_ms", "p99_ms", "max_ms"}


def test_stream_length_mismatch_raises() -> None:
    """times_s and accepted must pair up."""
    with pytest.raises(ValueError, match="accepted has 1"):
        evaluate_gps_stream([0.0, 0.1], [True])


def test_stream_times_going_backwards_raises() -> None:
    """Times must be non-decreasing, and the error names the index."""
    with pytest.raises(ValueError, match=r"\[2\]"):
        evaluate_gps_stream([0.0, 0.2, 0.1], [True] * 3)


def test_stream_end_before_last_message_raises() -> None:
    """end_s cannot precede the last message."""
    with pytest.raises(ValueError, match="end_s"):
        evaluate_gps_stream([0.0, 1.0], [True, True], end_s=0.5)


def test_stream_empty_has_no_verdict_items() -> None:
    """An empty stream gives an empty verdict rather than an error."""
    verdict = evaluate_gps_stream([], [])
    assert verdict.messages == 0 and verdict.interval_ms is None and not verdict.health_tripped



def test_speed_accuracy_glitch_filter_peak_hold_and_hysteresis() -> None:
    """EKF3 calcGpsGoodForFlight: one 2.5 m/s sample after 1.0 m/s is filtered below the 1.5 m/s limit,
    a run of them fails it; the peak then decays over 10 s and passes again only below 1.0 m/s."""
    from gps_denied_onboard.sitl.ardupilot_rules import SpeedAccuracyGlitch

    g = SpeedAccuracyGlitch()
    t = 0.0
    for _ in range(30):
        t += 0.1
        assert not g.update(t, 1.0)
    t += 0.1
    assert not g.update(t, 2.5)  # lpf 0.2 x 2.5 + 0.8 x 1.0 = 1.3
    for _ in range(3):
        t += 0.1
        g.update(t, 2.5)
    assert g.glitching and g.peak_m_s > 1.5
    t_fail = t
    while g.glitching and t - t_fail < 30.0:
        t += 0.1
        g.update(t, 0.3)
    assert 3.0 < t - t_fail < 10.0  # the 10 s peak hold, down to below 1.0 m/s


def test_stream_silence_after_the_gnss_took_over_trips_nothing() -> None:
    """GPS_INPUT stops 10 s after another source (the GNSS back on) took over: no NO_FIX, no failsafe;
    the same silence while the stream was relied on predicts both."""
    times = [i * 0.1 for i in range(100)]
    ok = [True] * len(times)
    relied = evaluate_gps_stream(times, ok, end_s=30.0)
    assert relied.ekf_failsafe_land_s is not None and relied.no_fix
    after = evaluate_gps_stream(times, ok, end_s=30.0, relied_on_until_s=5.0)
    assert after.ekf_failsafe_land_s is None and not after.no_fix and not after.ekf_position_lost
