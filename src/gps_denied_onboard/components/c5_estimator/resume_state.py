"""C5 resume state file: the last estimate sent as a 3D fix, kept apart from the flight data recorder (F8).

The recorder stops recording on a nearly full disk (``fdr.min_free_bytes``) and its records may be
deleted, so a restart in flight could find nothing to resume from and had to search the whole map. This
file keeps one small JSON object (position, 1-sigma, time, provenance, and a CRC-32 of the rest),
rewritten in place at most once a second by the daemon and read by ``prior`` at start beside the FDR.
Path: ``init.resume_state_path``, by default ``<fdr.dir>/resume_state.json`` (the one directory the
shipped unit may write; the recorder ignores files it did not name; the writer creates the directory when
the recorder has not).

Writes are atomic: a temporary file in the same directory, fsync, rename over the old one, fsync of the
directory. A kill at any point leaves the old file or the new one, never a torn one. The write does not
obey the recorder's low-disk policy: it needs a few hundred bytes, and a failure is logged once per
outage and counted, never raised.

Reading refuses, in one logged line, and treats as absent: a file larger than ``MAX_BYTES``, not a regular
file, not UTF-8 JSON (nested too deeply included), another version (version 1 had no checksum), a
checksum that does not match the fields (``crc32``: CRC-32 of the other fields as canonical JSON, sorted
keys, no spaces: a bit flipped on the card, an edit by hand), a missing or mistyped field, a position off
the Earth, a sigma not finite and positive, a time in the future.
"""

from __future__ import annotations

import json
import math
import os
import stat
import zlib
from pathlib import Path
from typing import Any, Final

import structlog

from gps_denied_onboard.components.c5_estimator.prior import ResumeState
from gps_denied_onboard.constants import RESUME_STATE_FILENAME, LogEvent

_log = structlog.get_logger(__name__)

#: Format version written and accepted (2: with ``crc32``).
VERSION: Final[int] = 2
#: Larger files are refused unread (the file written is about 200 bytes).
MAX_BYTES: Final[int] = 4096
#: A state written this far ahead of the reader's clock is refused (clocks of two boots may differ a
#: little; a state from the future cannot be resumed from honestly), s.
MAX_FUTURE_S: Final[float] = 5.0


class ResumeStateError(ValueError):
    """The state file is refused: ``path`` and the reason in the message."""

    def __init__(self, path: Path, reason: str) -> None:
        super().__init__(f"resume state {path}: {reason}")
        self.path = path
        self.reason = reason


def default_path(fdr_dir: str | Path) -> Path:
    """Where the state file lives when ``init.resume_state_path`` is null."""
    return Path(fdr_dir) / RESUME_STATE_FILENAME


def checksum(fields: dict[str, Any]) -> int:
    """CRC-32 of ``fields`` without ``crc32``, as canonical JSON (sorted keys, no spaces, UTF-8)."""
    body = {k: v for k, v in fields.items() if k != "crc32"}
    return zlib.crc32(json.dumps(body, sort_keys=True, separators=(",", ":")).encode())


def _parse(path: Path, data: bytes, now_unix_s: float) -> ResumeState:
    try:
        obj = json.loads(data)
    except RecursionError:
        raise ResumeStateError(path, "nested too deeply, expected one flat JSON object") from None
    except (UnicodeDecodeError, ValueError) as exc:
        raise ResumeStateError(path, f"not JSON ({exc})") from None
    if not isinstance(obj, dict):
        raise ResumeStateError(path, f"expected a JSON object, got {type(obj).__name__}")
    if obj.get("version") != VERSION:
        raise ResumeStateError(path, f"version {obj.get('version')!r}, expected {VERSION}")
    crc = obj.get("crc32")
    if isinstance(crc, bool) or not isinstance(crc, int):
        raise ResumeStateError(path, f"crc32 is {crc!r}, expected an integer")
    if crc != checksum(obj):
        raise ResumeStateError(path, f"checksum mismatch (crc32 {crc}, the fields give {checksum(obj)})")

    def number(key: str) -> float:
        value = obj.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ResumeStateError(path, f"{key} is {value!r}, expected a finite number")
        return float(value)

    lat, lon, sigma = number("lat_deg"), number("lon_deg"), number("horiz_sigma_m")
    time_usec = obj.get("time_unix_usec")
    if isinstance(time_usec, bool) or not isinstance(time_usec, int) or time_usec <= 0:
        raise ResumeStateError(path, f"time_unix_usec is {time_usec!r}, expected a positive integer")
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise ResumeStateError(path, f"position ({lat}, {lon}) is not on the Earth")
    if sigma <= 0.0:
        raise ResumeStateError(path, f"horiz_sigma_m is {sigma}, expected > 0")
    if time_usec / 1e6 > now_unix_s + MAX_FUTURE_S:
        raise ResumeStateError(path, f"time_unix_usec {time_usec} is in the future")
    return ResumeState(lat, lon, sigma, time_usec)


def read_resume_state(path: str | Path, now_unix_s: float) -> ResumeState | None:
    """The state in ``path``, or None when there is none or it is refused (logged in one line)."""
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except FileNotFoundError:
        return None
    except OSError as exc:
        _log.warning(LogEvent.RESUME_STATE_REFUSED, path=str(p), reason=f"cannot open: {exc.strerror}")
        return None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise ResumeStateError(p, "not a regular file")
        data = os.read(fd, MAX_BYTES + 1)
        if len(data) > MAX_BYTES:
            raise ResumeStateError(p, f"larger than {MAX_BYTES} bytes")
        return _parse(p, data, now_unix_s)
    except ResumeStateError as exc:
        _log.warning(LogEvent.RESUME_STATE_REFUSED, path=str(p), reason=exc.reason)
        return None
    except OSError as exc:
        _log.warning(LogEvent.RESUME_STATE_REFUSED, path=str(p), reason=f"cannot read: {exc.strerror}")
        return None
    finally:
        os.close(fd)


class ResumeStateFile:
    """Writes the state file (see the module docstring); used from one thread at a time."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.writes = 0
        self.failures = 0
        self._failing = False

    def write(self, state: ResumeState, *, provenance: str, written_unix_s: float) -> bool:
        """Replace the file with ``state``; returns False (logged once per run of failures) on an error."""
        body: dict[str, Any] = {
            "version": VERSION,
            "lat_deg": state.lat_deg,
            "lon_deg": state.lon_deg,
            "horiz_sigma_m": state.horiz_sigma_m,
            "time_unix_usec": state.time_unix_usec,
            "provenance": provenance,
            "written_unix_s": written_unix_s,
        }
        body["crc32"] = checksum(body)
        data = json.dumps(body).encode()
        tmp = self.path.with_name(f".{self.path.name}.tmp")
        try:
            # The recorder creates its directory only when it records: on a full disk it never may.
            self.path.parent.mkdir(mode=0o750, parents=True, exist_ok=True)
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, 0o640)
            try:
                os.write(fd, data)
                os.fsync(fd)
            finally:
                os.close(fd)
            os.replace(tmp, self.path)
            dir_fd = os.open(self.path.parent, os.O_RDONLY | os.O_DIRECTORY)
            try:
                os.fsync(dir_fd)
            finally:
                os.close(dir_fd)
        except OSError as exc:
            self.failures += 1
            if not self._failing:
                self._failing = True
                _log.warning(LogEvent.RESUME_STATE_WRITE_FAILED, path=str(self.path), error=str(exc))
            return False
        self.writes += 1
        self._failing = False
        return True
