"""The start-up beacon: the MAVLink link's first second, before the daemon's tasks exist.

``gdnav run`` opens the link right after reading its configuration (``runtime_root.link_first``) and
starts this thread; the map cache, the models, the estimator and their imports then load on the main
thread (about a second on two cores). Meanwhile the beacon reads the autopilot (its address, its
state, TIMESYNC), sends HEARTBEAT with MAV_STATE_BOOT at ``mavlink.heartbeat_hz`` and GPS_INPUT with
fix_type 0 (no estimate) at ``mavlink.estimate_rate_hz``, and says "GDN: starting" once the autopilot
is heard. It claims nothing: no position leaves it. ``stop`` ends it and hands the link to the
daemon's own tasks (``NavDaemon.run``), on the same link object.

Once the autopilot is heard, the beacon also asks it what the start-up prior needs (its estimate, EKF
status and home every ``ESTIMATE_ASK_PERIOD_S``; its landed state every ``PHASE_ASK_PERIOD_S``), as the
daemon's first frame would: the answers are in the tracker when that frame comes, so a restart in flight
starts its estimator a frame sooner. ``asked`` says when, for the daemon to carry on from.
"""

from __future__ import annotations

import select
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import structlog
from pymavlink import mavutil

from gps_denied_onboard.components.c5_estimator.types import EstimatorState
from gps_denied_onboard.components.c8_mavlink import MavlinkLink
from gps_denied_onboard.config import MavlinkConfig
from gps_denied_onboard.constants import LogEvent

log = structlog.get_logger(__name__)

#: The text the operator sees once the autopilot is heard.
STARTING_TEXT = "GDN: starting"
#: How often the beacon asks for the autopilot's estimate and home, and for its landed state, s (the
#: daemon's own start-up asks keep the same pace: ``NavDaemon._prior``).
ESTIMATE_ASK_PERIOD_S = 0.25
PHASE_ASK_PERIOD_S = 1.0


@dataclass(frozen=True)
class BeaconAsks:
    """When the beacon asked the autopilot (daemon clock, Unix s; None: never): the first and the last
    request for its estimate and home, and the last for its landed state."""

    estimate_first_unix_s: float | None = None
    estimate_last_unix_s: float | None = None
    phase_last_unix_s: float | None = None


class StartupBeacon:
    """Keeps ``link`` talking on a thread of its own until ``stop``."""

    def __init__(
        self,
        link: MavlinkLink,
        config: MavlinkConfig,
        clock: Callable[[], float],
        *,
        ask_estimate: bool = True,
    ) -> None:
        """``clock``: the daemon's clock (Unix s), which stamps the GPS_INPUT. ``ask_estimate``: ask for the
        autopilot's estimate and home (False where ``init.autopilot_wait_s`` is 0: "do not ask")."""
        self._link = link
        self._ask_estimate = ask_estimate
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
        #: What it asked the autopilot, and when (written by the beacon's thread only).
        self.asked = BeaconAsks()

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
                if link.tracker.autopilot_seen:
                    if not self._said_starting:
                        info = mavutil.mavlink.MAV_SEVERITY_INFO
                        self._said_starting = link.send_statustext(info, STARTING_TEXT)
                    self._ask(link)
                self._wait_readable(min(next_estimate, next_heartbeat) - time.monotonic())
                link.poll()
                now = time.monotonic()
        except Exception as exc:  # the daemon's own tasks take over (or report) at stop; never lost
            self._error = exc
            log.exception(LogEvent.DAEMON_BEACON_STOPPED, error=repr(exc))

    def _ask(self, link: MavlinkLink) -> None:
        """Ask the autopilot for its estimate and home, and its landed state, each at its own pace."""
        now_s = self._clock()
        asked = self.asked
        last = asked.estimate_last_unix_s
        due = last is None or now_s - last >= ESTIMATE_ASK_PERIOD_S
        if self._ask_estimate and due and link.request_autopilot_estimate():
            first = asked.estimate_first_unix_s if asked.estimate_first_unix_s is not None else now_s
            asked = replace(asked, estimate_first_unix_s=first, estimate_last_unix_s=now_s)
        last = asked.phase_last_unix_s
        if (last is None or now_s - last >= PHASE_ASK_PERIOD_S) and link.request_flight_phase():
            asked = replace(asked, phase_last_unix_s=now_s)
        self.asked = asked

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
