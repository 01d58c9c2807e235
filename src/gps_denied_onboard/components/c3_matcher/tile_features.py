"""Precomputed tile features: a learned extractor's output for every tile's chip, read memory-mapped.

``gdnav cache features`` (``c10_cache_build.tile_features``) runs the configured strategy's
``extract_tile`` once over ``TileStore.chip(tile_id, chip_size_px)`` of every tile and writes, per strategy
``<label>``, into the cache directory::

    tilefeat_<label>_keypoints.npy    float32 (K, 2)  keypoints (x, y), chip px, every tile's back to back
    tilefeat_<label>_descriptors.npy  float32 (K, D)  their descriptors, same order
    tilefeat_<label>_tiles.npy        TILE_TABLE_DTYPE (N,), row i = tile i of the cache (``tile_ids``):
                                      offset/count into the two arrays above, the chip it was extracted
                                      from (width, height, lon/lat of chip px (0, 0), GSD) and the CRC-32
                                      of that tile's keypoint and descriptor bytes

and records them in the manifest's ``tile_features[<label>]`` with the extractor's identity
(``ExtractorIdentity``) and each file's size and sha256.

``PrecomputedTileFeatures.open`` refuses a set (``TileFeaturesRefused``, with the reason) that was made by
another extractor (any identity field differs: a different model file, chip size, keypoint cap or input
size), for other tiles or another mosaic, or whose files do not match their size or the sha256 its
``Verification`` asks for (full: every file; light, the daemon's start: the tile table, read whole, while
the keypoints and descriptors are checked per tile on read); it never hands out features of another
model. ``lookup`` returns a tile's features only for exactly the chip they were extracted from, copied out
of the mapping and checked against their CRC-32 (the bytes checked are the bytes used, as in
``TileStore.chip``); an entry that fails is never used again in this run and the matcher extracts that
tile live.
"""

from __future__ import annotations

import hashlib
import threading
import zlib
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np
import structlog

from gps_denied_onboard.components.c3_matcher.features import Features
from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.components.c6_tiles.types import TileId, TilePixelsHandle
from gps_denied_onboard.components.c10_cache_build.manifest import (
    TILES_NAME,
    CacheManifestError,
    TileFeatureSetInfo,
    Verification,
    sha256_file,
)
from gps_denied_onboard.config import MatcherConfig
from gps_denied_onboard.constants import LogEvent

_LOG = structlog.get_logger(__name__)

#: Layout version of the feature files; part of the identity, so a change refuses older sets.
TILE_FEATURES_FORMAT: Final[int] = 1

#: One row per tile of the cache, in ``TileStore.tile_ids`` order.
TILE_TABLE_DTYPE: Final[np.dtype] = np.dtype(
    [
        ("offset", "<i8"),  # first keypoint row of this tile
        ("count", "<i4"),  # its keypoints
        ("width_px", "<i4"),  # the chip it was extracted from
        ("height_px", "<i4"),
        ("lon0_deg", "<f8"),  # lon/lat of that chip's pixel (0, 0)
        ("lat0_deg", "<f8"),
        ("gsd_m_px", "<f8"),
        ("crc32", "<u4"),  # of keypoints[offset:offset+count] bytes + descriptors[...] bytes
    ]
)


def file_names(label: str) -> tuple[str, str, str]:
    """(keypoints, descriptors, tile table) file names of strategy ``label``'s set."""
    return (
        f"tilefeat_{label}_keypoints.npy",
        f"tilefeat_{label}_descriptors.npy",
        f"tilefeat_{label}_tiles.npy",
    )


def model_sha256(path: str | Path) -> str:
    """sha256 of an ONNX model file (the model manifest's own figure); with external weights
    (``<file>.data`` beside it) the sha256 of both digests, so new weights change it too."""
    p = Path(path)
    digest = sha256_file(p)
    data = p.with_name(p.name + ".data")
    if data.is_file():
        digest = hashlib.sha256(f"{digest}:{sha256_file(data)}".encode("ascii")).hexdigest()
    return digest


@dataclass(frozen=True)
class ExtractorIdentity:
    """Everything a learned strategy's tile features depend on besides the pixels.

    ``strategy``: the C3 label; ``model_sha256``: of the extractor model (``model_sha256``);
    ``chip_size_px``: side of the chips; ``max_keypoints``: keypoints kept per image;
    ``input_long_side_px``: image long side given to a dynamic-size model; ``format``: the files' layout.
    """

    strategy: str
    model_sha256: str
    chip_size_px: int
    max_keypoints: int
    input_long_side_px: int
    format: int = TILE_FEATURES_FORMAT

    @classmethod
    def of(cls, strategy: str, model_path: str | Path, config: MatcherConfig) -> ExtractorIdentity:
        """The identity of ``strategy`` run with the extractor at ``model_path`` and ``config``."""
        return cls(
            strategy=strategy,
            model_sha256=model_sha256(model_path),
            chip_size_px=int(config.chip_size_px),
            max_keypoints=int(config.max_keypoints),
            input_long_side_px=int(config.input_long_side_px),
        )

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    def differences(self, recorded: Mapping[str, Any]) -> list[str]:
        """Human-readable differences between this identity and one recorded in a manifest."""
        out = []
        for key, mine in self.to_json().items():
            theirs = recorded.get(key)
            if theirs != mine:
                out.append(f"{key} {_short(theirs)} (set) vs {_short(mine)} (matcher)")
        return out


