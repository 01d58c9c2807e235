"""C10: what every Dask worker of a cache build sets up when it starts (imported on the Dask path only,
so that a one-process build and the daemon never import Dask)."""

from __future__ import annotations

from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin


class OneNativeThread(WorkerPlugin):
    """OpenCV runs one thread in each worker: the build runs one single-threaded worker per core, and
    OpenCV's own pool on top of that made the fields' bands take 21 % more CPU and 17 % more time
    (2 cores, docs/benchmarks.md, "Mission scale: the distributed build")."""

    name = "gdnav-one-native-thread"

    def setup(self, worker: Any) -> None:
        import cv2

        cv2.setNumThreads(1)
