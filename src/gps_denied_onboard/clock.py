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
cancels, and so does NTP slewing. Only a frame exposed before a step and mapped after it is off by the
step (for a step above the time axis's tolerances it is refused as future or stale: one or two frames).
A camera on another host whose clock steps on its own is not cancelled: its frames are refused as
future or stale and counted (the daemon cannot tell a remote clock that stepped back from frames that
arrive late; synchronise that clock, or stamp on this host).

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
    time). Thread-safe: reads are lock-free; ``check_step`` is serialised.
    """

    def __init__(
        self,
        *,
        monotonic_ns: Callable[[], int] = time.monotonic_ns,
        wall_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self._mono = monotonic_ns
        self._wall = wall_ns
        #: Unix ns at monotonic 0: the one anchor of the run.
        self._anchor_ns = self._read_offset()
        self._last_offset_ns = 0
        self._steps = 0
        self._lock = threading.Lock()

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
        return (self._read_offset() - self._anchor_ns) // 1000

    def from_wall_usec(self, wall_unix_usec: int) -> int:
        """A stamp taken with this host's wall clock, in the daemon's clock (see the module docstring)."""
        return int(wall_unix_usec) - self.wall_offset_usec()

    # -- steps ----------------------------------------------------------------------------------------

    @property
    def steps(self) -> int:
        """Wall-clock steps detected so far."""
        return self._steps

    def check_step(self, min_step_s: float = CLOCK_STEP_MIN_S) -> ClockStep | None:
        """The wall clock's step since the last check, when it moved by more than ``min_step_s`` against
        the daemon's clock; None otherwise. Call it periodically (the daemon's status task does)."""
        with self._lock:
            offset_ns = self.wall_offset_usec() * 1000
            delta_ns = offset_ns - self._last_offset_ns
            if abs(delta_ns) <= min_step_s * 1e9:
                return None
            self._last_offset_ns = offset_ns
            self._steps += 1
            return ClockStep(delta_ns / 1e9, offset_ns / 1e9, self.now_unix_usec())


def system_clock() -> DaemonClock:
    """The process's clock, anchored now (the composition root builds one per run)."""
    return DaemonClock()
