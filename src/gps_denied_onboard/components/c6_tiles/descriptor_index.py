"""C6 descriptor index: FAISS HNSW over the tiles' global descriptors (C2), built at cache time.

Input: one L2-normalised float32 descriptor per tile, in ``TileStore.tile_ids`` order (pinned by the
hashed ``tiles.json``), so the FAISS label is the tile's position and no id map is stored. Output: the
nearest tiles to a query descriptor, with their L2 distance ``sqrt(d2)`` in ``[0, 2]`` (``d2 = 2 - 2 cos``).

Rule: ``IndexHNSWFlat``, L2, M=32 neighbours, efConstruction=80, efSearch=128. Loaded with
``faiss.IO_FLAG_MMAP_IFC``, so the flat vectors stay memory-mapped and only the graph is read
(``IO_FLAG_MMAP`` alone does not map HNSW storage; without the flag, an older FAISS reads it normally).
Prior-gated search over a subset of tiles: up to ``exact_subset_max`` tiles their vectors are
reconstructed and searched exactly; above that HNSW with an ``IDSelectorBatch`` and efSearch raised to
at least 4k (the graph walk over a small allowed fraction visits mostly disallowed nodes and can return
fewer than k results, which is the nominal-flight case).

Tuning and memory, measured: docs/benchmarks.md, "C2 place recognition".
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import faiss
import numpy as np

from gps_denied_onboard.components.c2_vpr.types import IndexUnavailableError

HNSW_M: Final[int] = 32
HNSW_EF_CONSTRUCTION: Final[int] = 80
HNSW_EF_SEARCH: Final[int] = 128
#: Subsets up to this many tiles are searched exactly (see the module docstring).
EXACT_SUBSET_MAX: Final[int] = 4096

_MMAP_FLAG: Final[int | None] = getattr(faiss, "IO_FLAG_MMAP_IFC", None)


@dataclass(frozen=True)
class IndexHits:
    """Result of one search: ``positions`` (k',) int64 tile positions (index rows), nearest first;
    ``distances`` (k',) float32 L2 distances between normalised vectors, ascending; ``k' <= k``."""

    positions: np.ndarray
    distances: np.ndarray


def l2_normalise(vectors: np.ndarray) -> np.ndarray:
    """Rows of (N, D) (or one (D,) vector) scaled to unit L2 norm, float32. Zero rows stay zero."""
    v = np.asarray(vectors, dtype=np.float32)
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return (v / np.maximum(norm, 1e-12)).astype(np.float32, copy=False)


class DescriptorIndex:
    """HNSW index over N tile descriptors of dimension D (see the module docstring).

    Build with ``DescriptorIndex.build`` (cache time) or ``DescriptorIndex.load`` (daemon start).
    ``search`` is thread-safe for concurrent readers (FAISS search is const); ``ef_search`` is fixed
    at construction for that reason.
    """

    def __init__(
        self,
        index: faiss.IndexHNSWFlat,
        *,
        path: str | None = None,
        mmapped: bool = False,
        ef_search: int = HNSW_EF_SEARCH,
        exact_subset_max: int = EXACT_SUBSET_MAX,
    ) -> None:
        if ef_search < 1:
            raise ValueError(f"ef_search must be >= 1, got {ef_search}")
        self._index = index
        self._index.hnsw.efSearch = int(ef_search)
        self._path = path
        self._mmapped = mmapped
        self._ef_search = int(ef_search)
        self._exact_subset_max = int(exact_subset_max)

    # --- construction ------------------------------------------------------------------------------
    @classmethod
    def build(
        cls,
        descriptors: np.ndarray,
        *,
        m: int = HNSW_M,
        ef_construction: int = HNSW_EF_CONSTRUCTION,
        ef_search: int = HNSW_EF_SEARCH,
    ) -> DescriptorIndex:
        """Index (N, D) float32 descriptors (L2-normalised here; row i = tile position i).

        Raises ValueError for an empty, non-2-D or non-finite matrix.
        """
        x = np.asarray(descriptors)
        if x.ndim != 2 or x.shape[0] < 1 or x.shape[1] < 1:
            raise ValueError(f"descriptors must be a non-empty (N, D) matrix, got shape {x.shape}")
        if not np.isfinite(x).all():
            raise ValueError("descriptors contain NaN or inf")
        x = np.ascontiguousarray(l2_normalise(x))
        index = faiss.IndexHNSWFlat(int(x.shape[1]), int(m), faiss.METRIC_L2)
        index.hnsw.efConstruction = int(ef_construction)
        index.add(x)
        return cls(index, ef_search=ef_search)

    @classmethod
    def load(
        cls,
        path: Path,
        *,
        expected_dim: int | None = None,
        expected_count: int | None = None,
        mmap: bool = True,
        ef_search: int = HNSW_EF_SEARCH,
    ) -> DescriptorIndex:
        """Read an index file written by ``save``.

        Raises ``IndexUnavailableError`` (with ``path``) when the file is missing or unreadable, is
        not an HNSW-flat index, or its dimension / vector count differs from the expected ones.
        """
        p = Path(path)
        if not p.is_file():
            raise IndexUnavailableError("descriptor index file not found", path=str(p))
        flag = _MMAP_FLAG if mmap else None
        use_mmap = flag is not None
        try:
            raw = faiss.read_index(str(p), flag) if flag is not None else faiss.read_index(str(p))
        except RuntimeError as exc:  # FAISS raises RuntimeError for any I/O or format problem
            raise IndexUnavailableError(f"cannot read descriptor index: {exc}".strip(), path=str(p)) from exc
        # faiss.read_index already returns the concrete class (and owns it; a downcast_index() wrapper
        # would not, and would dangle once ``raw`` is collected).
        index = raw
        if not isinstance(index, faiss.IndexHNSWFlat):
            raise IndexUnavailableError(
                f"descriptor index is a {type(index).__name__}, expected IndexHNSWFlat", path=str(p)
            )
        if index.metric_type != faiss.METRIC_L2:
            raise IndexUnavailableError("descriptor index metric is not L2", path=str(p))
        if expected_dim is not None and index.d != expected_dim:
            raise IndexUnavailableError(
                f"descriptor index has dimension {index.d}, the VPR backbone produces {expected_dim}",
                path=str(p),
            )
        if expected_count is not None and index.ntotal != expected_count:
            raise IndexUnavailableError(
                f"descriptor index holds {index.ntotal} vectors, the cache has {expected_count} tiles",
                path=str(p),
            )
        return cls(index, path=str(p), mmapped=use_mmap, ef_search=ef_search)

    def save(self, path: Path) -> None:
        """Write the index to ``path`` atomically (temporary file + fsync + rename)."""
        p = Path(path)
        tmp = p.with_name(p.name + ".tmp")
        faiss.write_index(self._index, str(tmp))
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, p)

    # --- description -------------------------------------------------------------------------------
    @property
    def dim(self) -> int:
        return int(self._index.d)

    @property
    def ntotal(self) -> int:
        return int(self._index.ntotal)

    def __len__(self) -> int:
        return self.ntotal

    @property
    def path(self) -> str | None:
        return self._path

    @property
    def mmapped(self) -> bool:
        """True when the vector storage is mapped from the file (``IO_FLAG_MMAP_IFC``)."""
        return self._mmapped

    @property
    def ef_search(self) -> int:
        return self._ef_search

    # --- search ------------------------------------------------------------------------------------
    def search(self, query: np.ndarray, k: int, *, allowed: np.ndarray | None = None) -> IndexHits:
        """Top-k tile positions by L2 distance to ``query`` (D,) (normalised here).

        ``allowed``: int array of tile positions the search is restricted to (prior-gated search), or
        None for the whole corpus. Returns fewer than k hits when fewer tiles are eligible.
        Raises ValueError for a bad k, a query of the wrong shape, non-finite values, or positions
        outside ``[0, ntotal)``.
        """
        if k < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        q = np.asarray(query, dtype=np.float32)
        if q.shape != (self.dim,):
            raise ValueError(f"query must have shape ({self.dim},), got {q.shape}")
        if not np.isfinite(q).all():
            raise ValueError("query contains NaN or inf")
        q = l2_normalise(q).reshape(1, -1)
        if allowed is None:
            d2, labels = self._index.search(q, min(k, self.ntotal))
            return _hits(d2[0], labels[0])
        subset = np.unique(np.asarray(allowed, dtype=np.int64).ravel())
        if subset.size == 0:
            return IndexHits(np.empty(0, np.int64), np.empty(0, np.float32))
        if subset[0] < 0 or subset[-1] >= self.ntotal:
            raise ValueError(
                f"allowed positions must lie in [0, {self.ntotal}), got {subset[0]}..{subset[-1]}"
            )
        if subset.size <= self._exact_subset_max:
            vectors = self._index.reconstruct_batch(subset)
            d2 = ((vectors - q) ** 2).sum(axis=1)
            # Stable sort: equal distances keep tile order, so results are deterministic.
            order = np.argsort(d2, kind="stable")[:k]
            return _hits(d2[order], subset[order])
        params = faiss.SearchParametersHNSW()  # type: ignore[attr-defined]
        params.efSearch = max(self._ef_search, 4 * k)
        selector = faiss.IDSelectorBatch(subset)
        params.sel = selector
        d2, labels = self._index.search(q, min(k, subset.size), params=params)
        return _hits(d2[0], labels[0])

    def reconstruct(self, position: int) -> np.ndarray:
        """The stored (normalised) descriptor of one tile position, (D,) float32."""
        return np.asarray(self._index.reconstruct(int(position)), dtype=np.float32)


def _hits(d2: np.ndarray, labels: np.ndarray) -> IndexHits:
    """FAISS squared distances + labels -> IndexHits; drops FAISS's -1 padding for missing results."""
    keep = labels >= 0
    dist = np.sqrt(np.maximum(np.asarray(d2, dtype=np.float32)[keep], 0.0)).astype(np.float32)
    return IndexHits(positions=np.asarray(labels, dtype=np.int64)[keep], distances=dist)
