"""The start-up beacon: the MAVLink link's first second, before the daemon's tasks exist.

``gdnav run`` opens the link right after reading its configuration (``runtime_root.link_first``) and
starts this thread; the map cache, the models, the estimator and their imports then load on the main
thread (about a second on two cores). Meanwhile the beacon reads the autopilot (its address, its
state, TIMESYNC), sends HEARTBEAT with MAV_STATE_BOOT at ``mavlink.heartbeat_hz`` and GPS_INPUT with
fix_type 0 (no estimate) at ``mavlink.estimate_rate_hz``, and says "GDN: starting" once the autopilot
is heard. It claims nothing: no position leaves it. ``stop`` ends it and hands the link to the
daemon's own tasks (``NavDaemon.run``), on the same link object.
"""

from __future__ import annotations

import select
import threading
import time
from collections.abc import Callable

import structlog
from pymavlink import mavutil

from gps_denied_onboard.components.c5_estimator.types import EstimatorState
from gps_denied_onboard.components.c8_mavlink import MavlinkLink
from gps_denied_onboard.config import MavlinkConfig
from gps_denied_onboard.constants import LogEvent

log = structlog.get_logger(__name__)

#: The text the operator sees once the autopilot is heard.
STARTING_TEXT = "GDN: starting"


class StartupBeacon:
    """Keeps ``link`` talking on a thread of its own until ``stop``."""

    def __init__(self, link: MavlinkLink, config: MavlinkConfig, clock: Callable[[], float]) -> None:
        """``clock``: the daemon's clock (Unix s), which stamps the GPS_INPUT."""
        self._link = link
        self._clock = clock
        self._estimate_period_s = 1.0 / config.estimate_rate_hz
        self._heartbeat_period_s = 1.0 / config.heartbeat_hz
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="startup_beacon", daemon=True)
        #: GPS_INPUT (fix_type 0) sent, and the first one's time (Unix s), for the log.
        self.estimates_sent = 0
        self.first_estimate_unix_s: float | None = None
        self._said_starting = False
        self._error: BaseException | None = None

    def start(self) -> None:
        log.info(LogEvent.DAEMON_BEACON_STARTED)
        self._thread.start()

    def stop(self) -> None:
        """End the thread (within one poll interval) and log what it sent. Idempotent."""
        if self._stop.is_set():
            return
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)
        log.info(
            LogEvent.DAEMON_BEACON_STOPPED,
            estimates_sent=self.estimates_sent,
            first_estimate_unix_s=self.first_estimate_unix_s,
            error=repr(self._error) if self._error is not None else None,
        )

    def _run(self) -> None:
        link = self._link
        now = time.monotonic()
        next_estimate, next_heartbeat = now, now
        try:
            while not self._stop.is_set():
                if now >= next_heartbeat:
                    link.send_heartbeat(mavutil.mavlink.MAV_STATE_BOOT)
                    next_heartbeat += self._heartbeat_period_s
                if now >= next_estimate:
                    t_usec = int(self._clock() * 1e6)
                    if link.send_estimate(EstimatorState.no_estimate(t_usec), time_unix_usec=t_usec):
                        self.estimates_sent += 1
                        if self.first_estimate_unix_s is None:
                            self.first_estimate_unix_s = t_usec / 1e6
                    next_estimate += self._estimate_period_s
                    if next_estimate < now:  # late (the GIL was busy): the next one a period from now
                        next_estimate = now + self._estimate_period_s
                if not self._said_starting and link.tracker.autopilot_seen:
                    info = mavutil.mavlink.MAV_SEVERITY_INFO
                    self._said_starting = link.send_statustext(info, STARTING_TEXT)
                self._wait_readable(min(next_estimate, next_heartbeat) - time.monotonic())
                link.poll()
                now = time.monotonic()
        except Exception as exc:  # the daemon's own tasks take over (or report) at stop; never lost
            self._error = exc
            log.exception(LogEvent.DAEMON_BEACON_STOPPED, error=repr(exc))

    def _wait_readable(self, timeout_s: float) -> None:
        timeout_s = min(max(0.0, timeout_s), 0.05)
        fd = self._link.fileno()
        if fd is None:
            self._stop.wait(timeout_s)
            return
        try:
            select.select([fd], [], [], timeout_s)
        except (OSError, ValueError):  # the link reconnecting under us: try again next round
            self._stop.wait(timeout_s)
