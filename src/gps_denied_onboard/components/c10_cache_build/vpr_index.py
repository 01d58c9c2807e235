"""C10: add appearance-VPR artifacts to an existing map cache (F1, after the tiles are built).

Adds to the cache directory (names in ``c2_vpr.retrieval`` / ``c2_vpr.vlad``)::

    vpr_descriptors.npy          float32 (N, D): global descriptor of every tile's chip, row i = tile i
    vpr_index.faiss              FAISS IndexHNSWFlat over those rows (C6 ``DescriptorIndex``)
    vpr_meta.json                backbone label, model sha256, dim, chip size, parameters, tile count
    vpr_vlad_vocabulary.npz      (``vlad``, ``vlad_xfeat``) vocabulary + PCA-whitening learned from this cache

and updates the manifest's ``vpr`` block (backbone label + model sha256: the VLAD vocabulary's for the
weights-free ``vlad``, the XFeat extractor's ONNX file for ``vlad_xfeat``, the ONNX file's for a global
model) and ``artifacts`` (size + sha256 of each file), so the daemon refuses a cache whose descriptors
come from another backbone or model, and C6's hash gate covers the index.

Sharding: with an engine of other processes (``shards``: ``--workers`` / ``--address``), the VLAD
descriptors of weights-free ``vlad`` are computed in shards of ``VPR_SHARD_TILES`` consecutive tiles by
``describe_tile_range``, which rebuilds the encoder from the vocabulary file, and gathered in tile order:
the same bytes as in one process. The vocabulary and the index are made in this process.

Crash safety: the manifest is first rewritten *without* VPR artifacts (backbone ``geo_prior``), then the
files are written (temporary name + fsync + rename), then the manifest with them is written last. A run
interrupted anywhere leaves a cache that verifies; re-running finishes the job. Idempotent: when the
manifest already records this backbone with the same parameters (and model hash), intact artifacts and
the same tile list, nothing is recomputed.
"""

from __future__ import annotations

import dataclasses
import functools
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Final

import numpy as np
import structlog
from tqdm import tqdm

from gps_denied_onboard.components.c2_vpr.retrieval import (
    VPR_DESCRIPTORS_NAME,
    VPR_INDEX_NAME,
    VPR_META_NAME,
    GlobalEncoder,
)
from gps_denied_onboard.components.c2_vpr.vlad import (
    VLAD_VOCABULARY_NAME,
    LocalDescriber,
    VladEncoder,
    VladError,
    VladParams,
    VladVocabulary,
    train_vocabulary,
)
from gps_denied_onboard.components.c6_tiles.descriptor_index import DescriptorIndex
from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.components.c6_tiles.types import TileStoreError
from gps_denied_onboard.components.c10_cache_build.manifest import (
    TILES_NAME,
    ArtifactInfo,
    CacheBuildError,
    CacheManifest,
    CacheManifestError,
    Verification,
    VprInfo,
    sha256_file,
    write_json_atomic,
)
from gps_denied_onboard.components.c10_cache_build.npy_stream import save_npy_atomic
from gps_denied_onboard.components.c10_cache_build.shards import (
    EngineSpec,
    ShardEngine,
    engine_scope,
    is_distributed,
    run_ordered,
)
from gps_denied_onboard.constants import LogEvent
from gps_denied_onboard.helpers import bounded_json

_log = structlog.get_logger(__name__)

#: Every artifact this module may own; they are removed from the manifest before a rebuild.
VPR_ARTIFACT_NAMES: Final[frozenset[str]] = frozenset(
    {VPR_DESCRIPTORS_NAME, VPR_INDEX_NAME, VPR_META_NAME, VLAD_VOCABULARY_NAME}
)
_NO_VPR = VprInfo(backbone="geo_prior", model_sha256=None)
#: Tiles a VPR shard describes (about the mosaic's shard: 64 tiles).
VPR_SHARD_TILES: Final = 64


