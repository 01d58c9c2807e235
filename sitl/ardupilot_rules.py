"""What ArduPilot does with a GPS_INPUT stream: a TEST DOUBLE of measured behaviour, not the autopilot.

No ArduPilot binary ships with this project, so the simulator judges the daemon's GPS_INPUT stream with
these rules. They reproduce what copter SITL 4.7.0-dev did on the project's machines (DESIGN.md, "What a
real ArduPilot does with GPS_INPUT"), cross-checked against ArduPilot's public source. No report may
present a verdict from this module as the autopilot's.

Input: GPS_INPUT messages with their receive times (and the parameters that select the instance).
Output: each rule's verdict; :func:`evaluate_gps_stream` replays a whole received stream through all:
- acceptance (:func:`gps_input_rejection`, :func:`gps_input_accepted`): ``gps_id`` selects the instance
  whose ``GPSn_TYPE`` is 14, ``fix_type`` >= 3, ``time_week`` > 0; ``GPSn_TYPE`` is reboot-required
  (:class:`GpsTypeParams`); no accepted GPS_INPUT fails pre-arm with "Bad fix" (:func:`prearm_gps_failures`);
- health (:class:`GpsHealthMonitor`): filtered mean interval < 215 ms, fewer than 2 consecutive > 245 ms;
- loss (:func:`gps_loss_stage`): NO_FIX after 4 s, EKF position lost after 7 s, failsafe to LAND after
  7.8 s, and LAND stays;
- speed accuracy (:class:`SpeedAccuracyGlitch`): "GPS Glitch" while the filtered, peak-held
  ``speed_accuracy`` is above 1.5 m/s, until below 1.0 m/s;
- lag (:func:`gps_lag_s`): ``GPSn_DELAY_MS`` before arrival, 0.2 s when 0.
Each timeout fires at the earliest time of its measured window; a GPS_INPUT that is not accepted counts
as absent for every rule; times are taken to the microsecond.

Why those choices: docs/ardupilot.md, "The emulator and its rules in full".
"""

from __future__ import annotations

import enum
import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Final

import numpy as np

# --- parameters and acceptance ------------------------------------------------------------------------
#: ``GPSn_TYPE`` value of a MAVLink GPS (GPS_INPUT).
GPS_TYPE_MAV: Final[int] = 14
#: Receivers ArduPilot has (``GPS1_*``, ``GPS2_*``); instance index = ``gps_id`` = n - 1.
GPS_MAX_RECEIVERS: Final[int] = 2
#: Lowest GPS_INPUT ``fix_type`` that is used (GPS_FIX_TYPE_3D_FIX).
MIN_ACCEPTED_FIX_TYPE: Final[int] = 3

# --- speed accuracy and lag ----------------------------------------------------------------------------
#: EKF3 ``calcGpsGoodForFlight`` (AP_NavEKF3_VehicleStatus.cpp): first-stage low-pass coefficient per GPS
#: sample, peak-hold decay time constant (s), and the hysteresis thresholds (m/s).
SACC_ALPHA: Final[float] = 0.2
SACC_PEAK_TAU_S: Final[float] = 10.0
SACC_FAIL_M_S: Final[float] = 1.5
SACC_PASS_M_S: Final[float] = 1.0
#: ``GPS_Backend::get_lag`` (GPS_Backend.h): the lag a backend without its own (the MAVLink one) reports
#: when ``GPSn_DELAY_MS`` is 0 (AP_GPS.cpp ``get_lag``: a user value > 0 always wins), s.
DEFAULT_GPS_LAG_S: Final[float] = 0.2


def gps_lag_s(delay_ms_param: float) -> float:
    """How long before its arrival the EKF takes a GPS_INPUT to have been measured (EKF3
    ``readGpsData``: ``time_ms = last_message_time_ms - lag``), s."""
    return delay_ms_param / 1000.0 if delay_ms_param > 0 else DEFAULT_GPS_LAG_S


