"""C10 contract: the map cache's on-disk layout, its manifest, and how much of it is checked at open.

A cache is a directory::

    manifest.json               written last, atomically: its presence means "complete"
    mosaic_z{Z}.npy             uint8 (H, W, 3) BGR Web-Mercator mosaic, opened with np.load(mmap_mode="r")
    mosaic_z{Z}_cell_crc32.npy  uint32 (rows, cols): CRC-32 of every grid cell (one tile) of the mosaic,
                                taken at build (``cell_crc``); C6 checks each cell it reads against it
    tiles.json                  valid XYZ tiles: x, y, TileId (zoom, lat, lon of the centre), valid fraction
    tile_valid_fraction.npy     float32 (rows, cols): valid-pixel fraction of every tile in the range

Every artifact is listed in ``manifest.artifacts`` with its size and sha256; C6 refuses a cache whose
artifacts do not match (D-C10-3). The map's orientation fields for the area correlation
(``c10_cache_build/map_fields.py``) are listed apart, in ``map_fields``, with their calibration, and so
are precomputed tile features (``gdnav cache features``), an optional accelerator listed in
``tile_features`` (one set per C3 strategy, with the identity of the extractor that made it and its own
files' sizes and sha256): the matcher verifies and uses a set, or refuses it and extracts live; a damaged
set never refuses the cache itself. The manifest carries the sha256 of its own content
(``content_sha256``: canonical JSON of every other key), so an edited or corrupted manifest is refused.

Two levels of checking (``Verification``; the daemon's is chosen by ``runtime_root.cache_check``):

- **full**: the manifest's own hash and the sha256 of every artifact. ``gdnav cache build`` runs it at its
  end and ``gdnav preflight`` before a flight; it reads every byte, so its cost grows with the map.
- **light** (the daemon's start): the manifest's own hash, every artifact present with its recorded size,
  and the sha256 of the artifacts read whole at open (the tile list, the cell CRC tables, the tile
  feature tables, the VPR vocabulary and metadata). What is read by window and never whole
  (``read_by_window``: the mosaic, the orientation fields, the tile features' keypoints and descriptors,
  the VPR index and descriptors) is checked by size here, and then on every read against the CRC of
  the cell or entry read, where a reader keeps one. Its cost does not grow with the mosaic.

This module is deliberately light (json + hashlib) because the daemon imports it at start-up.
"""

from __future__ import annotations

import enum
import hashlib
import json
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gps_denied_onboard.helpers import bounded_json

#: Version of the cache layout; bump on any incompatible change.
CACHE_FORMAT_VERSION = 1
MANIFEST_NAME = "manifest.json"
#: The largest manifest read (a real one is a few kB; its tile list is in tiles.json), bytes.
MAX_MANIFEST_BYTES = 1 << 20
TILES_NAME = "tiles.json"
TILE_VALID_FRACTION_NAME = "tile_valid_fraction.npy"
_HASH_CHUNK_BYTES = 8 << 20


#: The manifest's key holding the sha256 of its other keys (``content_sha256``).
CONTENT_SHA256_KEY = "content_sha256"
#: Artifacts read by window, never whole, in flight (see the module docstring): the light check takes
#: their size only. The VPR names are ``c2_vpr.retrieval``'s (a test keeps them equal).
_READ_BY_WINDOW = re.compile(
    r"^(mosaic_z\d+\.npy|field_l\d+\.npy|tilefeat_.+_(keypoints|descriptors)\.npy"
    r"|vpr_index\.faiss|vpr_descriptors\.npy)$"
)


class Verification(str, enum.Enum):
    """How much of a cache is checked when it is opened (module docstring)."""

    #: sha256 of every artifact: ``gdnav cache build``, ``gdnav preflight``, an explicit request.
    FULL = "full"
    #: The manifest's own hash, every size, the sha256 of what is read whole: the daemon's start.
    LIGHT = "light"


def read_by_window(name: str) -> bool:
    """Whether the artifact ``name`` is read by window and never whole (the light check takes its size)."""
    return _READ_BY_WINDOW.match(name) is not None


def mosaic_name(zoom: int) -> str:
    """File name of the mosaic at ``zoom``."""
    return f"mosaic_z{zoom}.npy"


def cell_crc_name(zoom: int) -> str:
    """File name of the CRC-32 table of the mosaic's cells at ``zoom``."""
    return f"mosaic_z{zoom}_cell_crc32.npy"


