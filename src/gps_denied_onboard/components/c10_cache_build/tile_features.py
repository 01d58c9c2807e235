"""C10: add a learned strategy's precomputed tile features to a map cache (``gdnav cache features``).

Runs the strategy's own ``extract_tile`` (the hook the candidate loop calls live) once over
``TileStore.chip(tile_id, chip_size_px)`` of every tile and writes the set described in
``c3_matcher.tile_features`` (files, identity, manifest block ``tile_features[<label>]``).

Crash safety, as for the VPR index: the manifest is first rewritten without this strategy's set, then
each file is streamed to a temporary name, fsynced and renamed, then the manifest with the set is written
last. A run interrupted anywhere leaves a cache that verifies and has no set for this strategy.

Idempotent: a set recorded with the same extractor identity for the same tiles and mosaic, whose files
are intact (sizes and sha256), is kept (``force`` rebuilds it). A set made by another extractor (another
model file, chip size, keypoint cap, input size) is replaced, and the replaced identity is logged: the
cache holds at most one set per strategy, and it always says which model made it.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import structlog
from tqdm import tqdm

from gps_denied_onboard.components.c3_matcher.features import Features
from gps_denied_onboard.components.c3_matcher.learned import LearnedPairMatcher
from gps_denied_onboard.components.c3_matcher.tile_features import (
    TILE_TABLE_DTYPE,
    ExtractorIdentity,
    chip_origin,
    entry_crc32,
    file_names,
)
from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.components.c6_tiles.types import TileStoreError
from gps_denied_onboard.components.c10_cache_build.manifest import (
    TILES_NAME,
    CacheBuildError,
    CacheManifest,
    CacheManifestError,
    TileFeatureSetInfo,
    Verification,
)
from gps_denied_onboard.components.c10_cache_build.npy_stream import NpyStream
from gps_denied_onboard.constants import LogEvent

_log = structlog.get_logger(__name__)

_COPY_CHUNK_BYTES = 8 << 20


@dataclasses.dataclass(frozen=True)
class TileFeatureBuild:
    """What ``build_tile_features`` did: the manifest after it, whether it built (False = up to date),
    the set's figures (``TileFeatureSetInfo.stats``) and its size on disk."""

    manifest: CacheManifest
    built: bool
    stats: dict[str, Any]
    bytes: int


