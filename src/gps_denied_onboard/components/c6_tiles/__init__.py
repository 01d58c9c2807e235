"""C6: tile identity, Web-Mercator georeference and the page-cache-backed tile store."""

from gps_denied_onboard.components.c6_tiles.georef import WebMercatorGrid
from gps_denied_onboard.components.c6_tiles.store import TileCentreIndex, TileChip, TileStore
from gps_denied_onboard.components.c6_tiles.types import TileId, TilePixelsHandle, TileStoreError

__all__ = [
    "TileCentreIndex",
    "TileChip",
    "TileId",
    "TilePixelsHandle",
    "TileStore",
    "TileStoreError",
    "WebMercatorGrid",
]
