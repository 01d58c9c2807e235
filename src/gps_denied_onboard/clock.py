"""The daemon's clocks: its own (monotonic, anchored to Unix time once, at start), the autopilot's mapped
onto it, and the camera's lateness.

``DaemonClock``: every "now" of the daemon (time axis, link, tracker, FDR, ages) comes from this one
object, built by the composition root. It never follows the host's wall clock, which NTP, ``date -s`` or
a first GPS time can step; a camera stamp (the host's wall clock at exposure) is mapped with the wall
clock's offset of its own epoch (``from_wall_usec``), so stamps and offset move together. Steps are
detected (``check_step``), logged, recorded and counted; they change nothing else.

``AutopilotClock``: the autopilot's boot time on the daemon's clock, from MAVLink TIMESYNC round trips
(offset and drift over the low-round-trip answers of the last minute), bounded by the receive times of
its timestamped messages; the receive-time bound alone without answers. The autopilot's own Unix time
(SYSTEM_TIME) is never used: without GNSS it is whatever somebody set.

``CameraStampOffset``: how late the camera stamps, fitted from image-minus-autopilot tilts against
world-down's motion in the camera around each stamp; the time axis subtracts it once sure, within
``camera.max_stamp_offset_s``, and until then every frame carries ``camera.stamp_sigma_s`` of doubt.

Why each, and what it cannot see: docs/design.md, "The time axis" and "The camera's clock and the
autopilot's".
"""

from __future__ import annotations