def build_tile_features(
    cache_dir: Path,
    matcher: LearnedPairMatcher,
    *,
    force: bool = False,
    progress: bool = True,
    extract: Callable[[np.ndarray], Features] | None = None,
) -> TileFeatureBuild:
    """Precompute ``matcher``'s tile features for every tile of the cache at ``cache_dir``.

    ``extract``: the extraction to run per chip (default ``matcher.extract_tile``; tests wrap it).
    Raises ``CacheBuildError`` for a cache that does not verify or an extraction that fails (naming the
    tile): a set is complete or absent, never partial.
    """
    cache_dir = Path(cache_dir)
    identity: ExtractorIdentity = matcher.extractor_identity
    label = identity.strategy
    extract_fn = extract if extract is not None else matcher.extract_tile
    try:
        store = TileStore.open(cache_dir, Verification.FULL)
    except TileStoreError as exc:
        raise CacheBuildError(f"cache does not verify: {exc}", path=str(cache_dir)) from exc
    manifest = store.manifest
    tiles_sha = manifest.artifacts[TILES_NAME].sha256
    mosaic_sha = manifest.artifacts[manifest.mosaic_name].sha256
    existing = manifest.tile_features.get(label)
    if (
        existing is not None
        and not force
        and _intact(existing, cache_dir, identity, tiles_sha, mosaic_sha, len(store))
    ):
        _log.info(LogEvent.TILE_FEATURES_UP_TO_DATE, cache_dir=str(cache_dir), strategy=label)
        return TileFeatureBuild(manifest, False, dict(existing.stats), _bytes(existing))
    if existing is not None:
        diffs = identity.differences(existing.identity)
        _log.warning(
            LogEvent.TILE_FEATURES_BUILT,
            cache_dir=str(cache_dir),
            strategy=label,
            action="replacing the existing set",
            differences=diffs or ["same identity: forced, or its files or tiles changed"],
        )
    base = dataclasses.replace(
        manifest, tile_features={k: v for k, v in manifest.tile_features.items() if k != label}
    )
    base.save(cache_dir)

    t0 = time.monotonic()
    n = len(store)
    table = np.zeros(n, dtype=TILE_TABLE_DTYPE)
    kp_name, desc_name, table_name = file_names(label)
    kp_out = NpyStream(cache_dir / kp_name)
    desc_out = NpyStream(cache_dir / desc_name)
    dim: int | None = None
    offset = 0
    show = progress and sys.stderr.isatty()
    try:
        for i, tile_id in enumerate(
            tqdm(store.tile_ids, unit="tile", desc=f"tile features {label}", disable=not show)
        ):
            chip = store.chip(tile_id, identity.chip_size_px)
            try:
                feats = extract_fn(chip.pixels())
            except Exception as exc:
                raise CacheBuildError(
                    f"{label} extraction failed on tile {tuple(tile_id)}: {type(exc).__name__}: {exc}",
                    path=str(cache_dir),
                ) from exc
            kp = np.ascontiguousarray(feats.keypoints_px, dtype=np.float32).reshape(-1, 2)
            desc = np.ascontiguousarray(feats.descriptors, dtype=np.float32)
            if desc.ndim != 2 or desc.shape[0] != kp.shape[0]:
                raise CacheBuildError(
                    f"{label} gave {kp.shape[0]} keypoints and descriptors {desc.shape} on tile "
                    f"{tuple(tile_id)}",
                    path=str(cache_dir),
                )
            if dim is None:
                dim = int(desc.shape[1])
            elif desc.shape[1] != dim:
                raise CacheBuildError(
                    f"{label} gave {desc.shape[1]}-D descriptors on tile {tuple(tile_id)}, {dim}-D before",
                    path=str(cache_dir),
                )
            width, height = chip.size_px
            if tuple(feats.image_size) != (width, height):
                raise CacheBuildError(
                    f"{label} reported image size {feats.image_size} for a {width}x{height} chip",
                    path=str(cache_dir),
                )
            lon0, lat0 = chip_origin(chip)
            table[i] = (
                offset,
                kp.shape[0],
                width,
                height,
                lon0,
                lat0,
                chip.gsd_m_px,
                entry_crc32(kp, desc),
            )
            kp_out.append(kp)
            desc_out.append(desc)
            offset += kp.shape[0]
        extract_s = time.monotonic() - t0
        files = {
            kp_name: kp_out.finish(np.dtype(np.float32), (offset, 2)),
            desc_name: desc_out.finish(np.dtype(np.float32), (offset, dim or 0)),
        }
        table_stream = NpyStream(cache_dir / table_name)
        table_stream.append(table)
        files[table_name] = table_stream.finish(TILE_TABLE_DTYPE, (n,))
    except OSError as exc:
        raise CacheBuildError(f"cannot write {label} tile features: {exc}", path=str(cache_dir)) from exc
    finally:
        kp_out.discard()
        desc_out.discard()
    stats = {
        "keypoints": int(offset),
        "keypoints_per_tile_mean": round(offset / max(1, n), 1),
        "descriptor_dim": int(dim or 0),
        "extract_s": round(extract_s, 2),
        "total_s": round(time.monotonic() - t0, 2),
        "created_utc": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
    }
    info = TileFeatureSetInfo(
        identity=identity.to_json(),
        tiles_sha256=tiles_sha,
        mosaic_sha256=mosaic_sha,
        tile_count=n,
        files=files,
        stats=stats,
    )
    updated = dataclasses.replace(base, tile_features={**base.tile_features, label: info})
    try:
        updated.save(cache_dir)
    except OSError as exc:
        raise CacheBuildError(f"cannot write the cache manifest: {exc}", path=str(cache_dir)) from exc
    size = _bytes(info)
    _log.info(
        LogEvent.TILE_FEATURES_BUILT,
        cache_dir=str(cache_dir),
        strategy=label,
        model_sha256=identity.model_sha256,
        tile_count=n,
        bytes=size,
        **stats,
    )
    return TileFeatureBuild(updated, True, stats, size)


def _bytes(info: TileFeatureSetInfo) -> int:
    return sum(f.bytes for f in info.files.values())


def _intact(
    info: TileFeatureSetInfo,
    cache_dir: Path,
    identity: ExtractorIdentity,
    tiles_sha: str,
    mosaic_sha: str,
    n_tiles: int,
) -> bool:
    if identity.differences(info.identity) or set(info.files) != set(file_names(identity.strategy)):
        return False
    if info.tiles_sha256 != tiles_sha or info.mosaic_sha256 != mosaic_sha or info.tile_count != n_tiles:
        return False
    try:
        info.verify_files(cache_dir, Verification.FULL)
    except CacheManifestError:
        return False
    return True