def content_sha256(payload: Mapping[str, Any]) -> str:
    """sha256 of a manifest object without its ``content_sha256`` key, as canonical JSON (sorted keys,
    no spaces, ASCII): what ``CacheManifest.save`` records and ``CacheManifest.load`` checks."""
    body = {k: v for k, v in payload.items() if k != CONTENT_SHA256_KEY}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=True)
    return hashlib.sha256(text.encode("ascii")).hexdigest()


def sha256_file(path: Path) -> str:
    """Hex sha256 of a file, streamed in 8 MiB chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(_HASH_CHUNK_BYTES):
            digest.update(chunk)
    return digest.hexdigest()


def write_json_atomic(path: Path, payload: Any) -> None:
    """Write JSON to ``path`` via a temporary file, fsync and os.replace, so readers never see half."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(payload, fh, indent=1, sort_keys=True)
        fh.write("\n")
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


class CacheManifestError(RuntimeError):
    """A cache directory is incomplete, of another format version, or its artifacts do not match the
    manifest. C6 re-raises it as TileStoreError; this module stays free of C6 imports so that C6 can
    depend on it without an import cycle."""

    def __init__(self, message: str, *, path: str | None = None) -> None:
        super().__init__(f"{message} ({path})" if path else message)
        self.message = message
        self.path = path


class CacheBuildError(RuntimeError):
    """The cache could not be built (bad source, bad parameters, empty result, I/O)."""

    def __init__(self, message: str, *, path: str | None = None) -> None:
        super().__init__(f"{message} ({path})" if path else message)
        self.path = path


@dataclass(frozen=True)
class SourceInfo:
    """Where the map came from: ``kind`` ("geotiff"), path, sha256 of the file, CRS as text."""

    kind: str
    path: str
    sha256: str
    crs: str


@dataclass(frozen=True)
class TileRange:
    """Inclusive XYZ tile range ``[x0..x1] x [y0..y1]`` at the cache zoom."""

    x0: int
    y0: int
    x1: int
    y1: int

    @property
    def n_cols(self) -> int:
        return self.x1 - self.x0 + 1

    @property
    def n_rows(self) -> int:
        return self.y1 - self.y0 + 1


@dataclass(frozen=True)
class VprInfo:
    """Global-descriptor backbone used for the cache ("geo_prior" = no descriptors yet)."""

    backbone: str
    model_sha256: str | None


@dataclass(frozen=True)
class ArtifactInfo:
    """Recorded size (bytes) and sha256 of one artifact file."""

    sha256: str
    bytes: int


@dataclass(frozen=True)
class TileFeatureSetInfo:
    """One set of precomputed tile features (``c3_matcher.tile_features``): what made it, and its files.

    ``identity`` names the extractor and everything its output depends on (strategy, model sha256, chip
    size, keypoint cap, input long side: ``ExtractorIdentity.to_json``); ``tiles_sha256`` and
    ``mosaic_sha256`` tie it to this cache's tiles; ``files`` maps each file to its size and sha256.
    ``stats`` holds build figures (keypoints, seconds), for people, not checked.
    """

    identity: Mapping[str, Any]
    tiles_sha256: str
    mosaic_sha256: str
    tile_count: int
    files: Mapping[str, ArtifactInfo]
    stats: Mapping[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            "identity": dict(self.identity),
            "tiles_sha256": self.tiles_sha256,
            "mosaic_sha256": self.mosaic_sha256,
            "tile_count": self.tile_count,
            "files": {name: vars(info).copy() for name, info in sorted(self.files.items())},
            "stats": dict(self.stats),
        }

    @classmethod
    def from_json(cls, payload: Mapping[str, Any]) -> TileFeatureSetInfo:
        return cls(
            identity=dict(payload["identity"]),
            tiles_sha256=str(payload["tiles_sha256"]),
            mosaic_sha256=str(payload["mosaic_sha256"]),
            tile_count=int(payload["tile_count"]),
            files={
                str(name): ArtifactInfo(sha256=str(info["sha256"]), bytes=int(info["bytes"]))
                for name, info in payload["files"].items()
            },
            stats=dict(payload.get("stats", {})),
        )

    def verify_files(self, cache_dir: Path, verification: Verification = Verification.FULL) -> None:
        """Every file present with its recorded size and, as ``verification`` says, sha256;
        CacheManifestError names the first that is not."""
        _verify_files(Path(cache_dir), self.files, verification)


