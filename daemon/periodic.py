"""The two periodic tasks the single-process daemon and the navigator core share.

- ``on_deadlines``: a tick on absolute deadlines (no drift, bounded jitter) whatever the tick costs; a
  deadline missed by more than a period (the loop was blocked) is skipped, not run in a burst. The
  estimate stream runs on it (ArduPilot needs >= 5 Hz with little jitter).
- ``keep_resume_state``: the newest 3D estimate sent, to the resume state file about once a second
  (F8), atomic and fsynced, so on a worker thread, never on the loop.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from gps_denied_onboard.components.c5_estimator.prior import ResumeState
from gps_denied_onboard.components.c5_estimator.resume_state import ResumeStateFile
from gps_denied_onboard.constants import RESUME_STATE_INTERVAL_S


async def on_deadlines(period_s: float, tick: Callable[[], None]) -> None:
    """Call ``tick`` every ``period_s`` on absolute deadlines, for ever (``tick`` handles its own errors)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time()
    while True:
        tick()
        deadline += period_s
        now = loop.time()
        if now - deadline > period_s:
            deadline = now
        await asyncio.sleep(max(0.0, deadline - now))


async def keep_resume_state(
    store: ResumeStateFile,
    latest: Callable[[], tuple[ResumeState, str] | None],
    now_unix_s: Callable[[], float],
) -> None:
    """Write ``latest()`` (the last 3D estimate sent and its provenance) to ``store`` whenever it changed,
    about once a second, for ever."""
    written: tuple[ResumeState, str] | None = None
    while True:
        await asyncio.sleep(RESUME_STATE_INTERVAL_S)
        state = latest()
        if state is None or state is written:
            continue
        await asyncio.to_thread(store.write, state[0], provenance=state[1], written_unix_s=now_unix_s())
        written = state
