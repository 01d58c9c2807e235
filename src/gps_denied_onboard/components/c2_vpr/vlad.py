"""``vlad``: weights-free appearance VPR: dense upright RootSIFT aggregated with VLAD.

Input: a tile chip (C10, at cache time) or a query normalised to the map's frame (``query_norm``:
north-up, map GSD, chip-sized), with its invalid pixels. Output: a descriptor (``VladEncoder``) and, in
``VladVpr``, the nearest tiles from the HNSW index.

Rule (the recipe): dense, upright SIFT-layout descriptors on a fixed grid at one scale (patches touching
an invalid pixel dropped), RootSIFT; VLAD over a k-means vocabulary learned at cache time from the
corpus's own chips, intra-normalised, power-law, L2; PCA to ``pca_dim`` with regularised whitening
(eigenvalue + ``whiten_eps`` x the largest). ``VladVocabulary`` is the learned state, a cache artifact
whose sha256 is the manifest's ``vpr.model_sha256``. The local descriptors are a seam, ``LocalDescriber``
(``VladParams.descriptor``): ``RootSiftDescriber`` here, ``learned_local.XFeatDescriber`` for
``vlad_xfeat`` (then ``vpr.model_sha256`` is the extractor model's, and another model is refused).

Why this recipe, and the settings tried: docs/design.md, "`c2_vpr/vlad.py`: weights-free VPR";
docs/benchmarks.md, "C2 place recognition".
"""

from __future__ import annotations

import io
import json
import os
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Final, Protocol, runtime_checkable

import cv2
import faiss
import numpy as np

from gps_denied_onboard.components.c2_vpr.query_norm import QueryNormaliser
from gps_denied_onboard.components.c2_vpr.retrieval import (
    VPR_DESCRIPTORS_NAME,
    VPR_INDEX_NAME,
    IndexedVpr,
    check_cache_backbone,
)
from gps_denied_onboard.components.c2_vpr.types import IndexUnavailableError
from gps_denied_onboard.components.c6_tiles.descriptor_index import (
    HNSW_EF_SEARCH,
    DescriptorIndex,
    l2_normalise,
)
from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.helpers import bounded_json

LABEL: Final[str] = "vlad"
#: Cache artifact holding the vocabulary, PCA and parameters (npz, no pickle).
VLAD_VOCABULARY_NAME: Final[str] = "vpr_vlad_vocabulary.npz"
_SIFT_DIM: Final[int] = 128
_N_BINS: Final[int] = 8
#: Local descriptors VLAD aggregates (``VladParams.descriptor``) -> their dimension.
LOCAL_DESCRIPTOR_DIMS: Final[Mapping[str, int]] = {"rootsift": _SIFT_DIM, "xfeat": 64}
#: C2 strategy label (``vpr.strategy``, the manifest's ``vpr.backbone``) of VLAD over each descriptor.
STRATEGY_LABELS: Final[Mapping[str, str]] = {"rootsift": LABEL, "xfeat": "vlad_xfeat"}


class VladError(ValueError):
    """A VLAD vocabulary cannot be trained or loaded (too little texture, malformed file)."""

    def __init__(self, message: str, *, path: str | None = None) -> None:
        super().__init__(f"{message} ({path})" if path else message)
        self.path = path