class SpeedAccuracyGlitch:
    """EKF3's speed-accuracy test, one update per GPS sample: ``lpf = 0.2 sAcc + 0.8 lpf`` (clamped to
    [0, 10]), ``peak = max(lpf, (1 - dt/10) peak)``; failing above 1.5, passing again below 1.0. While it
    fails, the AHRS reports GPS_GLITCHING and ArduCopter says "GPS Glitch or Compass error"
    (events.cpp ``gpsglitch_check``)."""

    def __init__(self) -> None:
        self.lpf_m_s = 0.0
        self.peak_m_s = 0.0
        self.glitching = False
        self._last_s: float | None = None

    def update(self, t_s: float, speed_accuracy_m_s: float) -> bool:
        dt = 0.0 if self._last_s is None else max(0.0, t_s - self._last_s)
        self._last_s = t_s
        alpha2 = min(max(dt / SACC_PEAK_TAU_S, 0.0), 1.0)
        self.lpf_m_s = min(max(SACC_ALPHA * speed_accuracy_m_s + (1 - SACC_ALPHA) * self.lpf_m_s, 0.0), 10.0)
        self.peak_m_s = max(self.lpf_m_s, (1.0 - alpha2) * self.peak_m_s)
        if self.peak_m_s > SACC_FAIL_M_S:
            self.glitching = True
        elif self.peak_m_s < SACC_PASS_M_S:
            self.glitching = False
        return self.glitching


# --- health -------------------------------------------------------------------------------------------
#: The filtered mean interval must stay below this for the GPS to be healthy, ms.
HEALTH_MEAN_INTERVAL_MAX_MS: Final[float] = 215.0
#: An interval longer than this is a delayed frame, ms ("200 ms (5Hz) + 45 ms buffer").
HEALTH_DELAYED_INTERVAL_MS: Final[float] = 245.0
#: This many consecutive delayed frames make the GPS unhealthy.
HEALTH_MAX_CONSECUTIVE_DELAYED: Final[int] = 2
#: Weight of the newest interval in the filtered mean (ArduPilot: 0.98 * mean + 0.02 * interval).
HEALTH_MEAN_FILTER_WEIGHT: Final[float] = 0.02
#: Intervals this long or longer are left out of the filtered mean, ms.
HEALTH_MEAN_MAX_INTERVAL_MS: Final[float] = 2000.0

# --- loss of the stream -------------------------------------------------------------------------------
#: Silence after the last accepted GPS_INPUT that reports NO_FIX, ms (measured 4.0-4.2 s).
NO_FIX_TIMEOUT_MS: Final[int] = 4000
#: Silence after which the EKF drops its position flags, ms (measured 7.0-7.2 s).
EKF_POSITION_TIMEOUT_MS: Final[int] = 7000
#: Silence after which copter's EKF failsafe switches to LAND, ms (measured 7.8-8.0 s).
EKF_FAILSAFE_TIMEOUT_MS: Final[int] = 7800


def _us(t_s: float) -> int:
    """Seconds -> integer microseconds (MAVLink's time resolution; keeps interval boundaries exact)."""
    return round(t_s * 1_000_000)


def gps_instance_for(gps_id: int, gps_types: Mapping[int, int]) -> int | None:
    """The GPS instance (0 = GPS1) that takes a GPS_INPUT with ``gps_id``, or None when none does.

    Measured: "gps_id selects the instance: GPS1_TYPE=14 takes gps_id 0, GPS2_TYPE=14 takes gps_id 1,
    other ids ignored". ``gps_types``: ``GPSn_TYPE`` by instance index (0 -> ``GPS1_TYPE``), the values
    in effect (see :class:`GpsTypeParams`); a missing instance is type 0 (none).
    """
    if 0 <= gps_id < GPS_MAX_RECEIVERS and gps_types.get(gps_id, 0) == GPS_TYPE_MAV:
        return gps_id
    return None


