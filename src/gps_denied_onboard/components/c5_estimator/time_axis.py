"""C5 time axis: the one place that decides what time it is for the estimator.

Input: every input with the time it describes (a frame's exposure, an IMU sample's time), never the time
it arrived. Output: admitted inputs fused into the estimator at their own time, refusals counted by
reason and logged, and the state at any requested time.

Rule, three jobs:
1. **Admission**: refused and never allowed to move the filter's clock: ``future`` (more than
   ``max_future_s`` ahead of the daemon's clock), ``stale`` (a frame older than ``max_frame_age_s`` when
   picked up), ``out_of_order`` (not after the previous admitted frame), ``too_late`` (more than
   ``max_delay_s`` behind the newest measurement fused, or before the filter was (re)initialised).
2. **Delayed fusion**: a checkpoint is kept before each fused input of the last ``max_delay_s``; an older
   input rewinds to the checkpoint before its time, is fused there, and every later input is fused again
   in time order (their events are not logged twice).
3. **Output at any time**: :meth:`TimeAxis.state_at` predicts from the newest fused input to the
   requested time without changing the filter; the steady MAVLink stream sends this.
Whose clock: the daemon's (``DaemonClock``), never the wall clock. ``admit_frame`` maps a frame's
wall-clock stamp into it (``DaemonClock.from_wall_usec``) and every later use of the frame uses the
mapped time (``Admission.exposure_time_unix_usec``), less the camera's measured lateness
(``clock.CameraStampOffset``). Thread-safe: one lock for the VO worker, the fix worker and the output task.

Why: docs/design.md, "The time axis".
"""

from __future__ import annotations

import bisect
import contextlib
import itertools
import math
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, Final

import numpy as np
import structlog

from gps_denied_onboard.clock import CameraStampOffset, DaemonClock
from gps_denied_onboard.components.c1_vio.types import VoMotion
from gps_denied_onboard.components.c4_pose.types import PoseFix
from gps_denied_onboard.components.c5_estimator.ekf import EstimatorCheckpoint, FixReason, NavEstimator
from gps_denied_onboard.components.c5_estimator.journal import InputJournal
from gps_denied_onboard.components.c5_estimator.types import EstimatorState, FixDecision
from gps_denied_onboard.constants import LogEvent

_log = structlog.get_logger(__name__)

#: Default tolerance for a timestamp ahead of the daemon's clock (camera and clock jitter), s.
DEFAULT_MAX_FUTURE_S: Final[float] = 0.25


class Refusal(str, Enum):
    """Why the time axis refused an input's timestamp (also ``FixDecision.reason``)."""

    FUTURE = "future"
    STALE = "stale"
    OUT_OF_ORDER = "out_of_order"
    TOO_LATE = "too_late"


@dataclass(frozen=True)
class Admission:
    """The verdict on one frame's exposure time. ``ahead_s``: exposure minus the clock (> 0: future).
    ``exposure_time_unix_usec``: the exposure in the daemon's clock (the stamp mapped from the host's wall
    clock); every later use of the frame uses this time."""

    admitted: bool
    reason: Refusal | None
    ahead_s: float
    exposure_time_unix_usec: int
    #: The camera's measured lateness subtracted from the stamp, s (``clock.CameraStampOffset``).
    stamp_offset_s: float = 0.0


@dataclass(frozen=True)
class TimeAxisStats:
    """Counters since start, for the status line and the FDR."""

    refused: dict[str, int]
    frames_admitted: int
    measurements_fused: int
    #: Inputs that arrived behind the newest one and were fused at their own time by rewinding.
    rewinds: int
    #: Largest ``newest - input`` time of a rewound input, s.
    max_rewind_s: float


@dataclass
class _Entry:
    time_usec: int
    seq: int
    kind: str
    apply: Callable[[NavEstimator], FixDecision]
    #: The filter just before this entry was (last) applied.
    before: EstimatorCheckpoint | None = field(default=None, repr=False)

    @property
    def key(self) -> tuple[int, int]:
        return self.time_usec, self.seq


