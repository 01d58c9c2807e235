"""C11: download XYZ tiles from a tile server URL template (retries, rate limit, resumable)."""

from __future__ import annotations

from gps_denied_onboard.components.c11_tile_download.downloader import (
    DownloadSummary,
    TileDownloader,
    TileDownloadError,
    TileFailure,
    redact_url,
)

__all__ = [
    "DownloadSummary",
    "TileDownloadError",
    "TileDownloader",
    "TileFailure",
    "redact_url",
]
