"""C6: the cache's orientation fields (``c10_cache_build/map_fields.py``), memory-mapped, read by window.

What the area correlation (C3 ``orientation_corr``) reads instead of pixels. ``MapFields.window`` copies the
grid cells a window covers, checks each copy against the CRC-32 recorded when the field was written, and
cuts the window from the copy, so the bytes checked are the bytes matched. A cell that fails is nodata for
the rest of the run (never trusted again), logged (``c6.map_fields.cell_corrupt``), counted and reported
to the listener (the daemon records it in the FDR): no fix is ever made from it. Opening checks the files
at the level the tile store was opened at (``Verification``): light (the daemon's start) reads the
manifest's block, the fields' sizes and the small CRC tables (their sha256), never the fields, so the
open costs the same on any map; full (``gdnav preflight``, the builds) hashes every file.
"""

from __future__ import annotations

import threading
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.components.c10_cache_build.manifest import (
    CacheManifestError,
    FieldCalibration,
    MapFieldsInfo,
    Verification,
)
from gps_denied_onboard.constants import LogEvent
from gps_denied_onboard.helpers.orientation_field import FIELD_VERSION, NODATA, dequantise

#: The pyramid levels a cache's fields hold (``c10_cache_build.map_fields.LEVELS``; a test keeps them equal).
FIELD_LEVELS = (1, 2, 3)

_log = structlog.get_logger(__name__)


class MapFieldsRefused(RuntimeError):
    """The cache's fields cannot be used: absent (``absent``), of another definition, not matching the
    mosaic, or failing their sizes, hashes or layout."""

    def __init__(self, message: str, *, absent: bool = False) -> None:
        super().__init__(message)
        self.absent = absent