def gps_input_rejection(fields: Mapping[str, Any], gps_types: Mapping[int, int]) -> str | None:
    """Why ArduPilot would not use this GPS_INPUT, or None when it would.

    Measured: "GPS_INPUT is used only with fix_type >= 3 and time_week > 0"; ``gps_id`` must select an
    instance whose ``GPSn_TYPE`` is 14 (:func:`gps_instance_for`). Source (AP_GPS_MAV.cpp,
    ``handle_msg``): only a message with ``fix_type >= 3 && time_week > 0`` gets the jitter-corrected
    GPS timestamp that the timing and the EKF work from.

    ``fields``: the message as pymavlink's ``to_dict()`` gives it (``gps_id``, ``fix_type``,
    ``time_week`` are read). Raises ValueError when one of those is missing.
    """
    try:
        gps_id = int(fields["gps_id"])
        fix_type = int(fields["fix_type"])
        time_week = int(fields["time_week"])
    except KeyError as exc:
        raise ValueError(
            f"GPS_INPUT fields lack {exc.args[0]!r}; expected gps_id, fix_type and time_week"
        ) from exc
    if gps_instance_for(gps_id, gps_types) is None:
        mav = sorted(i for i, t in gps_types.items() if t == GPS_TYPE_MAV)
        return f"gps_id {gps_id}: no GPS{gps_id + 1}_TYPE={GPS_TYPE_MAV} (MAVLink instances: {mav})"
    if fix_type < MIN_ACCEPTED_FIX_TYPE:
        return f"fix_type {fix_type} < {MIN_ACCEPTED_FIX_TYPE}"
    if time_week <= 0:
        return f"time_week {time_week} (must be > 0)"
    return None


def gps_input_accepted(fields: Mapping[str, Any], gps_types: Mapping[int, int]) -> bool:
    """True when ArduPilot would use this GPS_INPUT (:func:`gps_input_rejection` gives no reason)."""
    return gps_input_rejection(fields, gps_types) is None


@dataclass(frozen=True)
class GpsTypeParams:
    """``GPSn_TYPE`` by instance index (0 -> ``GPS1_TYPE``): the values the GPS drivers started with,
    and values set since, which wait for a reboot.

    Measured: "GPS1_TYPE is reboot-required: setting it in flight does nothing" (EKF failsafe followed
    8 s later when a flight relied on it). Use :attr:`in_effect` for :func:`gps_input_accepted`.
    """

    at_boot: Mapping[int, int]
    pending: Mapping[int, int] = field(default_factory=dict)

    @property
    def in_effect(self) -> dict[int, int]:
        """The values the running autopilot uses: those it booted with."""
        return dict(self.at_boot)

    def set(self, instance: int, gps_type: int) -> GpsTypeParams:
        """Set ``GPS{instance+1}_TYPE`` (e.g. in flight); it takes effect at the next :meth:`reboot`."""
        if not 0 <= instance < GPS_MAX_RECEIVERS:
            raise ValueError(f"GPS instance {instance} out of range 0..{GPS_MAX_RECEIVERS - 1}")
        return replace(self, pending={**self.pending, instance: gps_type})

    def reboot(self) -> GpsTypeParams:
        """After a reboot the pending values are the ones in effect."""
        return GpsTypeParams(at_boot={**self.at_boot, **self.pending})


def prearm_gps_failures(gps_types: Mapping[int, int], instances_with_fix: Collection[int]) -> list[str]:
    """The pre-arm texts for MAVLink GPS instances that have not yet had an accepted GPS_INPUT.

    Measured: "GPS 2 must receive GPS_INPUT before arming ('PreArm: GPS 2: Bad fix' otherwise)". The
    same text is assumed for GPS 1 (not measured). Instances of other types are the simulator's own
    receivers and outside this double. ``instances_with_fix``: instance indices (0 = GPS1) that have
    received an accepted GPS_INPUT.
    """
    return [
        f"PreArm: GPS {i + 1}: Bad fix"
        for i in sorted(gps_types)
        if gps_types[i] == GPS_TYPE_MAV and i not in instances_with_fix
    ]