@dataclass(frozen=True)
class VladParams:
    """How chips are described.

    ``descriptor``: the local descriptors aggregated (``LOCAL_DESCRIPTOR_DIMS``: dense RootSIFT, or a
    learned extractor's keypoint descriptors, see ``LocalDescriber``). ``max_keypoints``: learned
    extractors keep at most this many keypoints (top scores) per image.
    ``n_clusters``: vocabulary size k (VLAD dim = d k before PCA, d = the local descriptor's dim).
    ``pca_dim``: output dim after PCA-whitening (0 = no PCA, output d k). ``work_size_px``: chips (and
    queries) are resized to this square before extraction (cost control; XFeat: its input side).
    ``grid_step_px`` / ``patch_px``: dense grid spacing and SIFT patch size, px at ``work_size_px``.
    ``chip_size_px``: map chip side the descriptors are computed on (the query is normalised to the
    same). ``train_samples``: chips sampled at random mosaic positions to learn the vocabulary and PCA.
    ``whiten_eps``: added to each PCA eigenvalue (relative to the largest) before whitening, so near-zero
    directions are not blown up. ``seed``: k-means and sampling seed.
    """

    n_clusters: int = 64
    pca_dim: int = 256
    work_size_px: int = 256
    grid_step_px: int = 8
    patch_px: int = 16
    chip_size_px: int = 512
    train_samples: int = 600
    whiten_eps: float = 1.0
    seed: int = 0
    descriptor: str = "rootsift"
    max_keypoints: int = 1024

    def __post_init__(self) -> None:
        if self.descriptor not in LOCAL_DESCRIPTOR_DIMS:
            raise ValueError(
                f"descriptor must be one of {sorted(LOCAL_DESCRIPTOR_DIMS)}, got {self.descriptor!r}"
            )
        if self.max_keypoints < 16:
            raise ValueError(f"max_keypoints must be >= 16, got {self.max_keypoints}")
        if not 2 <= self.n_clusters <= 1024:
            raise ValueError(f"n_clusters must be in 2..1024, got {self.n_clusters}")
        if self.pca_dim < 0:
            raise ValueError(f"pca_dim must be >= 0, got {self.pca_dim}")
        if self.work_size_px < 32 or self.chip_size_px < 32:
            raise ValueError("work_size_px and chip_size_px must be >= 32")
        if self.grid_step_px < 1 or self.patch_px < 4:
            raise ValueError("grid_step_px must be >= 1 and patch_px >= 4")
        if self.train_samples < 8:
            raise ValueError(f"train_samples must be >= 8, got {self.train_samples}")
        if not self.whiten_eps >= 0:
            raise ValueError(f"whiten_eps must be >= 0, got {self.whiten_eps}")

    @property
    def local_dim(self) -> int:
        return LOCAL_DESCRIPTOR_DIMS[self.descriptor]

    @property
    def vlad_dim(self) -> int:
        return self.n_clusters * self.local_dim

    @property
    def label(self) -> str:
        """The C2 strategy these parameters make (``vlad``, ``vlad_xfeat``)."""
        return STRATEGY_LABELS[self.descriptor]


@dataclass(frozen=True, eq=False)
class VladVocabulary:
    """Learned state: ``centroids`` (k, d) float32 words of the local descriptor (d = 128 for RootSIFT,
    64 for XFeat); ``pca_mean`` (d k,) float32 and ``pca_proj`` (d k, D) float32 (whitening folded in),
    both empty when ``params.pca_dim == 0``."""

    params: VladParams
    centroids: np.ndarray
    pca_mean: np.ndarray
    pca_proj: np.ndarray

    @property
    def dim(self) -> int:
        return int(self.pca_proj.shape[1]) if self.pca_proj.size else self.params.vlad_dim

    def save(self, path: Path) -> None:
        """Write as an npz (no pickle) atomically."""
        p = Path(path)
        buf = io.BytesIO()
        np.savez(
            buf,
            params=np.array(json.dumps(asdict(self.params), sort_keys=True)),
            centroids=self.centroids,
            pca_mean=self.pca_mean,
            pca_proj=self.pca_proj,
        )
        tmp = p.with_name(p.name + ".tmp")
        with open(tmp, "wb") as fh:
            fh.write(buf.getvalue())
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, p)

    @classmethod
    def load(cls, path: Path) -> VladVocabulary:
        """Read a vocabulary written by ``save``; ``VladError`` when missing or malformed."""
        p = Path(path)
        try:
            with np.load(p, allow_pickle=False) as data:
                stored = bounded_json.loads(str(data["params"]), max_bytes=1 << 16, what="VLAD params")
                params = VladParams(**stored)
                centroids = np.asarray(data["centroids"], dtype=np.float32)
                pca_mean = np.asarray(data["pca_mean"], dtype=np.float32)
                pca_proj = np.asarray(data["pca_proj"], dtype=np.float32)
        except (OSError, KeyError, ValueError, TypeError) as exc:
            raise VladError(f"cannot read VLAD vocabulary: {exc}", path=str(p)) from exc
        if centroids.shape != (params.n_clusters, params.local_dim):
            raise VladError(
                f"centroids have shape {centroids.shape}, params say k={params.n_clusters}", path=str(p)
            )
        if pca_proj.size and (pca_proj.shape[0] != params.vlad_dim or pca_mean.shape != (params.vlad_dim,)):
            raise VladError(
                f"PCA of shape {pca_proj.shape} does not fit VLAD dim {params.vlad_dim}", path=str(p)
            )
        return cls(params, centroids, pca_mean, pca_proj)


