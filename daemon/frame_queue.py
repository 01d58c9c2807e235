"""Bounded frame queue where the newest frame wins and every drop is counted."""

from __future__ import annotations

import asyncio
from collections import deque
from typing import Generic, TypeVar

T = TypeVar("T")


class LatestQueue(Generic[T]):
    def __init__(self, depth: int) -> None:
        self._items: deque[T] = deque()
        self._depth = depth
        self._available = asyncio.Event()
        self.dropped = 0

    def put(self, item: T) -> bool:
        """Add an item; when full, drop the OLDEST (a stale frame is worth less than a fresh one).
        Returns False when something was dropped."""
        dropped = False
        while len(self._items) >= self._depth:
            self._items.popleft()
            self.dropped += 1
            dropped = True
        self._items.append(item)
        self._available.set()
        return not dropped

    async def get(self) -> T:
        while not self._items:
            self._available.clear()
            await self._available.wait()
        return self._items.popleft()

    def __len__(self) -> int:
        return len(self._items)