class GpsHealthMonitor:
    """ArduPilot's GPS health rule, fed with the times of the accepted messages of one GPS instance.

    Measured: "A MAVLink GPS counts as healthy only while the mean interval between its messages is
    below 215 ms, and while fewer than 2 consecutive intervals exceed 245 ms. So 5 Hz is the minimum,
    with little jitter; a jittery 5 Hz stream already gave 'PreArm: GPS 1: not healthy' once; exactly
    3 Hz gave 'not healthy' permanently."

    Source (AP_GPS.cpp ``update_instance`` and ``is_healthy``; AP_GPS.h ``GPS_MAX_DELTA_MS 245``):

    - per message, the interval to the previous one; > 245 ms increments a delayed-frame counter, any
      other interval resets it to 0;
    - the "mean" is a filtered mean, ``mean = 0.98 * mean + 0.02 * interval``, seeded with the first
      interval; intervals of 2000 ms or more are left out of it;
    - after 4000 ms without a message the instance times out: that counts as one delayed 4000 ms
      interval (not averaged) and the next interval is measured from the timeout, not from the last
      message; each further 4000 ms of silence counts again;
    - healthy: fewer than 2 consecutive delayed frames and a filtered mean < 215 ms.

    This class follows that, the filter included: nothing measured contradicts it, and the filter has
    consequences a plain mean over the flight would miss. At 5 Hz a single 1 s hiccup lifts the
    filtered mean to 216 ms, "not healthy" for the next few messages although only one interval was
    late; a steady 4.5 Hz (222 ms, never late) is unhealthy on the mean alone; exactly 3 Hz (333 ms) is
    unhealthy on both counts, for good. Health is re-evaluated only when a message or a timeout
    arrives, as in the source: a late message is seen as late when it comes.

    ArduPilot takes the time of an accepted GPS_INPUT from its ``time_week_ms``, corrected for transport
    jitter (AP_GPS_MAV.cpp, JitterCorrection.cpp: the sender's clock plus the smallest lag seen,
    clamped to a maximum lag). Feed the receive times when the sender stamps at send time; when it
    stamps an earlier event (e.g. a camera exposure), the intervals ArduPilot sees follow those stamps.
    """

    def __init__(self) -> None:
        self._last_us: int | None = None  # last message or timeout
        self._mean_ms: float | None = None
        self._delayed_count = 0
        self._last_interval_ms: float | None = None
        self._messages = 0

    @property
    def messages(self) -> int:
        """Messages fed so far."""
        return self._messages

    @property
    def healthy(self) -> bool:
        """False before the first message; afterwards the rule above."""
        if self._last_us is None:
            return False
        mean_ok = self._mean_ms is None or self._mean_ms < HEALTH_MEAN_INTERVAL_MAX_MS
        return self._delayed_count < HEALTH_MAX_CONSECUTIVE_DELAYED and mean_ok

    @property
    def mean_interval_ms(self) -> float | None:
        """The filtered mean interval (None until an interval under 2000 ms has been seen)."""
        return self._mean_ms

    @property
    def delayed_count(self) -> int:
        """Consecutive intervals (timeouts included) longer than 245 ms."""
        return self._delayed_count

    @property
    def last_interval_ms(self) -> float | None:
        """The latest interval (a timeout counts as 4000 ms); None before the second message."""
        return self._last_interval_ms

    def next_timeout_s(self) -> float | None:
        """When the instance times out if nothing arrives (None before the first message)."""
        if self._last_us is None:
            return None
        return (self._last_us + NO_FIX_TIMEOUT_MS * 1000) / 1e6

    def _interval(self, now_us: int, interval_ms: float) -> None:
        self._last_us = now_us
        self._last_interval_ms = interval_ms
        if interval_ms > HEALTH_DELAYED_INTERVAL_MS:
            self._delayed_count += 1
        else:
            self._delayed_count = 0
        if interval_ms < HEALTH_MEAN_MAX_INTERVAL_MS:
            if self._mean_ms is None:
                self._mean_ms = interval_ms
            else:
                # same as 0.98 * mean + 0.02 * interval, but a steady interval leaves the mean exact
                self._mean_ms += HEALTH_MEAN_FILTER_WEIGHT * (interval_ms - self._mean_ms)

    def step_timeout(self, t_s: float) -> float | None:
        """Apply the next timeout if it fires before ``t_s`` (ArduPilot: silence > 4000 ms) and return
        its time, s; None when none is due. A message exactly 4000 ms after the last one arrives first."""
        timeout_us = NO_FIX_TIMEOUT_MS * 1000
        if self._last_us is None or _us(t_s) - self._last_us <= timeout_us:
            return None
        self._interval(self._last_us + timeout_us, float(NO_FIX_TIMEOUT_MS))
        return self._last_us / 1e6

    def advance_to(self, t_s: float) -> list[float]:
        """Apply every timeout that fires before ``t_s``; returns their times, s."""
        fired: list[float] = []
        while (t_timeout := self.step_timeout(t_s)) is not None:
            fired.append(t_timeout)
        return fired

    def on_message(self, t_s: float) -> None:
        """An accepted message at ``t_s`` (s, any epoch). Applies pending timeouts first.
        Raises ValueError when ``t_s`` is earlier than the last message or timeout."""
        now_us = _us(t_s)
        if self._last_us is not None and now_us < self._last_us:
            raise ValueError(
                f"message at {t_s:.6f} s is earlier than the last message or timeout at "
                f"{self._last_us / 1e6:.6f} s"
            )
        self.advance_to(t_s)
        self._messages += 1
        if self._last_us is None:
            # the source's first interval runs from boot; the double has no boot time, so it starts here
            self._last_us = now_us
            return
        self._interval(now_us, (now_us - self._last_us) / 1000.0)


