"""C10: build the map cache (F1 pre-flight): mosaic, tile list and manifest."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from gps_denied_onboard.components.c10_cache_build.manifest import (
    CACHE_FORMAT_VERSION,
    ArtifactInfo,
    CacheBuildError,
    CacheManifest,
    CacheManifestError,
    SourceInfo,
    TileRange,
    VprInfo,
)

if TYPE_CHECKING:
    from gps_denied_onboard.components.c10_cache_build.geotiff import build_cache_from_geotiff, choose_zoom
    from gps_denied_onboard.components.c10_cache_build.xyz import (
        build_cache,
        build_cache_from_url,
        build_cache_from_xyz_dir,
    )

__all__ = [
    "CACHE_FORMAT_VERSION",
    "ArtifactInfo",
    "CacheBuildError",
    "CacheManifest",
    "CacheManifestError",
    "SourceInfo",
    "TileRange",
    "VprInfo",
    "build_cache",
    "build_cache_from_geotiff",
    "build_cache_from_url",
    "build_cache_from_xyz_dir",
    "choose_zoom",
]


def __getattr__(name: str) -> Any:
    # The builder pulls in rasterio/GDAL and tqdm; the daemon only needs the manifest (via C6, which
    # every stage imports for TileId), so the builder is imported on first use.
    if name in {"build_cache_from_geotiff", "choose_zoom"}:
        from gps_denied_onboard.components.c10_cache_build import geotiff

        return getattr(geotiff, name)
    if name in {"build_cache", "build_cache_from_url", "build_cache_from_xyz_dir"}:
        from gps_denied_onboard.components.c10_cache_build import xyz

        return getattr(xyz, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
