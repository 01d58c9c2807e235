"""Rolling matcher health: ONE implementation shared by every strategy (seed risk 5)."""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable

from gps_denied_onboard.components.c3_matcher.types import MatcherHealth

_NS_PER_S = 1_000_000_000


class RollingHealthWindow:
    """Per-frame best-inlier counts over a sliding window of monotonic time.

    ``low_inlier_threshold``: a frame whose best inlier count is below it counts as "low" (the
    composition root passes ``matcher.min_inliers_threshold``). ``clock``: monotonic ns, injectable for
    tests; ``snapshot`` uses it to age out old frames. ``update`` is called by the matcher thread,
    ``snapshot`` by any thread (status task), hence the lock.
    """

    def __init__(
        self,
        low_inlier_threshold: int,
        *,
        window_s: float = 60.0,
        clock: Callable[[], int] | None = None,
    ) -> None:
        if low_inlier_threshold < 0:
            raise ValueError(f"low_inlier_threshold must be >= 0, got {low_inlier_threshold!r}")
        if not window_s > 0:
            raise ValueError(f"window_s must be > 0, got {window_s!r}")
        self._threshold = int(low_inlier_threshold)
        self._window_ns = int(window_s * _NS_PER_S)
        self._clock: Callable[[], int] = clock if clock is not None else time.monotonic_ns
        self._frames: deque[tuple[int, int, bool]] = deque()  # (t_ns, best_inliers, had_backbone_error)
        self._consecutive_low = 0
        self._last_ns: int | None = None
        self._lock = threading.Lock()

    @property
    def low_inlier_threshold(self) -> int:
        return self._threshold

    def now_ns(self) -> int:
        """The window's clock (monotonic ns)."""
        return self._clock()

    def update(self, now_ns: int, *, best_inlier_count: int, had_backbone_error: bool) -> None:
        """Record one frame's outcome (``best_inlier_count`` = 0 when the frame failed)."""
        if best_inlier_count < 0:
            raise ValueError(f"best_inlier_count must be >= 0, got {best_inlier_count!r}")
        with self._lock:
            if self._last_ns is not None and now_ns < self._last_ns:
                raise ValueError(f"now_ns went backwards ({now_ns} < {self._last_ns}); use a monotonic clock")
            self._last_ns = now_ns
            self._frames.append((int(now_ns), int(best_inlier_count), bool(had_backbone_error)))
            self._consecutive_low = self._consecutive_low + 1 if best_inlier_count < self._threshold else 0
            self._prune(now_ns)

    def snapshot(self) -> MatcherHealth:
        """Health as of the clock's now."""
        now = self._clock()
        with self._lock:
            self._prune(now)
            n = len(self._frames)
            mean = sum(f[1] for f in self._frames) / n if n else 0.0
            return MatcherHealth(
                consecutive_low_inlier=self._consecutive_low,
                mean_inliers_60s=float(mean),
                frames_60s=n,
                backbone_error_frames_60s=sum(1 for f in self._frames if f[2]),
            )

    def _prune(self, now_ns: int) -> None:
        horizon = now_ns - self._window_ns
        while self._frames and self._frames[0][0] <= horizon:
            self._frames.popleft()