class GpsLossStage(enum.IntEnum):
    """How far the vehicle has got after the accepted GPS_INPUT stream stopped; each includes the last."""

    OK = 0
    NO_FIX = 1
    EKF_POSITION_LOST = 2
    EKF_FAILSAFE_LAND = 3


def gps_loss_stage(silence_s: float) -> GpsLossStage:
    """What a silence of ``silence_s`` since the last accepted GPS_INPUT has done to a flying copter.

    Measured: "GPS_INPUT absent for 4.0-4.2 s means NO_FIX. At 7.0-7.2 s the EKF position flags are
    lost. At 7.8-8.0 s comes 'EKF Failsafe: changed to LAND Mode', and the vehicle stays in LAND after
    the stream resumes (latched)." Each stage fires at the earliest measured time, strictly after it.

    Source: AP_GPS.cpp ``GPS_TIMEOUT_MS 4000u`` (a MAV instance whose last message is older than that
    is reset to NO_FIX and keeps its driver); the EKF's GPS retry time without airspeed,
    ``gpsRetryTimeNoTAS_ms(7000)`` (AP_NavEKF2.cpp, the same name in EKF3); ArduCopter/ekf_check.cpp
    runs at 10 Hz and declares the failsafe after ``EKF_CHECK_ITERATIONS_MAX`` (10, "1 second") failed
    checks, no position estimate being a failed check, then ``set_mode_land_with_pause`` and "EKF
    Failsafe: changed to %s Mode"; clearing the failsafe later does not restore the mode (the latch
    belongs to the caller, see :func:`evaluate_gps_stream`). Assumes an armed copter in a mode that
    needs a position, with the EKF failsafe enabled (defaults).
    """
    silence_us = _us(silence_s)
    if silence_us > EKF_FAILSAFE_TIMEOUT_MS * 1000:
        return GpsLossStage.EKF_FAILSAFE_LAND
    if silence_us > EKF_POSITION_TIMEOUT_MS * 1000:
        return GpsLossStage.EKF_POSITION_LOST
    if silence_us > NO_FIX_TIMEOUT_MS * 1000:
        return GpsLossStage.NO_FIX
    return GpsLossStage.OK


@dataclass(frozen=True)
class GpsOutage:
    """One silence long enough to reach a :class:`GpsLossStage`. Times in the stream's seconds."""

    last_accepted_s: float  # the last accepted GPS_INPUT before the silence
    start_s: float  # when the stage was reached
    end_s: float | None  # the next accepted GPS_INPUT; None when the observation ended first

    def to_dict(self) -> dict[str, float | None]:
        return {
            "last_accepted_s": round(self.last_accepted_s, 6),
            "start_s": round(self.start_s, 6),
            "end_s": None if self.end_s is None else round(self.end_s, 6),
        }


@dataclass(frozen=True)
class IntervalStats:
    """Intervals between consecutive accepted GPS_INPUT messages, ms."""

    n: int
    mean_ms: float
    p50_ms: float
    p99_ms: float
    max_ms: float

    def to_dict(self) -> dict[str, float | int]:
        return {
            "n": self.n,
            "mean_ms": round(self.mean_ms, 3),
            "p50_ms": round(self.p50_ms, 3),
            "p99_ms": round(self.p99_ms, 3),
            "max_ms": round(self.max_ms, 3),
        }


