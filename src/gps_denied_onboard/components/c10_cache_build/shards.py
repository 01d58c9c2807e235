"""C10: the cache build's per-tile work, cut in shards, run on an engine, resumable.

**Shards.** A shard is one block of whole tiles of the mosaic (``geotiff._blocks``: about 4 Mpx, row-major)
and its tiles' valid fractions. The shard layout is a function of the tile range and the tile size alone,
never of the engine or the number of workers, and a shard's bytes depend only on the source and the
shard: any process may make it, in any order, and the cache comes out the same, byte for byte.

**Engines** (``EngineSpec``). ``workers=1`` (the default) runs the shards in this process: no cluster, and
Dask is never imported. ``workers=N`` starts a Dask ``LocalCluster`` of N single-threaded worker
processes; ``address`` connects to a running Dask scheduler (``tcp://host:8786``). A worker opens the
source from the path it was given (a path every worker shares) and returns the shard's pixels; this
process alone writes the cache. So a worker needs nothing but read access to the source, and a worker
lost mid-shard has written nothing: Dask runs the shard again on another worker.

**Resume.** The cache directory keeps a journal in ``_build/`` while a build runs: ``plan.json`` (the
build's identity, its shard layout and its time stamp) and one ``shard_NNNNNN.npy`` per shard done (its
tiles' valid fractions), each written only after that shard's pixels are in the temporary mosaic and
``fdatasync``'ed. A build run again with the same identity skips the shards recorded and redoes any other
(one killed mid-write included: its region is written whole again). Any other identity starts afresh.
The manifest and the hashes are written after the last shard (``geotiff.finalize_cache``), then the
journal is removed: a torn build never reads as a cache.

**Time stamps.** A cache's only bytes that are not a function of its inputs are its creation stamps.
``build_timestamp_utc`` honours ``SOURCE_DATE_EPOCH`` (the reproducible-builds.org convention) so that
two builds can be compared byte for byte, and a resumed build keeps the stamp of its first start.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from functools import partial
from itertools import islice
from pathlib import Path
from typing import Any, Final, Protocol, TypeVar

import numpy as np
import structlog
from tqdm import tqdm

from gps_denied_onboard.components.c10_cache_build.manifest import (
    CacheBuildError,
    TileRange,
    write_json_atomic,
)
from gps_denied_onboard.components.c10_cache_build.npy_stream import save_npy_atomic
from gps_denied_onboard.constants import LogEvent

_log = structlog.get_logger(__name__)

_Item = TypeVar("_Item")
_Result = TypeVar("_Result")

#: The journal's sub-directory of the cache directory (removed when the build completes).
JOURNAL_DIR_NAME: Final = "_build"
_PLAN_NAME: Final = "plan.json"
_JOURNAL_VERSION: Final = 1
#: Seconds to wait for a running scheduler to answer, and for its first worker.
CLUSTER_CONNECT_TIMEOUT_S: Final = 30.0
#: Shards in flight per worker: enough to keep a worker busy while its last result travels back,
#: few enough that the pixels waiting to be written stay bounded (a shard is ~12 MB of mosaic).
_IN_FLIGHT_PER_WORKER: Final = 2


@dataclass(frozen=True)
class Shard:
    """One block of whole tiles: its index in the layout and its place in the tile range, in tiles."""

    index: int
    row0_tiles: int
    col0_tiles: int
    n_rows_tiles: int
    n_cols_tiles: int

    @property
    def n_tiles(self) -> int:
        return self.n_rows_tiles * self.n_cols_tiles


@dataclass(frozen=True)
class ShardOutput:
    """What a worker returns for one shard.

    ``bgr``: uint8 (n_rows_tiles * ts, n_cols_tiles * ts, 3) BGR pixels of the block, or None when the
    source does not reach it (all nodata: the mosaic's zeros stay). ``valid_fraction``: float32
    (n_rows_tiles, n_cols_tiles), the valid-pixel fraction of each of its tiles.
    """

    index: int
    bgr: np.ndarray | None
    valid_fraction: np.ndarray


def shards_of(blocks: Sequence[tuple[int, int, int, int]]) -> list[Shard]:
    """The shards of a block layout ``(row0, col0, n_rows, n_cols)`` in tiles, in layout order."""
    return [Shard(i, r, c, nr, nc) for i, (r, c, nr, nc) in enumerate(blocks)]


def build_timestamp_utc() -> str:
    """The build's time stamp, ``YYYY-MM-DDTHH:MM:SSZ``: ``SOURCE_DATE_EPOCH`` (seconds) when set, else now.

    Raises CacheBuildError for a ``SOURCE_DATE_EPOCH`` that is not a non-negative integer.
    """
    raw = os.environ.get("SOURCE_DATE_EPOCH")
    if raw is None or raw == "":
        when = datetime.now(timezone.utc)
    else:
        try:
            epoch_s = int(raw)
        except ValueError as exc:
            raise CacheBuildError(f"SOURCE_DATE_EPOCH={raw!r}: expected integer seconds") from exc
        if epoch_s < 0:
            raise CacheBuildError(f"SOURCE_DATE_EPOCH={raw!r}: expected non-negative seconds")
        when = datetime.fromtimestamp(epoch_s, timezone.utc)
    return when.strftime("%Y-%m-%dT%H:%M:%SZ")


# --- engines ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class EngineSpec:
    """Where the shards run: ``workers`` 1 in this process; N > 1 on a local Dask cluster of N worker
    processes; ``address`` a running Dask scheduler (``workers`` is then the cluster's)."""

    workers: int = 1
    address: str | None = None

    def __post_init__(self) -> None:
        if self.workers < 1:
            raise CacheBuildError(f"workers {self.workers}: expected 1 or more")
        if self.address is not None and not self.address.strip():
            raise CacheBuildError("an empty cluster address; expected e.g. tcp://host:8786")

    @property
    def distributed(self) -> bool:
        return self.address is not None or self.workers > 1


class ShardEngine(Protocol):
    """Runs ``work`` over items (shards of tiles, bands of the fields); yields each result as it completes,
    in any order. ``work`` and the items must be picklable for an engine of other processes."""

    #: Workers the engine runs on (for the progress bar and the logs).
    workers: int
    name: str

    def run(self, work: Callable[[_Item], _Result], items: Sequence[_Item]) -> Iterator[_Result]: ...


class SerialEngine:
    """Every item in this process, in order (the default: no cluster)."""

    workers = 1
    name = "serial"

    def run(self, work: Callable[[_Item], _Result], items: Sequence[_Item]) -> Iterator[_Result]:
        for item in items:
            yield work(item)


class DaskEngine:
    """Shards as tasks on a Dask ``distributed`` client, a bounded number in flight.

    ``work`` must be picklable (a module-level function, or a ``functools.partial`` of one with picklable
    arguments). A task whose worker dies is rescheduled by Dask on another worker; a task that raises
    stops the build with the worker's exception.
    """

    name = "dask"

    def __init__(self, client: Any) -> None:
        self._client = client
        self.workers = max(1, len(client.scheduler_info(n_workers=-1).get("workers", {})))

    def run(self, work: Callable[[_Item], _Result], items: Sequence[_Item]) -> Iterator[_Result]:
        from distributed import as_completed

        todo = iter(items)
        window = max(2, _IN_FLIGHT_PER_WORKER * self.workers)
        futures = as_completed([self._client.submit(work, s, pure=False) for s in islice(todo, window)])
        try:
            for future in futures:
                output: _Result = future.result()
                future.release()
                nxt = next(todo, None)
                if nxt is not None:
                    futures.add(self._client.submit(work, nxt, pure=False))
                yield output
        finally:
            # On an error or an interrupt nothing is left running on the cluster for this build.
            for future in list(futures.futures):
                future.cancel()


def run_ordered(
    engine: ShardEngine, work: Callable[[_Item], _Result], items: Sequence[_Item]
) -> Iterator[_Result]:
    """``engine.run`` with the results yielded in the items' order (a stream that must be written in
    order). Results that arrive early wait here; the engine's bounded window bounds them."""
    pending: dict[int, _Result] = {}
    following = 0
    for index, result in engine.run(partial(_indexed, work), list(enumerate(items))):
        pending[index] = result
        while following in pending:
            yield pending.pop(following)
            following += 1


def _indexed(work: Callable[[_Item], _Result], indexed_item: tuple[int, _Item]) -> tuple[int, _Result]:
    index, item = indexed_item
    return index, work(item)


def is_distributed(engine: EngineSpec | ShardEngine | None) -> bool:
    """Whether ``engine`` (a spec, an open engine, or None: in this process) runs work in other processes."""
    if engine is None:
        return False
    if isinstance(engine, EngineSpec):
        return engine.distributed
    return not isinstance(engine, SerialEngine)


@contextmanager
def engine_scope(engine: EngineSpec | ShardEngine | None) -> Iterator[ShardEngine]:
    """An engine for one stage: ``engine`` itself when it is open (its owner closes it), else the one
    the spec names (None: in this process), opened and closed around the stage."""
    if engine is None or isinstance(engine, EngineSpec):
        with open_engine(engine or EngineSpec()) as opened:
            yield opened
    else:
        yield engine


@contextmanager
def open_engine(spec: EngineSpec) -> Iterator[ShardEngine]:
    """The engine ``spec`` names, for the duration of the build (a local cluster is shut down after).

    Raises CacheBuildError when Dask is not installed or the scheduler does not answer in
    ``CLUSTER_CONNECT_TIMEOUT_S``.
    """
    if not spec.distributed:
        yield SerialEngine()
        return
    try:
        from distributed import Client, LocalCluster

        from gps_denied_onboard.components.c10_cache_build.dask_worker import OneNativeThread
    except ImportError as exc:
        raise CacheBuildError(
            "--workers > 1 and --address need Dask's distributed scheduler: pip install distributed"
        ) from exc
    if spec.address is not None:
        try:
            client = Client(spec.address, timeout=f"{CLUSTER_CONNECT_TIMEOUT_S}s")
            client.wait_for_workers(1, timeout=CLUSTER_CONNECT_TIMEOUT_S)
            client.register_plugin(OneNativeThread())
        except (OSError, TimeoutError) as exc:
            raise CacheBuildError(f"no Dask cluster answered at {spec.address}: {exc}") from exc
        try:
            yield DaskEngine(client)
        finally:
            client.close()
        return
    # One thread per worker process: the warp holds the GIL for part of its time, and one worker per
    # core is what a shard-parallel build wants. No dashboard (it would need bokeh and a port).
    cluster = LocalCluster(
        n_workers=spec.workers,
        threads_per_worker=1,
        processes=True,
        dashboard_address=None,
        silence_logs=logging.WARNING,
    )
    client = Client(cluster)
    try:
        client.wait_for_workers(spec.workers, timeout=CLUSTER_CONNECT_TIMEOUT_S)
        client.register_plugin(OneNativeThread())
        yield DaskEngine(client)
    finally:
        client.close()
        cluster.close()


# --- the journal ----------------------------------------------------------------------------------


class ShardJournal:
    """The record of a build in progress (module docstring, "Resume"): its plan, the temporary mosaic
    the shards are written into, and the shards done."""

    def __init__(
        self, out_dir: Path, plan: Mapping[str, Any], mosaic_tmp: Path, data_offset: int, width_px: int
    ) -> None:
        self._dir = out_dir / JOURNAL_DIR_NAME
        self._plan = dict(plan)
        self.mosaic_tmp = mosaic_tmp
        self._data_offset = data_offset
        self._row_bytes = width_px * 3

    @property
    def created_utc(self) -> str:
        return str(self._plan["created_utc"])

    @classmethod
    def resume(
        cls, out_dir: Path, identity: Mapping[str, Any], mosaic_tmp: Path, shape: tuple[int, int, int]
    ) -> ShardJournal | None:
        """The journal of an interrupted build with exactly this ``identity`` whose temporary mosaic is
        intact in shape and size, or None (then the build starts afresh)."""
        try:
            plan = json.loads((out_dir / JOURNAL_DIR_NAME / _PLAN_NAME).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        if not isinstance(plan, dict) or plan.get("identity") != _jsonable(identity):
            return None
        if plan.get("version") != _JOURNAL_VERSION or plan.get("mosaic_tmp") != mosaic_tmp.name:
            return None
        offset = _npy_data_offset(mosaic_tmp, shape)
        if offset is None:
            return None
        return cls(out_dir, plan, mosaic_tmp, offset, shape[1])

    @classmethod
    def start(
        cls, out_dir: Path, identity: Mapping[str, Any], mosaic_tmp: Path, shape: tuple[int, int, int]
    ) -> ShardJournal:
        """A fresh journal and an all-zero temporary mosaic of ``shape`` (uint8)."""
        journal_dir = out_dir / JOURNAL_DIR_NAME
        shutil.rmtree(journal_dir, ignore_errors=True)
        journal_dir.mkdir(parents=True)
        mosaic = np.lib.format.open_memmap(mosaic_tmp, mode="w+", dtype=np.uint8, shape=shape)
        offset = int(mosaic.offset)
        del mosaic
        with open(mosaic_tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        plan = {
            "version": _JOURNAL_VERSION,
            "identity": _jsonable(identity),
            "mosaic_tmp": mosaic_tmp.name,
            "created_utc": build_timestamp_utc(),
        }
        # The plan goes last: a journal without its mosaic never looks resumable.
        write_json_atomic(journal_dir / _PLAN_NAME, plan)
        return cls(out_dir, plan, mosaic_tmp, offset, shape[1])

    def done(self, shards: Sequence[Shard]) -> dict[int, np.ndarray]:
        """Shard index -> valid fractions, for every shard recorded done (a malformed record is not)."""
        out: dict[int, np.ndarray] = {}
        for shard in shards:
            path = self._record_path(shard.index)
            if not path.is_file():
                continue
            try:
                fractions = np.load(path, allow_pickle=False)
            except (OSError, ValueError):
                continue
            if fractions.dtype == np.float32 and fractions.shape == (shard.n_rows_tiles, shard.n_cols_tiles):
                out[shard.index] = fractions
        return out

    def write(self, output: ShardOutput, shard: Shard, tile_size_px: int) -> None:
        """Write one shard's pixels into its region of the temporary mosaic, flush them to disk, then
        record the shard done (with its valid fractions)."""
        if output.bgr is not None:
            ts = tile_size_px
            expected = (shard.n_rows_tiles * ts, shard.n_cols_tiles * ts, 3)
            if output.bgr.shape != expected or output.bgr.dtype != np.uint8:
                raise CacheBuildError(
                    f"shard {shard.index}: {output.bgr.dtype} {output.bgr.shape} pixels, "
                    f"expected uint8 {expected}"
                )
            block = np.ascontiguousarray(output.bgr)
            row0_px, col0_px = shard.row0_tiles * ts, shard.col0_tiles * ts
            fd = os.open(self.mosaic_tmp, os.O_WRONLY)
            try:
                if col0_px == 0 and block.shape[1] * 3 == self._row_bytes:
                    at = self._data_offset + row0_px * self._row_bytes
                    _pwrite_all(fd, block.data.cast("B"), at)
                else:
                    for i in range(block.shape[0]):
                        at = self._data_offset + (row0_px + i) * self._row_bytes + col0_px * 3
                        _pwrite_all(fd, block[i].data.cast("B"), at)
                os.fdatasync(fd)
            finally:
                os.close(fd)
        self.record(shard.index, np.asarray(output.valid_fraction, dtype=np.float32))

    def record(self, index: int, fractions: np.ndarray) -> None:
        """Record shard ``index`` done (atomic: temporary file, fsync, rename)."""
        save_npy_atomic(self._record_path(index), fractions)

    def remove(self) -> None:
        """Drop the journal (after the manifest is written)."""
        discard_journal(self._dir.parent)

    def _record_path(self, index: int) -> Path:
        return self._dir / f"shard_{index:06d}.npy"


def discard_journal(out_dir: Path) -> None:
    """Remove a build journal left in ``out_dir`` (none: nothing happens)."""
    shutil.rmtree(Path(out_dir) / JOURNAL_DIR_NAME, ignore_errors=True)


def _pwrite_all(fd: int, data: memoryview, offset: int) -> None:
    while data:
        n = os.pwrite(fd, data, offset)
        data, offset = data[n:], offset + n


def _npy_data_offset(path: Path, shape: tuple[int, int, int]) -> int | None:
    """Where the data of the uint8 ``.npy`` at ``path`` starts, when it has ``shape`` and its full size."""
    try:
        with open(path, "rb") as fh:
            major, _ = np.lib.format.read_magic(fh)
            if major != 1:
                return None
            got_shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
            offset = fh.tell()
        size = path.stat().st_size
    except (OSError, ValueError):
        return None
    if tuple(got_shape) != tuple(shape) or fortran or dtype != np.uint8:
        return None
    return offset if size == offset + int(np.prod(shape)) else None


def _jsonable(value: Mapping[str, Any]) -> Any:
    """``value`` as it reads back from JSON (tuples become lists), for comparing identities."""
    return json.loads(json.dumps(value, sort_keys=True))


# --- the run --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ShardRun:
    """What ``run_shards`` did: the valid fractions of the whole tile range, float32 (n_rows, n_cols);
    the shards found done from an earlier run and the shards run now; the stage's wall time and, within
    it, the time this process spent writing and flushing shards (the part no worker can take)."""

    fractions: np.ndarray
    resumed: int
    ran: int
    seconds: float
    write_s: float


def run_shards(
    journal: ShardJournal,
    shards: Sequence[Shard],
    work: Callable[[Shard], ShardOutput],
    engine: ShardEngine,
    *,
    tile_range: TileRange,
    tile_size_px: int,
    progress: bool,
    desc: str,
) -> ShardRun:
    """Run every shard not yet done on ``engine``, writing each into the journal's mosaic as it arrives.

    The fractions are gathered by shard index, so they are in tile order whatever order the shards
    completed in. A progress bar over the shards (with its ETA) is shown when ``progress`` and stderr
    is a terminal.
    """
    fractions = np.zeros((tile_range.n_rows, tile_range.n_cols), dtype=np.float32)
    done = journal.done(shards)
    by_index = {s.index: s for s in shards}
    for index, f in done.items():
        s = by_index[index]
        r, c = s.row0_tiles, s.col0_tiles
        fractions[r : r + s.n_rows_tiles, c : c + s.n_cols_tiles] = f
    todo = [s for s in shards if s.index not in done]
    if done:
        _log.info(LogEvent.CACHE_BUILD_RESUMED, shards_done=len(done), shards_left=len(todo))
    _log.info(
        LogEvent.CACHE_BUILD_SHARDS,
        engine=engine.name,
        workers=engine.workers,
        shards=len(shards),
        shards_to_run=len(todo),
        tiles_to_run=sum(s.n_tiles for s in todo),
    )
    show = progress and sys.stderr.isatty()
    t0 = time.monotonic()
    tiles = 0
    write_s = 0.0
    with tqdm(
        total=len(shards), initial=len(done), unit="shard", desc=desc, disable=not show, smoothing=0.1
    ) as bar:
        for output in engine.run(work, todo):
            shard = by_index[output.index]
            t_write = time.monotonic()
            journal.write(output, shard, tile_size_px)
            write_s += time.monotonic() - t_write
            r, c = shard.row0_tiles, shard.col0_tiles
            fractions[r : r + shard.n_rows_tiles, c : c + shard.n_cols_tiles] = output.valid_fraction
            tiles += shard.n_tiles
            bar.update(1)
            bar.set_postfix(tiles_s=f"{tiles / max(time.monotonic() - t0, 1e-9):.0f}", refresh=False)
    seconds = time.monotonic() - t0
    _log.info(
        LogEvent.CACHE_BUILD_SHARDS_DONE,
        engine=engine.name,
        workers=engine.workers,
        shards_run=len(todo),
        tiles_run=tiles,
        seconds=round(seconds, 3),
        write_s=round(write_s, 3),
        tiles_per_s=round(tiles / seconds, 1) if seconds > 0 else None,
    )
    return ShardRun(fractions=fractions, resumed=len(done), ran=len(todo), seconds=seconds, write_s=write_s)
