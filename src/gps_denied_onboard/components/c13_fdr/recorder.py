"""C13 flight data recorder: size-bounded, crash-safe JSON-lines segments.

Input: ``record(kind, **fields)`` from every component (kinds in ``constants.FdrKind``), and optional
frame images (``record_frame_image``). Output: ``<dir>/fdr-<start>-<seq>.jsonl`` segments, one record per
line (``{"t_unix_s": ..., "kind": ..., "seq": ..., ...fields}``; fields converted to JSON, a field named
like a common one stored as ``<name>_field``), images under ``<dir>/images/``, and ``health`` for the
status line and ``GDN_FDR``.

Rules:
- crash safety: one ``os.write`` per record on an ``O_APPEND`` descriptor, so a crash loses at most the
  line being written; after a failed write the next record starts with a newline; on open a torn last
  line is terminated; ``fdr.opened`` starts every run and ``fdr.closed`` ends a clean one;
- size: a segment closes before it would pass ``segment_bytes``; the oldest segments (never the open
  one) are deleted while all of them exceed ``max_bytes``; images have their own budget
  (``images_max_bytes``) and are written as ``.part`` then renamed;
- low disk: below ``min_free_bytes`` images go first; below a quarter of it, or when a write fails,
  records are dropped and counted, so the daemon keeps flying without its recorder;
- ``record`` never raises: errors are counted and logged (rate-limited), and opening a segment is
  retried on the next record;
- only regular files are read: a FIFO, a device, a socket or a symbolic link named like a segment or an
  image is refused unopened (``refused_files``), so nothing in the directory can block a reader or feed
  it without end (a FIFO blocked ``gdnav run`` before ready; a link to /dev/zero read until MemoryError).

Files, encoding and every record kind: docs/fdr.md.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import enum
import errno
import json
import math
import os
import re
import shutil
import stat
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path, PurePath
from typing import Any, BinaryIO, Final

import numpy as np
import structlog

from gps_denied_onboard.constants import FdrHealthState, FdrKind, LogEvent
from gps_denied_onboard.helpers import bounded_json

_log = structlog.get_logger(__name__)

#: Segment file names: fdr-<start>-<seq>.jsonl.
SEGMENT_RE: Final = re.compile(r"^fdr-(\d{8}T\d{6}\.\d{3}Z)-(\d{6})\.jsonl$")
#: Write errors are logged at most once per this interval (all are counted).
ERROR_LOG_INTERVAL_S: Final[float] = 5.0
_RESERVED: Final[frozenset[str]] = frozenset({"t_unix_s", "kind", "seq"})
_MAX_DEPTH: Final[int] = 32
#: The longest record line written or read, bytes (the largest, the config record, is a few kB): a longer
#: one is dropped and counted by the recorder, and skipped as unreadable by the readers.
MAX_RECORD_BYTES: Final[int] = 4 << 20
#: ``read_records_newest_first`` reads at most this much of each segment, from its end, bytes.
NEWEST_FIRST_MAX_BYTES: Final[int] = 256 << 20
#: How much of the newest existing segment's end is scanned for torn lines when a recorder opens.
RECOVERY_TAIL_BYTES: Final[int] = 1 << 16
#: Frame image files in ``<dir>/images``: img-<start>-<n>-<frame seq>.jpg.
IMAGE_RE: Final = re.compile(r"^img-(\d{8}T\d{6}\.\d{3}Z)-(\d{6})-(\d+)\.(?:jpg|png)$")
#: Frame image encodings: name -> (file extension, OpenCV encoder extension).
IMAGE_FORMATS: Final[dict[str, str]] = {"jpeg": "jpg", "png": "png"}
IMAGES_SUBDIR: Final[str] = "images"
#: Defaults of the constructor (the config's defaults: ``fdr.frame_jpeg_max_bytes``, ``fdr.min_free_bytes``).
DEFAULT_IMAGES_MAX_BYTES: Final[int] = 64 << 20
DEFAULT_MIN_FREE_BYTES: Final[int] = 64 << 20
#: Records are dropped below ``min_free_bytes // RECORD_FLOOR_DIVISOR`` of free space.
RECORD_FLOOR_DIVISOR: Final[int] = 4
#: ``health`` stays degraded/failing this long after the last dropped image/record, s (monotonic).
HEALTH_HOLD_S: Final[float] = 10.0


@dataclasses.dataclass(frozen=True)
class FdrHealth:
    """What the recorder can still do (``FlightDataRecorder.health``); counters are for this run.

    ``state``: ``ok``; ``degraded`` while free space is below ``min_free_bytes`` or an image was dropped
    in the last ``HEALTH_HOLD_S`` (images are being sacrificed, records are safe); ``failing`` while free
    space is below the records' floor or a record was dropped in the last ``HEALTH_HOLD_S``.
    """

    state: FdrHealthState
    #: Bytes of all record segments (earlier runs included) and of all frame images.
    record_bytes: int
    image_bytes: int
    #: Free bytes of the file system (None: unknown, the check failed or is disabled).
    free_bytes: int | None
    records_written: int
    records_dropped: int
    images_written: int
    #: Images not written (low space, over the budget alone, or a write error).
    images_dropped: int
    #: Images deleted: the images budget (oldest first) and the low-disk policy.
    images_deleted: int
    #: I/O and encode errors (records and images).
    write_errors: int


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


def _image_key(path: Path) -> tuple[str, int] | None:
    m = IMAGE_RE.match(path.name)
    return (m.group(1), int(m.group(2))) if m else None


class NotRegularFileError(OSError):
    """A file of the FDR that is not a regular file (FIFO, device, socket, symbolic link): refused
    unopened. ``what`` names its type."""

    def __init__(self, path: Path, what: str) -> None:
        super().__init__(errno.EINVAL, f"not a regular file ({what}); refused unread", str(path))
        self.what = what


def _file_type(mode: int) -> str:
    """What a non-regular ``st_mode`` is, in words."""
    for test, name in (
        (stat.S_ISLNK, "symbolic link"),
        (stat.S_ISFIFO, "FIFO"),
        (stat.S_ISCHR, "character device"),
        (stat.S_ISBLK, "block device"),
        (stat.S_ISSOCK, "socket"),
        (stat.S_ISDIR, "directory"),
    ):
        if test(mode):
            return name
    return "not a regular file"


def open_regular(path: Path, *, follow_symlinks: bool = False) -> BinaryIO:
    """``path`` opened for reading when it is a regular file; else ``NotRegularFileError``, without ever
    blocking (a FIFO is opened non-blocking, then refused) or following a symbolic link unless asked."""
    flags = os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC | (0 if follow_symlinks else os.O_NOFOLLOW)
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        if exc.errno == errno.ELOOP and not follow_symlinks:  # O_NOFOLLOW on a link
            raise NotRegularFileError(path, "symbolic link") from None
        raise
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise NotRegularFileError(path, _file_type(mode))
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def _entries(directory: Path, key: Callable[[Path], Any]) -> list[tuple[Any, Path, bool]]:
    """(key, path, is a regular file) of the entries of ``directory`` that ``key`` recognises; [] when
    unreadable. Symbolic links are not followed."""
    out = []
    try:
        with os.scandir(directory) as it:
            for entry in it:
                path = directory / entry.name
                if (k := key(path)) is None:
                    continue
                try:
                    regular = entry.is_file(follow_symlinks=False)
                except OSError:
                    regular = False
                out.append((k, path, regular))
    except OSError:
        return []
    return out


def _sorted_files(directory: Path, key: Callable[[Path], Any]) -> list[Path]:
    """Regular files of ``directory`` that ``key`` recognises (not None), in ``key`` order; [] when
    unreadable. Anything else under such a name is left out (``refused_files``)."""
    keyed = [(k, p) for k, p, regular in _entries(directory, key) if regular]
    return [p for _, p in sorted(keyed)]


def refused_files(directory: str | Path) -> list[tuple[Path, str]]:
    """Entries named like a segment of ``directory`` (or an image in its ``images/``) that are not regular
    files, with what each is (``FIFO``, ``symbolic link``...): never opened by the recorder or the readers."""
    d = Path(directory)
    out = []
    for where, key in ((d, _segment_key), (d / IMAGES_SUBDIR, _image_key)):
        for _k, path, regular in sorted(_entries(where, key), key=lambda e: e[1].name):
            if regular:
                continue
            try:
                what = _file_type(path.lstat().st_mode)
            except OSError:
                what = "unreadable"
            out.append((path, what))
    return out


def _last_number(keys: Iterable[tuple[str, int] | None], tag: str) -> int:
    """The highest file number under ``tag`` among ``keys`` (``_segment_key``/``_image_key``), 0 if none."""
    return max((k[1] for k in keys if k is not None and k[0] == tag), default=0)


def list_images(directory: str | Path) -> list[Path]:
    """Frame image files of the FDR at ``directory`` (in its ``images/``), oldest first."""
    return _sorted_files(Path(directory) / IMAGES_SUBDIR, _image_key)


def _disk_free_bytes(path: Path) -> int:
    return int(shutil.disk_usage(path).free)


def list_segments(directory: str | Path) -> list[Path]:
    """FDR segment files in ``directory``, oldest first (by start time, then sequence number)."""
    return _sorted_files(Path(directory), _segment_key)


def parse_line(raw: bytes) -> dict[str, Any] | None:
    """One segment line as a record, or None for a torn, blank or unreadable line, and for one the
    recorder never writes: longer than ``MAX_RECORD_BYTES`` or nested past what the parser follows."""
    try:
        rec = bounded_json.loads(raw, max_bytes=MAX_RECORD_BYTES, what="FDR line")
    except ValueError:
        return None
    return rec if isinstance(rec, dict) and "kind" in rec else None


def bounded_lines(fh: BinaryIO) -> Iterator[bytes]:
    """The lines of ``fh``, each held in memory up to ``MAX_RECORD_BYTES`` + 1 bytes: a longer line is
    yielded as that prefix (which ``parse_line`` refuses) and the rest of it is skipped."""
    while True:
        raw = fh.readline(MAX_RECORD_BYTES + 1)
        if not raw:
            return
        if len(raw) > MAX_RECORD_BYTES and not raw.endswith(b"\n"):
            while (rest := fh.readline(1 << 20)) and not rest.endswith(b"\n"):
                pass
        yield raw


def read_records(directory: str | Path) -> Iterator[dict[str, Any]]:
    """Every record in ``directory`` in recording order; torn or unreadable lines are skipped."""
    for seg in list_segments(directory):
        try:
            fh = open_regular(seg)
        except OSError:
            continue
        with fh:
            for raw in bounded_lines(fh):
                rec = parse_line(raw)
                if rec is not None:
                    yield rec


def read_records_newest_first(directory: str | Path) -> Iterator[dict[str, Any]]:
    """Every record in ``directory``, newest first (for "what was the last ..." questions at start-up:
    the caller stops early, so only the newest segment is usually read); torn lines are skipped."""
    for seg in reversed(list_segments(directory)):
        try:
            with open_regular(seg) as fh:
                # A segment is at most fdr.segment_bytes plus one record; a file far larger than any (not
                # the recorder's) is read from its last NEWEST_FIRST_MAX_BYTES only.
                start = max(0, fh.seek(0, os.SEEK_END) - NEWEST_FIRST_MAX_BYTES)
                fh.seek(start)
                data = fh.read()
        except OSError:
            continue
        lines = data.splitlines()
        if start > 0:
            lines = lines[1:]  # began mid-line
        for raw in reversed(lines):
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
        *,
        images_max_bytes: int = DEFAULT_IMAGES_MAX_BYTES,
        min_free_bytes: int = DEFAULT_MIN_FREE_BYTES,
        free_bytes: Callable[[Path], int] = _disk_free_bytes,
        free_check_interval_s: float = 1.0,
    ) -> None:
        """``images_max_bytes``: budget of the frame images (0: no image is kept). ``min_free_bytes``:
        the low-disk threshold (0: free space is not checked). ``free_bytes(dir)``: the file system's
        free bytes (injectable for tests)."""
        if segment_bytes <= 0 or max_bytes < segment_bytes:
            raise ValueError(
                f"FDR needs 0 < segment_bytes <= max_bytes, got segment_bytes={segment_bytes}, "
                f"max_bytes={max_bytes}"
            )
        if images_max_bytes < 0 or min_free_bytes < 0:
            raise ValueError(
                f"FDR needs images_max_bytes >= 0 and min_free_bytes >= 0, got {images_max_bytes}, "
                f"{min_free_bytes}"
            )
        self.dir = Path(dir)
        self.max_bytes = int(max_bytes)
        self.segment_bytes = int(segment_bytes)
        self.images_max_bytes = int(images_max_bytes)
        self.min_free_bytes = int(min_free_bytes)
        self._free_fn = free_bytes
        self._free_check_interval_s = float(free_check_interval_s)
        self._free_cached: int | None = None
        self._free_checked_mono = -math.inf
        self._images: dict[Path, int] = {}
        self._image_seq = 0
        self._last_image_drop_mono = -math.inf
        self._last_record_drop_mono = -math.inf
        self._last_state = FdrHealthState.OK
        self.images_written = 0
        self.images_dropped = 0
        self.images_deleted = 0
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
        #: Files named like segments or images that are not regular files, never opened (``refused_files``).
        self.refused: list[tuple[Path, str]] = []
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
                    "refused_files": [f"{path.name}: {what}" for path, what in self.refused],
                    "max_bytes": self.max_bytes,
                    "segment_bytes": self.segment_bytes,
                    "images_max_bytes": self.images_max_bytes,
                    "min_free_bytes": self.min_free_bytes,
                },
                t=self.started_unix_s,
            )

    # --- files --------------------------------------------------------------------------------------
    def _scan_existing(self) -> None:
        self.refused = refused_files(self.dir)
        for path, what in self.refused:
            _log.warning(LogEvent.FDR_FILE_REFUSED, path=str(path), what=what, reason="not a regular file")
        for seg in list_segments(self.dir):
            try:
                self._sizes[seg] = seg.stat().st_size
            except OSError:
                continue
        images = self.dir / IMAGES_SUBDIR
        with contextlib.suppress(OSError):
            for part in images.glob("*.part"):  # a crash mid-image: never a final name, reclaim it
                part.unlink()
        for img in list_images(self.dir):
            try:
                self._images[img] = img.stat().st_size
            except OSError:
                continue
        # Names must sort in recording order across runs. A run that starts in the same millisecond as
        # the last, or on a clock that reads earlier (a companion computer with no real-time clock boots
        # at its last saved time), goes on under the newest earlier tag, numbered after its files.
        tags = [k[0] for k in map(_segment_key, self._sizes) if k is not None]
        tags += [k[0] for k in map(_image_key, self._images) if k is not None]
        newest = max(tags, default="")
        if newest >= self._start_tag:
            self._start_tag = newest
            self._seg_seq = _last_number(map(_segment_key, self._sizes), newest)
            self._image_seq = _last_number(map(_image_key, self._images), newest)

    def _recover_previous(self) -> tuple[Path | None, int, bool | None]:
        """Scan the end of the newest existing segment: (that segment, torn lines in its last
        ``RECOVERY_TAIL_BYTES``, whether its last good record is ``fdr.closed``; None when it has no
        good record there). A last line without a newline is terminated (see the module docstring)."""
        segs = list_segments(self.dir)
        if not segs:
            return None, 0, None
        newest = segs[-1]
        try:
            with open_regular(newest) as fh:
                size = fh.seek(0, os.SEEK_END)
                start = max(0, size - RECOVERY_TAIL_BYTES)
                fh.seek(start)
                tail = fh.read()
            if tail and not tail.endswith(b"\n"):
                fd = os.open(newest, os.O_WRONLY | os.O_APPEND | os.O_CLOEXEC | os.O_NOFOLLOW | os.O_NONBLOCK)
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
            if path not in self._sizes and not os.path.lexists(path):
                break
        # O_EXCL: never a name that appeared since (a link or a FIFO put there would be written through)
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND | os.O_CLOEXEC, 0o644)
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

    # --- free space and images ------------------------------------------------------------------------
    def _free(self, *, force: bool = False) -> int | None:
        """Free bytes of the file system, at most every ``free_check_interval_s`` unless ``force``;
        None when the check is disabled or failed."""
        if self.min_free_bytes == 0:
            return None
        now = time.monotonic()
        if force or now - self._free_checked_mono >= self._free_check_interval_s:
            self._free_checked_mono = now
            try:
                self._free_cached = int(self._free_fn(self.dir if self.dir.exists() else self.dir.parent))
            except OSError as exc:
                self._free_cached = None
                self._error("disk_usage", exc)
        return self._free_cached

    @property
    def _record_floor(self) -> int:
        return self.min_free_bytes // RECORD_FLOOR_DIVISOR

    def _delete_oldest_image(self, why: str) -> bool:
        """Delete the oldest known image; False when there is none (or it cannot be deleted)."""
        for img in sorted(self._images, key=lambda p: _image_key(p) or ("", 0)):
            try:
                img.unlink()
            except FileNotFoundError:
                pass
            except OSError as exc:
                self._error("delete_image", exc)
                self._images.pop(img)  # do not retry it forever; it no longer counts against the budget
                continue
            self._images.pop(img)
            self.images_deleted += 1
            _log.debug(LogEvent.FDR_IMAGE_DELETED, path=str(img), why=why)
            return True
        return False

    def _make_room(self, need_bytes: int) -> bool:
        """Free space for ``need_bytes`` more by deleting the oldest images (never a record segment);
        True when the free space is then at least ``min_free_bytes`` + ``need_bytes``."""
        free = self._free(force=True)
        while free is not None and free - need_bytes < self.min_free_bytes:
            if not self._delete_oldest_image("low_free_space"):
                return False
            free = self._free(force=True)
        return True

    def _drop_record(self) -> None:
        self.records_dropped += 1
        self._last_record_drop_mono = time.monotonic()

    def _drop_image(self) -> None:
        self.images_dropped += 1
        self._last_image_drop_mono = time.monotonic()

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
            self._drop_record()
            return
        if len(line) > MAX_RECORD_BYTES:  # the readers would skip it as unreadable
            self._error("encode", ValueError(f"{kind} record of {len(line)} bytes > {MAX_RECORD_BYTES}"))
            self._drop_record()
            return
        self._write(line)

    def _write(self, line: bytes) -> None:
        free = self._free()
        if free is not None and free - len(line) < self._record_floor:
            # Images are sacrificed first; the records stop only when that is not enough.
            self._make_room(len(line))
            free = self._free(force=True)
            if free is not None and free - len(line) < self._record_floor:
                self._drop_record()
                self._error("low_free_space", OSError(errno.ENOSPC, f"{free} bytes free"))
                return
        try:
            if self._fd is not None and self._fd_size > 0 and self._fd_size + len(line) > self.segment_bytes:
                self._close_segment()
            if self._fd is None:
                self._open_segment()
                self._enforce_budget()
        except OSError as exc:
            self._close_segment()
            self._error("open", exc)
            self._drop_record()
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
            self._drop_record()
            if exc.errno == errno.ENOSPC:
                self._make_room(len(line))  # the next record may fit where an image was
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

    def images(self) -> list[Path]:
        """Frame image files of the directory (earlier runs' too), oldest first."""
        return list_images(self.dir)

    def record_frame_image(
        self, frame_seq: int, exposure_time_unix_usec: int, jpeg: bytes, *, ext: str = "jpg"
    ) -> Path | None:
        """Store one encoded frame image and write its ``pipeline.frame_image`` record; returns its path,
        or None when it was dropped (counted: low space, over budget, I/O error, closed). Never raises."""
        with self._lock:
            if self._closed or self.images_max_bytes == 0:
                self._drop_image()
                return None
            size = len(jpeg)
            if size > self.images_max_bytes:
                self._drop_image()
                return None
            free = self._free(force=True)
            if free is not None and free - size < self.min_free_bytes:
                # Low disk: reclaim the oldest images and skip this one (degraded), rather than churn
                # images on a disk that has no room for them.
                self._make_room(0)
                self._drop_image()
                return None
            while sum(self._images.values()) + size > self.images_max_bytes:
                if not self._delete_oldest_image("budget"):
                    break
            self._image_seq += 1
            if ext not in IMAGE_FORMATS.values():
                valid = sorted(IMAGE_FORMATS.values())
                raise ValueError(f"image extension must be one of {valid}, got {ext!r}")
            name = f"img-{self._start_tag}-{self._image_seq:06d}-{max(0, int(frame_seq))}.{ext}"
            path = self.dir / IMAGES_SUBDIR / name
            part = path.with_name(name + ".part")
            try:
                os.makedirs(path.parent, exist_ok=True)
                fd = os.open(part, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o644)
                try:
                    view = memoryview(jpeg)
                    written = 0
                    while written < size:
                        n = os.write(fd, view[written:])
                        if n <= 0:
                            raise OSError("short write (0 bytes)")
                        written += n
                finally:
                    os.close(fd)
                os.replace(part, path)
            except OSError as exc:
                with contextlib.suppress(OSError):
                    part.unlink(missing_ok=True)
                self._error("image", exc)
                self._drop_image()
                if exc.errno == errno.ENOSPC:
                    self._make_room(size)
                return None
            self._images[path] = size
            self.images_written += 1
            self._append(
                FdrKind.FRAME_IMAGE,
                {
                    "frame_seq": int(frame_seq),
                    "exposure_time_unix_usec": int(exposure_time_unix_usec),
                    "file": f"{IMAGES_SUBDIR}/{name}",
                    "bytes": size,
                },
            )
            return path

    def record_frame_jpeg(
        self, frame_seq: int, exposure_time_unix_usec: int, image: np.ndarray, quality: int
    ) -> Path | None:
        """Encode ``image`` (uint8 (H, W) grey or (H, W, 3) BGR) as JPEG at ``quality`` (1..100) on the
        caller's thread and store it (``record_frame_image``). Never raises: a failed encode is logged
        and counted as a dropped image."""
        return self.record_frame_encoded(frame_seq, exposure_time_unix_usec, image, "jpeg", quality=quality)

    def record_frame_encoded(
        self, frame_seq: int, exposure_time_unix_usec: int, image: np.ndarray, fmt: str, *, quality: int = 80
    ) -> Path | None:
        """Encode ``image`` (uint8 (H, W) grey or (H, W, 3) BGR) as ``fmt`` (``jpeg`` at ``quality``, or
        lossless ``png``) on the caller's thread and store it (``record_frame_image``). Never raises: a
        failed encode is logged and counted as a dropped image."""
        import cv2  # only where images are on: OpenCV takes a while to import

        try:
            ext = IMAGE_FORMATS[fmt]
            params = [int(cv2.IMWRITE_JPEG_QUALITY), int(quality)] if fmt == "jpeg" else []
            ok, buf = cv2.imencode(f".{ext}", image, params)
            if not ok:
                raise ValueError("cv2.imencode returned False")
        except (cv2.error, ValueError, TypeError, KeyError) as exc:
            with self._lock:
                self._error(f"{fmt}_encode", exc)
                self._drop_image()
            return None
        return self.record_frame_image(frame_seq, exposure_time_unix_usec, buf.tobytes(), ext=ext)

    def health(self) -> FdrHealth:
        """The recorder's state now (see ``FdrHealth``); a change of state is logged."""
        with self._lock:
            free = self._free()
            now = time.monotonic()
            if now - self._last_record_drop_mono < HEALTH_HOLD_S or (
                free is not None and free < self._record_floor
            ):
                state = FdrHealthState.FAILING
            elif now - self._last_image_drop_mono < HEALTH_HOLD_S or (
                free is not None and free < self.min_free_bytes
            ):
                state = FdrHealthState.DEGRADED
            else:
                state = FdrHealthState.OK
            snapshot = FdrHealth(
                state=state,
                record_bytes=sum(self._sizes.values()),
                image_bytes=sum(self._images.values()),
                free_bytes=free,
                records_written=self.records_written,
                records_dropped=self.records_dropped,
                images_written=self.images_written,
                images_dropped=self.images_dropped,
                images_deleted=self.images_deleted,
                write_errors=self.errors,
            )
            if state is not self._last_state:
                old, self._last_state = self._last_state, state
                log = _log.info if state is FdrHealthState.OK else _log.warning
                log(
                    LogEvent.FDR_HEALTH_CHANGED,
                    old=old.value,
                    new=state.value,
                    free_bytes=free,
                    records_dropped=self.records_dropped,
                    images_dropped=self.images_dropped,
                )
            return snapshot

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
                    "images_written": self.images_written,
                    "images_dropped": self.images_dropped,
                    "images_deleted": self.images_deleted,
                },
            )
            self._closed = True
            self._close_segment()

    def __enter__(self) -> FlightDataRecorder:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

