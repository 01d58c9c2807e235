"""C6 DescriptorIndex: real FAISS HNSW build/save/load, gated search, and refusal of bad index files."""

from __future__ import annotations

from pathlib import Path

import faiss
import numpy as np
import pytest

from gps_denied_onboard.components.c2_vpr.types import IndexUnavailableError
from gps_denied_onboard.components.c6_tiles.descriptor_index import DescriptorIndex, l2_normalise

DIM = 64
N = 2000


@pytest.fixture(scope="module")
def vectors() -> np.ndarray:
    return l2_normalise(np.random.default_rng(7).standard_normal((N, DIM)).astype(np.float32))


@pytest.fixture(scope="module")
def index(vectors: np.ndarray) -> DescriptorIndex:
    return DescriptorIndex.build(vectors)


@pytest.fixture(scope="module")
def saved(index: DescriptorIndex, tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("idx") / "vpr_index.faiss"
    index.save(path)
    return path


def test_search_stored_vector_returns_itself_at_zero_distance(
    index: DescriptorIndex, vectors: np.ndarray
) -> None:
    """A stored vector's nearest neighbour is its own row at L2 distance ~0, distances ascending."""
    hits = index.search(vectors[123], 10)
    assert hits.positions[0] == 123
    assert hits.distances[0] == pytest.approx(0.0, abs=1e-3)
    assert np.all(np.diff(hits.distances) >= 0)
    assert hits.distances.max() <= 2.0


def test_search_distances_are_l2_not_squared(index: DescriptorIndex, vectors: np.ndarray) -> None:
    """Returned distances equal the true L2 distance between the normalised vectors."""
    q = vectors[5]
    hits = index.search(q, 3)
    expected = np.linalg.norm(vectors[hits.positions] - q, axis=1)
    np.testing.assert_allclose(hits.distances, expected, atol=1e-4)


def test_round_trip_save_load_gives_identical_results(
    index: DescriptorIndex, saved: Path, vectors: np.ndarray
) -> None:
    """An index saved and loaded (memory-mapped) answers exactly like the in-memory one."""
    loaded = DescriptorIndex.load(saved, expected_dim=DIM, expected_count=N)
    assert loaded.ntotal == N and loaded.dim == DIM
    for row in (0, 17, 1999):
        a, b = index.search(vectors[row], 10), loaded.search(vectors[row], 10)
        np.testing.assert_array_equal(a.positions, b.positions)
        np.testing.assert_allclose(a.distances, b.distances, atol=1e-6)


def test_load_uses_mmap_when_faiss_supports_it(saved: Path) -> None:
    """With FAISS's IO_FLAG_MMAP_IFC available the vector storage is mapped, not copied."""
    loaded = DescriptorIndex.load(saved)
    assert loaded.mmapped == hasattr(faiss, "IO_FLAG_MMAP_IFC")


def test_gated_search_exact_path_returns_only_allowed(index: DescriptorIndex, vectors: np.ndarray) -> None:
    """A small allowed subset is searched exactly and never returns a tile outside it."""
    allowed = np.arange(100, 160)
    hits = index.search(vectors[5], 10, allowed=allowed)
    assert len(hits.positions) == 10
    assert set(hits.positions.tolist()) <= set(allowed.tolist())
    exact = allowed[np.argsort(np.linalg.norm(vectors[allowed] - vectors[5], axis=1))[:10]]
    np.testing.assert_array_equal(hits.positions, exact)


def test_gated_search_selector_path_returns_only_allowed(vectors: np.ndarray) -> None:
    """Above the exact-subset limit the FAISS IDSelector path also keeps results inside the subset."""
    idx = DescriptorIndex(DescriptorIndex.build(vectors)._index, exact_subset_max=0)
    allowed = np.arange(0, N, 3)
    hits = idx.search(vectors[9], 10, allowed=allowed)
    assert hits.positions[0] == 9
    assert len(hits.positions) == 10
    assert set(hits.positions.tolist()) <= set(allowed.tolist())


def test_gated_search_fewer_allowed_than_k_returns_all_allowed(
    index: DescriptorIndex, vectors: np.ndarray
) -> None:
    """With 3 allowed tiles and k=10 the 3 are returned; an empty subset returns nothing."""
    hits = index.search(vectors[0], 10, allowed=np.array([4, 8, 15]))
    assert sorted(hits.positions.tolist()) == [4, 8, 15]
    assert index.search(vectors[0], 10, allowed=np.array([], dtype=np.int64)).positions.size == 0


def test_gated_search_position_out_of_range_raises(index: DescriptorIndex, vectors: np.ndarray) -> None:
    """Allowed positions outside the index are a caller bug and raise ValueError."""
    with pytest.raises(ValueError, match="allowed positions"):
        index.search(vectors[0], 5, allowed=np.array([1, N]))


def test_search_wrong_query_dim_raises(index: DescriptorIndex) -> None:
    """A query of the wrong dimension is refused with the expected shape in the message."""
    with pytest.raises(ValueError, match=rf"\({DIM},\)"):
        index.search(np.ones(DIM + 1, np.float32), 5)


def test_load_corrupted_file_raises_index_unavailable(saved: Path, tmp_path: Path) -> None:
    """A truncated / overwritten index file gives IndexUnavailableError naming the path."""
    bad = tmp_path / "vpr_index.faiss"
    data = saved.read_bytes()
    bad.write_bytes(data[: len(data) // 3])
    with pytest.raises(IndexUnavailableError) as info:
        DescriptorIndex.load(bad)
    assert info.value.path == str(bad)
    bad.write_bytes(b"\x00" * 4096)
    with pytest.raises(IndexUnavailableError):
        DescriptorIndex.load(bad)


def test_load_missing_file_raises_index_unavailable(tmp_path: Path) -> None:
    """A missing index file gives IndexUnavailableError."""
    with pytest.raises(IndexUnavailableError, match="not found"):
        DescriptorIndex.load(tmp_path / "nope.faiss")


def test_load_wrong_dim_or_count_raises_index_unavailable(saved: Path) -> None:
    """An index whose dimension or size differs from the backbone/cache is refused."""
    with pytest.raises(IndexUnavailableError, match="dimension 64"):
        DescriptorIndex.load(saved, expected_dim=128)
    with pytest.raises(IndexUnavailableError, match=f"holds {N} vectors"):
        DescriptorIndex.load(saved, expected_count=N + 1)


def test_load_non_hnsw_index_raises_index_unavailable(tmp_path: Path, vectors: np.ndarray) -> None:
    """A valid FAISS file of another index type is refused."""
    flat = faiss.IndexFlatL2(DIM)
    flat.add(vectors)
    path = tmp_path / "flat.faiss"
    faiss.write_index(flat, str(path))
    with pytest.raises(IndexUnavailableError, match="IndexFlatL2"):
        DescriptorIndex.load(path)


def test_build_rejects_non_finite_descriptors() -> None:
    """NaN descriptors are refused at build time."""
    x = np.ones((4, 8), np.float32)
    x[2, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        DescriptorIndex.build(x)