class MapFields:
    """Read-only orientation fields of one cache (module docstring); a ``FieldWindowSource``."""

    def __init__(
        self,
        cache_dir: Path,
        info: MapFieldsInfo,
        fields: dict[int, np.ndarray],
        crcs: dict[int, np.ndarray],
        store: TileStore,
    ) -> None:
        """Prefer :meth:`open`."""
        self._cache_dir = cache_dir
        self._info = info
        self._fields = fields
        self._crcs = crcs
        self._store = store
        self._corrupt: set[tuple[int, int, int]] = set()
        self._lock = threading.Lock()
        #: Called once per newly corrupt cell with its description (the daemon records it in the FDR).
        self.on_corrupt: Callable[[dict[str, Any]], None] | None = None

    @classmethod
    def open(
        cls, store: TileStore, info: MapFieldsInfo | None = None, verification: Verification | None = None
    ) -> MapFields:
        """The fields of ``store``'s cache (its manifest's block unless ``info`` is given), their files
        checked at ``verification`` (None: the level ``store`` was opened at). Raises
        ``MapFieldsRefused`` saying why they cannot be used."""
        cache_dir = store.cache_dir
        info = info if info is not None else store.manifest.map_fields
        if info is None:
            raise MapFieldsRefused(
                f"{cache_dir}: the cache has no orientation fields (run gdnav cache fields --cache "
                f"{cache_dir})",
                absent=True,
            )
        if info.version != FIELD_VERSION:
            raise MapFieldsRefused(
                f"{cache_dir}: orientation fields of definition {info.version!r}, this daemon uses "
                f"{FIELD_VERSION!r} (run gdnav cache fields --force)"
            )
        mosaic_sha = store.manifest.artifacts[store.manifest.mosaic_name].sha256
        if info.mosaic_sha256 != mosaic_sha:
            raise MapFieldsRefused(f"{cache_dir}: the orientation fields were made from another mosaic")
        try:
            info.verify_files(cache_dir, store.verification if verification is None else verification)
        except CacheManifestError as exc:
            raise MapFieldsRefused(f"orientation fields: {exc.message} ({exc.path})") from exc
        height, width = store.mosaic.shape[:2]
        fields: dict[int, np.ndarray] = {}
        crcs: dict[int, np.ndarray] = {}
        for level, (field_name, crc_name, cell) in sorted(info.levels.items()):
            try:
                f = np.load(cache_dir / field_name, mmap_mode="r", allow_pickle=False)
                c = np.load(cache_dir / crc_name, allow_pickle=False)
            except (OSError, ValueError) as exc:
                raise MapFieldsRefused(f"orientation field level {level}: {exc}") from exc
            shape = (height >> (level - 1), width >> (level - 1), 2)
            cells = (-(-shape[0] // cell), -(-shape[1] // cell))
            if f.dtype != np.int8 or tuple(f.shape) != shape or c.dtype != np.uint32 or c.shape != cells:
                raise MapFieldsRefused(
                    f"orientation field level {level}: {f.dtype} {f.shape} with CRC table {c.dtype} "
                    f"{c.shape}, expected int8 {shape} and uint32 {cells}"
                )
            fields[level] = f
            crcs[level] = c
        if set(fields) != set(FIELD_LEVELS):
            raise MapFieldsRefused(
                f"{cache_dir}: orientation fields of levels {sorted(fields)}, need {list(FIELD_LEVELS)} "
                "(run gdnav cache fields --force)"
            )
        return cls(cache_dir, info, fields, crcs, store)

    def calibration(self, level: int) -> FieldCalibration | None:
        """The map's calibration at working ``level`` (None: not made, or no room for it there)."""
        return self._info.calibrations.get(level)

    @property
    def calibrated_levels(self) -> tuple[int, ...]:
        """The working levels with a calibration, finest first."""
        return tuple(sorted(self._info.calibrations))

    @property
    def info(self) -> MapFieldsInfo:
        return self._info

    @property
    def store(self) -> TileStore:
        """The tile store whose mosaic the fields describe (its pixel grid is level 1)."""
        return self._store

    @property
    def corrupt_cells(self) -> int:
        with self._lock:
            return len(self._corrupt)

    def window(self, level: int, x0: int, y0: int, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """``(z, valid)`` of the level's pixels [y0, y0 + height) x [x0, x0 + width): (h, w) complex64
        and bool; outside the map, and in a corrupt cell, ``valid`` is false and ``z`` 0."""
        if width < 1 or height < 1:
            raise ValueError(f"window must be at least 1 x 1 px, got {width} x {height}")
        f = self._fields[level]
        cell = self._info.levels[level][2]
        out = np.zeros((height, width, 2), np.int8)
        out[..., 0] = NODATA
        fh, fw = f.shape[:2]
        xa, ya, xb, yb = max(x0, 0), max(y0, 0), min(x0 + width, fw), min(y0 + height, fh)
        if xb > xa and yb > ya:
            r_lo, r_hi = ya // cell, (yb - 1) // cell
            c_lo, c_hi = xa // cell, (xb - 1) // cell
            block = np.array(f[r_lo * cell : (r_hi + 1) * cell, c_lo * cell : (c_hi + 1) * cell])
            for r in range(r_lo, r_hi + 1):
                for c in range(c_lo, c_hi + 1):
                    part = block[
                        (r - r_lo) * cell : (r - r_lo + 1) * cell, (c - c_lo) * cell : (c - c_lo + 1) * cell
                    ]
                    if not self._cell_ok(level, r, c, part):
                        part[..., 0] = NODATA
                        part[..., 1] = 0
            top, left = ya - r_lo * cell, xa - c_lo * cell
            out[ya - y0 : yb - y0, xa - x0 : xb - x0] = block[top : top + (yb - ya), left : left + (xb - xa)]
        return dequantise(out)

    def _cell_ok(self, level: int, row: int, col: int, part: np.ndarray) -> bool:
        key = (level, row, col)
        with self._lock:
            if key in self._corrupt:
                return False
        crc = zlib.crc32(np.ascontiguousarray(part).data)
        if crc == int(self._crcs[level][row, col]):
            return True
        with self._lock:
            if key in self._corrupt:
                return False
            self._corrupt.add(key)
            total = len(self._corrupt)
        info = {
            "level": level,
            "row": row,
            "col": col,
            "crc32_built": int(self._crcs[level][row, col]),
            "crc32_read": int(crc),
            "corrupt_cells": total,
            "file": str(self._cache_dir / self._info.levels[level][0]),
        }
        _log.error(
            LogEvent.MAP_FIELDS_CELL_CORRUPT, action="masked as nodata for the rest of the run", **info
        )
        listener = self.on_corrupt
        if listener is not None:
            listener(info)
        return False
