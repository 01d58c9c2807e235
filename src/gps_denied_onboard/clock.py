"""The daemon's clock: monotonic time, anchored to Unix time once, at start.

Why not the wall clock: ``CLOCK_REALTIME`` steps. NTP/chrony step it when the offset is large, an
operator sets the date, a companion computer without an RTC jumps from 1970 to the GPS time it was
given. A backwards step of a wall-clock "now" makes every later frame look out of order and every fix
too late until the clock catches up (a long outage); a forward step makes the filter's clock leap
(a 10 Hz stream stamped seconds apart). The daemon's "now" is therefore ``CLOCK_MONOTONIC`` plus an
offset fixed at start (``anchor``): it reads Unix time for the first instant of the run and never
follows the wall clock afterwards. Every component that needs "now" gets this one object from the
composition root: the C5 time axis, the MAVLink link (GPS_INPUT ``time_usec``/``time_week``), the
vehicle-state tracker (receive times, link liveness), the flight data recorder, the daemon's ages and
latencies.

What a camera stamp is measured against
---------------------------------------
A frame's ``exposure_time_unix_usec`` (network stream, OpenCV sources) is **this host's wall clock at
exposure** (the camera process and the daemon share the companion computer's clock; the OpenCV sources
stamp with it in-process). ``from_wall_usec`` maps such a stamp into the daemon's clock with the wall
clock's offset read *now*: a step of the host clock moves the stamps and the offset together, so it
cancels, and so does NTP slewing.
A camera on another host whose clock steps on its own is not cancelled: its frames are refused as
future or stale and counted (the daemon cannot tell a remote clock that stepped back from frames that
arrive late; synchronise that clock, or stamp on this host).

Around a step, a frame exposed before it but read after it (a backlog in the stream) is mapped with the
offset of its own epoch: the clock keeps the offsets of the last ``EPOCH_HISTORY_S`` and picks the one
that gives the frame a plausible age (``from_wall_usec``).

Steps are detected (``check_step``), logged, recorded in the flight data recorder and counted by the
daemon; they change nothing else.

The autopilot's clock
---------------------
``AutopilotClock`` maps the autopilot's boot time onto the daemon's clock: MAVLink TIMESYNC round trips
(offset and drift, continuously re-synced), bounded by the receive times of its timestamped messages;
the receive-time bound alone when the autopilot does not answer TIMESYNC. The autopilot's own Unix time
(SYSTEM_TIME) is never the link: without GNSS it is whatever somebody set.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import Final

import numpy as np

#: A change of the wall clock's offset from the daemon's clock larger than this is a step, s. NTP slews
#: at most 500 ppm (0.5 ms per second checked); ntpd steps above 0.128 s.
CLOCK_STEP_MIN_S: Final[float] = 0.1
#: How long an earlier offset of the wall clock is still used to map a frame exposed before a step and
#: read after it (a backlog in the camera stream), s.
EPOCH_HISTORY_S: Final[float] = 10.0
#: A mapped exposure may lie this far after the daemon's now and still count as consistent, s.
MAP_FUTURE_TOLERANCE_S: Final[float] = 0.25
#: Two wall-clock reads around one monotonic read further apart than this are retried (preemption), ns.
_TIGHT_READ_NS: Final[int] = 200_000


@dataclass(frozen=True)
class ClockStep:
    """A step of the wall clock relative to the daemon's clock. ``step_s`` > 0: the wall clock jumped
    forward. ``wall_offset_s``: wall minus the daemon's clock after the step (0 at start)."""

    step_s: float
    wall_offset_s: float
    at_unix_usec: int


