"""The signals ``gdnav run`` ignores: SIGHUP, SIGUSR1, SIGUSR2.

Left at their defaults each ends the process at once, with no clean stop: the autopilot loses GPS_INPUT.
After SIGHUP (exit by signal 1, ``rc`` 129 in a shell) systemd's ``Restart=on-failure`` takes the stop
for a clean one and does not restart the daemon. Nothing in the daemon is re-read on a signal (the
profile, the cache and the models are verified once, at start), so each is ignored: from the first
moment of ``gdnav run`` (``ignore``), then, once the event loop runs, logged and counted
(``NavDaemon.run``). SIGTERM and SIGINT stop the daemon cleanly.
"""

from __future__ import annotations

import signal
from typing import Final

#: Signals the daemon survives (module docstring).
IGNORED_SIGNALS: Final[tuple[signal.Signals, ...]] = (signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2)


def ignore() -> None:
    """Ignore ``IGNORED_SIGNALS`` in this process until the daemon's loop handles them."""
    for sig in IGNORED_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
