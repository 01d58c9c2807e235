"""C5 input journal: what the estimator was given, unit by unit, so a replay can give it the same again.

The estimator's result depends, besides the frames, on the order in which the two pipeline halves reached
the time axis, the daemon's clock at each step, and the IMU's answer for each prediction interval at that
moment. A **unit** is one atomic visit of a pipeline half to the time axis, under the axis' lock:
``track`` (a frame's VO fused at its exposure, and the initialisation on the first frame with a prior),
``fix_prior`` (the state the fix path searches around, read when it starts), ``fix`` (the fix, or the
note that there was none, fused at its frame's exposure).

:class:`RecordingJournal` sits between the estimator and the real acceleration source, passes every
answer through and keeps those inside a unit; at the unit's end it hands one record (``n``, ``unit``,
``time_unix_usec``, ``clock_unix_usec``, the ``accel`` answers in order, each ``[t0, t1, mean or None,
tilt bound]``) to its sink (the FDR's ``estimator.input``). ``n`` is given under the lock (the order
the units happened); the record is written after the lock is released, so readers order by ``n``.
Queries outside a unit (the output stream's ``state_at(now)``) never change the filter and are not kept.

:class:`ReplayJournal` plays the records back: the same units in the same order, the recorded answers
and the recorded clock. A question the recording does not hold raises :class:`ReplayDivergence`: the
replay says where it stopped being exact instead of inventing an answer.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Final, Protocol

import numpy as np

from gps_denied_onboard.components.c5_estimator.protocol import AccelerationSource, ImuAcceleration

#: Unit kinds (the ``unit`` field of an ``estimator.input`` record).
UNIT_TRACK: Final = "track"
UNIT_FIX_PRIOR: Final = "fix_prior"
UNIT_FIX: Final = "fix"
UNIT_KINDS: Final = frozenset({UNIT_TRACK, UNIT_FIX_PRIOR, UNIT_FIX})


class InputJournal(AccelerationSource, Protocol):
    """What the time axis needs from a journal (it is also the estimator's acceleration source)."""

    def begin(self, unit: str, time_unix_usec: int, clock_unix_usec: int) -> None: ...

    def end(self, extra: Mapping[str, Any]) -> dict[str, Any] | None: ...

    def abort(self) -> dict[str, Any] | None: ...

    def emit(self, record: dict[str, Any]) -> None: ...


class ReplayDivergence(RuntimeError):
    """The replay asked the journal something the recording does not hold (``unit``: its number)."""

    def __init__(self, message: str, *, unit: int | None) -> None:
        super().__init__(message)
        self.unit = unit


def _entry(t0_unix_usec: int, t1_unix_usec: int, a: ImuAcceleration | None) -> list[Any]:
    """One recorded answer: ``[t0, t1, None]``, or ``[t0, t1, mean (3 floats), tilt bound]``."""
    if a is None:
        return [int(t0_unix_usec), int(t1_unix_usec), None]
    mean = [float(v) for v in np.asarray(a.mean_ned_m_s2, dtype=np.float64).reshape(-1)]
    return [int(t0_unix_usec), int(t1_unix_usec), mean, float(a.tilt_bound_m_s2)]


def _replayed(entry: Sequence[Any]) -> ImuAcceleration | None:
    """The answer an entry recorded (a recording made before the tilt doubt existed had none: 0)."""
    if entry[2] is None:
        return None
    tilt = float(entry[3]) if len(entry) > 3 else 0.0
    return ImuAcceleration(np.asarray(entry[2], dtype=np.float64), tilt)


class RecordingJournal:
    """Passes ``inner``'s answers through and records each unit through ``sink(fields)``.

    ``inner``: the real acceleration source (None: no IMU, every answer None). Must only be used under
    the time axis' lock (the axis calls ``begin``/``end``; the estimator it owns asks ``accel_ned_mean``).
    """

    def __init__(self, inner: AccelerationSource | None, sink: Callable[[dict[str, Any]], None]) -> None:
        self._inner = inner
        self._sink = sink
        self._n = 0
        self._open: dict[str, Any] | None = None
        self._owner: int | None = None

    def begin(self, unit: str, time_unix_usec: int, clock_unix_usec: int) -> None:
        if self._open is not None:
            raise RuntimeError(f"journal unit {self._open['unit']!r} still open; units do not nest")
        self._n += 1
        self._owner = threading.get_ident()
        self._open = {
            "n": self._n,
            "unit": unit,
            "time_unix_usec": int(time_unix_usec),
            "clock_unix_usec": int(clock_unix_usec),
            "accel": [],
        }

    def end(self, extra: Mapping[str, Any]) -> dict[str, Any] | None:
        """Close the unit; returns its record for :meth:`emit` (called once the axis' lock is released)."""
        rec, self._open, self._owner = self._open, None, None
        return None if rec is None else {**rec, **dict(extra)}

    def abort(self) -> dict[str, Any] | None:
        """The unit raised: its record is still written (marked), so the replay knows it happened."""
        return self.end({"aborted": True})

    def emit(self, record: dict[str, Any]) -> None:
        self._sink(record)

    def accel_ned_mean(self, t0_unix_usec: int, t1_unix_usec: int) -> ImuAcceleration | None:
        a = self._inner.accel_ned_mean(t0_unix_usec, t1_unix_usec) if self._inner is not None else None
        if self._open is not None and self._owner == threading.get_ident():
            self._open["accel"].append(_entry(t0_unix_usec, t1_unix_usec, a))
        return a


class ReplayJournal:
    """Serves recorded units (``estimator.input`` records, in recording order) back to a replay.

    The replay announces each unit through the time axis (``begin``); the unit must be the next one
    recorded, with the same kind and time. ``clock_unix_usec`` is the axis' clock for the replay: the
    recorded clock of the open unit (or of the last one, between units).
    """

    def __init__(self, records: Sequence[Mapping[str, Any]]) -> None:
        # Written after the lock was released, so two threads' records may be swapped in the file: ``n``
        # is the order the units happened.
        self._records = sorted(records, key=lambda r: int(r.get("n", 0)))
        self._next = 0
        self._open: Mapping[str, Any] | None = None
        self._answers: list[Any] = []
        self._clock = int(self._records[0]["clock_unix_usec"]) if self._records else 0

    @property
    def units_replayed(self) -> int:
        return self._next

    @property
    def units_total(self) -> int:
        return len(self._records)

    def peek(self) -> Mapping[str, Any] | None:
        """The next recorded unit, or None when all were replayed."""
        return self._records[self._next] if self._next < len(self._records) else None

    def clock_unix_usec(self) -> int:
        return self._clock

    def begin(self, unit: str, time_unix_usec: int, clock_unix_usec: int) -> None:
        rec = self.peek()
        if rec is None:
            raise ReplayDivergence(
                f"a {unit} unit at {time_unix_usec} after the last recorded one", unit=None
            )
        n = int(rec.get("n", self._next + 1))
        if rec.get("unit") != unit or int(rec.get("time_unix_usec", -1)) != int(time_unix_usec):
            raise ReplayDivergence(
                f"unit {n}: recorded {rec.get('unit')} at {rec.get('time_unix_usec')}, "
                f"replayed {unit} at {time_unix_usec}",
                unit=n,
            )
        self._next += 1
        self._open = rec
        self._answers = list(rec.get("accel") or [])
        self._clock = int(rec["clock_unix_usec"])

    def end(self, extra: Mapping[str, Any]) -> dict[str, Any] | None:
        rec, self._open = self._open, None
        if rec is not None and self._answers:
            raise ReplayDivergence(
                f"unit {rec.get('n')}: {len(self._answers)} recorded IMU answers were not asked for",
                unit=int(rec.get("n", 0)),
            )
        return None

    def abort(self) -> dict[str, Any] | None:
        self._open = None
        self._answers = []
        return None

    def emit(self, record: dict[str, Any]) -> None:
        """Nothing to write: a replay plays records back."""

    def accel_ned_mean(self, t0_unix_usec: int, t1_unix_usec: int) -> ImuAcceleration | None:
        rec = self._open
        if rec is None:
            raise ReplayDivergence(
                f"IMU asked for [{t0_unix_usec}, {t1_unix_usec}] outside a unit", unit=None
            )
        n = int(rec.get("n", 0))
        if not self._answers:
            raise ReplayDivergence(
                f"unit {n}: IMU asked for [{t0_unix_usec}, {t1_unix_usec}] beyond the recorded answers",
                unit=n,
            )
        entry = self._answers.pop(0)
        t0, t1 = int(entry[0]), int(entry[1])
        if (t0, t1) != (int(t0_unix_usec), int(t1_unix_usec)):
            raise ReplayDivergence(
                f"unit {n}: IMU asked for [{t0_unix_usec}, {t1_unix_usec}], recorded [{t0}, {t1}]", unit=n
            )
        return _replayed(entry)