import math
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

    @property
    def anchor_unix_ns(self) -> int:
        """Unix ns at monotonic 0: this clock's one anchor. CLOCK_MONOTONIC is the host's, so two
        processes' clocks name one instant alike up to the difference of their anchors: the wall clock's
        slewing and steps between their starts (``c5_estimator/wire.py`` maps one onto the other)."""
        return self._anchor_ns

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
RECEIVE_BOUND_BUCKET_S: Final[float] = 0.25
RECEIVE_BOUND_WINDOW_S: Final[float] = 1.0
#: The receive-time envelope (``AutopilotClock._envelope``) is a line fitted over this window once it
#: holds ``RECEIVE_DRIFT_MIN_BUCKETS`` buckets spanning ``RECEIVE_DRIFT_MIN_SPAN_S``, s; buckets further
#: above the first line than ``RECEIVE_DRIFT_OUTLIER_S`` (every message of that bucket delayed) are left
#: out of the second.
RECEIVE_DRIFT_WINDOW_S: Final[float] = 3.0
RECEIVE_DRIFT_MIN_BUCKETS: Final[int] = 8
RECEIVE_DRIFT_MIN_SPAN_S: Final[float] = 2.0
RECEIVE_DRIFT_OUTLIER_S: Final[float] = 0.002
#: The TIMESYNC mapping may lie this far below the receive-time envelope at least (and half the best
#: round trip where that is more: what the answers can tell), s.
TIMESYNC_ALLOWANCE_MIN_S: Final[float] = 0.001
#: Requests whose answers are still awaited (older ones are forgotten).
TIMESYNC_PENDING: Final[int] = 16
#: The doubt of a mapping on receive times alone: the link's smallest latency, which it leaves in, s.
RECEIVE_BOUND_SIGMA_S: Final[float] = 0.01
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

    The lower envelope is a line, not a constant: the smallest (receive - boot) of each quarter second
    over the last ``RECEIVE_DRIFT_WINDOW_S`` is fitted with its drift and read at ``now``, and the
    TIMESYNC mapping is kept within half the best round trip (at least ``TIMESYNC_ALLOWANCE_MIN_S``)
    below it: what the answers can tell.
    An autopilot clock is not always a crystal: PX4's SITL (SIH, lockstep) ran 1.5-2.1 % slower than the
    host and unevenly (0.07-0.4 s lost per 10 s with two busy loops), and under load its round trips
    scatter by tens of milliseconds, so the answers fitted no drift; the mapping then put every boot
    time 40-120 ms early (measured), up to 0.6 s over a flight: at a 30 deg/s roll, degrees of attitude
    from the wrong moment.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._samples: deque[TimesyncSample] = deque(maxlen=TIMESYNC_MAX_SAMPLES)
        #: bucket -> (smallest receive - boot, its receive time), us
        self._rx_min: dict[int, tuple[float, int]] = {}
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
            if cur is None or d < cur[0]:
                self._rx_min[bucket] = (d, int(recv_usec))
            oldest = bucket - int(RECEIVE_DRIFT_WINDOW_S / RECEIVE_BOUND_BUCKET_S)
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

    def _envelope(self) -> tuple[float, float, float] | None:
        """The receive-time lower envelope as a line (t_ref us, receive - boot there us, drift), or None
        while it holds too few seconds (class docstring)."""
        if len(self._rx_min) < RECEIVE_DRIFT_MIN_BUCKETS:
            return None
        pts = np.array([(t, d) for d, t in self._rx_min.values()], dtype=np.float64)
        t, d = pts[:, 0], pts[:, 1]
        if t.max() - t.min() < RECEIVE_DRIFT_MIN_SPAN_S * 1e6:
            return None
        t_ref = float(t.max())
        slope, icpt = np.polyfit(t - t_ref, d, 1)
        keep = d - (icpt + slope * (t - t_ref)) <= RECEIVE_DRIFT_OUTLIER_S * 1e6
        if keep.sum() >= RECEIVE_DRIFT_MIN_BUCKETS // 2:
            slope, icpt = np.polyfit(t[keep] - t_ref, d[keep], 1)
        limit = TIMESYNC_MAX_DRIFT_PPM * 1e-6
        return t_ref, float(icpt), float(np.clip(slope, -limit, limit))

    def _rx_bound(self, now_usec: float) -> float | None:
        """offset <= receive - boot: the envelope's line at ``now_usec``, or (before it can be fitted)
        the smallest of the last ``RECEIVE_BOUND_WINDOW_S`` of buckets."""
        if not self._rx_min:
            return None
        envelope = self._envelope()
        if envelope is not None:
            t_ref, d_ref, drift = envelope
            return d_ref + drift * (now_usec - t_ref)
        recent = max(self._rx_min) - int(RECEIVE_BOUND_WINDOW_S / RECEIVE_BOUND_BUCKET_S)
        return min(d for b, (d, _) in self._rx_min.items() if b >= recent)

    def offset_usec(self, now_usec: float) -> float | None:
        """Daemon clock minus autopilot boot time at ``now_usec`` (daemon clock), us; None before any
        TIMESYNC answer or timestamped message."""
        with self._lock:
            bound = self._rx_bound(now_usec)
            if self._fit is None:
                return bound
            offset = _offset_at(self._fit, now_usec)
            if bound is None:
                return offset
            # the answers say where within the link's latency below the envelope; a clock whose rate
            # changed since they were fitted is read from the envelope
            best_rtt = min((s.rtt_usec for s in self._samples), default=0)
            allowance = max(TIMESYNC_ALLOWANCE_MIN_S * 1e6, best_rtt / 2.0)
            return min(max(offset, bound - allowance), bound)

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
    def sigma_s(self) -> float | None:
        """1-sigma of the mapping, s: half the shortest round trip with TIMESYNC, ``RECEIVE_BOUND_SIGMA_S``
        on receive times alone, None before either."""
        with self._lock:
            if self._fit is not None and self._samples:
                return min(s.rtt_usec for s in self._samples) / 2e6
            return RECEIVE_BOUND_SIGMA_S if self._rx_min else None

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