def build_vlad_index(
    cache_dir: Path,
    params: VladParams | None = None,
    *,
    describer: LocalDescriber | None = None,
    force: bool = False,
    progress: bool = True,
    engine: EngineSpec | ShardEngine | None = None,
) -> CacheManifest:
    """Train a VLAD vocabulary on the cache's own mosaic, describe every tile, build the HNSW index.

    ``describer`` gives the local descriptors ``params.descriptor`` names (default: dense RootSIFT,
    strategy ``vlad``; an ``XFeatDescriber`` for ``vlad_xfeat``, whose model sha256 the manifest then
    records). ``engine`` (``shards``) describes the tiles in shards on other processes; only the default
    describer can be rebuilt there. Returns the updated manifest. Raises ``CacheBuildError`` for an
    unusable cache or map, a describer that does not give ``params.descriptor``, or a describer given
    with an engine of other processes.
    """
    if describer is not None and is_distributed(engine):
        raise CacheBuildError(
            "VLAD descriptors run on workers with the default dense RootSIFT only; "
            "a learned describer is built in this process (drop --workers/--address)",
            path=str(cache_dir),
        )
    params = params or VladParams()
    cache_dir = Path(cache_dir)
    wanted: dict[str, Any] = {
        "backbone": params.label,
        "params": asdict(params),
        "chip_size_px": params.chip_size_px,
    }
    if describer is not None and describer.model_sha256 is not None:
        wanted["model_sha256"] = describer.model_sha256
    existing = _up_to_date(cache_dir, wanted)
    if existing is not None and not force:
        return existing
    t0 = time.monotonic()
    store = _open_base(cache_dir)
    try:
        vocab = train_vocabulary(store, params, describer=describer)
    except VladError as exc:
        raise CacheBuildError(f"cannot train the VLAD vocabulary: {exc}", path=str(cache_dir)) from exc
    vocab_path = cache_dir / VLAD_VOCABULARY_NAME
    try:
        vocab.save(vocab_path)
    except OSError as exc:
        raise CacheBuildError(f"cannot write the VLAD vocabulary: {exc}", path=str(vocab_path)) from exc
    train_s = time.monotonic() - t0
    vocab_sha = sha256_file(vocab_path)
    encoder = VladEncoder(vocab, model_sha256=vocab_sha, describer=describer)
    return _describe_and_index(
        store,
        encoder,
        params.chip_size_px,
        wanted,
        extra_artifacts=(VLAD_VOCABULARY_NAME,),
        progress=progress,
        t_start=t0,
        extra_timing={"vocabulary_s": round(train_s, 2)},
        engine=engine,
        vocab_sha256=vocab_sha,
    )


def build_encoder_index(
    cache_dir: Path,
    encoder: GlobalEncoder,
    *,
    chip_size_px: int = 512,
    force: bool = False,
    progress: bool = True,
) -> CacheManifest:
    """Describe every tile with a ready encoder (e.g. ``OnnxGlobalEncoder``) and build the HNSW index.

    The manifest records ``encoder.label`` and ``encoder.model_sha256``. Raises ``CacheBuildError``.
    """
    cache_dir = Path(cache_dir)
    wanted = {
        "backbone": encoder.label,
        "model_sha256": encoder.model_sha256,
        "chip_size_px": int(chip_size_px),
        "dim": encoder.dim,
    }
    existing = _up_to_date(cache_dir, wanted)
    if existing is not None and not force:
        return existing
    t0 = time.monotonic()
    store = _open_base(cache_dir)
    return _describe_and_index(
        store,
        encoder,
        chip_size_px,
        wanted,
        extra_artifacts=(),
        progress=progress,
        t_start=t0,
        extra_timing={},
    )


def read_vpr_meta(cache_dir: Path) -> dict[str, Any]:
    """The cache's ``vpr_meta.json`` (``CacheBuildError`` when absent or malformed)."""
    path = Path(cache_dir) / VPR_META_NAME
    try:
        payload = bounded_json.loads(path.read_bytes(), max_bytes=1 << 20, what="VPR metadata")
    except (OSError, ValueError) as exc:
        raise CacheBuildError(f"cannot read VPR metadata: {exc}", path=str(path)) from exc
    if not isinstance(payload, dict):
        raise CacheBuildError("VPR metadata is not a JSON object", path=str(path))
    return payload