@dataclass(frozen=True)
class GpsStreamVerdict:
    """What this double predicts ArduPilot made of one received GPS_INPUT stream (times in the stream's
    seconds). A prediction of the test double, never the autopilot's own report."""

    messages: int
    accepted: int
    first_accepted_s: float | None
    end_s: float  # end of the observation
    interval_ms: IntervalStats | None  # None with fewer than 2 accepted messages
    unhealthy_spans_s: tuple[tuple[float, float], ...]  # (start, end); a span still open ends at end_s
    healthy_at_end: bool
    no_fix: tuple[GpsOutage, ...]
    ekf_position_lost: tuple[GpsOutage, ...]
    ekf_failsafe_land_s: float | None  # first EKF failsafe -> LAND; latched from then on

    @property
    def health_tripped(self) -> bool:
        return bool(self.unhealthy_spans_s)

    def in_land_at(self, t_s: float) -> bool:
        """True once the EKF failsafe has switched to LAND: the mode stays when the stream resumes."""
        return self.ekf_failsafe_land_s is not None and t_s >= self.ekf_failsafe_land_s

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready; the rule thresholds are included so a report states what it was judged by."""
        return {
            "source": "test double of measured ArduPilot copter 4.7.0-dev behaviour (not the autopilot)",
            "messages": self.messages,
            "accepted": self.accepted,
            "first_accepted_s": None if self.first_accepted_s is None else round(self.first_accepted_s, 6),
            "end_s": round(self.end_s, 6),
            "interval_ms": None if self.interval_ms is None else self.interval_ms.to_dict(),
            "health": {
                "tripped": self.health_tripped,
                "unhealthy_spans_s": [[round(a, 6), round(b, 6)] for a, b in self.unhealthy_spans_s],
                "healthy_at_end": self.healthy_at_end,
            },
            "no_fix": [o.to_dict() for o in self.no_fix],
            "ekf_position_lost": [o.to_dict() for o in self.ekf_position_lost],
            "ekf_failsafe_land_s": (
                None if self.ekf_failsafe_land_s is None else round(self.ekf_failsafe_land_s, 6)
            ),
            "rules": {
                "health_mean_interval_max_ms": HEALTH_MEAN_INTERVAL_MAX_MS,
                "health_delayed_interval_ms": HEALTH_DELAYED_INTERVAL_MS,
                "health_max_consecutive_delayed": HEALTH_MAX_CONSECUTIVE_DELAYED,
                "no_fix_timeout_ms": NO_FIX_TIMEOUT_MS,
                "ekf_position_timeout_ms": EKF_POSITION_TIMEOUT_MS,
                "ekf_failsafe_timeout_ms": EKF_FAILSAFE_TIMEOUT_MS,
            },
        }


def _interval_stats(times_s: Sequence[float]) -> IntervalStats | None:
    if len(times_s) < 2:
        return None
    us = np.array([_us(t) for t in times_s], dtype=np.int64)
    ms = np.diff(us) / 1000.0
    return IntervalStats(
        n=int(ms.size),
        mean_ms=float(ms.mean()),
        p50_ms=float(np.percentile(ms, 50)),
        p99_ms=float(np.percentile(ms, 99)),
        max_ms=float(ms.max()),
    )


def _health_spans(accepted_s: Sequence[float], end_s: float) -> tuple[list[tuple[float, float]], bool]:
    monitor = GpsHealthMonitor()
    spans: list[tuple[float, float]] = []
    open_since: float | None = None

    def note(t_s: float) -> None:
        nonlocal open_since
        if not monitor.healthy and open_since is None:
            open_since = t_s
        elif monitor.healthy and open_since is not None:
            spans.append((open_since, t_s))
            open_since = None

    def timeouts_before(t_s: float) -> None:
        while (t_timeout := monitor.step_timeout(t_s)) is not None:
            note(t_timeout)  # health can change at each timeout, so judge it after each one

    for t in accepted_s:
        timeouts_before(t)
        monitor.on_message(t)
        note(t)
    timeouts_before(end_s)
    if open_since is not None:
        spans.append((open_since, end_s))
    return spans, monitor.healthy


def evaluate_gps_stream(
    times_s: Sequence[float],
    accepted: Sequence[bool],
    *,
    end_s: float | None = None,
    relied_on_until_s: float | None = None,
) -> GpsStreamVerdict:
    """Replay one GPS instance's received GPS_INPUT stream through every rule of this double.

    ``times_s``: the time of each message, s, non-decreasing (receive times; see
    :class:`GpsHealthMonitor` on which times ArduPilot uses). ``accepted``: per message, whether
    :func:`gps_input_accepted` holds; a message that is not accepted counts as absent for every rule.
    ``end_s``: when the observation ended (e.g. the end of the flight), so that a silence after the
    last message is judged too; defaults to the last message's time. ``relied_on_until_s``: when another
    position source took over for good (the GNSS back on with ``GPS_AUTO_SWITCH``: GPS 1 primary again,
    measured), after which a silence of this stream trips nothing: the EKF is not using it.

    Outages are counted from the first accepted message on (before it the GPS never had a fix, which
    the pre-arm checks catch, :func:`prearm_gps_failures`). Raises ValueError on mismatched lengths,
    times that go backwards or an ``end_s`` before the last message.
    """
    if len(times_s) != len(accepted):
        raise ValueError(f"times_s has {len(times_s)} entries but accepted has {len(accepted)}")
    for i, t in enumerate(times_s):
        if not math.isfinite(t):
            raise ValueError(f"times_s[{i}] is {t}, expected a finite time in s")
        if i and t < times_s[i - 1]:
            raise ValueError(f"times_s must not go backwards: [{i - 1}]={times_s[i - 1]} > [{i}]={t}")
    last_s = times_s[-1] if times_s else None
    if end_s is None:
        end = last_s if last_s is not None else 0.0
    elif last_s is not None and end_s < last_s:
        raise ValueError(f"end_s={end_s} is before the last message at {last_s}")
    else:
        end = end_s

    accepted_s = [float(t) for t, ok in zip(times_s, accepted, strict=True) if ok]
    spans, healthy_at_end = _health_spans(accepted_s, end)
    if relied_on_until_s is not None:
        spans = [(a, b) for a, b in spans if a < relied_on_until_s]

    thresholds_s = {
        GpsLossStage.NO_FIX: NO_FIX_TIMEOUT_MS / 1000.0,
        GpsLossStage.EKF_POSITION_LOST: EKF_POSITION_TIMEOUT_MS / 1000.0,
    }
    outages: dict[GpsLossStage, list[GpsOutage]] = {stage: [] for stage in thresholds_s}
    failsafe_s: float | None = None
    nexts: list[float | None] = [*accepted_s[1:], None] if accepted_s else []
    for last, nxt in zip(accepted_s, nexts, strict=True):
        stage = gps_loss_stage((end if nxt is None else nxt) - last)
        relied = relied_on_until_s if relied_on_until_s is not None else math.inf
        for s, threshold_s in thresholds_s.items():
            if stage >= s and last + threshold_s < relied:
                outages[s].append(GpsOutage(last_accepted_s=last, start_s=last + threshold_s, end_s=nxt))
        fs_s = last + EKF_FAILSAFE_TIMEOUT_MS / 1000.0
        if stage >= GpsLossStage.EKF_FAILSAFE_LAND and failsafe_s is None and fs_s < relied:
            failsafe_s = fs_s

    return GpsStreamVerdict(
        messages=len(times_s),
        accepted=len(accepted_s),
        first_accepted_s=accepted_s[0] if accepted_s else None,
        end_s=end,
        interval_ms=_interval_stats(accepted_s),
        unhealthy_spans_s=tuple(spans),
        healthy_at_end=healthy_at_end,
        no_fix=tuple(outages[GpsLossStage.NO_FIX]),
        ekf_position_lost=tuple(outages[GpsLossStage.EKF_POSITION_LOST]),
        ekf_failsafe_land_s=failsafe_s,
    )
