"""C13 reader: an FDR directory (or one segment file) as daemon runs and typed records.

``FdrReader(path)`` streams the segments in recording order; every method is one pass over the files, so
a full-size recorder (hundreds of MB) is never held in memory. Records of other kinds are skipped
without a full JSON parse (the recorder writes ``{"t_unix_s":..,"kind":"..","seq":..`` first).

Runs: a run starts at each ``fdr.opened`` record and, for records written by a recorder without markers,
wherever ``seq`` starts again (every recorder numbers its records from 1). A run's stop is ``clean``
when it has ``fdr.closed``, ``crash`` when it has ``fdr.opened`` but no ``fdr.closed`` (the newest run of
a daemon still running reads as ``crash`` too: the recorder cannot tell), and ``unknown`` when it has
neither marker (an older recorder, or its ``fdr.opened`` segment was deleted by the size bound).
See docs/fdr.md for every kind and field.
"""

from __future__ import annotations

import enum
import math
import re
from collections import Counter
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

from gps_denied_onboard.components.c13_fdr.recorder import (
    MAX_RECORD_BYTES,
    bounded_lines,
    list_segments,
    open_regular,
    parse_line,
    refused_files,
)
from gps_denied_onboard.constants import FdrKind
from gps_denied_onboard.helpers import bounded_json

#: The head the recorder writes on every line (t_unix_s, then kind): lets ``records`` skip other kinds
#: without parsing them.
_HEAD_RE: Final = re.compile(rb'^\{"t_unix_s":[^,]*,"kind":"([^"\\]*)"')


class FdrReadError(Exception):
    """The path is not a readable FDR (missing, or no segment in it)."""

    def __init__(self, message: str, *, path: Path) -> None:
        super().__init__(message)
        self.path = path


class RunStop(str, enum.Enum):
    """How a daemon run ended, as the recorder's markers tell it."""

    CLEAN = "clean"
    CRASH = "crash"
    UNKNOWN = "unknown"


@dataclass(frozen=True)
class FdrRun:
    """One daemon run: the records from one ``fdr.opened`` to the next."""

    #: 0-based, in recording order.
    index: int
    #: The daemon's process id (from ``fdr.opened``/``fdr.closed``), or None when neither was read.
    pid: int | None
    #: First record's time, Unix s (``fdr.opened``'s when present).
    start_unix_s: float
    #: Last record's time, Unix s (``fdr.closed``'s on a clean stop).
    end_unix_s: float
    stop: RunStop
    #: Records by kind, markers included.
    counts: Mapping[str, int]
    #: Torn or unreadable lines inside this run's part of the files.
    bad_lines: int = 0
    #: Torn lines the next run's recorder found at the end of this run's last segment
    #: (``fdr.opened.previous_torn_lines``); 0 for the newest run.
    torn_lines_at_end: int = 0

    @property
    def duration_s(self) -> float:
        return max(0.0, self.end_unix_s - self.start_unix_s)

    def rate_hz(self, kind: str) -> float | None:
        """Records of ``kind`` per second over the run, or None for a run shorter than 1 ms."""
        d = self.duration_s
        return self.counts.get(kind, 0) / d if d > 1e-3 else None


@dataclass(frozen=True)
class EstimateRecord:
    """``mavlink.estimate``: one estimate sent to the autopilot."""

    t_unix_s: float
    time_unix_usec: int | None
    provenance: str
    fix_type: int | None
    lat_deg: float | None
    lon_deg: float | None
    horiz_sigma_m: float | None


@dataclass(frozen=True)
class FixRecord:
    """``pipeline.fix``: one absolute-fix attempt."""

    t_unix_s: float
    frame_seq: int | None
    fix_accepted: bool
    inliers: int
    residual_px: float | None
    no_fix_reason: str | None


@dataclass(frozen=True)
class ProvenanceChange:
    """``estimator.provenance_changed``."""

    t_unix_s: float
    old: str
    new: str
    reason: str | None


@dataclass(frozen=True)
class FrameError:
    """``pipeline.frame_error``."""

    t_unix_s: float
    frame_seq: int | None
    stage: str
    error: str


@dataclass(frozen=True)
class FrameRefusal:
    """``pipeline.frame_refused``."""

    t_unix_s: float
    frame_seq: int | None
    reason: str


@dataclass(frozen=True)
class FdrScan:
    """What a full read of an FDR found (``scan``): what the daemon's start-up read would skip."""

    segments: int
    records: int
    #: Lines that are not JSON: a write torn by a crash or a full disk (the recorder expects these).
    torn_lines: int
    #: Lines the recorder never writes: over ``MAX_RECORD_BYTES``, nested past the parser, or JSON that
    #: is not a record. Damage or tampering.
    corrupt_lines: int
    #: The first corrupt line as ``segment:line: reason``, or None.
    first_corrupt: str | None
    #: Segments that cannot be opened or read, and files named like segments or images that are not
    #: regular files (refused unopened), with the reason.
    unreadable_segments: tuple[str, ...]