def _axes_disagreement_s(
    axis_costs: np.ndarray, taus: np.ndarray, curves: np.ndarray, offs: np.ndarray
) -> float:
    """Half the difference between the lateness the camera's x-axis tilts and its y-axis tilts each fit
    best, s, where world-down moved on both (else 0). A camera's lateness is one for both axes; an
    autopilot's attitude error that follows its manoeuvres differs between roll and pitch, and alone it
    reads as a lateness the fit cannot tell from a real one (PX4 SITL: an on-time camera fitted at 0.31 s,
    stating 0.013 s, against EKF2's 1-3 deg of tilt error)."""
    k0 = int(np.clip(np.rint(-offs[0] / CAMERA_CURVE_STEP_S), 1, offs.size - 2))
    rates = np.abs(curves[:, k0 + 1] - curves[:, k0 - 1]) / (2 * CAMERA_CURVE_STEP_S)  # (n, 2)
    moving = (rates >= CAMERA_OFFSET_MIN_RATE_RAD_S).sum(axis=0)
    if np.any(moving < CAMERA_OFFSET_MIN_SAMPLES // 2):
        return 0.0
    tau_x = float(taus[int(np.argmin(axis_costs[:, 0]))])
    tau_y = float(taus[int(np.argmin(axis_costs[:, 1]))])
    return abs(tau_x - tau_y) / 2.0


def _effective_samples(residual: np.ndarray) -> float:
    """How many independent samples a fit's residuals (n, 2), in time order, are worth: ``n (1 - r) /
    (1 + r)`` with ``r`` their lag-1 autocorrelation (0 to ``CAMERA_OFFSET_MAX_AUTOCORR``), at least 2.
    An autopilot's attitude error wanders with its manoeuvres for seconds, so consecutive frames'
    residuals share it; counted as independent, PX4 SITL's fits of an on-time camera stated 0.01-0.05 s
    and 0.26 s was applied (the output then led the vehicle by as much: EKF2 p95 5 m)."""
    n = residual.shape[0]
    if n < 3:
        return float(max(n, 1))
    e = residual - residual.mean(axis=0)
    denom = float(np.sum(e * e))
    r = float(np.sum(e[1:] * e[:-1]) / denom) if denom > 0 else 0.0
    r = min(max(r, 0.0), CAMERA_OFFSET_MAX_AUTOCORR)
    return max(2.0, n * (1.0 - r) / (1.0 + r))


def _offset_at(fit: tuple[float, float, float], now_usec: float) -> float:
    t_ref, offset, drift = fit
    return offset + drift * (now_usec - t_ref)


# -- the camera's stamps ---------------------------------------------------------------------------------

#: Tilt samples kept for the camera stamp fit, and tilts waiting for the autopilot's attitude.
CAMERA_OFFSET_SAMPLES: Final[int] = 300
CAMERA_OFFSET_PENDING: Final[int] = 64
#: The autopilot's world-down is sampled this often around each exposure for the fit, s, and this far
#: after it (an early camera: what can be seen without waiting long for the autopilot's attitude), s.
CAMERA_CURVE_STEP_S: Final[float] = 0.01
CAMERA_CURVE_AHEAD_S: Final[float] = 0.04
#: A sample whose world-down moves slower than this says little about timing (it still pins the bias).
CAMERA_OFFSET_MIN_RATE_RAD_S: Final[float] = 0.035  # 2 deg/s
#: The fit is used once it has this many informative samples and its standard error is below the bound.
#: With 8, a fit of 0.14 s (stated 0.018-0.019 s) was applied to an on-time camera over NAIP at 1200 m
#: AGL, whose slow fixed-wing turns say little: output p95 7.7 m against 1.4 m.
CAMERA_OFFSET_MIN_SAMPLES: Final[int] = 40
#: The most lag-1 autocorrelation a fit's residuals are credited with (``_effective_samples``).
CAMERA_OFFSET_MAX_AUTOCORR: Final[float] = 0.95
CAMERA_OFFSET_MAX_SE_S: Final[float] = 0.02
#: A lateness is applied only when it accounts for at least this share of the tilts' scatter about their
#: bias (``CameraOffsetFit.explained``); one that explains less is carried as the frames' timing doubt. A
#: late camera moves every tilt by the rate times the lateness; an autopilot whose attitude error only
#: partly follows its manoeuvres fits a lateness too, and leaves most of the scatter where it was.
#: Measured: on PX4 SITL (SIH), fits of 0.07-0.34 s on a camera on time explained 0.004-0.18; on the
#: ArduPilot emulator (its AHRS error follows every swing, as measured on ArduPilot SITL) a camera 0.2 s
#: late explained 0.23-0.50; in the unit tests' late camera over 0.95. The margin is thin.
CAMERA_OFFSET_MIN_EXPLAINED: Final[float] = 0.2
#: Candidate latenesses tried, s apart.
CAMERA_OFFSET_GRID_S: Final[float] = 0.005
#: The applied correction moves only when the fit differs from it by more than this many standard errors
#: (and at least CAMERA_OFFSET_MIN_STEP_S), so that it does not chase noise: the floored error to leave
#: no correction, the fit's own once a correction is applied, so that an early fit which later fits
#: disown (0.315 s against a true 0.2 s, in the emulator) is not kept.
CAMERA_OFFSET_STEP_SE: Final[float] = 2.0
#: The fit's standard error is taken as at least this, s: neighbouring tilts share their errors, which
#: the scatter alone does not show. Measured on copter SITL 4.7.0-dev with a camera on time: fits of
#: -0.035 to +0.065 s, each stating 0.008-0.013 s; a 0.065 s correction applied on that claim put the
#: output 3.9 m off at a stated 1.17 m in a hard deceleration (31 deg/s of pitch).
CAMERA_OFFSET_SE_FLOOR_S: Final[float] = 0.04
CAMERA_OFFSET_MIN_STEP_S: Final[float] = 0.005
#: The fit's error is also taken as at least the scatter (standard deviation) of the last this many sure
#: fits, once there are CAMERA_OFFSET_SCATTER_MIN_FITS: an autopilot whose attitude error follows its
#: manoeuvres reads as camera lateness, which no standard error shows. Measured on PX4 SITL (SIH) with a
#: camera on time: fits of -0.03 to +0.34 s within a minute, each stating 0.01-0.02 s; the 0.30 s applied
#: put the output 2-3 m ahead along the track at 7-10 m/s, and PX4's EKF2 with it.
CAMERA_OFFSET_SCATTER_FITS: Final[int] = 30
CAMERA_OFFSET_SCATTER_MIN_FITS: Final[int] = 5


@dataclass(frozen=True)
class CameraOffsetFit:
    """The fit of the camera's stamp lateness: ``offset_s`` (+: stamps later than the exposure), its
    standard error, the tilt bias on the camera's x and y axes it was fitted with (rad), how many
    samples (with a useful rate) it rests on, and ``explained``: the share of the tilts' scatter about
    their bias, with the stamps taken as the camera gives them, that the lateness accounts for."""

    offset_s: float
    se_s: float
    bias_cam_rad: tuple[float, float]
    samples: int
    informative: int
    explained: float = 1.0


def unapplied_doubt_s(fit: CameraOffsetFit, applied_s: float) -> float:
    """The timing doubt a fit adds beyond its own error when its lateness is not the applied one, s.

    A fit that explains at least ``CAMERA_OFFSET_MIN_EXPLAINED`` of the tilts' scatter would be applied,
    so the gap to it is carried whole. One that explains less is carried in proportion to the share it
    explains: a lateness that leaves the tilts nearly as scattered as the stamps taken as they are (the
    autopilot's attitude error partly following its manoeuvres) is evidence of little, and carried whole
    it made the frames' timing doubt the fit's whole 0.32 s on a camera on time (a real PX4 under SIH: the
    fit explained 0.04-0.06, the position's sigma doubled, and EKF2, weighing the positions by it, ran
    6.5 m off at p95 on its own IMU). A real lateness of the same size explains most of the scatter and
    is applied."""
    gap = abs(fit.offset_s - applied_s)
    return gap * min(1.0, max(fit.explained, 0.0) / CAMERA_OFFSET_MIN_EXPLAINED)


class CameraStampOffset:
    """Online estimate of how late the camera stamps its frames (module docstring); thread-safe.

    ``note`` queues one image-minus-autopilot tilt (a fix's, or VO's ground tilt) with its frame's
    admitted exposure and the correction it was admitted with; ``complete`` (called as the autopilot's
    attitude arrives) fetches world-down in the camera around each queued frame's *stamp* through
    ``curve(time_unix_usec, offsets_s)``, so no frame waits for it. A lateness ``tau`` predicts the tilt
    ``down(stamp - tau) - down(stamp - applied)`` plus a bias; the fit is the ``tau`` (on a grid) whose
    prediction leaves the least scatter. ``applied_s`` is the correction the time axis subtracts from
    new stamps; ``sigma_s`` how well a corrected exposure time is known: ``prior_sigma_s`` until the fit
    is sure, then its standard error (floored) with the doubt an unapplied fit adds
    (``unapplied_doubt_s``). ``out_of_bounds``: the fit is sure and beyond
    ``max_offset_s``, which the correction then stays at, the frames carrying the rest as doubt.
    """

    def __init__(self, *, max_offset_s: float, prior_sigma_s: float) -> None:
        if max_offset_s < 0 or prior_sigma_s <= 0:
            raise ValueError(
                f"max_offset_s must be >= 0 and prior_sigma_s > 0, got {max_offset_s}, {prior_sigma_s}"
            )
        self._max_s = float(max_offset_s)
        self._prior_sigma_s = float(prior_sigma_s)
        n_past = math.ceil((self._max_s + CAMERA_CURVE_AHEAD_S) / CAMERA_CURVE_STEP_S)
        n_ahead = round(CAMERA_CURVE_AHEAD_S / CAMERA_CURVE_STEP_S)
        #: Where world-down is sampled, relative to a frame's stamp, s.
        self.curve_offsets_s: np.ndarray = np.arange(-n_past, n_ahead + 1) * CAMERA_CURVE_STEP_S
        self._lock = threading.Lock()
        self._pending: deque[tuple[np.ndarray, int, float]] = deque(maxlen=CAMERA_OFFSET_PENDING)
        self._samples: deque[tuple[np.ndarray, np.ndarray, float, bool]] = deque(maxlen=CAMERA_OFFSET_SAMPLES)
        self._applied_s = 0.0
        self._sigma_s = self._prior_sigma_s
        self._fit: CameraOffsetFit | None = None
        self._out_of_bounds = False
        self._changes = 0
        self._recent_fits: deque[float] = deque(maxlen=CAMERA_OFFSET_SCATTER_FITS)

    def note(self, tilt_off_cam_rad: tuple[float, float], exposure_unix_usec: int, applied_s: float) -> None:
        """Queue one tilt of the frame admitted at ``exposure_unix_usec`` with ``applied_s`` taken off."""
        tilt = np.asarray(tilt_off_cam_rad, dtype=np.float64)
        if np.all(np.isfinite(tilt)) and math.isfinite(applied_s):
            with self._lock:
                self._pending.append((tilt, int(exposure_unix_usec), float(applied_s)))

    def due_before_unix_usec(self) -> int | None:
        """The attitude must reach this time (the oldest queued stamp plus the curve's reach) for
        ``complete`` to take the oldest queued tilt; None when nothing is queued."""
        with self._lock:
            if not self._pending:
                return None
            _, t, applied = self._pending[0]
            return t + round((applied + CAMERA_CURVE_AHEAD_S) * 1e6)

    def complete(self, curve: Callable[[int, np.ndarray], np.ndarray | None], latest_unix_usec: int) -> bool:
        """Take every queued tilt whose curve the attitude up to ``latest_unix_usec`` covers (a tilt whose
        curve ``curve`` cannot give is dropped). True when the applied correction changed."""
        taken: list[tuple[np.ndarray, int, float]] = []  # (tilt, stamp us, applied s)
        with self._lock:
            while self._pending:
                tilt, t_usec, applied = self._pending[0]
                stamp_usec = t_usec + round(applied * 1e6)
                if stamp_usec + CAMERA_CURVE_AHEAD_S * 1e6 > latest_unix_usec:
                    break
                self._pending.popleft()
                taken.append((tilt, stamp_usec, applied))
        samples = []
        for tilt, stamp_usec, applied in taken:
            c = curve(stamp_usec, self.curve_offsets_s)
            if c is not None and c.shape == (self.curve_offsets_s.size, 2) and np.all(np.isfinite(c)):
                samples.append((tilt, np.asarray(c, dtype=np.float64), applied))
        if not samples:
            return False
        with self._lock:
            for tilt, c, applied in samples:
                self._samples.append((tilt, c, applied, self._informative(c, applied)))
            return self._refit_locked()

    def _informative(self, curve: np.ndarray, applied_s: float) -> bool:
        """Whether world-down moved fast enough around the admitted exposure to show a timing error."""
        k = int(np.rint((-applied_s - self.curve_offsets_s[0]) / CAMERA_CURVE_STEP_S))
        k = min(max(k, 1), self.curve_offsets_s.size - 2)
        rate = np.hypot(*(curve[k + 1] - curve[k - 1])) / (2 * CAMERA_CURVE_STEP_S)
        return bool(rate >= CAMERA_OFFSET_MIN_RATE_RAD_S)

    def _refit_locked(self) -> bool:
        fit = self._fit_locked()
        self._fit = fit
        sure = fit is not None and fit.informative >= CAMERA_OFFSET_MIN_SAMPLES
        if fit is None or not sure or fit.se_s > CAMERA_OFFSET_MAX_SE_S:
            return False
        target = min(max(fit.offset_s, -CAMERA_CURVE_AHEAD_S), self._max_s)
        self._out_of_bounds = fit.offset_s > self._max_s + CAMERA_OFFSET_GRID_S / 2
        self._recent_fits.append(fit.offset_s)
        scatter = (
            float(np.std(self._recent_fits))
            if len(self._recent_fits) >= CAMERA_OFFSET_SCATTER_MIN_FITS
            else 0.0
        )
        se = max(fit.se_s, CAMERA_OFFSET_SE_FLOOR_S, scatter)
        # leaving the prior (stamps as the camera gives them) takes the floored error; once left, the
        # correction is the fit's and follows it beyond the fit's own error (never within the fits'
        # scatter), so that an early fit that later ones disown is not kept
        moving_se = se if self._changes == 0 else max(fit.se_s, scatter)
        threshold_s = max(CAMERA_OFFSET_STEP_SE * moving_se, CAMERA_OFFSET_MIN_STEP_S)
        # a correction moves only to a lateness that accounts for the tilts (module docstring): one that
        # leaves them as scattered is carried as doubt below, never applied
        step = abs(target - self._applied_s) > threshold_s and fit.explained >= CAMERA_OFFSET_MIN_EXPLAINED
        if step:
            self._applied_s = target
            self._changes += 1
        self._sigma_s = math.hypot(se, unapplied_doubt_s(fit, self._applied_s))
        return step

    def _fit_locked(self) -> CameraOffsetFit | None:
        samples = list(self._samples)
        informative = sum(1 for *_, inf in samples if inf)
        if len(samples) < 3 or informative < 2:
            return None
        tilts = np.stack([t for t, *_ in samples])  # (n, 2)
        curves = np.stack([c for _, c, *_ in samples])  # (n, m, 2), on each frame's stamp
        applied = np.array([a for _, _, a, _ in samples])
        offs = self.curve_offsets_s

        def down_at(lateness_s: np.ndarray) -> np.ndarray:
            """Each sample's world-down at its stamp minus ``lateness_s`` (one per sample), (n, 2)."""
            pos = np.clip((-lateness_s - offs[0]) / CAMERA_CURVE_STEP_S, 0.0, offs.size - 1.0)
            lo = np.minimum(np.floor(pos).astype(int), offs.size - 2)
            frac = (pos - lo)[:, None]
            rows = np.arange(len(samples))
            return np.asarray(curves[rows, lo] * (1 - frac) + curves[rows, lo + 1] * frac)

        seen_by_ap = down_at(applied)  # what the autopilot's attitude said at the admitted exposure
        # a little past the bound too, so that a lateness beyond it shows as one
        taus = np.arange(
            -CAMERA_CURVE_AHEAD_S, self._max_s + CAMERA_CURVE_AHEAD_S + 1e-9, CAMERA_OFFSET_GRID_S
        )
        costs = np.empty(taus.size)
        biases = np.zeros((taus.size, 2))
        axis_costs = np.empty((taus.size, 2))
        for k, tau in enumerate(taus):
            e = tilts - (down_at(np.full(len(samples), tau)) - seen_by_ap)
            biases[k] = e.mean(axis=0)
            axis_costs[k] = np.mean((e - biases[k]) ** 2, axis=0)
            costs[k] = float(axis_costs[k].sum())
        k = int(np.argmin(costs))
        n = len(samples)
        se = math.inf
        if 0 < k < taus.size - 1:
            curvature = (costs[k - 1] + costs[k + 1] - 2 * costs[k]) / CAMERA_OFFSET_GRID_S**2
            if curvature > 0:
                se = math.sqrt(2.0 * costs[k] / max(2 * n - 3, 1) / curvature)
                residual = tilts - (down_at(np.full(n, taus[k])) - seen_by_ap) - biases[k]
                se *= math.sqrt(n / _effective_samples(residual))
                se = max(se, _axes_disagreement_s(axis_costs, taus, curves, offs))
        elif (
            k == taus.size - 1
            and costs[k] < costs[k - 1] < costs[k - 2]
            and informative >= 3 * CAMERA_OFFSET_MIN_SAMPLES
        ):
            se = CAMERA_OFFSET_MAX_SE_S  # still falling at the grid's end: at least this late
        on_time = costs[int(np.argmin(np.abs(taus)))]
        explained = 1.0 - costs[k] / on_time if on_time > 0.0 else 0.0
        bias = (float(biases[k][0]), float(biases[k][1]))
        return CameraOffsetFit(float(taus[k]), se, bias, n, informative, float(explained))

    @property
    def applied_s(self) -> float:
        with self._lock:
            return self._applied_s

    @property
    def sigma_s(self) -> float:
        with self._lock:
            return self._sigma_s

    @property
    def fit(self) -> CameraOffsetFit | None:
        with self._lock:
            return self._fit

    @property
    def out_of_bounds(self) -> bool:
        with self._lock:
            return self._out_of_bounds

    @property
    def changes(self) -> int:
        with self._lock:
            return self._changes
