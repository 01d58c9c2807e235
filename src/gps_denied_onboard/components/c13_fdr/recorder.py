"""C13 flight data recorder: size-bounded, crash-safe JSON-lines segments, and a reader for replay.

Layout: ``<dir>/fdr-<start>-<seq>.jsonl`` where ``<start>`` is the recorder's start time
(``YYYYMMDDTHHMMSS.mmmZ``, UTC) and ``<seq>`` the segment number (6 digits), so names sort in recording
order across daemon restarts. One record per line::

    {"t_unix_s": 1717000000.123, "kind": "pipeline.frame", "seq": 42, ...fields}

Fields are converted to JSON: numpy arrays -> nested lists, numpy scalars -> Python numbers, UUID ->
string, Enum -> its value, tuples/sets -> lists, dataclasses -> objects, Path/datetime -> strings,
bytes -> hex, non-string mapping keys -> ``str(key)``; anything else -> ``repr``. Non-finite floats are
written as ``NaN``/``Infinity`` (Python's JSON dialect; ``read_records`` reads them back). A field whose
name collides with ``t_unix_s``/``kind``/``seq`` is stored as ``<name>_field``.

Crash safety: each record is written with one ``os.write`` on an ``O_APPEND`` descriptor (no user-space
buffer), so a crashed process loses at most the line being written; ``read_records`` skips a torn line.
After a failed or short write, the next record starts with a newline, so the torn fragment never glues
onto a good record. (No fsync per record: the bound is a process crash, not a power cut; segments are
fsynced when they are closed.)

Run markers: the first record a recorder writes is ``fdr.opened`` (pid, start time, and what it found at
the end of the newest existing segment: torn lines, and whether that run closed cleanly); ``close``
writes ``fdr.closed`` as the run's last record. A run with ``fdr.opened`` and no ``fdr.closed`` ended in
a crash (``reader.FdrReader.runs`` reports it). Recovery on open: when the newest existing segment ends
without a newline (a process killed mid-write), a newline is appended to it, so the torn fragment stays
a line of its own that readers skip.

Size bound: a segment is closed when the next record would take it past ``segment_bytes``; whenever the
total of all ``fdr-*.jsonl`` files in the directory (including previous runs) exceeds ``max_bytes``, the
oldest segments are deleted (never the open one).

``record`` never raises: I/O errors are counted in ``errors`` and logged (rate-limited), and the
recorder retries opening a segment on the next record.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import enum
import json
import math
import os
import re
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path, PurePath
from typing import Any, Final

import numpy as np
import structlog

from gps_denied_onboard.constants import FdrKind, LogEvent

_log = structlog.get_logger(__name__)

#: Segment file names: fdr-<start>-<seq>.jsonl.
SEGMENT_RE: Final = re.compile(r"^fdr-(\d{8}T\d{6}\.\d{3}Z)-(\d{6})\.jsonl$")
#: Write errors are logged at most once per this interval (all are counted).
ERROR_LOG_INTERVAL_S: Final[float] = 5.0
_RESERVED: Final[frozenset[str]] = frozenset({"t_unix_s", "kind", "seq"})
_MAX_DEPTH: Final[int] = 32
#: How much of the newest existing segment's end is scanned for torn lines when a recorder opens.
RECOVERY_TAIL_BYTES: Final[int] = 1 << 16


def to_jsonable(obj: Any, _depth: int = 0) -> Any:
    """Convert ``obj`` to plain JSON types (see the module docstring for the rules)."""
    if _depth > _MAX_DEPTH:
        return repr(obj)
    if isinstance(obj, enum.Enum):
        return to_jsonable(obj.value, _depth + 1)
    if obj is None or isinstance(obj, (bool, str, int, float)):
        return obj
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist(), _depth + 1)
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, uuid.UUID):
        return str(obj)
    if isinstance(obj, Mapping):
        return {
            (k if isinstance(k, str) else str(to_jsonable(k))): to_jsonable(v, _depth + 1)
            for k, v in obj.items()
        }
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v, _depth + 1) for v in obj]
    if isinstance(obj, (set, frozenset)):
        items = [to_jsonable(v, _depth + 1) for v in obj]
        try:
            return sorted(items)
        except TypeError:
            return items
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_jsonable(getattr(obj, f.name), _depth + 1) for f in dataclasses.fields(obj)}
    if isinstance(obj, PurePath):
        return str(obj)
    if isinstance(obj, (_dt.datetime, _dt.date, _dt.time)):
        return obj.isoformat()
    if isinstance(obj, (bytes, bytearray, memoryview)):
        return bytes(obj).hex()
    return repr(obj)


def _segment_key(path: Path) -> tuple[str, int] | None:
    m = SEGMENT_RE.match(path.name)
    return (m.group(1), int(m.group(2))) if m else None


def list_segments(directory: str | Path) -> list[Path]:
    """FDR segment files in ``directory``, oldest first (by start time, then sequence number)."""
    d = Path(directory)
    try:
        entries = list(d.iterdir())
    except OSError:
        return []
    keyed = [(k, p) for p in entries if (k := _segment_key(p)) is not None]
    return [p for _, p in sorted(keyed)]


def parse_line(raw: bytes) -> dict[str, Any] | None:
    """One segment line as a record, or None for a torn, blank or unreadable line."""
    try:
        rec = json.loads(raw)
    except (ValueError, UnicodeDecodeError):
        return None
    return rec if isinstance(rec, dict) and "kind" in rec else None


def read_records(directory: str | Path) -> Iterator[dict[str, Any]]:
    """Every record in ``directory`` in recording order; torn or unreadable lines are skipped."""
    for seg in list_segments(directory):
        try:
            fh = seg.open("rb")
        except OSError:
            continue
        with fh:
            for raw in fh:
                rec = parse_line(raw)
                if rec is not None:
                    yield rec


def read_records_newest_first(directory: str | Path) -> Iterator[dict[str, Any]]:
    """Every record in ``directory``, newest first (for "what was the last ..." questions at start-up:
    the caller stops early, so only the newest segment is usually read); torn lines are skipped."""
    for seg in reversed(list_segments(directory)):
        try:
            data = seg.read_bytes()
        except OSError:
            continue
        for raw in reversed(data.splitlines()):
            rec = parse_line(raw)
            if rec is not None:
                yield rec


class FlightDataRecorder:
    """JSON-lines flight data recorder implementing ``FdrClient``; thread-safe, never raises on record."""

    def __init__(
        self,
        dir: str | Path,
        max_bytes: int,
        segment_bytes: int,
        clock: Callable[[], float] = time.time,
    ) -> None:
        if segment_bytes <= 0 or max_bytes < segment_bytes:
            raise ValueError(
                f"FDR needs 0 < segment_bytes <= max_bytes, got segment_bytes={segment_bytes}, "
                f"max_bytes={max_bytes}"
            )
        self.dir = Path(dir)
        self.max_bytes = int(max_bytes)
        self.segment_bytes = int(segment_bytes)
        self._clock = clock
        self._lock = threading.Lock()
        self.started_unix_s = float(clock())
        start = _dt.datetime.fromtimestamp(self.started_unix_s, tz=_dt.timezone.utc)
        self._start_tag = start.strftime("%Y%m%dT%H%M%S.") + f"{start.microsecond // 1000:03d}Z"
        self._seg_seq = 0
        self._fd: int | None = None
        self._fd_path: Path | None = None
        self._fd_size = 0
        self._sizes: dict[Path, int] = {}
        self._seq = 0
        self._need_newline = False
        self._closed = False
        self._last_error_log_s = -math.inf
        self.errors = 0
        self.records_written = 0
        self.records_dropped = 0
        self.segments_deleted = 0
        self._scan_existing()
        previous, torn, previous_closed = self._recover_previous()
        with self._lock:
            self._append(
                FdrKind.FDR_OPENED,
                {
                    "pid": os.getpid(),
                    "started_unix_s": self.started_unix_s,
                    "previous_segment": previous.name if previous is not None else None,
                    "previous_torn_lines": torn,
                    "previous_closed": previous_closed,
                    "max_bytes": self.max_bytes,
                    "segment_bytes": self.segment_bytes,
                },
                t=self.started_unix_s,
            )

    # --- files --------------------------------------------------------------------------------------
    def _scan_existing(self) -> None:
        for seg in list_segments(self.dir):
            try:
                self._sizes[seg] = seg.stat().st_size
            except OSError:
                continue

    def _recover_previous(self) -> tuple[Path | None, int, bool | None]:
        """Scan the end of the newest existing segment: (that segment, torn lines in its last
        ``RECOVERY_TAIL_BYTES``, whether its last good record is ``fdr.closed``; None when it has no
        good record there). A last line without a newline is terminated (see the module docstring)."""
        segs = list_segments(self.dir)
        if not segs:
            return None, 0, None
        newest = segs[-1]
        try:
            with newest.open("rb") as fh:
                size = fh.seek(0, os.SEEK_END)
                start = max(0, size - RECOVERY_TAIL_BYTES)
                fh.seek(start)
                tail = fh.read()
            if tail and not tail.endswith(b"\n"):
                fd = os.open(newest, os.O_WRONLY | os.O_APPEND | os.O_CLOEXEC)
                try:
                    os.write(fd, b"\n")
                finally:
                    os.close(fd)
                self._sizes[newest] = size + 1
        except OSError as exc:
            self._error("recover", exc)
            return newest, 0, None
        lines = tail.split(b"\n")
        if start > 0:
            lines = lines[1:]  # the scan began mid-line: not a torn line
        torn = 0
        last_kind: str | None = None
        for raw in lines:
            if not raw.strip():
                continue
            rec = parse_line(raw)
            if rec is None:
                torn += 1
            else:
                last_kind = str(rec["kind"])
        return newest, torn, (last_kind == FdrKind.FDR_CLOSED) if last_kind is not None else None

    def _open_segment(self) -> None:
        os.makedirs(self.dir, exist_ok=True)
        while True:
            self._seg_seq += 1
            path = self.dir / f"fdr-{self._start_tag}-{self._seg_seq:06d}.jsonl"
            if path not in self._sizes and not path.exists():
                break
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_CLOEXEC, 0o644)
        self._fd_path = path
        self._fd_size = 0
        self._need_newline = False
        self._sizes[path] = 0

    def _close_segment(self) -> None:
        fd, self._fd = self._fd, None
        self._fd_path = None
        if fd is not None:
            try:
                os.fsync(fd)
            except OSError as exc:
                self._error("fsync", exc)
            try:
                os.close(fd)
            except OSError as exc:
                self._error("close", exc)

    def _enforce_budget(self) -> None:
        total = sum(self._sizes.values())
        for seg in sorted(self._sizes, key=lambda p: _segment_key(p) or ("", 0)):
            if total <= self.max_bytes:
                break
            if seg == self._fd_path:
                continue
            try:
                seg.unlink()
            except FileNotFoundError:
                pass
            except OSError as exc:
                self._error("delete", exc)
                continue
            total -= self._sizes.pop(seg)
            self.segments_deleted += 1
            _log.info(LogEvent.FDR_SEGMENT_DELETED, path=str(seg), total_bytes=total)

    def _error(self, phase: str, exc: BaseException) -> None:
        self.errors += 1
        now = time.monotonic()
        if now - self._last_error_log_s >= ERROR_LOG_INTERVAL_S:
            self._last_error_log_s = now
            _log.error(
                LogEvent.FDR_WRITE_ERROR, phase=phase, dir=str(self.dir), error=repr(exc), errors=self.errors
            )

    # --- api ----------------------------------------------------------------------------------------
    def record(self, kind: str, fields: Mapping[str, object]) -> None:
        """Append one record (see the module docstring). Never raises."""
        with self._lock:
            self._append(kind, fields)

    def _append(self, kind: str, fields: Mapping[str, object], t: float | None = None) -> None:
        """``record`` with the lock held; ``t`` defaults to the clock now."""
        if t is None:
            t = self._clock()
        if self._closed:
            self.records_dropped += 1
            return
        self._seq += 1
        rec: dict[str, Any] = {"t_unix_s": t, "kind": str(kind), "seq": self._seq}
        try:
            for key, value in dict(fields).items():
                name = str(key)
                rec[f"{name}_field" if name in _RESERVED else name] = to_jsonable(value)
            line = (json.dumps(rec, separators=(",", ":"), allow_nan=True) + "\n").encode("utf-8")
        except (TypeError, ValueError, RecursionError) as exc:
            self._error("encode", exc)
            self.records_dropped += 1
            return
        self._write(line)

    def _write(self, line: bytes) -> None:
        try:
            if self._fd is not None and self._fd_size > 0 and self._fd_size + len(line) > self.segment_bytes:
                self._close_segment()
            if self._fd is None:
                self._open_segment()
                self._enforce_budget()
        except OSError as exc:
            self._close_segment()
            self._error("open", exc)
            self.records_dropped += 1
            return
        if self._need_newline:
            line = b"\n" + line
        view = memoryview(line)
        written = 0
        try:
            while written < len(view):
                n = os.write(self._fd, view[written:])  # type: ignore[arg-type]
                if n <= 0:
                    raise OSError("short write (0 bytes)")
                written += n
        except OSError as exc:
            self._need_newline = written > 0 or self._need_newline
            self._account(written)
            self._error("write", exc)
            self.records_dropped += 1
            return
        self._need_newline = False
        self._account(written)
        self.records_written += 1
        if sum(self._sizes.values()) > self.max_bytes:
            self._enforce_budget()

    def _account(self, n: int) -> None:
        self._fd_size += n
        if self._fd_path is not None:
            self._sizes[self._fd_path] = self._fd_size

    @property
    def total_bytes(self) -> int:
        """Bytes in all known segments of the directory (this run and earlier ones)."""
        with self._lock:
            return sum(self._sizes.values())

    def segments(self) -> list[Path]:
        return list_segments(self.dir)

    def close(self) -> None:
        """Write ``fdr.closed``, flush (fsync) and close the open segment; later records are dropped and
        counted. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._append(
                FdrKind.FDR_CLOSED,
                {
                    "pid": os.getpid(),
                    "started_unix_s": self.started_unix_s,
                    "records_written": self.records_written,
                    "records_dropped": self.records_dropped,
                    "errors": self.errors,
                    "segments_deleted": self.segments_deleted,
                },
            )
            self._closed = True
            self._close_segment()

    def __enter__(self) -> FlightDataRecorder:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