@dataclass(frozen=True)
class FieldCalibration:
    """What the area correlation scores on this map at one working level (``c10_cache_build/map_fields.py``,
    "Calibration").

    Templates cut from the map itself at ``level`` (degraded like a frame) are searched in discs of
    ``radius_px`` px of that level: once where the truth lies inside (``right_*``: how well this map's
    own structure is found, an upper bound for a real frame) and once where it lies outside (``null_*``:
    what a wrong place scores here, the level a real fix must clear). ``texture_p50`` is the median share
    of structure in those templates.
    """

    level: int
    samples: int
    radius_px: float
    template_px: tuple[int, int]
    null_psr_max: float
    null_psr_p95: float
    null_peak_max: float
    right_psr_p5: float
    right_peak_p5: float
    texture_p50: float

    def to_json(self) -> dict[str, Any]:
        out = vars(self).copy()
        out["template_px"] = list(self.template_px)
        return out

    @classmethod
    def from_json(cls, payload: Mapping[str, Any]) -> FieldCalibration:
        return cls(
            level=int(payload["level"]),
            samples=int(payload["samples"]),
            radius_px=float(payload["radius_px"]),
            template_px=(int(payload["template_px"][0]), int(payload["template_px"][1])),
            null_psr_max=float(payload["null_psr_max"]),
            null_psr_p95=float(payload["null_psr_p95"]),
            null_peak_max=float(payload["null_peak_max"]),
            right_psr_p5=float(payload["right_psr_p5"]),
            right_peak_p5=float(payload["right_peak_p5"]),
            texture_p50=float(payload["texture_p50"]),
        )


@dataclass(frozen=True)
class MapFieldsInfo:
    """The map's orientation fields (``c10_cache_build/map_fields.py``): the field definition they were
    made with (``version``), the mosaic they were made from, one quantised field and one CRC-32 table per
    pyramid level (``levels``: level -> (field file, CRC file, cell side px)), every file's size and
    sha256, the map's calibration at each working level it has room for (empty until it is made) and
    build figures (``stats``, for people)."""

    version: str
    mosaic_sha256: str
    levels: Mapping[int, tuple[str, str, int]]
    files: Mapping[str, ArtifactInfo]
    calibrations: Mapping[int, FieldCalibration] = field(default_factory=dict)
    #: Whether the calibration was run (it may have found no level with room for it).
    calibrated: bool = False
    stats: Mapping[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            "version": self.version,
            "mosaic_sha256": self.mosaic_sha256,
            "levels": {
                str(level): {"file": f, "crc_file": c, "cell_px": cell}
                for level, (f, c, cell) in sorted(self.levels.items())
            },
            "files": {name: vars(info).copy() for name, info in sorted(self.files.items())},
            "calibrated": self.calibrated,
            "calibrations": {str(level): c.to_json() for level, c in sorted(self.calibrations.items())},
            "stats": dict(self.stats),
        }

    @classmethod
    def from_json(cls, payload: Mapping[str, Any]) -> MapFieldsInfo:
        return cls(
            version=str(payload["version"]),
            mosaic_sha256=str(payload["mosaic_sha256"]),
            levels={
                int(level): (str(v["file"]), str(v["crc_file"]), int(v["cell_px"]))
                for level, v in payload["levels"].items()
            },
            files={
                str(name): ArtifactInfo(sha256=str(info["sha256"]), bytes=int(info["bytes"]))
                for name, info in payload["files"].items()
            },
            calibrations={
                int(level): FieldCalibration.from_json(c)
                for level, c in payload.get("calibrations", {}).items()
            },
            calibrated=bool(payload.get("calibrated", False)),
            stats=dict(payload.get("stats", {})),
        )

    def verify_files(self, cache_dir: Path, verification: Verification = Verification.FULL) -> None:
        """Every file present with its recorded size and, as ``verification`` says, sha256;
        CacheManifestError names the first that is not."""
        _verify_files(Path(cache_dir), self.files, verification)


