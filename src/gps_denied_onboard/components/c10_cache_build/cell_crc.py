"""C10: the CRC-32 of every grid cell of the mosaic, the table C6 checks each read against.

A cell is one tile, ``tile_size_px`` square, of the mosaic's bytes in C order (rows of BGR pixels). The
table is computed once, at build (``finalize_cache``, whatever the source: GeoTIFF or XYZ tiles), and
saved as the artifact ``mosaic_z{Z}_cell_crc32.npy`` (uint32 (rows, cols)), listed in the manifest with
its sha256 like the others; so the daemon's start never reads the mosaic, and every cell a chip covers is
checked against what the build wrote. A cache built before the table existed has it computed at open
by the same function (``TileStore.open``, with a warning). CRC-32 detects corruption (a failing flash
page, a torn copy), not an adversary who can write the cache.
"""

from __future__ import annotations

import os
import zlib
from pathlib import Path

import numpy as np


def cell_crc32(pixels: np.ndarray) -> int:
    """CRC-32 of one cell's bytes (C order, whatever the strides of ``pixels``)."""
    return zlib.crc32(np.ascontiguousarray(pixels).data)


def cell_crc32_table(mosaic: np.ndarray, tile_size_px: int) -> np.ndarray:
    """CRC-32 of every ``tile_size_px`` square cell of the (H, W, 3) ``mosaic``, uint32 (rows, cols);
    edge cells are smaller where the mosaic is not a whole number of cells. Reads the mosaic once, one
    band of cells at a time."""
    ts = int(tile_size_px)
    rows, cols = -(-mosaic.shape[0] // ts), -(-mosaic.shape[1] // ts)
    table = np.zeros((rows, cols), dtype=np.uint32)
    for r in range(rows):
        band = np.array(mosaic[r * ts : (r + 1) * ts])  # one sequential read per band of cells
        for c in range(cols):
            table[r, c] = cell_crc32(band[:, c * ts : (c + 1) * ts])
    return table


def write_cell_crc_table(path: Path, table: np.ndarray) -> None:
    """Save ``table`` (uint32 (rows, cols)) to ``path`` via a temporary file, fsync and os.replace."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        np.save(fh, np.asarray(table, dtype=np.uint32), allow_pickle=False)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
