"""The pipeline's worker thread: runs submitted calls one at a time, off the event loop.

Not a ThreadPoolExecutor: CPython joins executor workers at interpreter exit, so a frame in flight
would hold the process past its 2 s stop budget. This is a daemon thread; at stop it gets a short
grace to finish the frame (its FDR record is line-atomic either way) and is then abandoned.
"""

from __future__ import annotations

import asyncio
import contextlib
import queue
import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")


def _settle(fut: asyncio.Future[Any], result: Any, exc: BaseException | None) -> None:
    if fut.cancelled():
        return
    if exc is not None:
        fut.set_exception(exc)
    else:
        fut.set_result(result)


class WorkerThread:
    def __init__(self, name: str) -> None:
        self._jobs: queue.SimpleQueue[tuple[Any, ...] | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, fn: Callable[..., T], *args: Any) -> asyncio.Future[T]:
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[T] = loop.create_future()
        self._jobs.put((loop, fut, fn, args))
        return fut

    def _run(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            loop, fut, fn, args = job
            result, exc = None, None
            try:
                result = fn(*args)
            except BaseException as e:  # handed to the awaiting coroutine, not swallowed
                exc = e
            with contextlib.suppress(RuntimeError):  # the loop closed while we worked: nobody waits
                loop.call_soon_threadsafe(_settle, fut, result, exc)

    async def stop(self, grace_s: float) -> bool:
        """Ask the thread to finish; wait up to ``grace_s``. Returns True when it finished."""
        self._jobs.put(None)
        deadline = time.monotonic() + grace_s
        while self._thread.is_alive() and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        return not self._thread.is_alive()