@runtime_checkable
class LocalDescriber(Protocol):
    """The seam between VLAD and where its local descriptors come from.

    ``name``: the ``VladParams.descriptor`` it implements. ``model_sha256``: sha256 of the weights the
    descriptors come from (None for a weights-free describer); the cache records it and a cache built
    with another model is refused. ``describe``: (H, W, 3) uint8 BGR image (0 = invalid) and the
    cache's parameters -> (n, d) float32 local descriptors of its valid area (n may be 0). Must be
    thread-safe.
    """

    @property
    def name(self) -> str: ...

    @property
    def model_sha256(self) -> str | None: ...

    def describe(self, image_bgr: np.ndarray, params: VladParams) -> np.ndarray: ...


class RootSiftDescriber:
    """``LocalDescriber`` of dense upright RootSIFT (``local_descriptors``); weights-free."""

    name: Final[str] = "rootsift"

    def __init__(self) -> None:
        self._grids: dict[tuple[int, int, int], np.ndarray] = {}

    @property
    def model_sha256(self) -> str | None:
        return None

    def describe(self, image_bgr: np.ndarray, params: VladParams) -> np.ndarray:
        key = (params.work_size_px, params.grid_step_px, params.patch_px)
        grid = self._grids.get(key)
        if grid is None:
            grid = self._grids.setdefault(key, _dense_grid(params))
        return local_descriptors(image_bgr, params, grid)


def _check_describer(describer: LocalDescriber, params: VladParams) -> None:
    if describer.name != params.descriptor:
        raise VladError(
            f"the vocabulary was learned on {params.descriptor!r} descriptors, "
            f"the describer gives {describer.name!r}"
        )


