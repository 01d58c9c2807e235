"""C11: download the XYZ tiles of an area from a tile server into an ``{z}/{x}/{y}.{ext}`` directory.

Politeness and robustness rules (tile servers ban clients that hammer them):

- one token bucket shared by all workers caps the request rate (retries included);
- 429 / 5xx / 408 / timeouts / connection errors / non-image bodies are retried with exponential
  backoff and jitter; a ``Retry-After`` header is honoured exactly and pauses *every* worker, since a
  rate limit is per client, not per tile;
- 404 / 410 / 204 mean "the server has no such tile": a gap, recorded, not fatal;
- any other 4xx (401, 403, 400, ...) is a configuration problem (key, referer policy, template) that
  every further request would repeat: everything stops with a ``TileDownloadError``;
- a body is written only after it proved to be a complete, decodable PNG/JPEG/WebP, via a temporary
  file and ``os.replace``, so an interrupted run never leaves a torn tile; a re-run skips every tile
  already present and complete (resume).

On disk the y index is always the XYZ one (row 0 at the north), whatever the server's scheme: a
``{-y}`` placeholder in the template asks the server for the TMS row ``2**z - 1 - y``.

HTTP is done with ``urllib`` from the standard library: at the request rates a public server allows
(~10/s) connection reuse would not change the run time, and urllib brings proxies (``HTTPS_PROXY``),
redirects and TLS verification with no extra dependency.
"""

from __future__ import annotations

import email.utils
import http.client
import math
import os
import random
import re
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import structlog
from tqdm import tqdm

from gps_denied_onboard import __version__
from gps_denied_onboard.components.c6_tiles.georef import WebMercatorGrid
from gps_denied_onboard.components.c10_cache_build.geotiff import tile_range_for_bbox
from gps_denied_onboard.constants import LogEvent

_log = structlog.get_logger(__name__)

#: Extensions a tile may have on disk, in the order a resume looks for them.
TILE_EXTENSIONS: tuple[str, ...] = ("png", "jpg", "jpeg", "webp")
#: Statuses meaning "no tile here" (some servers answer 204 for empty ocean tiles).
_GAP_STATUSES = frozenset({204, 404, 410})
#: Transient statuses worth retrying (besides every 5xx).
_RETRY_STATUSES = frozenset({408, 425, 429})
#: A tile bigger than this is not a map tile (runaway or wrong URL); the read stops there.
_MAX_BODY_BYTES = 32 << 20
#: Temporary files of an interrupted write end with this (never matched by the XYZ reader).
PART_SUFFIX = ".part"
_PLACEHOLDER = re.compile(r"\{([^{}]*)\}")
_KNOWN_PLACEHOLDERS = frozenset({"z", "x", "y", "-y", "s"})
#: Query-parameter names whose values are treated as secrets and never recorded or logged.
_SECRET_PARAM = re.compile(
    r"key|token|secret|sig|password|passwd|pwd|auth|credential|session|access|client_id", re.IGNORECASE
)
REDACTED = "REDACTED"
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_PNG_TRAILER = b"IEND\xaeB`\x82"
_JPEG_MAGIC = b"\xff\xd8\xff"
_JPEG_EOI = b"\xff\xd9"


class TileDownloadError(RuntimeError):
    """A download cannot go on: the server refuses us (401/403/...), the template or area is invalid,
    or the server asks to wait longer than allowed. ``url`` is redacted (no secrets); ``status`` is
    the HTTP status when there was one."""

    def __init__(self, message: str, *, url: str | None = None, status: int | None = None) -> None:
        context = ", ".join(
            part for part in (f"url {url}" if url else "", f"HTTP {status}" if status else "") if part
        )
        super().__init__(f"{message} ({context})" if context else message)
        self.message = message
        self.url = url
        self.status = status


class TileFailure(NamedTuple):
    """A tile that was not downloaded: XYZ ``(z, x, y)`` and why."""

    z: int
    x: int
    y: int
    reason: str


@dataclass(frozen=True)
class DownloadSummary:
    """Outcome of one ``TileDownloader.download`` run.

    ``requested`` tiles cover the bbox; each was ``downloaded``, ``skipped_existing`` (already on disk
    and complete) or is in ``failed``. ``gaps`` is the subset of ``failed`` that the server reported
    as absent (204/404/410): map gaps, not errors. ``requests_sent`` counts HTTP attempts, retries
    included.
    """

    requested: int
    downloaded: int
    skipped_existing: int
    failed: tuple[TileFailure, ...]
    gaps: tuple[TileFailure, ...]
    requests_sent: int
    bytes_downloaded: int
    seconds: float

    @property
    def errors(self) -> tuple[TileFailure, ...]:
        """Failures other than gaps (retries exhausted, bad bodies): a re-run may fetch them."""
        gaps = set(self.gaps)
        return tuple(f for f in self.failed if f not in gaps)