@dataclass(frozen=True)
class CacheManifest:
    """In-memory form of ``manifest.json`` (field names mirror the JSON keys).

    ``bbox_lonlat`` is the mapped area ``(west, south, east, north)`` in degrees: the source footprint
    intersected with the requested bbox (the mosaic itself covers the whole tile range around it).
    ``mosaic_shape`` is ``(H, W, 3)`` px. ``artifacts`` maps a file name relative to the cache
    directory to its size and sha256 and is treated as read-only.
    """

    format_version: int
    created_utc: str
    source: SourceInfo
    zoom: int
    tile_size_px: int
    tile_range: TileRange
    bbox_lonlat: tuple[float, float, float, float]
    mosaic_shape: tuple[int, int, int]
    tile_count: int
    min_tile_valid_fraction: float
    resampling: str
    vpr: VprInfo
    artifacts: Mapping[str, ArtifactInfo] = field(default_factory=dict)
    #: Precomputed tile features by C3 strategy label (optional; absent in caches made before them).
    tile_features: Mapping[str, TileFeatureSetInfo] = field(default_factory=dict)
    #: The orientation fields of the area correlation (optional; absent in caches made before them).
    map_fields: MapFieldsInfo | None = None
    #: The sha256 of the manifest's content as read (``content_sha256``; checked by ``load``); None for a
    #: manifest written before it was recorded, or not read from a file. Derived from the other fields, so
    #: not compared; ``to_json`` computes it afresh.
    content_sha256: str | None = field(default=None, compare=False)

    @property
    def mosaic_name(self) -> str:
        return mosaic_name(self.zoom)

    @property
    def cell_crc_name(self) -> str:
        return cell_crc_name(self.zoom)

    @property
    def has_cell_crc(self) -> bool:
        """Whether the build recorded the mosaic's cell CRC table (caches built before it did not)."""
        return self.cell_crc_name in self.artifacts

    def to_json(self) -> dict[str, Any]:
        """The JSON object written to ``manifest.json``, with the sha256 of its content."""
        body = self._body()
        # Hashed as it will read back (tuples become lists, keys strings), so ``load`` computes the same.
        body[CONTENT_SHA256_KEY] = content_sha256(json.loads(json.dumps(body)))
        return body

    def _body(self) -> dict[str, Any]:
        return {
            "format_version": self.format_version,
            "created_utc": self.created_utc,
            "source": vars(self.source).copy(),
            "zoom": self.zoom,
            "tile_size_px": self.tile_size_px,
            "tile_range": vars(self.tile_range).copy(),
            "bbox_lonlat": list(self.bbox_lonlat),
            "mosaic_shape": list(self.mosaic_shape),
            "tile_count": self.tile_count,
            "min_tile_valid_fraction": self.min_tile_valid_fraction,
            "resampling": self.resampling,
            "vpr": vars(self.vpr).copy(),
            "artifacts": {name: vars(info).copy() for name, info in sorted(self.artifacts.items())},
            "tile_features": {name: info.to_json() for name, info in sorted(self.tile_features.items())},
            "map_fields": None if self.map_fields is None else self.map_fields.to_json(),
        }

    @classmethod
    def from_json(cls, payload: Mapping[str, Any], *, path: str | None = None) -> CacheManifest:
        """Parse a manifest object; a wrong version, a missing/mistyped key or a content that does not
        hash to its recorded ``content_sha256`` raises CacheManifestError."""
        version = payload.get("format_version") if isinstance(payload, Mapping) else None
        if version != CACHE_FORMAT_VERSION:
            raise CacheManifestError(
                f"unsupported cache format_version {version!r}, expected {CACHE_FORMAT_VERSION}; "
                "rebuild the cache",
                path=path,
            )
        recorded = payload.get(CONTENT_SHA256_KEY)
        if recorded is not None:
            actual = content_sha256(payload)
            if recorded != actual:
                raise CacheManifestError(
                    f"cache manifest content sha256 mismatch: its content hashes to {actual[:16]}..., "
                    f"{CONTENT_SHA256_KEY} records {str(recorded)[:16]}... (edited or corrupted; rebuild "
                    "with gdnav cache build)",
                    path=path,
                )
        try:
            bbox = tuple(float(v) for v in payload["bbox_lonlat"])
            shape = tuple(int(v) for v in payload["mosaic_shape"])
            if len(bbox) != 4 or len(shape) != 3:
                raise ValueError("bbox_lonlat needs 4 values and mosaic_shape 3")
            vpr = payload["vpr"]
            return cls(
                format_version=int(version),
                created_utc=str(payload["created_utc"]),
                source=SourceInfo(**{k: str(v) for k, v in payload["source"].items()}),
                zoom=int(payload["zoom"]),
                tile_size_px=int(payload["tile_size_px"]),
                tile_range=TileRange(**{k: int(v) for k, v in payload["tile_range"].items()}),
                bbox_lonlat=bbox,  # type: ignore[arg-type]
                mosaic_shape=shape,  # type: ignore[arg-type]
                tile_count=int(payload["tile_count"]),
                min_tile_valid_fraction=float(payload["min_tile_valid_fraction"]),
                resampling=str(payload["resampling"]),
                vpr=VprInfo(backbone=str(vpr["backbone"]), model_sha256=vpr["model_sha256"]),
                artifacts={
                    str(name): ArtifactInfo(sha256=str(info["sha256"]), bytes=int(info["bytes"]))
                    for name, info in payload["artifacts"].items()
                },
                tile_features={
                    str(name): TileFeatureSetInfo.from_json(info)
                    for name, info in payload.get("tile_features", {}).items()
                },
                map_fields=(
                    MapFieldsInfo.from_json(payload["map_fields"])
                    if payload.get("map_fields") is not None
                    else None
                ),
                content_sha256=None if recorded is None else str(recorded),
            )
        except (KeyError, TypeError, ValueError, AttributeError, OverflowError, RecursionError) as exc:
            raise CacheManifestError(f"malformed cache manifest: {exc!r}"[:500], path=path) from exc

    @classmethod
    def load(cls, cache_dir: Path) -> CacheManifest:
        """Read ``cache_dir/manifest.json``; a missing or unreadable manifest raises CacheManifestError."""
        path = Path(cache_dir) / MANIFEST_NAME
        try:
            with path.open("rb") as fh:
                raw = fh.read(MAX_MANIFEST_BYTES + 1)
            text = raw.decode("utf-8")
        except FileNotFoundError as exc:
            raise CacheManifestError(
                "no cache manifest: the directory is not a cache or its build did not finish", path=str(path)
            ) from exc
        except OSError as exc:
            raise CacheManifestError(f"cannot read cache manifest: {exc}", path=str(path)) from exc
        except UnicodeDecodeError as exc:
            raise CacheManifestError(
                f"cache manifest is not UTF-8 text (byte {exc.start}: {exc.reason})", path=str(path)
            ) from exc
        try:
            payload = bounded_json.loads(text, max_bytes=MAX_MANIFEST_BYTES, what="cache manifest")
        except bounded_json.BoundedJsonError as exc:
            raise CacheManifestError(str(exc), path=str(path)) from exc
        if not isinstance(payload, dict):
            raise CacheManifestError(
                f"cache manifest is a JSON {type(payload).__name__}, expected an object", path=str(path)
            )
        return cls.from_json(payload, path=str(path))

    def save(self, cache_dir: Path) -> None:
        """Write ``manifest.json`` atomically (the last step of a build)."""
        write_json_atomic(Path(cache_dir) / MANIFEST_NAME, self.to_json())

    def verify_artifacts(self, cache_dir: Path, verification: Verification = Verification.FULL) -> None:
        """Check that every artifact exists with its recorded size and the sha256 ``verification`` asks
        for (every artifact's when full; only those not ``read_by_window`` when light).

        Raises CacheManifestError naming the first artifact that is missing, truncated/grown or altered.
        """
        cache_dir = Path(cache_dir)
        for name in (self.mosaic_name, TILES_NAME):
            if name not in self.artifacts:
                raise CacheManifestError(
                    f"manifest does not list required artifact {name!r}", path=str(cache_dir)
                )
        _verify_files(cache_dir, self.artifacts, verification)


