"""The pipeline's worker thread: runs submitted calls one at a time, off the event loop.

Not a ThreadPoolExecutor: CPython joins executor workers at interpreter exit, so a frame in flight
would hold the process past its 2 s stop budget. This is a daemon thread; at stop it gets a short
grace to finish the frame (its FDR record is line-atomic either way) and is then abandoned.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
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
    def __init__(self, name: str, *, nice: int = 0) -> None:
        """``nice``: added to the thread's nice value when it starts (Linux sets it per thread), so the
        scheduler runs the daemon's other threads first when the cores are short."""
        self._jobs: queue.SimpleQueue[tuple[Any, ...] | None] = queue.SimpleQueue()
        self._nice = nice
        #: The thread's nice value once it has started (None before, or where it cannot be read).
        self.nice_value: int | None = None
        self._started = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()
        self._started.wait(timeout=1.0)

    def _lower_priority(self) -> None:
        try:
            tid = threading.get_native_id()
            if self._nice > 0:
                os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + self._nice)
            self.nice_value = os.getpriority(os.PRIO_PROCESS, tid)
        except (OSError, AttributeError):  # not Linux, or refused: the thread runs at the daemon's priority
            self.nice_value = None

    def submit(self, fn: Callable[..., T], *args: Any) -> asyncio.Future[T]:
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[T] = loop.create_future()
        self._jobs.put((loop, fut, fn, args))
        return fut

    def _run(self) -> None:
        self._lower_priority()
        self._started.set()
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