def scan(path: str | Path) -> FdrScan:
    """Read every line of the FDR at ``path`` (a directory; none yet is an empty scan) and classify it.
    Raises ``FdrReadError`` when ``path`` exists and is not a directory."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise FdrReadError(f"{p}: not a directory", path=p)
    segs = list_segments(p) if p.is_dir() else []
    records = torn = corrupt = 0
    first: str | None = None
    # a FIFO or a link among the segments is refused unopened: reading it could block or never end
    refused = refused_files(p) if p.is_dir() else []
    unreadable = [f"{f.name}: not a regular file ({what})" for f, what in refused]
    for seg in segs:
        try:
            with open_regular(seg) as fh:
                for n, raw in enumerate(bounded_lines(fh), start=1):
                    if not raw.strip():
                        continue
                    why = _line_fault(raw)
                    if why is None:
                        records += 1
                    elif why == "torn":
                        torn += 1
                    else:
                        corrupt += 1
                        first = first or f"{seg.name}:{n}: {why}"
        except OSError as exc:
            unreadable.append(f"{seg.name}: {exc.strerror or exc}")
    return FdrScan(len(segs), records, torn, corrupt, first, tuple(unreadable))


def _line_fault(raw: bytes) -> str | None:
    """None for a record, ``torn`` for a line that is not JSON, else why the line is corrupt."""
    try:
        rec = bounded_json.loads(raw, max_bytes=MAX_RECORD_BYTES, what="line")
    except bounded_json.BoundedJsonError as exc:
        return "torn" if exc.reason in ("syntax", "utf8") else str(exc)
    if not isinstance(rec, dict) or "kind" not in rec:
        return "JSON but not a record (no object with a kind)"
    return None


def split_runs(records: Iterable[dict[str, Any]]) -> list[list[dict[str, Any]]]:
    """Records per daemon run (the rule of :meth:`FdrReader.runs`: a run starts at ``fdr.opened`` or
    where the record sequence restarts)."""
    runs: list[list[dict[str, Any]]] = []
    last_seq = 0
    for rec in records:
        seq = _int(rec.get("seq")) or 0
        if not runs or rec.get("kind") == FdrKind.FDR_OPENED or 0 < seq <= last_seq:
            runs.append([])
        runs[-1].append(rec)
        last_seq = seq
    return runs


def _float(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    try:
        f = float(v)  # an integer too large for a float raises OverflowError
    except OverflowError:
        return None
    return f if math.isfinite(f) else None


def _int(v: Any) -> int | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return v if isinstance(v, int) else (int(v) if math.isfinite(v) else None)


def _str(v: Any) -> str | None:
    return None if v is None else str(v)


@dataclass
class _RunBuilder:
    index: int
    start_unix_s: float | None = None
    end_unix_s: float | None = None
    pid: int | None = None
    opened: bool = False
    closed: bool = False
    last_seq: int = 0
    bad_lines: int = 0
    counts: Counter[str] = field(default_factory=Counter)

    def build(self, torn_at_end: int) -> FdrRun:
        if self.closed:
            stop = RunStop.CLEAN
        elif self.opened:
            stop = RunStop.CRASH
        else:
            stop = RunStop.UNKNOWN
        start = self.start_unix_s if self.start_unix_s is not None else math.nan
        end = self.end_unix_s if self.end_unix_s is not None else start
        return FdrRun(self.index, self.pid, start, end, stop, dict(self.counts), self.bad_lines, torn_at_end)


class FdrReader:
    """Reads the FDR at ``path``: a recorder directory, or one ``fdr-*.jsonl`` segment file."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def segments(self) -> list[Path]:
        """The segment files, oldest first. Raises ``FdrReadError`` when there are none."""
        p = self.path
        if p.is_file():
            return [p]
        if not p.is_dir():
            there = p.exists() or p.is_symlink()
            what = "not a regular file or a directory" if there else "no such file or directory"
            raise FdrReadError(f"{p}: {what}", path=p)
        segs = list_segments(p)
        if not segs:
            raise FdrReadError(f"{p}: no FDR segments (fdr-*.jsonl) in this directory", path=p)
        return segs

    def refused(self) -> list[str]:
        """Files named like segments or images that are not regular files (FIFO, symbolic link, device),
        as ``name: what``: never read."""
        if not self.path.is_dir():
            return []
        return [f"{f.name}: {what}" for f, what in refused_files(self.path)]

    def _lines(self) -> Iterator[bytes]:
        for seg in self.segments():
            try:  # a segment named on the command line may be a link to a regular file; nothing else is
                fh = open_regular(seg, follow_symlinks=seg == self.path)
            except OSError:
                continue
            with fh:
                yield from bounded_lines(fh)

    def records(self, *kinds: str) -> Iterator[dict[str, Any]]:
        """Every record (of ``kinds`` when given) in recording order; torn lines skipped."""
        wanted = frozenset(kinds)
        for raw in self._lines():
            if wanted:
                head = _HEAD_RE.match(raw)
                if head is not None and head.group(1).decode("utf-8", "replace") not in wanted:
                    continue
            rec = parse_line(raw)
            if rec is not None and (not wanted or rec["kind"] in wanted):
                yield rec

    def __iter__(self) -> Iterator[dict[str, Any]]:
        return self.records()

    def counts(self) -> dict[str, int]:
        """Records by kind over all runs."""
        total: Counter[str] = Counter()
        for run in self.runs():
            total.update(run.counts)
        return dict(total)

    def runs(self) -> list[FdrRun]:
        """The daemon runs in recording order (see the module docstring). Parses every line: a torn
        line starts like a good one, so only a full parse tells them apart."""
        builders: list[_RunBuilder] = []
        torn_at_start: list[int] = []  # per run: what its fdr.opened found at the previous run's end
        pending_bad = 0  # torn lines before the first record
        for raw in self._lines():
            if not raw.strip():
                continue
            rec = parse_line(raw)
            if rec is None:
                if builders:
                    builders[-1].bad_lines += 1
                else:
                    pending_bad += 1
                continue
            kind, t, seq = str(rec["kind"]), _float(rec.get("t_unix_s")), _int(rec.get("seq")) or 0
            if not builders or kind == FdrKind.FDR_OPENED or 0 < seq <= builders[-1].last_seq:
                builders.append(_RunBuilder(len(builders), bad_lines=pending_bad))
                torn_at_start.append(0)
                pending_bad = 0
            run = builders[-1]
            run.counts[kind] += 1
            run.last_seq = seq
            if t is not None:
                if run.start_unix_s is None:
                    run.start_unix_s = t
                run.end_unix_s = t
            if kind == FdrKind.FDR_OPENED:
                run.opened = True
                run.pid = _int(rec.get("pid"))
                torn_at_start[-1] = _int(rec.get("previous_torn_lines")) or 0
            elif kind == FdrKind.FDR_CLOSED:
                run.closed = True
                if run.pid is None:
                    run.pid = _int(rec.get("pid"))
        return [b.build(torn_at_start[i + 1] if i + 1 < len(builders) else 0) for i, b in enumerate(builders)]

    # --- typed accessors ------------------------------------------------------------------------------
    def _timed(self, kind: str) -> Iterator[tuple[float, dict[str, Any]]]:
        """Records of ``kind`` with their time; one without a finite ``t_unix_s`` is not a record the
        recorder writes and is skipped."""
        for r in self.records(kind):
            t = _float(r.get("t_unix_s"))
            if t is not None:
                yield t, r

    def estimates(self) -> Iterator[EstimateRecord]:
        """``mavlink.estimate`` records (lat/lon/sigma None when the estimate had no position)."""
        for t, r in self._timed(FdrKind.ESTIMATE_SENT):
            yield EstimateRecord(
                t,
                _int(r.get("time_unix_usec")),
                str(r.get("provenance")),
                _int(r.get("fix_type")),
                _float(r.get("lat_deg")),
                _float(r.get("lon_deg")),
                _float(r.get("horiz_sigma_m")),
            )

    def fixes(self) -> Iterator[FixRecord]:
        """``pipeline.fix`` records."""
        for t, r in self._timed(FdrKind.FIX):
            yield FixRecord(
                t,
                _int(r.get("frame_seq")),
                bool(r.get("fix_accepted")),
                _int(r.get("inliers")) or 0,
                _float(r.get("residual_px")),
                _str(r.get("no_fix_reason")),
            )

    def provenance_changes(self) -> Iterator[ProvenanceChange]:
        """``estimator.provenance_changed`` records."""
        for t, r in self._timed(FdrKind.PROVENANCE_CHANGED):
            yield ProvenanceChange(
                t, str(r.get("old")), str(r.get("new")), _str(r.get("reason"))
            )

    def frame_errors(self) -> Iterator[FrameError]:
        """``pipeline.frame_error`` records."""
        for t, r in self._timed(FdrKind.FRAME_ERROR):
            yield FrameError(
                t, _int(r.get("frame_seq")), str(r.get("stage")), str(r.get("error"))
            )

    def frame_refusals(self) -> Iterator[FrameRefusal]:
        """``pipeline.frame_refused`` records."""
        for t, r in self._timed(FdrKind.FRAME_REFUSED):
            yield FrameRefusal(t, _int(r.get("frame_seq")), str(r.get("reason")))