def _short(value: object) -> str:
    return f"{value[:12]}..." if isinstance(value, str) and len(value) > 16 else repr(value)


class TileFeaturesRefused(RuntimeError):
    """A set of precomputed tile features is absent (``absent``), made by another extractor, or damaged."""

    def __init__(self, message: str, *, label: str, path: str | None = None, absent: bool = False) -> None:
        super().__init__(f"{message} ({path})" if path else message)
        self.message = message
        self.label = label
        self.path = path
        self.absent = absent


def chip_origin(handle: TilePixelsHandle) -> tuple[float, float]:
    """lon/lat (deg) of a chip's pixel (0, 0): with the size and GSD, which chip of the map it is."""
    lon, lat = handle.chip_px_to_lonlat(np.zeros((1, 2), dtype=np.float64))
    return float(np.asarray(lon).ravel()[0]), float(np.asarray(lat).ravel()[0])


def entry_crc32(keypoints: np.ndarray, descriptors: np.ndarray) -> int:
    """CRC-32 of one tile's keypoint bytes followed by its descriptor bytes."""
    crc = zlib.crc32(np.ascontiguousarray(keypoints).data)
    return zlib.crc32(np.ascontiguousarray(descriptors).data, crc)


class PrecomputedTileFeatures:
    """A verified, memory-mapped set of tile features for one extractor (see the module docstring).

    Thread-safe: ``lookup`` may run on the matcher's worker while another thread reads the counters.
    """

    def __init__(
        self,
        identity: ExtractorIdentity,
        tile_ids: tuple[TileId, ...],
        keypoints: np.ndarray,
        descriptors: np.ndarray,
        table: np.ndarray,
        source: str,
    ) -> None:
        """Prefer ``open``. ``keypoints`` (K, 2) / ``descriptors`` (K, D) float32 and ``table``
        (N,) ``TILE_TABLE_DTYPE`` are the (memory-mapped) arrays, row i of ``table`` = ``tile_ids[i]``."""
        self._identity = identity
        self._row_of = {tile_id: i for i, tile_id in enumerate(tile_ids)}
        self._keypoints = keypoints
        self._descriptors = descriptors
        self._table = table
        self._source = source
        self._bad: set[int] = set()
        self._lock = threading.Lock()
        self.hits = 0
        self.misses = 0
        #: Called once per entry that fails its CRC with its description (the daemon records it).
        self.on_corrupt: Callable[[dict[str, Any]], None] | None = None

    @property
    def identity(self) -> ExtractorIdentity:
        return self._identity

    @property
    def descriptor_dim(self) -> int:
        return int(self._descriptors.shape[1])

    def __len__(self) -> int:
        return len(self._row_of)

    @classmethod
    def open(
        cls, store: TileStore, identity: ExtractorIdentity, verification: Verification | None = None
    ) -> PrecomputedTileFeatures:
        """The cache's set for ``identity.strategy``, checked at ``verification`` (None: the level
        ``store`` was opened at); ``TileFeaturesRefused`` otherwise.

        Refused: no set; a set made with another identity (every differing field named); for another
        tile list or mosaic; files missing, of another size or sha256 (module docstring); arrays whose
        shapes or dtypes disagree with each other or with the cache.
        """
        label = identity.strategy
        manifest = store.manifest
        cache_dir = store.cache_dir
        info: TileFeatureSetInfo | None = manifest.tile_features.get(label)
        if info is None:
            raise TileFeaturesRefused(
                f"no precomputed {label} tile features in this cache (gdnav cache features)",
                label=label,
                path=str(cache_dir),
                absent=True,
            )
        diffs = identity.differences(info.identity)
        if diffs:
            raise TileFeaturesRefused(
                f"precomputed {label} tile features were made by another extractor: " + "; ".join(diffs),
                label=label,
                path=str(cache_dir),
            )
        if (
            info.tiles_sha256 != manifest.artifacts[TILES_NAME].sha256
            or info.mosaic_sha256 != manifest.artifacts[manifest.mosaic_name].sha256
            or info.tile_count != len(store)
        ):
            raise TileFeaturesRefused(
                f"precomputed {label} tile features were made for another build of this cache's tiles",
                label=label,
                path=str(cache_dir),
            )
        names = file_names(label)
        if set(info.files) != set(names):
            raise TileFeaturesRefused(
                f"precomputed {label} tile features list files {sorted(info.files)}, expected {list(names)}",
                label=label,
                path=str(cache_dir),
            )
        try:
            info.verify_files(cache_dir, store.verification if verification is None else verification)
        except CacheManifestError as exc:
            raise TileFeaturesRefused(exc.message, label=label, path=exc.path) from exc
        try:
            kp, desc, table = (np.load(cache_dir / n, mmap_mode="r", allow_pickle=False) for n in names)
        except (OSError, ValueError) as exc:
            raise TileFeaturesRefused(
                f"cannot memory-map precomputed {label} tile features: {exc}",
                label=label,
                path=str(cache_dir),
            ) from exc
        problem = _layout_problem(kp, desc, table, len(store))
        if problem is not None:
            raise TileFeaturesRefused(
                f"precomputed {label} tile features are malformed: {problem}",
                label=label,
                path=str(cache_dir),
            )
        return cls(identity, store.tile_ids, kp, desc, table, str(cache_dir))

    def lookup(self, handle: TilePixelsHandle, chip_wh: tuple[int, int]) -> Features | None:
        """The precomputed features of ``handle``'s chip (``chip_wh`` = its (width, height) px), or None
        when this set has none for exactly that chip (another tile, size, position or GSD) or the entry
        failed its CRC (now or earlier in this run)."""
        row = self._row_of.get(handle.tile_id)
        if row is None:
            return self._miss()
        entry = self._table[row]
        lon0, lat0 = chip_origin(handle)
        gsd = float(handle.gsd_m_px)
        # 1e-9 deg is 0.1 mm: the same chip computes the same floats; a chip cut 1 px away differs by 1e5x.
        same_chip = (
            (int(entry["width_px"]), int(entry["height_px"])) == (int(chip_wh[0]), int(chip_wh[1]))
            and abs(float(entry["lon0_deg"]) - lon0) <= 1e-9
            and abs(float(entry["lat0_deg"]) - lat0) <= 1e-9
            and abs(float(entry["gsd_m_px"]) - gsd) <= 1e-9 * max(1.0, gsd)
        )
        if not same_chip:
            return self._miss()
        with self._lock:
            known_bad = row in self._bad
        if known_bad:
            return self._miss()
        start, count = int(entry["offset"]), int(entry["count"])
        # Copies out of the mapping: the bytes checked are the bytes the matcher gets.
        kp = np.array(self._keypoints[start : start + count], dtype=np.float32)
        desc = np.array(self._descriptors[start : start + count], dtype=np.float32)
        crc = entry_crc32(kp, desc)
        if crc != int(entry["crc32"]):
            self._report_corrupt(row, handle.tile_id, int(entry["crc32"]), crc)
            return self._miss()
        with self._lock:
            self.hits += 1
        return Features(kp, desc, (int(entry["width_px"]), int(entry["height_px"])))

    def _miss(self) -> Features | None:
        with self._lock:
            self.misses += 1
        return None

    def _report_corrupt(self, row: int, tile_id: TileId, crc_built: int, crc_read: int) -> None:
        with self._lock:
            if row in self._bad:
                return
            self._bad.add(row)
            total = len(self._bad)
        info = {
            "strategy": self._identity.strategy,
            "tile_id": list(tile_id),
            "crc32_built": crc_built,
            "crc32_read": crc_read,
            "corrupt_entries": total,
            "cache_dir": self._source,
        }
        _LOG.error(LogEvent.TILE_FEATURES_CORRUPT, action="extracted live for the rest of the run", **info)
        listener = self.on_corrupt
        if listener is not None:
            listener(info)


def _layout_problem(kp: np.ndarray, desc: np.ndarray, table: np.ndarray, n_tiles: int) -> str | None:
    if kp.dtype != np.float32 or kp.ndim != 2 or kp.shape[1] != 2:
        return f"keypoints are {kp.dtype} {kp.shape}, expected float32 (K, 2)"
    if desc.dtype != np.float32 or desc.ndim != 2 or desc.shape[0] != kp.shape[0]:
        return f"descriptors are {desc.dtype} {desc.shape}, expected float32 ({kp.shape[0]}, D)"
    if table.dtype != TILE_TABLE_DTYPE or table.shape != (n_tiles,):
        return f"tile table is {table.dtype} {table.shape}, expected {n_tiles} rows of the tile-table layout"
    offsets = np.asarray(table["offset"], dtype=np.int64)
    counts = np.asarray(table["count"], dtype=np.int64)
    if n_tiles and (
        (counts < 0).any()
        or offsets[0] != 0
        or (offsets[1:] != offsets[:-1] + counts[:-1]).any()
        or offsets[-1] + counts[-1] != kp.shape[0]
    ):
        return "tile table offsets/counts do not cover the keypoint rows back to back"
    return None