class TimeAxis:
    """The estimator's time axis (see the module docstring).

    ``estimator``: the filter it owns (nothing else may call its update methods). ``clock``: the
    daemon's clock (one per run, from the composition root; default: a new one anchored now).
    ``clock_unix_usec``: a bare "now" instead (tests, replay: camera stamps are then taken as already in
    that clock). ``max_future_s``, ``max_frame_age_s``, ``max_delay_s``: the admission bounds, seconds.
    ``journal``: records (or, in a replay, plays back) each :meth:`unit` and the IMU answers inside it
    (``c5_estimator.journal``); it must also be the estimator's acceleration source.
    """

    def __init__(
        self,
        estimator: NavEstimator,
        *,
        max_delay_s: float,
        max_frame_age_s: float,
        max_future_s: float = DEFAULT_MAX_FUTURE_S,
        clock: DaemonClock | None = None,
        clock_unix_usec: Callable[[], int] | None = None,
        journal: InputJournal | None = None,
        camera_offset: CameraStampOffset | None = None,
    ) -> None:
        for name, value in (
            ("max_delay_s", max_delay_s),
            ("max_frame_age_s", max_frame_age_s),
            ("max_future_s", max_future_s),
        ):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number of seconds, got {value!r}")
        self._est = estimator
        if clock_unix_usec is not None:
            self._clock = clock_unix_usec
            self._from_wall: Callable[[int], int] = int
        else:
            daemon_clock = clock or DaemonClock()
            self._clock = daemon_clock.now_unix_usec
            self._from_wall = daemon_clock.from_wall_usec
        self._journal = journal
        self._camera_offset = camera_offset
        self._max_future_usec = round(max_future_s * 1e6)
        self._max_frame_age_usec = round(max_frame_age_s * 1e6)
        self._max_delay_usec = round(max_delay_s * 1e6)
        self._lock = threading.RLock()
        self._entries: list[_Entry] = []
        self._seq = itertools.count()
        self._last_frame_usec: int | None = None
        self._refused: dict[str, int] = {r.value: 0 for r in Refusal}
        self._frames_admitted = 0
        self._fused = 0
        self._rewinds = 0
        self._max_rewind_usec = 0

    # -- frames ---------------------------------------------------------------------------------------

    @property
    def camera_offset(self) -> CameraStampOffset | None:
        """The camera's measured stamp lateness that ``admit_frame`` subtracts (fed by the pipeline)."""
        return self._camera_offset

    def admit_frame(self, exposure_stamp_unix_usec: int) -> Admission:
        """Admit or refuse a frame by its exposure stamp (the host's wall clock at exposure; see the
        module docstring). An admitted frame's time becomes the bound for the next one; a refused one
        changes nothing but the counters."""
        with self._lock:
            late_s = self._camera_offset.applied_s if self._camera_offset is not None else 0.0
            t = self._from_wall(int(exposure_stamp_unix_usec)) - round(late_s * 1e6)
            now = self._clock()
            ahead_usec = t - now
            reason: Refusal | None = None
            if ahead_usec > self._max_future_usec:
                reason = Refusal.FUTURE
            elif -ahead_usec > self._max_frame_age_usec:
                reason = Refusal.STALE
            elif self._last_frame_usec is not None and t <= self._last_frame_usec:
                reason = Refusal.OUT_OF_ORDER
            if reason is not None:
                self._refuse("frame", reason, t, now)
                return Admission(False, reason, ahead_usec / 1e6, t, late_s)
            self._last_frame_usec = t
            self._frames_admitted += 1
            return Admission(True, None, ahead_usec / 1e6, t, late_s)

    def _refuse(self, kind: str, reason: Refusal, t: int, now: int) -> None:
        self._refused[reason.value] += 1
        head = self._est.time_unix_usec
        _log.warning(
            LogEvent.TIME_AXIS_REFUSED,
            input=kind,
            reason=reason.value,
            time_unix_usec=t,
            ahead_of_clock_s=round((t - now) / 1e6, 3),
            behind_filter_s=None if head is None else round((head - t) / 1e6, 3),
            refused_total=self._refused[reason.value],
        )

    # -- lifecycle ------------------------------------------------------------------------------------

    @property
    def is_initialised(self) -> bool:
        with self._lock:
            return self._est.is_initialised

    @property
    def head_unix_usec(self) -> int | None:
        """Time of the newest fused input (or of the initialisation); None before it."""
        with self._lock:
            return self._est.time_unix_usec

    def initialise(
        self, pos_ned_m: np.ndarray, sigma_m: float, time_unix_usec: int, *, map_confirmed: bool = False
    ) -> None:
        """(Re)start the filter at ``time_unix_usec``; nothing earlier can be fused afterwards.
        ``map_confirmed``: see :meth:`NavEstimator.initialise`."""
        with self._lock:
            self._est.initialise(pos_ned_m, sigma_m, int(time_unix_usec), map_confirmed=map_confirmed)
            self._entries.clear()

    def resume(self, checkpoint: EstimatorCheckpoint) -> None:
        """(Re)start the filter from ``checkpoint`` exactly (the navigator core's handover to a restarted
        vision worker); nothing before its time can be fused afterwards."""
        with self._lock:
            self._est.restore(checkpoint)
            self._entries.clear()

    def head_checkpoint(self) -> EstimatorCheckpoint | None:
        """The filter at its newest fused input (what the core predicts from); None before it starts."""
        with self._lock:
            return self._est.checkpoint() if self._est.is_initialised else None

    @contextlib.contextmanager
    def unit(self, kind: str, time_unix_usec: int) -> Iterator[dict[str, Any]]:
        """One atomic visit of a pipeline half (``c5_estimator.journal``): the axis' lock is held for the
        whole block, so no other thread's input lands inside it, and the journal (if any) records it
        with the clock now and the IMU answers the estimator got, numbered in lock order and written
        once the lock is released. The block may add fields to the yielded dict; they go into the
        unit's record."""
        journal = self._journal
        extra: dict[str, Any] = {}
        if journal is None:
            with self._lock:
                yield extra
            return
        record: dict[str, Any] | None = None
        try:
            with self._lock:
                journal.begin(kind, int(time_unix_usec), self._clock())
                try:
                    yield extra
                except BaseException:
                    record = journal.abort()
                    raise
                record = journal.end(extra)
        finally:
            if record is not None:
                journal.emit(record)  # outside the lock: the FDR write never holds up another input

    # -- measurements ---------------------------------------------------------------------------------

    def fuse_vo(self, motion: VoMotion, time_unix_usec: int) -> FixDecision:
        """VO motion over the interval ending at ``time_unix_usec`` (that frame's exposure)."""
        t = int(time_unix_usec)
        return self._fuse("vo", t, lambda est: est.update_vo(motion, time_unix_usec=t))

    def fuse_altitude(
        self, alt_agl_m: float, ground_alt_amsl_m: float, sigma_m: float, time_unix_usec: int
    ) -> FixDecision:
        """The autopilot's height above ground at ``time_unix_usec``."""
        t = int(time_unix_usec)
        return self._fuse(
            "altitude",
            t,
            lambda est: est.update_altitude(alt_agl_m, ground_alt_amsl_m, sigma_m, time_unix_usec=t),
        )

    def fuse_fix(self, fix: PoseFix) -> FixDecision:
        """An absolute fix, at its frame's exposure time however late it arrives (or refused)."""
        return self._fuse("fix", int(fix.exposure_time_unix_usec), lambda est: est.update_fix(fix))

    def note_no_fix(self, time_unix_usec: int) -> None:
        """The absolute-fix attempt on the frame exposed at ``time_unix_usec`` gave no fix."""
        self._note("no_fix", int(time_unix_usec), lambda est, at: est.note_no_fix(at))

    def raise_position_sigma(self, sigma_m: float, time_unix_usec: int) -> bool:
        """At ``time_unix_usec`` the position may be off by ``sigma_m`` more than the state says
        (:meth:`NavEstimator.raise_position_sigma`); an input like the others, so a rewind keeps it. Too
        late for ``time_unix_usec`` (a slow matcher's fix), it holds from the head on: what the estimate
        carried then it carries now. False when the axis took it at neither (not initialised)."""

        def raise_it(est: NavEstimator, _at: int) -> None:
            est.raise_position_sigma(sigma_m)

        return self._note("position_sigma", int(time_unix_usec), raise_it, late_at_head=True)

    def set_imu_trusted(self, trusted: bool, time_unix_usec: int) -> bool:
        """From ``time_unix_usec`` on (from the head on when that is too late, as
        :meth:`raise_position_sigma`), predict with the IMU or without it
        (:meth:`NavEstimator.set_imu_trusted`); an input like the others, so a rewind keeps it. False
        when the axis took it at neither (not initialised): the caller says it again."""

        def switch(est: NavEstimator, at: int) -> None:
            est.predict_to(at)  # the switch happens at ``at``: up to it the prediction is as it was
            est.set_imu_trusted(trusted)

        return self._note("imu_trust", int(time_unix_usec), switch, late_at_head=True)

    def _note(
        self, kind: str, t: int, action: Callable[[NavEstimator, int], None], *, late_at_head: bool = False
    ) -> bool:
        """An input at ``t`` that is not a measurement: applied (at the time it is placed at) and replayed
        on a rewind wherever the axis takes inputs at ``t`` (see ``_fuse``); with ``late_at_head``, one
        too late for ``t`` is placed at the head instead. Whether it was placed."""

        def at(time_usec: int) -> Callable[[NavEstimator], FixDecision]:
            def apply(est: NavEstimator) -> FixDecision:
                action(est, time_usec)
                return FixDecision(True, math.nan, FixReason.ACCEPTED)

            return apply

        decision = self._fuse(kind, t, at(t))
        if late_at_head and decision.reason == Refusal.TOO_LATE.value:
            head = self.head_unix_usec
            if head is not None:
                decision = self._fuse(kind, head, at(head))
        return decision.accepted

    def _fuse(self, kind: str, t: int, apply: Callable[[NavEstimator], FixDecision]) -> FixDecision:
        with self._lock:
            head = self._est.time_unix_usec
            if head is None:
                return FixDecision(False, math.nan, FixReason.NOT_INITIALISED)
            now = self._clock()
            if t - now > self._max_future_usec:
                self._refuse(kind, Refusal.FUTURE, t, now)
                return FixDecision(False, math.nan, Refusal.FUTURE.value)
            entry = _Entry(t, next(self._seq), kind, apply)
            idx = bisect.bisect_right([e.key for e in self._entries], entry.key)
            rewind_to = self._entries[idx].before if idx < len(self._entries) else None
            floor = rewind_to.time_usec if rewind_to is not None else head
            if head - t > self._max_delay_usec or floor is None or t < floor:
                self._refuse(kind, Refusal.TOO_LATE, t, now)
                return FixDecision(False, math.nan, Refusal.TOO_LATE.value)
            later = self._entries[idx:]
            if rewind_to is not None:
                self._est.restore(rewind_to)
                self._est.provenance_live = False
            try:
                entry.before = self._est.checkpoint()
                decision = entry.apply(self._est)
                self._entries.insert(idx, entry)
                self._replay(later)
            finally:
                self._est.provenance_live = True
            self._fused += 1
            if later:
                self._est.state()  # re-derive (and log, once) the provenance after the rewind
                self._rewinds += 1
                self._max_rewind_usec = max(self._max_rewind_usec, head - t)
                _log.debug(
                    LogEvent.TIME_AXIS_REWOUND, input=kind, behind_s=(head - t) / 1e6, replayed=len(later)
                )
            self._prune()
            return decision

    def _replay(self, entries: list[_Entry]) -> None:
        self._est.logging_enabled = False
        try:
            for e in entries:
                e.before = self._est.checkpoint()
                e.apply(self._est)
        finally:
            self._est.logging_enabled = True

    def _prune(self) -> None:
        head = self._est.time_unix_usec
        if head is None:
            return
        keep_from = bisect.bisect_left([e.time_usec for e in self._entries], head - self._max_delay_usec)
        if keep_from:
            del self._entries[:keep_from]

    # -- output ---------------------------------------------------------------------------------------

    def state_at(self, time_unix_usec: int | None = None) -> EstimatorState:
        """The estimate predicted to ``time_unix_usec`` (default: the clock's now); the filter is not
        changed. A time before the newest fused input is answered with that input's estimate (no
        retrodiction), stamped with its own time."""
        with self._lock:
            t = self._clock() if time_unix_usec is None else int(time_unix_usec)
            return self._est.state(t)

    def now_unix_usec(self) -> int:
        return self._clock()

    def stats(self) -> TimeAxisStats:
        with self._lock:
            return TimeAxisStats(
                dict(self._refused),
                self._frames_admitted,
                self._fused,
                self._rewinds,
                self._max_rewind_usec / 1e6,
            )