def redact_url(url: str) -> str:
    """``url`` with the values of secret-looking query parameters and any user:password replaced
    by ``REDACTED``, so it can be logged and recorded in a manifest."""
    scheme_sep = url.find("://")
    if scheme_sep >= 0:
        authority_start = scheme_sep + 3
        authority_end = len(url)
        for sep in "/?#":
            pos = url.find(sep, authority_start)
            if pos >= 0:
                authority_end = min(authority_end, pos)
        at = url.rfind("@", authority_start, authority_end)
        if at >= 0:
            url = url[:authority_start] + REDACTED + url[at:]
    base, sep, query = url.partition("?")
    if not sep:
        return url
    query, hash_sep, fragment = query.partition("#")
    parts = []
    for item in query.split("&"):
        name, eq, value = item.partition("=")
        # A value that is only a placeholder (e.g. "{s}") is not a secret.
        if eq and _SECRET_PARAM.search(name) and value and not _PLACEHOLDER.fullmatch(value):
            value = REDACTED
        parts.append(f"{name}{eq}{value}")
    return f"{base}?{'&'.join(parts)}{hash_sep}{fragment}"


def sniff_image(data: bytes) -> str | None:
    """File extension (``png``, ``jpg``, ``webp``) of an image from its magic bytes, else None."""
    if data.startswith(_PNG_MAGIC):
        return "png"
    if data.startswith(_JPEG_MAGIC):
        return "jpg"
    if len(data) >= 12 and data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "webp"
    return None


def image_looks_complete(head: bytes, tail: bytes, size: int) -> bool:
    """Cheap completeness check of an image file from its first/last 16 bytes and its size: the
    magic bytes and the format's end marker (PNG IEND, JPEG EOI, WebP RIFF length)."""
    kind = sniff_image(head)
    if kind == "png":
        return tail.endswith(_PNG_TRAILER)
    if kind == "jpg":
        # Some encoders pad after EOI with zero bytes.
        return tail.rstrip(b"\x00").endswith(_JPEG_EOI)
    if kind == "webp":
        return int.from_bytes(head[4:8], "little") + 8 <= size
    return False


def tile_file_is_complete(path: Path) -> bool:
    """True when ``path`` is a complete PNG/JPEG/WebP (see ``image_looks_complete``)."""
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(16)
            fh.seek(max(0, size - 16))
            tail = fh.read(16)
    except OSError:
        return False
    return image_looks_complete(head, tail, size)


class _BadBody(ValueError):
    """The server answered 200 with something that is not a complete image."""


