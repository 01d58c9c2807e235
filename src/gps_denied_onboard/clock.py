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
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

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