def _up_to_date(cache_dir: Path, wanted: dict[str, Any]) -> CacheManifest | None:
    """The manifest when it already records VPR artifacts made with exactly ``wanted``, intact in size."""
    try:
        manifest = CacheManifest.load(cache_dir)
        _without_vpr(manifest).verify_artifacts(cache_dir, Verification.LIGHT)
    except CacheManifestError as exc:
        raise CacheBuildError(f"not a usable cache: {exc.message}", path=str(cache_dir)) from exc
    if manifest.vpr.backbone != wanted["backbone"] or VPR_META_NAME not in manifest.artifacts:
        return None
    try:
        # Damaged VPR artifacts (an interrupted or tampered earlier run) just mean "rebuild them".
        manifest.verify_artifacts(cache_dir, Verification.LIGHT)
    except CacheManifestError:
        return None
    try:
        meta = read_vpr_meta(cache_dir)
    except CacheBuildError:
        return None
    same = (
        all(meta.get(key) == value for key, value in wanted.items())
        and meta.get("tiles_sha256") == manifest.artifacts[TILES_NAME].sha256
        and meta.get("mosaic_sha256") == manifest.artifacts[manifest.mosaic_name].sha256
    )
    if same:
        _log.info(LogEvent.VPR_INDEX_UP_TO_DATE, cache_dir=str(cache_dir), backbone=manifest.vpr.backbone)
        return manifest
    return None


def _without_vpr(manifest: CacheManifest) -> CacheManifest:
    """The manifest as it was before any VPR build: backbone ``geo_prior``, no VPR artifacts."""
    artifacts = {k: v for k, v in manifest.artifacts.items() if k not in VPR_ARTIFACT_NAMES}
    return dataclasses.replace(manifest, vpr=_NO_VPR, artifacts=artifacts)


def _open_base(cache_dir: Path) -> TileStore:
    """Drop any VPR artifacts from the manifest (saved atomically), then open and verify the tiles."""
    manifest = CacheManifest.load(cache_dir)
    base = _without_vpr(manifest)
    if base != manifest:
        base.save(cache_dir)
    try:
        return TileStore.open(cache_dir, Verification.FULL)
    except TileStoreError as exc:
        raise CacheBuildError(f"cache does not verify: {exc}", path=str(cache_dir)) from exc