def _verify_files(cache_dir: Path, files: Mapping[str, ArtifactInfo], verification: Verification) -> None:
    """Sizes first, of every file (cheap), then the sha256 ``verification`` asks for."""
    for name, info in sorted(files.items()):
        path = cache_dir / name
        try:
            size = path.stat().st_size
        except FileNotFoundError as exc:
            raise CacheManifestError(f"cache artifact {name!r} is missing", path=str(path)) from exc
        if size != info.bytes:
            raise CacheManifestError(
                f"cache artifact {name!r} has {size} bytes, manifest records {info.bytes} "
                "(truncated or replaced)",
                path=str(path),
            )
    for name, info in sorted(files.items()):
        if verification is Verification.LIGHT and read_by_window(name):
            continue
        path = cache_dir / name
        actual = sha256_file(path)
        if actual != info.sha256:
            raise CacheManifestError(
                f"cache artifact {name!r} sha256 mismatch: {actual[:16]}..., "
                f"manifest records {info.sha256[:16]}... (tampered or corrupted)",
                path=str(path),
            )


def verify_cache(cache_dir: Path, verification: Verification = Verification.FULL) -> CacheManifest:
    """Load the manifest of ``cache_dir`` (its own hash checked) and check, at ``verification``, its
    artifacts, its orientation fields' files and every tile feature set's files; return the manifest.
    Raises CacheManifestError naming the first file that fails."""
    cache_dir = Path(cache_dir)
    manifest = CacheManifest.load(cache_dir)
    manifest.verify_artifacts(cache_dir, verification)
    if manifest.map_fields is not None:
        manifest.map_fields.verify_files(cache_dir, verification)
    for info in manifest.tile_features.values():
        info.verify_files(cache_dir, verification)
    return manifest