def _check_image_body(body: bytes, content_type: str) -> str:
    """Extension of a valid image body; raise _BadBody naming what arrived instead.

    The magic bytes decide the extension, not Content-Type: servers often mislabel tiles
    (``application/octet-stream``), and an HTML error page is caught whatever its label.
    """
    kind = sniff_image(body)
    if kind is None:
        raise _BadBody(
            f"body is not a PNG/JPEG/WebP image (Content-Type {content_type!r}, {len(body)} bytes, "
            f"starts {body[:24]!r})"
        )
    if not image_looks_complete(body[:16], body[-16:], len(body)):
        raise _BadBody(f"{kind} body is truncated ({len(body)} bytes)")
    decoded = cv2.imdecode(np.frombuffer(body, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if decoded is None or decoded.size == 0:
        raise _BadBody(f"{kind} body cannot be decoded ({len(body)} bytes)")
    return kind


def _parse_retry_after_s(value: str | None) -> float | None:
    """Seconds from a Retry-After header (delta-seconds or HTTP-date), None when absent/unparseable."""
    if not value:
        return None
    value = value.strip()
    if value.isdigit():
        return float(value)
    try:
        when = email.utils.parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    if when is None:
        return None
    return max(0.0, when.timestamp() - time.time())


class _TokenBucket:
    """Token bucket of capacity ``burst`` refilled at ``rate_per_s``, shared by all workers.

    Implemented as its equivalent virtual-scheduling form (GCRA): each acquire reserves the next free
    slot under a lock and sleeps outside it, so waiting workers are served in order. ``pause`` (a
    429/503 Retry-After) holds every later slot until the pause ends.
    """

    def __init__(self, rate_per_s: float | None, burst: int = 1) -> None:
        self._interval_s = 0.0 if rate_per_s is None else 1.0 / rate_per_s
        self._tolerance_s = (burst - 1) * self._interval_s
        self._next_s = -math.inf
        self._paused_until_s = -math.inf
        self._lock = threading.Lock()

    def acquire(self, stop: threading.Event) -> bool:
        """Wait for a token; False when ``stop`` was set meanwhile."""
        with self._lock:
            now = time.monotonic()
            slot = max(self._next_s, now - self._tolerance_s, self._paused_until_s)
            self._next_s = slot + self._interval_s
        delay = slot - now
        if delay > 0:
            return not stop.wait(delay)
        return not stop.is_set()

    def pause(self, seconds: float) -> None:
        """No token is handed out for ``seconds`` from now."""
        with self._lock:
            self._paused_until_s = max(self._paused_until_s, time.monotonic() + seconds)


class _Outcome(NamedTuple):
    """What one worker did with one tile (``kind``: downloaded, gap, failed, cancelled)."""

    kind: str
    reason: str | None
    requests: int
    bytes: int


class TileDownloader:
    """Downloads the tiles of an area from ``url_template`` (placeholders ``{z}``, ``{x}``, ``{y}``;
    optional ``{-y}`` for TMS servers and ``{s}`` for a subdomain from ``subdomains``).

    ``concurrency`` worker threads share one rate limit of ``rate_limit_per_s`` requests (None: no
    limit, only for servers you run). A transient failure is retried up to ``max_retries`` times
    after ``backoff_base_s * 2**attempt`` seconds (capped at ``backoff_max_s``, with jitter); a
    ``Retry-After`` above ``retry_after_max_s`` stops the run (quota exhausted: resume later).
    ``timeout_s`` bounds every socket operation. ``headers`` are added to every request (e.g. a
    Referer or an Authorization the server requires; never logged). One ``download`` at a time.
    """

    def __init__(
        self,
        url_template: str,
        *,
        concurrency: int = 4,
        rate_limit_per_s: float | None = 10.0,
        max_retries: int = 5,
        backoff_base_s: float = 0.5,
        backoff_max_s: float = 30.0,
        retry_after_max_s: float = 300.0,
        timeout_s: float = 20.0,
        user_agent: str = f"gps-denied-onboard/{__version__}",
        headers: Mapping[str, str] | None = None,
        subdomains: Sequence[str] = ("a", "b", "c"),
    ) -> None:
        self._template = url_template
        self._redacted_template = redact_url(url_template)
        _check_template(url_template, self._redacted_template, subdomains)
        if not (1 <= concurrency <= 64):
            raise TileDownloadError(f"concurrency {concurrency} out of range, expected 1..64")
        if rate_limit_per_s is not None and not (math.isfinite(rate_limit_per_s) and rate_limit_per_s > 0):
            raise TileDownloadError(f"rate_limit_per_s must be > 0 or None, got {rate_limit_per_s}")
        if max_retries < 0 or backoff_base_s < 0 or backoff_max_s < 0 or retry_after_max_s < 0:
            raise TileDownloadError("max_retries and the backoff limits must be >= 0")
        if not timeout_s > 0:
            raise TileDownloadError(f"timeout_s must be > 0, got {timeout_s}")
        self._concurrency = concurrency
        self._rate_limit_per_s = rate_limit_per_s
        self._max_retries = max_retries
        self._backoff_base_s = backoff_base_s
        self._backoff_max_s = backoff_max_s
        self._retry_after_max_s = retry_after_max_s
        self._timeout_s = timeout_s
        self._headers = {"User-Agent": user_agent, "Accept": "image/png,image/jpeg,image/webp,image/*"}
        self._headers.update(headers or {})
        self._subdomains = tuple(subdomains)
        self._opener = urllib.request.build_opener()
        # Per-run state, set by download().
        self._stop = threading.Event()
        self._bucket = _TokenBucket(rate_limit_per_s)

    @property
    def redacted_template(self) -> str:
        """The URL template with secrets replaced by ``REDACTED`` (safe to log and record)."""
        return self._redacted_template

    def tile_url(self, z: int, x: int, y: int) -> str:
        """The URL of XYZ tile ``(z, x, y)`` (y from the north)."""
        values = {"z": str(z), "x": str(x), "y": str(y), "-y": str((1 << z) - 1 - y)}
        if self._subdomains:
            values["s"] = self._subdomains[(x + y) % len(self._subdomains)]
        return _PLACEHOLDER.sub(lambda m: values[m.group(1)], self._template)

    def download(
        self,
        zoom: int,
        bbox_lonlat: tuple[float, float, float, float],
        dest_dir: Path,
        progress: bool = True,
        *,
        max_tiles: int = 200_000,
    ) -> DownloadSummary:
        """Fetch every tile at ``zoom`` covering ``bbox_lonlat`` ``(west, south, east, north)`` degrees
        into ``dest_dir/{z}/{x}/{y}.{ext}``, skipping tiles already there and complete.

        Raises TileDownloadError for a bad zoom/bbox, more than ``max_tiles`` tiles (a zoom typo would
        otherwise ask a server for millions), a fatal HTTP status (401/403/other 4xx), a Retry-After
        beyond ``retry_after_max_s``, or an I/O error in ``dest_dir``. Gaps and exhausted retries do
        not raise: they are in the summary's ``failed``.
        """
        t_start = time.monotonic()
        dest_dir = Path(dest_dir)
        tiles = self._tiles(zoom, bbox_lonlat, max_tiles)
        existing = _complete_tiles_on_disk(dest_dir, zoom, {x for _, x, _ in tiles})
        todo = [t for t in tiles if (t[1], t[2]) not in existing]
        self._stop = threading.Event()
        self._bucket = _TokenBucket(self._rate_limit_per_s)
        _log.info(
            LogEvent.TILE_DOWNLOAD_STARTED,
            url_template=self._redacted_template,
            zoom=zoom,
            bbox_lonlat=list(bbox_lonlat),
            requested=len(tiles),
            already_present=len(tiles) - len(todo),
            dest_dir=str(dest_dir),
        )
        downloaded = requests = n_bytes = 0
        failed: list[TileFailure] = []
        gaps: list[TileFailure] = []
        show = progress and sys.stderr.isatty()
        executor = ThreadPoolExecutor(max_workers=self._concurrency, thread_name_prefix="c11-download")
        try:
            with tqdm(
                total=len(tiles),
                initial=len(tiles) - len(todo),
                unit="tile",
                desc=f"download z{zoom}",
                disable=not show,
            ) as bar:
                tile_of = {executor.submit(self._fetch_tile, dest_dir, *tile): tile for tile in todo}
                for future in as_completed(tile_of):
                    # A fatal TileDownloadError re-raises here; the handlers below stop the other workers.
                    outcome = future.result()
                    requests += outcome.requests
                    n_bytes += outcome.bytes
                    z, x, y = tile_of[future]
                    if outcome.kind == "downloaded":
                        downloaded += 1
                    elif outcome.kind in {"gap", "failed"}:
                        failure = TileFailure(z, x, y, outcome.reason or outcome.kind)
                        failed.append(failure)
                        if outcome.kind == "gap":
                            gaps.append(failure)
                        bar.set_postfix(failed=len(failed), refresh=False)
                    bar.update(1)
        except BaseException as exc:
            # Whatever ends the run early (fatal status, Ctrl-C) stops the workers and their sleeps.
            self._stop.set()
            _log.error(
                LogEvent.TILE_DOWNLOAD_FATAL,
                url_template=self._redacted_template,
                error=str(exc) or type(exc).__name__,
                downloaded=downloaded,
            )
            raise
        finally:
            self._stop.set()
            executor.shutdown(wait=True, cancel_futures=True)
        failed.sort()
        gaps.sort()
        summary = DownloadSummary(
            requested=len(tiles),
            downloaded=downloaded,
            skipped_existing=len(tiles) - len(todo),
            failed=tuple(failed),
            gaps=tuple(gaps),
            requests_sent=requests,
            bytes_downloaded=n_bytes,
            seconds=time.monotonic() - t_start,
        )
        _log.info(
            LogEvent.TILE_DOWNLOAD_DONE,
            url_template=self._redacted_template,
            zoom=zoom,
            requested=summary.requested,
            downloaded=summary.downloaded,
            skipped_existing=summary.skipped_existing,
            gaps=len(summary.gaps),
            errors=len(summary.errors),
            requests_sent=summary.requests_sent,
            seconds=round(summary.seconds, 3),
        )
        return summary

    # --- internals ---------------------------------------------------------------------------------
    def _tiles(
        self, zoom: int, bbox_lonlat: tuple[float, float, float, float], max_tiles: int
    ) -> list[tuple[int, int, int]]:
        """XYZ tiles covering the bbox, row-major from the north-west."""
        if not (0 <= int(zoom) <= 24):
            raise TileDownloadError(f"zoom {zoom} out of range, expected 0..24")
        if (
            len(bbox_lonlat) != 4
            or not all(math.isfinite(v) for v in bbox_lonlat)
            or not (bbox_lonlat[0] < bbox_lonlat[2] and bbox_lonlat[1] < bbox_lonlat[3])
        ):
            raise TileDownloadError(
                f"bbox_lonlat must be 4 finite numbers (W, S, E, N) with W < E and S < N, got {bbox_lonlat!r}"
            )
        tr = tile_range_for_bbox(WebMercatorGrid(int(zoom)), tuple(bbox_lonlat))  # type: ignore[arg-type]
        count = tr.n_rows * tr.n_cols
        if count > max_tiles:
            raise TileDownloadError(
                f"bbox at zoom {zoom} needs {count} tiles, more than max_tiles {max_tiles} "
                "(zoom too high or bbox too large?)",
                url=self._redacted_template,
            )
        return [(int(zoom), x, y) for y in range(tr.y0, tr.y1 + 1) for x in range(tr.x0, tr.x1 + 1)]

    def _backoff_s(self, attempt: int) -> float:
        """Exponential backoff with "equal jitter": half fixed, half random, so workers spread out."""
        cap = min(self._backoff_max_s, self._backoff_base_s * (2.0**attempt))
        return cap / 2.0 + random.uniform(0.0, cap / 2.0)

    def _fetch_tile(self, dest_dir: Path, z: int, x: int, y: int) -> _Outcome:
        """Download one tile with retries; runs in a worker thread. A fatal error stops every worker
        at once (before the main thread even sees it), so no further request goes out."""
        try:
            return self._fetch_tile_with_retries(dest_dir, z, x, y)
        except BaseException:
            self._stop.set()
            raise

    def _fetch_tile_with_retries(self, dest_dir: Path, z: int, x: int, y: int) -> _Outcome:
        url = self.tile_url(z, x, y)
        safe_url = redact_url(url)
        reason = "not attempted"
        requests = n_bytes = 0
        for attempt in range(self._max_retries + 1):
            if not self._bucket.acquire(self._stop):
                return _Outcome("cancelled", None, requests, n_bytes)
            requests += 1
            retry_after_s: float | None = None
            status: int | None = None
            try:
                status, content_type, retry_after, body = self._get(url)
            except TimeoutError as exc:
                reason = f"timeout after {self._timeout_s:g} s ({exc})"
            except (urllib.error.URLError, http.client.HTTPException, ConnectionError, OSError) as exc:
                reason = f"connection error: {getattr(exc, 'reason', exc)}"
            else:
                n_bytes += len(body)
                if status in _GAP_STATUSES:
                    reason = f"HTTP {status}: tile not on the server (map gap)"
                    _log.info(LogEvent.TILE_DOWNLOAD_TILE_MISSING, url=safe_url, status=status)
                    return _Outcome("gap", reason, requests, n_bytes)
                if 200 <= status < 300:
                    try:
                        ext = _check_image_body(body, content_type)
                    except _BadBody as exc:
                        reason = str(exc)
                    else:
                        _write_tile(dest_dir, z, x, y, ext, body)
                        return _Outcome("downloaded", None, requests, n_bytes)
                elif status in _RETRY_STATUSES or status >= 500:
                    reason = f"HTTP {status}"
                    retry_after_s = _parse_retry_after_s(retry_after)
                else:
                    raise TileDownloadError(
                        f"tile server refused the request: HTTP {status} "
                        f"{http.client.responses.get(status, '')}; expected 200 with a PNG/JPEG/WebP tile. "
                        "Check the URL template, the API key / access rights and the server's usage "
                        "policy (User-Agent, Referer); re-run resumes",
                        url=safe_url,
                        status=status,
                    )
            if attempt == self._max_retries:
                break
            if retry_after_s is not None:
                if retry_after_s > self._retry_after_max_s:
                    raise TileDownloadError(
                        f"server asks to wait {retry_after_s:.0f} s (Retry-After), more than "
                        f"retry_after_max_s {self._retry_after_max_s:g} s (quota exhausted?); "
                        "re-run later to resume",
                        url=safe_url,
                        status=status,
                    )
                # The limit is per client: every worker waits, not only this one.
                self._bucket.pause(retry_after_s)
                _log.warning(
                    LogEvent.TILE_DOWNLOAD_RATE_LIMITED, url=safe_url, reason=reason, wait_s=retry_after_s
                )
                continue
            delay_s = self._backoff_s(attempt)
            _log.warning(
                LogEvent.TILE_DOWNLOAD_RETRY, url=safe_url, reason=reason, attempt=attempt + 1, wait_s=delay_s
            )
            if self._stop.wait(delay_s):
                return _Outcome("cancelled", None, requests, n_bytes)
        reason = f"gave up after {requests} attempts: {reason}"
        _log.warning(LogEvent.TILE_DOWNLOAD_TILE_FAILED, url=safe_url, reason=reason)
        return _Outcome("failed", reason, requests, n_bytes)

    def _get(self, url: str) -> tuple[int, str, str | None, bytes]:
        """(status, Content-Type, Retry-After, body) of a GET; HTTP error statuses are returned, not
        raised; network errors raise."""
        request = urllib.request.Request(url, headers=self._headers)
        try:
            response = self._opener.open(request, timeout=self._timeout_s)
        except urllib.error.HTTPError as exc:
            with exc:
                return exc.code, exc.headers.get("Content-Type", ""), exc.headers.get("Retry-After"), b""
        with response:
            body = response.read(_MAX_BODY_BYTES + 1)
            if len(body) > _MAX_BODY_BYTES:
                raise ConnectionError(f"body larger than {_MAX_BODY_BYTES} bytes, not a map tile")
            return (
                response.status,
                response.headers.get("Content-Type", ""),
                response.headers.get("Retry-After"),
                body,
            )


def _check_template(template: str, redacted: str, subdomains: Sequence[str]) -> None:
    if not template.startswith(("http://", "https://")):
        raise TileDownloadError("URL template must start with http:// or https://", url=redacted)
    names = set(_PLACEHOLDER.findall(template))
    unknown = names - _KNOWN_PLACEHOLDERS
    if unknown:
        raise TileDownloadError(
            f"URL template has unknown placeholders {sorted(unknown)}; expected {{z}} {{x}} {{y}} "
            "and optionally {-y} (TMS) and {s} (subdomain)",
            url=redacted,
        )
    if not ({"z", "x"} <= names and names & {"y", "-y"}):
        raise TileDownloadError("URL template needs {z}, {x} and {y} (or {-y})", url=redacted)
    if "s" in names and not subdomains:
        raise TileDownloadError("URL template has {s} but no subdomains were given", url=redacted)


def _complete_tiles_on_disk(dest_dir: Path, zoom: int, xs: set[int]) -> set[tuple[int, int]]:
    """(x, y) of the complete tiles already in ``dest_dir/zoom``; removes leftover partial writes."""
    found: set[tuple[int, int]] = set()
    for x in xs:
        x_dir = dest_dir / str(zoom) / str(x)
        try:
            names = os.listdir(x_dir)
        except FileNotFoundError:
            continue
        except OSError as exc:
            raise TileDownloadError(f"cannot list the download directory: {exc}", url=str(x_dir)) from exc
        for name in names:
            if name.endswith(PART_SUFFIX):
                # A write interrupted by a kill: never complete, safe to drop.
                (x_dir / name).unlink(missing_ok=True)
                continue
            stem, _, ext = name.partition(".")
            if stem.isdigit() and ext.lower() in TILE_EXTENSIONS and tile_file_is_complete(x_dir / name):
                found.add((x, int(stem)))
    return found


def _write_tile(dest_dir: Path, z: int, x: int, y: int, ext: str, body: bytes) -> None:
    """Write a tile atomically (temp file, fsync, os.replace) and drop copies with another extension."""
    x_dir = dest_dir / str(z) / str(x)
    path = x_dir / f"{y}.{ext}"
    try:
        x_dir.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=x_dir, prefix=f".{y}.", suffix=PART_SUFFIX)
        try:
            with os.fdopen(fd, "wb") as fh:
                fh.write(body)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        # A stale or incomplete copy in another format would make the tile ambiguous for the reader.
        for other in TILE_EXTENSIONS:
            if other != ext:
                (x_dir / f"{y}.{other}").unlink(missing_ok=True)
    except OSError as exc:
        raise TileDownloadError(f"cannot write tile {z}/{x}/{y}: {exc}", url=str(path)) from exc