def _describe_and_index(
    store: TileStore,
    encoder: GlobalEncoder,
    chip_size_px: int,
    wanted: dict[str, Any],
    *,
    extra_artifacts: tuple[str, ...],
    progress: bool,
    t_start: float,
    extra_timing: dict[str, float],
    engine: EngineSpec | ShardEngine | None = None,
    vocab_sha256: str | None = None,
) -> CacheManifest:
    cache_dir = store.cache_dir
    n = len(store)
    descriptors = np.empty((n, encoder.dim), dtype=np.float32)
    t_desc = time.monotonic()
    show = progress and sys.stderr.isatty()
    if is_distributed(engine) and vocab_sha256 is not None:
        _describe_in_shards(store, descriptors, chip_size_px, vocab_sha256, engine, show, encoder.label)
    else:
        for i, tile_id in enumerate(
            tqdm(store.tile_ids, unit="tile", desc=f"vpr {encoder.label}", disable=not show)
        ):
            descriptors[i] = encoder.embed_image(np.asarray(store.chip(tile_id, chip_size_px).pixels()))
    describe_s = time.monotonic() - t_desc
    if not np.isfinite(descriptors).all():
        raise CacheBuildError(
            f"backbone {encoder.label!r} produced non-finite descriptors", path=str(cache_dir)
        )
    t_index = time.monotonic()
    index = DescriptorIndex.build(descriptors)
    index_s = time.monotonic() - t_index
    manifest = store.manifest
    meta = {
        **wanted,
        "model_sha256": encoder.model_sha256,
        "dim": encoder.dim,
        "tile_count": n,
        "tiles_sha256": manifest.artifacts[TILES_NAME].sha256,
        "mosaic_sha256": manifest.artifacts[manifest.mosaic_name].sha256,
        "index": {"type": "IndexHNSWFlat", "metric": "L2", "m": 32, "ef_construction": 80},
    }
    try:
        index.save(cache_dir / VPR_INDEX_NAME)
        save_npy_atomic(cache_dir / VPR_DESCRIPTORS_NAME, descriptors)
        write_json_atomic(cache_dir / VPR_META_NAME, meta)
        names = (VPR_DESCRIPTORS_NAME, VPR_INDEX_NAME, VPR_META_NAME, *extra_artifacts)
        artifacts = dict(manifest.artifacts)
        for name in names:
            path = cache_dir / name
            artifacts[name] = ArtifactInfo(sha256=sha256_file(path), bytes=path.stat().st_size)
        updated = dataclasses.replace(
            manifest,
            vpr=VprInfo(backbone=encoder.label, model_sha256=encoder.model_sha256),
            artifacts=artifacts,
        )
        updated.save(cache_dir)
    except OSError as exc:
        raise CacheBuildError(f"cannot write VPR artifacts: {exc}", path=str(cache_dir)) from exc
    _log.info(
        LogEvent.VPR_INDEX_BUILT,
        cache_dir=str(cache_dir),
        backbone=encoder.label,
        dim=encoder.dim,
        tile_count=n,
        describe_s=round(describe_s, 2),
        index_s=round(index_s, 3),
        total_s=round(time.monotonic() - t_start, 2),
        **extra_timing,
    )
    return updated


def _describe_in_shards(
    store: TileStore,
    descriptors: np.ndarray,
    chip_size_px: int,
    vocab_sha256: str,
    engine: EngineSpec | ShardEngine | None,
    show: bool,
    label: str,
) -> None:
    """Fill ``descriptors`` (N, D) float32 in tile order, shard by shard, on ``engine``."""
    n = len(store)
    ranges = [(i0, min(i0 + VPR_SHARD_TILES, n)) for i0 in range(0, n, VPR_SHARD_TILES)]
    work = functools.partial(describe_tile_range, str(store.cache_dir), vocab_sha256, chip_size_px)
    with (
        engine_scope(engine) as runner,
        tqdm(total=len(ranges), unit="shard", desc=f"vpr {label}", disable=not show) as bar,
    ):
        for (i0, i1), block in zip(ranges, run_ordered(runner, work, ranges), strict=True):
            descriptors[i0:i1] = block
            bar.update(1)


def describe_tile_range(
    cache_dir: str, vocab_sha256: str, chip_size_px: int, tile_range: tuple[int, int]
) -> np.ndarray:
    """The VLAD descriptors, float32 (i1 - i0, D), of tiles ``i0..i1`` of the cache's tile list, with the
    default describer and the cache's vocabulary file (whose sha256 names the encoder a worker keeps).

    Runs in any process (a Dask worker included): it opens the cache and the vocabulary itself.
    """
    store, encoder = _worker_encoder(cache_dir, vocab_sha256)
    i0, i1 = tile_range
    return np.stack(
        [
            encoder.embed_image(np.asarray(store.chip(tile_id, chip_size_px).pixels()))
            for tile_id in store.tile_ids[i0:i1]
        ]
    ).astype(np.float32, copy=False)


@functools.lru_cache(maxsize=2)
def _worker_encoder(cache_dir: str, vocab_sha256: str) -> tuple[TileStore, VladEncoder]:
    """This process's store and encoder for one build (the driver verified the cache's hashes)."""
    store = TileStore.open(Path(cache_dir), Verification.LIGHT)
    vocab = VladVocabulary.load(Path(cache_dir) / VLAD_VOCABULARY_NAME)
    return store, VladEncoder(vocab, model_sha256=vocab_sha256)