class DaemonClock:
    """Monotonic time anchored to Unix time at construction (see the module docstring).

    ``monotonic_ns`` and ``wall_ns`` are injectable for tests (and for a replay, which runs on recorded
    time). Thread-safe.
    """

    def __init__(
        self,
        *,
        monotonic_ns: Callable[[], int] = time.monotonic_ns,
        wall_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self._mono = monotonic_ns
        self._wall = wall_ns
        self._lock = threading.Lock()
        #: Unix ns at monotonic 0: the one anchor of the run.
        self._anchor_ns = self._read_offset()
        #: The wall clock's offset epochs, oldest first: (monotonic ns it was first seen, wall minus the
        #: daemon's clock ns). A new epoch starts at each step; within one the offset follows slewing.
        self._epochs: list[tuple[int, int]] = [(self._mono(), 0)]
        self._last_reading_ns = 0
        #: Steps seen but not yet reported by ``check_step``.
        self._unreported: list[ClockStep] = []
        self._steps = 0

    def _read_offset(self) -> int:
        """Wall minus monotonic, ns, from the tightest of up to three wall reads bracketing a monotonic
        read (a thread preempted between two reads would otherwise see a false offset)."""
        best_offset, best_width = 0, -1
        for _ in range(3):
            w1 = self._wall()
            m = self._mono()
            w2 = self._wall()
            width = abs(w2 - w1)
            if best_width < 0 or width < best_width:
                best_offset, best_width = (w1 + w2) // 2 - m, width
            if width <= _TIGHT_READ_NS:
                break
        return best_offset

    def _offset_ns(self) -> int:
        """The wall clock's offset now; a change beyond CLOCK_STEP_MIN_S since the last reading opens a
        new epoch (a step), a smaller one is slewing and moves the current epoch."""
        offset = self._read_offset() - self._anchor_ns
        with self._lock:
            delta = offset - self._last_reading_ns
            self._last_reading_ns = offset
            mono = self._mono()
            if abs(delta) > CLOCK_STEP_MIN_S * 1e9:
                self._epochs.append((mono, offset))
                self._steps += 1
                self._unreported.append(
                    ClockStep(delta / 1e9, offset / 1e9, (self._anchor_ns + mono) // 1000)
                )
                # keep the epochs a backlogged frame may still need, and the current one
                horizon = mono - round(EPOCH_HISTORY_S * 1e9)
                while len(self._epochs) > 1 and self._epochs[1][0] < horizon:
                    self._epochs.pop(0)
            else:
                self._epochs[-1] = (self._epochs[-1][0], offset)
        return offset

    # -- reading --------------------------------------------------------------------------------------

    def now_unix_usec(self) -> int:
        """The daemon's now, Unix microseconds (monotonic since the anchor)."""
        return (self._anchor_ns + self._mono()) // 1000

    def now_unix_s(self) -> float:
        """The daemon's now, Unix seconds."""
        return (self._anchor_ns + self._mono()) / 1e9

    def wall_offset_usec(self) -> int:
        """The host wall clock minus the daemon's clock, now, microseconds (0 until the wall clock steps
        or is slewed)."""
        return self._offset_ns() // 1000

    def from_wall_usec(self, wall_unix_usec: int) -> int:
        """A stamp taken with this host's wall clock, in the daemon's clock (see the module docstring).

        Normally the stamp minus the wall clock's offset now. Around a step, a frame exposed before it
        may be read after it (a backlog): every offset of the last ``EPOCH_HISTORY_S`` is a candidate,
        and the one that gives the frame the smallest age that is not in the future (within
        ``MAP_FUTURE_TOLERANCE_S``) wins. For a step larger than the camera's latency only the right
        epoch gives such an age; with none, the current offset is used (the time axis refuses it)."""
        stamp_ns = int(wall_unix_usec) * 1000
        current = self._offset_ns()
        mono = self._mono()
        now_ns = self._anchor_ns + mono
        with self._lock:
            epochs = list(self._epochs)
        horizon = mono - round(EPOCH_HISTORY_S * 1e9)
        candidates = [off for k, (_, off) in enumerate(epochs[:-1]) if epochs[k + 1][0] >= horizon] + [
            current
        ]
        tolerance = round(MAP_FUTURE_TOLERANCE_S * 1e9)
        best = current
        best_age: int | None = None
        for off in candidates:
            age = now_ns - (stamp_ns - off)
            if age >= -tolerance and (best_age is None or age < best_age):
                best, best_age = off, age
        return (stamp_ns - best) // 1000

    # -- steps ----------------------------------------------------------------------------------------

    @property
    def steps(self) -> int:
        """Wall-clock steps seen so far."""
        with self._lock:
            return self._steps

    def check_step(self) -> ClockStep | None:
        """The oldest step of the wall clock (a change of its offset beyond CLOCK_STEP_MIN_S between two
        readings) not reported yet, or None. Call it periodically (the daemon's status task does): it
        also reads the clock, so a step is seen within one call even when no frame arrives."""
        self._offset_ns()
        with self._lock:
            return self._unreported.pop(0) if self._unreported else None



# -- the autopilot's clock ------------------------------------------------------------------------------

#: TIMESYNC samples kept for the fit, and the oldest one used, s.
TIMESYNC_WINDOW_S: Final[float] = 60.0
TIMESYNC_MAX_SAMPLES: Final[int] = 64
#: A round trip longer than this says nothing useful about the offset, s.
TIMESYNC_MAX_RTT_S: Final[float] = 0.5
#: Samples within this of the shortest round trip in the window are used (queueing only adds delay), s.
TIMESYNC_RTT_MARGIN_S: Final[float] = 0.005
#: The drift is fitted once the used samples span this long, s; it is clamped to +-MAX_DRIFT_PPM (a
#: crystal is within 100 ppm; SITL under load runs slower than the host, which the clamp also covers).
TIMESYNC_DRIFT_MIN_SPAN_S: Final[float] = 20.0
TIMESYNC_MAX_DRIFT_PPM: Final[float] = 20_000.0
#: This many answers in a row that exclude the current mapping by more than the jump tolerance restart
#: it (the autopilot's clock stood still or was reset).
TIMESYNC_JUMP_SAMPLES: Final[int] = 3
TIMESYNC_JUMP_TOLERANCE_S: Final[float] = 0.05
#: Receive-time bound: the smallest (receive - boot) per bucket of this length, over this window, s.
RECEIVE_BOUND_BUCKET_S: Final[float] = 1.0
RECEIVE_BOUND_WINDOW_S: Final[float] = 6.0
#: Requests whose answers are still awaited (older ones are forgotten).
TIMESYNC_PENDING: Final[int] = 16
#: Boot time going back by more than this is a reboot of the autopilot, s.
AUTOPILOT_REBOOT_BACK_S: Final[float] = 1.0


class TimeSource(str, Enum):
    """How the autopilot's boot time is mapped onto the daemon's clock."""

    NONE = "none"
    TIMESYNC = "timesync"
    RECEIVE_TIME = "receive_time"


@dataclass(frozen=True)
class TimesyncSample:
    """One answered TIMESYNC request: sent and answered in the daemon's clock (us); ``tc1_usec`` the
    autopilot's boot time when it received the request (ArduPilot: ``handle_timesync``, the receive
    time of the request, GCS_Common.cpp)."""

    sent_usec: int
    recv_usec: int
    tc1_usec: int

    @property
    def rtt_usec(self) -> int:
        return self.recv_usec - self.sent_usec

    @property
    def offset_usec(self) -> float:
        """Daemon minus autopilot boot time, assuming the request spent half the round trip."""
        return (self.sent_usec + self.recv_usec) / 2.0 - self.tc1_usec


class AutopilotClock:
    """The autopilot's boot time on the daemon's clock; thread-safe.

    ``offset_usec(now)`` is daemon minus boot time. With TIMESYNC answers: the low-round-trip samples of
    the last ``TIMESYNC_WINDOW_S`` give the offset (their midpoint) and, over a long enough span, its
    drift (least squares); the result is kept inside what the messages prove: an answer cannot come
    before its request (offset >= sent - tc1) and a message cannot arrive before it was stamped
    (offset <= receive - boot, the lower envelope of every timestamped message). Without answers the
    receive-time bound is the mapping (late by the link's smallest latency). A reboot (boot time going
    back) or answers that exclude the mapping ``TIMESYNC_JUMP_SAMPLES`` times in a row restart it.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._samples: deque[TimesyncSample] = deque(maxlen=TIMESYNC_MAX_SAMPLES)
        self._rx_min: dict[int, float] = {}  # bucket -> smallest (receive - boot), us
        self._last_boot_usec: int | None = None
        self._fit: tuple[float, float, float] | None = None  # (t_ref_usec, offset_usec, drift)
        self._excluded = 0
        self._resets = 0
        self._answers = 0
        self._pending: deque[int] = deque(maxlen=TIMESYNC_PENDING)  # ts1 of requests not yet answered

    # -- input ---------------------------------------------------------------------------------------

    def note_stamp(self, boot_usec: int, recv_usec: int) -> bool:
        """A message stamped ``boot_usec`` (autopilot boot time) arrived at ``recv_usec`` (daemon clock).
        Returns True when it showed a reboot (the mapping was restarted)."""
        with self._lock:
            rebooted = self._note_boot(int(boot_usec))
            bucket = int(recv_usec // (RECEIVE_BOUND_BUCKET_S * 1e6))
            d = float(recv_usec - boot_usec)
            cur = self._rx_min.get(bucket)
            if cur is None or d < cur:
                self._rx_min[bucket] = d
            oldest = bucket - int(RECEIVE_BOUND_WINDOW_S / RECEIVE_BOUND_BUCKET_S)
            for b in [b for b in self._rx_min if b < oldest]:
                del self._rx_min[b]
            return rebooted

    def request(self, now_usec: int) -> int:
        """The ``ts1`` (ns) of a TIMESYNC request sent now; its answer is matched by it."""
        ts1_ns = int(now_usec) * 1000
        with self._lock:
            self._pending.append(ts1_ns)
        return ts1_ns

    def answer(self, tc1_ns: int, ts1_ns: int, recv_usec: int) -> bool:
        """A TIMESYNC with ``tc1`` != 0 arrived at ``recv_usec``: used when it answers one of our
        requests (any other, e.g. an answer to another node's request, is ignored)."""
        with self._lock:
            if ts1_ns not in self._pending:
                return False
            self._pending.remove(ts1_ns)
        return self.note_timesync(TimesyncSample(ts1_ns // 1000, int(recv_usec), int(tc1_ns) // 1000))

    def note_timesync(self, sample: TimesyncSample) -> bool:
        """An answer to one of our TIMESYNC requests. Returns True when it was used."""
        if sample.rtt_usec < 0 or sample.rtt_usec > TIMESYNC_MAX_RTT_S * 1e6 or sample.tc1_usec <= 0:
            return False
        with self._lock:
            self._note_boot(sample.tc1_usec)
            self._answers += 1
            if self._fit is not None:
                predicted = _offset_at(self._fit, sample.sent_usec)
                lo = sample.sent_usec - sample.tc1_usec - TIMESYNC_JUMP_TOLERANCE_S * 1e6
                hi = sample.recv_usec - sample.tc1_usec + TIMESYNC_JUMP_TOLERANCE_S * 1e6
                if not lo <= predicted <= hi:
                    self._excluded += 1
                    if self._excluded < TIMESYNC_JUMP_SAMPLES:
                        return False
                    self._samples.clear()
                    self._resets += 1
                self._excluded = 0
            self._samples.append(sample)
            self._refit(sample.recv_usec)
            return True

    def _note_boot(self, boot_usec: int) -> bool:
        last = self._last_boot_usec
        if last is not None and boot_usec < last - AUTOPILOT_REBOOT_BACK_S * 1e6:
            self._samples.clear()
            self._rx_min.clear()
            self._fit = None
            self._excluded = 0
            self._resets += 1
            self._last_boot_usec = boot_usec
            return True
        if last is None or boot_usec > last:
            self._last_boot_usec = boot_usec
        return False

    def _refit(self, now_usec: int) -> None:
        horizon = now_usec - TIMESYNC_WINDOW_S * 1e6
        while self._samples and self._samples[0].recv_usec < horizon:
            self._samples.popleft()
        if not self._samples:
            self._fit = None
            return
        best = min(s.rtt_usec for s in self._samples)
        used = [s for s in self._samples if s.rtt_usec <= best + TIMESYNC_RTT_MARGIN_S * 1e6]
        t = np.array([s.sent_usec for s in used], dtype=np.float64)
        off = np.array([s.offset_usec for s in used], dtype=np.float64)
        t_ref = float(t[-1])
        drift = 0.0
        if len(used) >= 4 and t[-1] - t[0] >= TIMESYNC_DRIFT_MIN_SPAN_S * 1e6:
            slope = float(np.polyfit(t - t_ref, off, 1)[0])
            drift = float(np.clip(slope, -TIMESYNC_MAX_DRIFT_PPM * 1e-6, TIMESYNC_MAX_DRIFT_PPM * 1e-6))
        offset = float(np.median(off - drift * (t - t_ref)))
        self._fit = (t_ref, offset, drift)

    # -- queries -------------------------------------------------------------------------------------

    def _rx_bound(self) -> float | None:
        return min(self._rx_min.values()) if self._rx_min else None

    def offset_usec(self, now_usec: float) -> float | None:
        """Daemon clock minus autopilot boot time at ``now_usec`` (daemon clock), us; None before any
        TIMESYNC answer or timestamped message."""
        with self._lock:
            bound = self._rx_bound()
            if self._fit is None:
                return bound
            offset = _offset_at(self._fit, now_usec)
            return offset if bound is None else min(offset, bound)

    @property
    def source(self) -> TimeSource:
        with self._lock:
            if self._fit is not None:
                return TimeSource.TIMESYNC
            return TimeSource.RECEIVE_TIME if self._rx_min else TimeSource.NONE

    @property
    def rtt_usec(self) -> int | None:
        """The shortest round trip in the window (twice the mapping's worst error), or None."""
        with self._lock:
            return min((s.rtt_usec for s in self._samples), default=None)

    @property
    def drift_ppm(self) -> float | None:
        with self._lock:
            return None if self._fit is None else self._fit[2] * 1e6

    @property
    def resets(self) -> int:
        """Mappings restarted (autopilot reboots, clock jumps)."""
        with self._lock:
            return self._resets

    @property
    def answers(self) -> int:
        with self._lock:
            return self._answers


def _offset_at(fit: tuple[float, float, float], now_usec: float) -> float:
    t_ref, offset, drift = fit
    return offset + drift * (now_usec - t_ref)
