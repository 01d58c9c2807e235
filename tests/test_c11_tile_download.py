"""C11 tile download against a real HTTP tile server on 127.0.0.1 serving PNG tiles cut in the test."""

from __future__ import annotations

import threading
import time
from collections import Counter, defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import cv2
import numpy as np
import pytest

from gps_denied_onboard.components.c6_tiles import TileStore, WebMercatorGrid
from gps_denied_onboard.components.c10_cache_build import CacheBuildError, build_cache
from gps_denied_onboard.components.c11_tile_download import (
    TileDownloader,
    TileDownloadError,
    redact_url,
)

ZOOM = 12
X0, Y0 = 2200, 1400
TS = 256
#: Fast settings for tests: no rate limit, millisecond backoff.
FAST = {"rate_limit_per_s": None, "backoff_base_s": 0.01, "backoff_max_s": 0.05, "timeout_s": 5.0}


@dataclass
class _Reply:
    """One scripted answer: HTTP status, headers, body; ``drop`` closes the socket without a reply;
    ``delay_s`` sleeps first (a slow server)."""

    status: int = 200
    headers: dict[str, str] = field(default_factory=dict)
    body: bytes = b""
    drop: bool = False
    delay_s: float = 0.0


class _TileServer:
    """Serves ``/tiles/{z}/{x}/{y}.png`` (and ``/tms/{z}/{x}/{-y}.png``) from PNG bytes, counting hits.

    ``script[(x, y)]`` replies are used first, in order; ``always[(x, y)]`` replaces the tile for good;
    after ``forbid_after`` tiles served, every request gets 403 (a server that cuts us off).
    """

    def __init__(self, image: np.ndarray) -> None:
        self.image = image
        self.tiles: dict[tuple[int, int], bytes] = {}
        for row in range(image.shape[0] // TS):
            for col in range(image.shape[1] // TS):
                tile = image[row * TS : (row + 1) * TS, col * TS : (col + 1) * TS]
                self.tiles[(X0 + col, Y0 + row)] = cv2.imencode(".png", tile)[1].tobytes()
        self.script: dict[tuple[int, int], list[_Reply]] = defaultdict(list)
        self.always: dict[tuple[int, int], _Reply] = {}
        self.forbid_after: int | None = None
        self.served_ok = 0
        self.hits: Counter[tuple[int, int]] = Counter()
        self.hit_times: dict[tuple[int, int], list[float]] = defaultdict(list)
        self.user_agents: set[str] = set()
        self.lock = threading.Lock()
        self.port = 0

    def template(self, query: str = "?api_key=SECRET123") -> str:
        return f"http://127.0.0.1:{self.port}/tiles/{{z}}/{{x}}/{{y}}.png{query}"

    def reply(self, path: str, user_agent: str) -> _Reply:
        parts = path.split("?")[0].strip("/").split("/")
        if len(parts) != 4 or parts[0] not in {"tiles", "tms"}:
            return _Reply(400, body=b"bad path")
        z, x, y = int(parts[1]), int(parts[2]), int(parts[3].split(".")[0])
        if parts[0] == "tms":
            y = (1 << z) - 1 - y
        key = (x, y)
        with self.lock:
            self.hits[key] += 1
            self.hit_times[key].append(time.monotonic())
            self.user_agents.add(user_agent)
            if self.forbid_after is not None and self.served_ok >= self.forbid_after:
                return _Reply(403, body=b"forbidden")
            if self.script[key]:
                return self.script[key].pop(0)
            if key in self.always:
                return self.always[key]
            if z != ZOOM or key not in self.tiles:
                return _Reply(404)
            self.served_ok += 1
            return _Reply(200, {"Content-Type": "image/png"}, self.tiles[key])

    @property
    def total_hits(self) -> int:
        return sum(self.hits.values())


def _handler(server: _TileServer) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            reply = server.reply(self.path, self.headers.get("User-Agent", ""))
            if reply.delay_s:
                time.sleep(reply.delay_s)
            if reply.drop:
                self.close_connection = True
                return
            self.send_response(reply.status)
            for name, value in reply.headers.items():
                self.send_header(name, value)
            self.send_header("Content-Length", str(len(reply.body)))
            self.end_headers()
            self.wfile.write(reply.body)

        def log_message(self, format: str, *args: object) -> None:
            pass

    return Handler


def _image(n_rows: int, n_cols: int) -> np.ndarray:
    rng = np.random.default_rng(42)
    return rng.integers(1, 256, size=(n_rows * TS, n_cols * TS, 3), dtype=np.uint8)


@pytest.fixture
def serve() -> Iterator[object]:
    """Factory: start a tile server on 127.0.0.1 for an n_rows x n_cols area; stopped after the test."""
    started: list[ThreadingHTTPServer] = []

    def start(n_rows: int = 3, n_cols: int = 4) -> _TileServer:
        tiles = _TileServer(_image(n_rows, n_cols))
        httpd = ThreadingHTTPServer(("127.0.0.1", 0), _handler(tiles))
        httpd.daemon_threads = True
        tiles.port = httpd.server_address[1]
        threading.Thread(
            target=httpd.serve_forever, kwargs={"poll_interval": 0.02}, name="test-tile-server", daemon=True
        ).start()
        started.append(httpd)
        return tiles

    yield start
    for httpd in started:
        httpd.shutdown()
        httpd.server_close()


def _bbox(n_rows: int = 3, n_cols: int = 4) -> tuple[float, float, float, float]:
    """Bbox from the centre of the NW tile to the centre of the SE tile: exactly the area's tiles."""
    grid = WebMercatorGrid(ZOOM, TS)
    west, north = grid.tile_center_lonlat(X0, Y0)
    east, south = grid.tile_center_lonlat(X0 + n_cols - 1, Y0 + n_rows - 1)
    return west, south, east, north


def _files(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.is_file())


def test_download_and_build_mosaic_equals_source(tmp_path: Path, serve) -> None:  # type: ignore[no-untyped-def]
    """A full download + build reproduces the server's pixels; the store opens it; a re-run is free."""
    server = serve()
    out = tmp_path / "cache"
    manifest = build_cache(
        server.template(), out, zoom=ZOOM, bbox_lonlat=_bbox(), progress=False, downloader_options=FAST
    )
    assert server.total_hits == 12
    assert all(ua.startswith("gps-denied-onboard/") for ua in server.user_agents)
    store = TileStore.open(out)
    np.testing.assert_array_equal(np.asarray(store.mosaic), server.image)
    assert len(store) == 12
    lon, lat = WebMercatorGrid(ZOOM, TS).tile_center_lonlat(X0 + 3, Y0 + 2)
    tile_id, _ = store.tiles_near(lat, lon, radius_m=100.0)[0]
    np.testing.assert_array_equal(store.chip(tile_id, TS).pixels(), server.image[2 * TS :, 3 * TS :])
    assert manifest.source.kind == "tile_server"
    assert manifest.source.path.endswith("?api_key=REDACTED")
    assert "SECRET123" not in (out / "manifest.json").read_text()
    again = build_cache(
        server.template(), out, zoom=ZOOM, bbox_lonlat=_bbox(), progress=False, downloader_options=FAST
    )
    assert again == manifest
    assert server.total_hits == 12


def test_download_retries_503_then_succeeds(tmp_path: Path, serve) -> None:  # type: ignore[no-untyped-def]
    """503 twice then 200: the tile is fetched on the third attempt and the run has no failure."""
    server = serve()
    server.script[(X0 + 1, Y0)] = [_Reply(503), _Reply(503)]
    summary = TileDownloader(server.template(), **FAST).download(ZOOM, _bbox(), tmp_path, progress=False)
    assert server.hits[(X0 + 1, Y0)] == 3
    assert summary.downloaded == 12 and summary.failed == ()
    assert summary.requests_sent == 14
    assert (tmp_path / str(ZOOM) / str(X0 + 1) / f"{Y0}.png").read_bytes() == server.tiles[(X0 + 1, Y0)]


def test_download_retries_timeouts_and_dropped_connections(tmp_path: Path, serve) -> None:  # type: ignore[no-untyped-def]
    """A reply slower than timeout_s and a connection closed without reply are both retried."""
    server = serve()
    server.script[(X0, Y0)] = [_Reply(delay_s=0.6)]
    server.script[(X0 + 2, Y0 + 1)] = [_Reply(drop=True)]
    options = {**FAST, "timeout_s": 0.3}
    summary = TileDownloader(server.template(), **options).download(ZOOM, _bbox(), tmp_path, progress=False)
    assert summary.downloaded == 12 and summary.failed == ()
    assert server.hits[(X0, Y0)] == 2 and server.hits[(X0 + 2, Y0 + 1)] == 2


def test_download_honours_retry_after_on_429(tmp_path: Path, serve) -> None:  # type: ignore[no-untyped-def]
    """429 with Retry-After: 1 delays the retry by about a second although the backoff is 10 ms."""
    server = serve()
    server.script[(X0, Y0)] = [_Reply(429, {"Retry-After": "1"})]
    summary = TileDownloader(server.template(), **FAST).download(ZOOM, _bbox(), tmp_path, progress=False)
    first, second = server.hit_times[(X0, Y0)]
    assert second - first >= 0.9
    assert summary.downloaded == 12


def test_download_retry_after_beyond_limit_raises(tmp_path: Path, serve) -> None:  # type: ignore[no-untyped-def]
    """A Retry-After longer than retry_after_max_s stops the run with a clear error (resume later)."""
    server = serve()
    server.script[(X0, Y0)] = [_Reply(429, {"Retry-After": "3600"})]
    downloader = TileDownloader(server.template(), **FAST, retry_after_max_s=5.0)
    with pytest.raises(TileDownloadError, match="wait 3600 s") as info:
        downloader.download(ZOOM, _bbox(), tmp_path, progress=False)
    assert info.value.status == 429


def test_download_404_is_a_gap_and_build_excludes_it(tmp_path: Path, serve) -> None:  # type: ignore[no-untyped-def]
    """A 404 tile is recorded as a gap, not retried; the build succeeds without that tile."""
    server = serve()
    gap = (X0 + 2, Y0 + 1)
    server.always[gap] = _Reply(404)
    downloader = TileDownloader(server.template(), **FAST)
    summary = downloader.download(ZOOM, _bbox(), tmp_path / "cache" / "_download", progress=False)
    assert [(f.z, f.x, f.y) for f in summary.failed] == [(ZOOM, *gap)]
    assert "404" in summary.failed[0].reason and summary.gaps == summary.failed and summary.errors == ()
    assert server.hits[gap] == 1
    manifest = build_cache(
        server.template(),
        tmp_path / "cache",
        zoom=ZOOM,
        bbox_lonlat=_bbox(),
        progress=False,
        downloader_options=FAST,
    )
    assert manifest.tile_count == 11
    store = TileStore.open(tmp_path / "cache")
    assert all(store.tile_xyz(t)[:2] != gap for t in store.tile_ids)
    assert not np.asarray(store.mosaic)[TS : 2 * TS, 2 * TS : 3 * TS].any()


def test_build_from_url_area_without_tiles_raises(tmp_path: Path, serve) -> None:  # type: ignore[no-untyped-def]
    """An area where the server has only 404s fails the build with the reason, not an empty cache."""
    server = serve()
    far = (-10.0, -10.0, -9.95, -9.95)
    with pytest.raises(CacheBuildError, match=r"server has none of the \d+ tiles .*HTTP 404"):
        build_cache(
            server.template(),
            tmp_path / "cache",
            zoom=ZOOM,
            bbox_lonlat=far,
            progress=False,
            downloader_options=FAST,
        )
    assert not (tmp_path / "cache" / "manifest.json").exists()


def test_download_403_raises_naming_url_and_status(tmp_path: Path, serve) -> None:  # type: ignore[no-untyped-def]
    """403 is fatal: TileDownloadError names the (redacted) URL and the status, and the run stops."""
    server = serve(5, 8)
    server.forbid_after = 0
    downloader = TileDownloader(server.template(), **FAST, concurrency=2)
    with pytest.raises(TileDownloadError, match="HTTP 403") as info:
        downloader.download(ZOOM, _bbox(5, 8), tmp_path, progress=False)
    message = str(info.value)
    assert f"127.0.0.1:{server.port}/tiles/{ZOOM}/" in message and "api_key=REDACTED" in message
    assert "SECRET123" not in message
    assert info.value.status == 403
    # Stopped at once: at most one request in flight per worker, not the other 38 tiles; nothing written.
    assert server.total_hits <= 2
    assert _files(tmp_path) == []


def test_download_resume_fetches_only_missing_tiles(tmp_path: Path, serve) -> None:  # type: ignore[no-untyped-def]
    """A run cut off after 5 tiles leaves only complete tiles; the re-run fetches just the rest."""
    server = serve()
    server.forbid_after = 5
    downloader = TileDownloader(server.template(), **FAST, concurrency=2)
    with pytest.raises(TileDownloadError, match="403"):
        downloader.download(ZOOM, _bbox(), tmp_path, progress=False)
    written = _files(tmp_path)
    assert len(written) == server.served_ok == 5
    assert all(server.tiles[(int(p.parent.name), int(p.stem))] == p.read_bytes() for p in written)
    # Debris of a killed run: a partial temp file and a torn tile (no PNG end marker).
    x_dir = tmp_path / str(ZOOM) / str(X0 + 3)
    x_dir.mkdir(parents=True, exist_ok=True)
    (x_dir / f".{Y0 + 2}.abc.part").write_bytes(b"partial")
    torn = x_dir / f"{Y0 + 2}.png"
    torn.write_bytes(server.tiles[(X0 + 3, Y0 + 2)][:300])
    torn_was_served = (X0 + 3, Y0 + 2) in {(int(p.parent.name), int(p.stem)) for p in written}
    server.forbid_after = None
    hits_before = server.total_hits
    summary = downloader.download(ZOOM, _bbox(), tmp_path, progress=False)
    expected_skipped = 5 - int(torn_was_served)
    assert summary.skipped_existing == expected_skipped
    assert summary.downloaded == 12 - expected_skipped
    assert server.total_hits - hits_before == 12 - expected_skipped
    assert torn.read_bytes() == server.tiles[(X0 + 3, Y0 + 2)]
    assert not list(tmp_path.rglob("*.part"))
    assert len(_files(tmp_path)) == 12


def test_download_rejects_non_image_bodies(tmp_path: Path, serve) -> None:  # type: ignore[no-untyped-def]
    """HTML or truncated PNG bodies are never written: retried, and recorded when they persist."""
    server = serve()
    html = _Reply(200, {"Content-Type": "text/html"}, b"<html><body>Service unavailable</body></html>")
    bad, flaky, torn = (X0, Y0), (X0 + 1, Y0), (X0 + 2, Y0)
    server.always[bad] = html
    server.script[flaky] = [html]
    server.script[torn] = [_Reply(200, {"Content-Type": "image/png"}, server.tiles[torn][:200])]
    options = {**FAST, "max_retries": 2}
    summary = TileDownloader(server.template(), **options).download(
        ZOOM, _bbox(), tmp_path / "cache" / "_download", progress=False
    )
    assert server.hits[bad] == 3 and server.hits[flaky] == 2 and server.hits[torn] == 2
    assert [(f.x, f.y) for f in summary.errors] == [bad]
    assert "not a PNG/JPEG/WebP" in summary.errors[0].reason and "text/html" in summary.errors[0].reason
    assert not list((tmp_path / "cache" / "_download" / str(ZOOM) / str(X0)).glob(f"*{Y0}*"))
    with pytest.raises(CacheBuildError, match="1 of 12 tiles could not be downloaded"):
        build_cache(
            server.template(),
            tmp_path / "cache",
            zoom=ZOOM,
            bbox_lonlat=_bbox(),
            progress=False,
            downloader_options=options,
        )
    manifest = build_cache(
        server.template(),
        tmp_path / "cache",
        zoom=ZOOM,
        bbox_lonlat=_bbox(),
        progress=False,
        allow_failed_tiles=True,
        downloader_options=options,
    )
    assert manifest.tile_count == 11


def test_download_rate_limit_spaces_requests(tmp_path: Path, serve) -> None:  # type: ignore[no-untyped-def]
    """At 20 requests/s, 40 tiles over 4 workers take at least ~1.9 s (39 intervals of 50 ms)."""
    server = serve(5, 8)
    downloader = TileDownloader(server.template(), rate_limit_per_s=20.0, concurrency=4, timeout_s=5.0)
    t0 = time.monotonic()
    summary = downloader.download(ZOOM, _bbox(5, 8), tmp_path, progress=False)
    elapsed_s = time.monotonic() - t0
    assert summary.downloaded == 40
    assert elapsed_s >= 1.9


def test_download_tms_template_requests_flipped_rows(tmp_path: Path, serve) -> None:  # type: ignore[no-untyped-def]
    """A {-y} template asks for TMS rows but stores tiles under XYZ rows."""
    server = serve()
    template = f"http://127.0.0.1:{server.port}/tms/{{z}}/{{x}}/{{-y}}.png"
    summary = TileDownloader(template, **FAST).download(ZOOM, _bbox(), tmp_path, progress=False)
    assert summary.downloaded == 12
    assert (tmp_path / str(ZOOM) / str(X0) / f"{Y0}.png").read_bytes() == server.tiles[(X0, Y0)]


def test_download_too_many_tiles_raises_before_any_request(tmp_path: Path, serve) -> None:  # type: ignore[no-untyped-def]
    """An area above max_tiles (a zoom typo) raises without contacting the server."""
    server = serve()
    downloader = TileDownloader(server.template(), **FAST)
    with pytest.raises(TileDownloadError, match="needs 12 tiles, more than max_tiles 10"):
        downloader.download(ZOOM, _bbox(), tmp_path, progress=False, max_tiles=10)
    assert server.total_hits == 0


@pytest.mark.parametrize(
    "template",
    ["http://127.0.0.1:9/{z}/{x}.png", "http://127.0.0.1:9/{z}/{x}/{y}/{q}.png", "file:///{z}/{x}/{y}"],
)
def test_downloader_bad_template_raises(template: str) -> None:
    """A template without {z}/{x}/{y}, with an unknown placeholder or not http(s) is refused."""
    with pytest.raises(TileDownloadError, match="template"):
        TileDownloader(template)


def test_redact_url_hides_secrets_and_keeps_placeholders() -> None:
    """Secret query values and user:password are redacted; placeholders and other params survive."""
    url = "https://bob:pw@{s}.example.com/{z}/{x}/{y}.jpg?style=sat&apikey=K1&access_token=T2&sig={s}"
    redacted = redact_url(url)
    assert redacted == (
        "https://REDACTED@{s}.example.com/{z}/{x}/{y}.jpg?style=sat&apikey=REDACTED&access_token=REDACTED&sig={s}"
    )