class VladEncoder:
    """Image (chip or normalised query) -> L2-normalised VLAD descriptor (see the module docstring).

    ``describer``: where the local descriptors come from (default: dense RootSIFT); it must give the
    descriptor the vocabulary was learned on (``VladError`` otherwise). ``model_sha256``: what the cache
    records for this encoder: the describer's model hash when it has weights, else the sha256 of the
    vocabulary file (None when built in memory). Thread-safe: the vocabulary is read-only.
    """

    def __init__(
        self,
        vocabulary: VladVocabulary,
        *,
        model_sha256: str | None = None,
        describer: LocalDescriber | None = None,
    ) -> None:
        self._vocab = vocabulary
        self._describer: LocalDescriber = describer if describer is not None else RootSiftDescriber()
        _check_describer(self._describer, vocabulary.params)
        self._model_sha256 = self._describer.model_sha256 or model_sha256
        self._words = faiss.IndexFlatL2(vocabulary.params.local_dim)
        self._words.add(np.ascontiguousarray(vocabulary.centroids))

    @property
    def label(self) -> str:
        return self._vocab.params.label

    @property
    def dim(self) -> int:
        return self._vocab.dim

    @property
    def model_sha256(self) -> str | None:
        """The describer's model sha256, else the vocabulary file's (None when built in memory)."""
        return self._model_sha256

    @property
    def params(self) -> VladParams:
        return self._vocab.params

    def embed_image(self, image_bgr: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 BGR image, 0 = invalid -> (D,) float32 unit-norm descriptor.

        An image with no valid local descriptor gives the zero vector (it matches nothing, distance ~1.41).
        """
        desc = self._describer.describe(image_bgr, self._vocab.params)
        vlad = _vlad(desc, self._vocab.centroids, self._words)
        return _project(vlad[None, :], self._vocab)[0]


def local_descriptors(
    image_bgr: np.ndarray, params: VladParams, grid: np.ndarray | None = None
) -> np.ndarray:
    """Dense upright RootSIFT of an image, (n, 128) float32; patches touching 0-pixels are dropped.

    The SIFT layout (4 x 4 cells x 8 orientation bins, linear orientation interpolation, 0.2 clipping)
    is computed for all grid points at once from pooled orientation maps: ~30x cheaper than OpenCV's
    ``SIFT.compute`` on explicit keypoints, which builds a full scale-space pyramid per image.
    """
    img: np.ndarray = np.asarray(image_bgr)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"image must be (H, W, 3) uint8, got {img.shape} {img.dtype}")
    size = params.work_size_px
    small = cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)
    grey = cv2.cvtColor(small, cv2.COLOR_BGR2GRAY).astype(np.float32)
    valid_full = np.asarray(img.any(axis=2), dtype=np.uint8)
    valid = cv2.resize(valid_full, (size, size), interpolation=cv2.INTER_NEAREST)
    pts = grid if grid is not None else _dense_grid(params)
    # A patch is usable when its whole support is valid: erode the mask by the patch radius.
    half = params.patch_px // 2 + 1
    eroded = cv2.erode(
        valid, np.ones((2 * half + 1, 2 * half + 1), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0
    )
    ok = eroded[pts[:, 1].astype(int), pts[:, 0].astype(int)] > 0
    if not ok.any():
        return np.empty((0, _SIFT_DIM), np.float32)
    pts = pts[ok]
    smooth = cv2.GaussianBlur(grey, (0, 0), 0.8)
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=1)
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=1)
    mag, ang = cv2.cartToPolar(gx, gy)
    pos = ang * (_N_BINS / (2.0 * np.pi))
    lo = np.floor(pos)
    frac = pos - lo
    lo = lo.astype(np.int32) % _N_BINS
    hi = (lo + 1) % _N_BINS
    cell = params.patch_px / 4.0
    pooled = np.empty((_N_BINS, size, size), np.float32)
    for b in range(_N_BINS):
        channel = mag * ((lo == b) * (1.0 - frac) + (hi == b) * frac)
        # Pool over one cell (box of the cell's size centred on each pixel).
        pooled[b] = cv2.blur(channel, (max(round(cell), 1),) * 2, borderType=cv2.BORDER_REFLECT)
    # The box filter's float sums leave values like -1e-17 where the gradient is zero; RootSIFT's square
    # root turns those into NaN (seen on the procedural demo map's flat areas: the index build failed).
    np.maximum(pooled, 0.0, out=pooled)
    offsets = (np.arange(4, dtype=np.float32) - 1.5) * cell
    cx = np.clip(np.rint(pts[:, 0:1] + offsets[None, :]), 0, size - 1).astype(np.int64)  # (n, 4)
    cy = np.clip(np.rint(pts[:, 1:2] + offsets[None, :]), 0, size - 1).astype(np.int64)
    # desc[n, row, col, bin] = pooled[bin, cy[n, row], cx[n, col]]
    desc = pooled[:, cy[:, :, None], cx[:, None, :]]  # (8, n, 4, 4)
    desc = np.moveaxis(desc, 0, -1).reshape(len(pts), _SIFT_DIM)
    desc = l2_normalise(desc)
    desc = np.minimum(desc, 0.2)  # SIFT's clipping: limits the weight of a few strong edges
    desc /= np.maximum(desc.sum(axis=1, keepdims=True), 1e-12)
    return np.sqrt(desc).astype(np.float32)


def _dense_grid(params: VladParams) -> np.ndarray:
    """(n, 2) float32 grid points (x, y) at ``work_size_px``, inset by half a patch."""
    start = params.patch_px / 2.0
    coords = np.arange(start, params.work_size_px - start + 1e-6, params.grid_step_px, dtype=np.float32)
    xs, ys = np.meshgrid(coords, coords)
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


def _vlad(desc: np.ndarray, centroids: np.ndarray, words: faiss.IndexFlatL2) -> np.ndarray:
    """(n, d) local descriptors -> (d k,) float32 VLAD, intra-normalised + power-law + L2."""
    k, d = centroids.shape
    out = np.zeros((k, d), np.float32)
    if desc.shape[0] == 0:
        return out.ravel()
    _, assign = words.search(np.ascontiguousarray(desc), 1)
    assign = assign[:, 0]
    np.add.at(out, assign, desc - centroids[assign])
    out = l2_normalise(out)  # intra-normalisation (per word)
    out = np.sign(out) * np.sqrt(np.abs(out))  # power law, alpha = 0.5
    return l2_normalise(out.ravel())


def _project(vlad: np.ndarray, vocab: VladVocabulary) -> np.ndarray:
    """(n, d k) VLAD -> (n, D) final descriptors (PCA-whitened when learned), L2-normalised."""
    if vocab.pca_proj.size == 0:
        return l2_normalise(vlad)
    return l2_normalise((vlad - vocab.pca_mean) @ vocab.pca_proj)


def sample_training_chips(store: TileStore, params: VladParams) -> list[np.ndarray]:
    """``params.train_samples`` chips of ``chip_size_px`` at seeded random mosaic positions, mostly valid.

    Random positions (not only tile centres) give the vocabulary and PCA enough samples on small
    corpora, and cover the half-tile offsets at which queries arrive.
    """
    rng = np.random.default_rng(params.seed)
    mosaic = store.mosaic
    height, width = mosaic.shape[:2]
    size = min(params.chip_size_px, height, width)
    chips: list[np.ndarray] = []
    attempts = 0
    while len(chips) < params.train_samples and attempts < params.train_samples * 10:
        attempts += 1
        row = int(rng.integers(0, height - size + 1))
        col = int(rng.integers(0, width - size + 1))
        chip = mosaic[row : row + size, col : col + size]
        # Cheap validity estimate on a subsample: skip chips mostly outside the map.
        if chip[::8, ::8].any(axis=2).mean() < 0.5:
            continue
        chips.append(chip)
    return chips


def train_vocabulary(
    store: TileStore,
    params: VladParams,
    *,
    describer: LocalDescriber | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> VladVocabulary:
    """Learn words and PCA-whitening from the cache's own mosaic (see ``sample_training_chips``).

    ``describer`` gives the local descriptors (default: dense RootSIFT; it must implement
    ``params.descriptor``). Raises ``VladError`` when the map has too little texture for ``n_clusters``
    words.
    """
    describer = describer if describer is not None else RootSiftDescriber()
    _check_describer(describer, params)
    chips = sample_training_chips(store, params)
    if len(chips) < 8:
        raise VladError(
            f"only {len(chips)} valid training chips in the mosaic; the map is too small or empty",
            path=str(store.cache_dir),
        )
    per_chip = [describer.describe(chip, params) for chip in chips]
    if progress is not None:
        progress("vlad_local_features", len(chips), len(chips))
    pool = np.concatenate(per_chip, axis=0)
    if not np.isfinite(pool).all():
        raise VladError(
            f"the {params.descriptor} describer gave non-finite descriptors for the training chips",
            path=str(store.cache_dir),
        )
    if pool.shape[0] < 20 * params.n_clusters:
        raise VladError(
            f"{pool.shape[0]} local descriptors are too few for {params.n_clusters} words",
            path=str(store.cache_dir),
        )
    # k-means on a bounded random subset: 200 points per word is plenty for the centroids.
    rng = np.random.default_rng(params.seed)
    take = min(pool.shape[0], 200 * params.n_clusters)
    subset = np.ascontiguousarray(pool[rng.choice(pool.shape[0], take, replace=False)])
    kmeans = faiss.Kmeans(params.local_dim, params.n_clusters, niter=25, seed=params.seed, verbose=False)
    kmeans.train(subset)
    centroids = np.asarray(kmeans.centroids, dtype=np.float32)
    no_pca = VladVocabulary(params, centroids, np.empty(0, np.float32), np.empty((0, 0), np.float32))
    if params.pca_dim == 0:
        return no_pca
    words = faiss.IndexFlatL2(params.local_dim)
    words.add(centroids)
    vlads = np.stack([_vlad(d, centroids, words) for d in per_chip])
    n_comp = min(params.pca_dim, vlads.shape[0] - 1, params.vlad_dim)
    mean = vlads.mean(axis=0)
    # SVD of the centred sample matrix: right singular vectors are the principal axes.
    _, sing, vt = np.linalg.svd(vlads - mean, full_matrices=False)
    eig = (sing[:n_comp] ** 2) / max(vlads.shape[0] - 1, 1)
    scale = 1.0 / np.sqrt(eig + params.whiten_eps * eig[0])
    proj = (vt[:n_comp].T * scale[None, :]).astype(np.float32)
    if progress is not None:
        progress("vlad_pca", n_comp, params.pca_dim)
    return VladVocabulary(params, centroids, mean.astype(np.float32), proj)


class VladVpr(IndexedVpr):
    """C2 strategies ``vlad`` (dense RootSIFT) and ``vlad_xfeat`` (a learned extractor's descriptors):
    VLAD descriptors of the normalised query against the cache's HNSW index.

    Build with ``VladVpr.from_cache`` (daemon) or directly from an encoder and index (tests, bench).
    """

    @classmethod
    def from_cache(
        cls,
        tile_store: TileStore,
        *,
        top1_distance_warn: float,
        ef_search: int | None = None,
        describer: LocalDescriber | None = None,
    ) -> VladVpr:
        """Load the vocabulary and index recorded in the cache's manifest.

        ``describer``: the local descriptors (default dense RootSIFT, strategy ``vlad``; e.g. an
        ``XFeatDescriber`` for ``vlad_xfeat``). Raises ``IndexUnavailableError`` when the cache was
        built with another strategy, with another extractor model (sha256), without descriptors, or
        when an artifact is missing, unreadable or inconsistent.
        """
        describer = describer if describer is not None else RootSiftDescriber()
        label = STRATEGY_LABELS.get(describer.name)
        if label is None:
            raise IndexUnavailableError(f"no VLAD strategy aggregates {describer.name!r} descriptors")
        cache_dir = tile_store.cache_dir
        manifest = tile_store.manifest
        vocab_path = cache_dir / VLAD_VOCABULARY_NAME
        check_cache_backbone(
            manifest,
            label,
            describer.model_sha256,
            cache_dir=cache_dir,
            required_artifacts=(VLAD_VOCABULARY_NAME, VPR_INDEX_NAME, VPR_DESCRIPTORS_NAME),
        )
        try:
            vocab = VladVocabulary.load(vocab_path)
            encoder = VladEncoder(vocab, model_sha256=manifest.vpr.model_sha256, describer=describer)
        except VladError as exc:
            raise IndexUnavailableError(str(exc), path=str(vocab_path)) from exc
        index = DescriptorIndex.load(
            cache_dir / VPR_INDEX_NAME,
            expected_dim=encoder.dim,
            expected_count=len(tile_store),
            ef_search=HNSW_EF_SEARCH if ef_search is None else ef_search,
        )
        normaliser = QueryNormaliser(
            gsd_m_px=tile_store.gsd_m_px, chip_size_px=vocab.params.chip_size_px, backbone=label
        )
        return cls(encoder, tile_store, index, normaliser, top1_distance_warn=top1_distance_warn)
