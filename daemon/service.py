"""The navigation daemon: one asyncio service owning named tasks.

Tasks:
- ``camera_ingest``: frames into a newest-wins queue;
- ``track_worker``: each frame's exposure time is admitted or refused by the C5 time axis (future,
  stale, out of order: counted, recorded, never processed), then decoded and tracked (C1 VO fused at the
  exposure time) on the ``track`` thread, and handed to the fix path;
- ``fix_worker``: the absolute-fix path (C2 -> C2.5 -> C3 -> C4) on the newest tracked frame, on the ``fix``
  thread, fused at that frame's exposure time (F3 "in parallel": a slow matcher never holds up VO or the
  output; frames it has no time for are skipped and counted);
- ``estimate_output``: the estimate propagated to the send time, at ``mavlink.estimate_rate_hz`` on
  absolute deadlines, whatever the frames do (ArduPilot needs >= 5 Hz with little jitter);
- ``mavlink_rx`` (drains the link whenever its socket is readable), ``mavlink_tx`` (own HEARTBEAT),
  ``status`` (status log, ground-station values, systemd watchdog), ``resume_state`` (the last 3D estimate
  to its state file, about once a second, off the loop: F8).
Leaving ``run`` cancels and awaits every task; only CancelledError is swallowed. A failing task is
logged with its name and stops the daemon (systemd restarts it: F8).
"""

from __future__ import annotations

import asyncio
import contextlib
import faulthandler
import math
import signal
import time
import uuid
from collections.abc import Coroutine
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import structlog
from pymavlink import mavutil

from gps_denied_onboard.camera.sources import CapturedFrame
from gps_denied_onboard.camera.stream import FrameStreamError
from gps_denied_onboard.camera.types import FrameTiming, NavCameraFrame
from gps_denied_onboard.components.c4_pose.attitude_check import AttitudeVerdict
from gps_denied_onboard.components.c4_pose.heading_height_check import HeadingHeightVerdict
from gps_denied_onboard.components.c5_estimator.prior import (
    InitialPrior,
    PriorSource,
    ResumeState,
    choose_prior,
    in_the_air,
)
from gps_denied_onboard.components.c5_estimator.time_axis import TimeAxisStats
from gps_denied_onboard.components.c5_estimator.types import EstimatorState
from gps_denied_onboard.components.c5_estimator.wire import state_to_wire
from gps_denied_onboard.components.c8_mavlink.messages import Fix3dGate, stated_speed_sigma_m_s
from gps_denied_onboard.components.c8_mavlink.px4_params import PX4_AGP_PARAMS, px4_agp_problems
from gps_denied_onboard.components.c13_fdr import FdrHealth
from gps_denied_onboard.constants import (
    STATUSTEXT_PRIOR_DISPUTED,
    STATUSTEXT_PRIOR_DOUBTED,
    STATUSTEXT_PRIOR_REANCHORED,
    STATUSTEXT_PRIOR_UNCONFIRMED,
    FdrKind,
    LogEvent,
    Provenance,
)
from gps_denied_onboard.daemon.beacon import ESTIMATE_ASK_PERIOD_S, PHASE_ASK_PERIOD_S, StartupBeacon
from gps_denied_onboard.daemon.core_channel import CoreChannel
from gps_denied_onboard.daemon.frame_queue import LatestQueue
from gps_denied_onboard.daemon.periodic import keep_resume_state, on_deadlines
from gps_denied_onboard.daemon.sd_notify import SdNotifier
from gps_denied_onboard.daemon.signals import IGNORED_SIGNALS
from gps_denied_onboard.daemon.worker import WorkerThread
from gps_denied_onboard.geo import haversine_m
from gps_denied_onboard.pipeline import FIX_TOO_LATE_REASON, FixOutcome, TrackOutcome
from gps_denied_onboard.runtime_root import RuntimeRoot

log = structlog.get_logger(__name__)

#: Seconds allowed for cancelled tasks when stopping (then ``daemon.frame_stop_grace_s`` for the frames
#: in flight; 2 s budget in all).
_STOP_GRACE_S = 0.5
#: A frame waits for the autopilot's attitude to reach this far past its exposure (its attitude is then
#: interpolated, never extrapolated, and the rate around it known), s, but never longer than
#: ATTITUDE_WAIT_MAX_S.
ATTITUDE_RATE_HALF_SPAN_S = 0.02
ATTITUDE_WAIT_MAX_S = 0.3
#: The operator hears that a doubted prior's search grew at most this often (the first time at once), s.
PRIOR_DOUBT_TEXT_INTERVAL_S = 5.0
#: PX4's parameters (``_check_px4_parameters``): how often to look for its HEARTBEAT, how long to wait
#: for the answers to one round of PARAM_REQUEST_READ, and how many rounds, s.
PX4_PARAM_POLL_S = 0.05
PX4_PARAM_WAIT_S = 0.5
PX4_PARAM_TRIES = 6
#: A worker waiting for its next core and stuck in native code is ended this long after
#: ``daemon.worker_orphan_s`` (``faulthandler``'s timer), s.
ORPHAN_HARD_STOP_S = 5.0


@dataclass
class DaemonCounters:
    frames_received: int = 0
    #: Refused by the time axis before any processing (future, stale, out of order).
    frames_refused: int = 0
    frames_processed: int = 0
    frames_bad: int = 0
    frame_errors: int = 0
    fix_attempts: int = 0
    fixes_accepted: int = 0
    #: Tracked frames the fix path had no time for (a newer frame replaced them).
    fix_frames_skipped: int = 0
    estimates_sent: int = 0
    last_latency_ms: float | None = None
    #: Steps of the host's wall clock against the daemon's clock (detected and recorded, not followed).
    clock_steps: int = 0
    #: Times the autopilot's ground altitude was found to disagree with the daemon's.
    ground_alt_disagreements: int = 0
    #: Solved fixes the integrity rule refused, by reason (``IntegrityReason``), and those the consistency
    #: monitor did not fuse (``unverified``).
    fixes_refused_integrity: dict[str, int] = field(default_factory=dict)
    #: Solved fixes that passed every check but arrived later than the time axis can fuse them
    #: (``estimator.max_fix_delay_s``): the matcher is too slow for that setting on this computer.
    fixes_too_late: int = 0
    #: Fix attempts and accepted fixes per effort-ladder rung (``c3_matcher/ladder.py``), and the rung of
    #: the newest attempt.
    rung_attempts: dict[str, int] = field(default_factory=dict)
    rung_accepted: dict[str, int] = field(default_factory=dict)
    last_fix_rung: str | None = None
    #: What the area fixes measured of the autopilot's heading (deg) and height (scale), medians
    #: (``c4_pose/heading_height_check.py``; None before enough strong area fixes).
    heading_offset_deg: float | None = None
    height_scale: float | None = None
    #: SIGHUP, SIGUSR1 and SIGUSR2 received and ignored (``daemon.signals``), by name.
    signals_ignored: dict[str, int] = field(default_factory=dict)
    #: The start prior's doubt (``c5_estimator/prior_doubt.py``): whether a map fix has confirmed it,
    #: failed attempts counted against it, how often its sigma grew and to what, and how far from it the
    #: map fix that confirmed it after a doubt was.
    prior_confirmed: bool = False
    prior_failures: int = 0
    prior_widenings: int = 0
    prior_sigma_m: float | None = None
    prior_reanchored_m: float | None = None


class NavDaemon:
    def __init__(
        self,
        root: RuntimeRoot,
        *,
        notifier: SdNotifier | None = None,
        beacon: StartupBeacon | None = None,
        core: CoreChannel | None = None,
    ) -> None:
        """``beacon``: the start-up beacon on ``root.link`` (``gdnav run``), stopped when the tasks start.
        ``core``: this daemon is a navigator core's vision worker (``daemon/core.py``): its estimate goes
        to the core, which sends it, tells the ground of its provenance and keeps the resume state."""
        self._root = root
        self._core = core
        self._beacon = beacon
        self._cfg = root.config
        self._axis = root.time_axis
        self._clock = root.clock
        self._notifier = notifier or SdNotifier()
        self._queue: LatestQueue[tuple[CapturedFrame, int]] = LatestQueue(self._cfg.camera.queue_depth)
        self._fix_mailbox: LatestQueue[NavCameraFrame] = LatestQueue(1)
        self._track_thread = WorkerThread("track")
        self._fix_thread = WorkerThread("fix", nice=self._cfg.daemon.fix_thread_nice)
        self._provenance = Provenance.NO_ESTIMATE
        #: The autopilot's ground altitude disagrees with the daemon's (``_check_ground_alt``).
        self._ground_alt_off = False
        self._last_state: EstimatorState | None = None
        self._fix_gate = Fix3dGate()  # the output stream's fix_type: one gate for the one stream
        self._last_fix: FixOutcome | None = None
        self._last_fix_reason: str | None = None
        #: The tilt checks' last verdicts on the autopilot's tilt (``c4_pose/attitude_check.py``): the
        #: fixes' and VO's ground tilt (``c1_vio/ground_tilt.py``); the operator hears when either finds
        #: it off and when both agree again.
        self._attitude_off = {"fixes": False, "vo": False}
        self._heading_off = False
        self._height_off = False
        #: Inside a run of fixes dropped as too late (``_note_too_late``): the operator has been told.
        self._fixes_late_run = False
        #: F8: when the autopilot was first / last asked for its estimate after a restart (daemon clock, s).
        self._asked_autopilot_first_s: float | None = None
        self._asked_autopilot_last_s: float | None = None
        #: F8: when the autopilot was last asked for its landed state (daemon clock, s).
        self._asked_phase_s: float | None = None
        #: When the operator was last told the prior's search grew (daemon clock, s; None: not yet).
        self._doubt_told_s: float | None = None
        #: F8: the last estimate sent as a 3D fix and its provenance, for the resume state file.
        self._last_3d: tuple[ResumeState, str] | None = None
        #: Worker threads still inside a frame when the daemon stopped (see ``run``).
        self.abandoned_threads: list[str] = []
        #: Tasks that ignored their cancellation within the stop grace (the caller must not wait on them).
        self.stuck_tasks: list[str] = []
        #: Set before the tasks are cancelled. asyncio.wait_for can swallow a cancellation that lands as its
        #: inner wait completes (CPython 3.10/3.11), so the I/O loop also checks this flag.
        self._stopping = False
        self.counters = DaemonCounters()

    # -- lifecycle ---------------------------------------------------------------------------------
    async def run(self, stop: asyncio.Event | None = None) -> int:
        """Run until ``stop`` is set or SIGTERM/SIGINT; returns the process exit code."""
        stop = stop or asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            with contextlib.suppress(NotImplementedError, RuntimeError):
                loop.add_signal_handler(sig, stop.set)
        for sig in IGNORED_SIGNALS:  # survived, logged and counted (``daemon.signals``)
            with contextlib.suppress(NotImplementedError, RuntimeError):
                loop.add_signal_handler(sig, self._signal_ignored, sig)
        if self._beacon is not None:
            self._beacon.stop()  # the link is the tasks' from here
            # Its asks for the autopilot's estimate count as the daemon's own: the start-up wait runs from
            # the first, and the answers that came are the ones the first frame's prior may take.
            asked = self._beacon.asked
            self._asked_autopilot_first_s = asked.estimate_first_unix_s
            self._asked_autopilot_last_s = asked.estimate_last_unix_s
            self._asked_phase_s = asked.phase_last_unix_s
        self._root.link.open()
        bodies = {
            "camera_ingest": self._camera_ingest(),
            "track_worker": self._track_worker(),
            "fix_worker": self._fix_worker(),
            "estimate_output": self._estimate_output(),
            "mavlink_rx": self._mavlink_rx(),
            "mavlink_tx": self._mavlink_tx(),
            "status": self._status(),
        }
        if self._root.resume_state is not None and self._core is None:
            resume = self._root.resume_state
            bodies["resume_state"] = keep_resume_state(resume, lambda: self._last_3d, self._clock.now_unix_s)
        if self._core is not None:
            bodies["core_channel"] = self._core_channel()
        if "global_position_sensor" in self._cfg.mavlink.outputs:
            self._root.link.hold_global_position_sensor("PX4's EKF2_AGP0 parameters not checked yet")
            bodies["px4_parameters"] = self._idle_after(self._check_px4_parameters())
        tasks = {name: asyncio.create_task(body, name=name) for name, body in bodies.items()}
        stopper = asyncio.create_task(stop.wait(), name="stop")
        self._notifier.ready(f"matcher={self._cfg.matcher.strategy} tiles={len(self._root.tile_store)}")
        log.info(
            LogEvent.DAEMON_READY,
            tasks=sorted(tasks),
            matcher=self._cfg.matcher.strategy,
            rungs=[r.name for r in self._root.pipeline.ladder.rungs] if self._root.pipeline.ladder else [],
            nice={"track": self._track_thread.nice_value, "fix": self._fix_thread.nice_value},
        )
        exit_code = 0
        try:
            done, _ = await asyncio.wait([stopper, *tasks.values()], return_when=asyncio.FIRST_COMPLETED)
            for task in done:
                if task is not stopper and not task.cancelled() and task.exception() is not None:
                    exc = task.exception()
                    log.error(LogEvent.DAEMON_TASK_FAILED, task=task.get_name(), error=repr(exc))
                    exit_code = 1
        finally:
            log.info(LogEvent.DAEMON_STOPPING)
            self._notifier.stopping()
            self._stopping = True
            everything = [stopper, *tasks.values()]
            for task in everything:
                task.cancel()
            # Bounded: a task that ignores cancellation must not hold the process past its stop budget.
            _, stuck = await asyncio.wait(everything, timeout=_STOP_GRACE_S)
            for task in stuck:
                self.stuck_tasks.append(task.get_name())
                log.error(
                    LogEvent.DAEMON_TASK_STUCK,
                    task=task.get_name(),
                    stack=[f"{f.f_code.co_filename}:{f.f_lineno}" for f in task.get_stack()],
                )
            # The workers may be inside a frame: a bounded grace, then they are abandoned (daemon threads).
            # The caller must then end the process without interpreter teardown (``exit_now``): a
            # thread inside ONNX Runtime that is torn down under it aborts the process (SIGABRT).
            grace_s = self._cfg.daemon.frame_stop_grace_s
            finished = await asyncio.gather(self._track_thread.stop(grace_s), self._fix_thread.stop(grace_s))
            for name, ok in zip(("track_thread", "fix_thread"), finished, strict=True):
                if not ok:
                    self.abandoned_threads.append(name)
                    log.warning(LogEvent.DAEMON_TASK_STUCK, task=name, grace_s=grace_s)
            self._root.close()
            self._notifier.close()
            log.info(LogEvent.DAEMON_STOPPED, exit_code=exit_code, **vars(self.counters))
        return exit_code

    def _signal_ignored(self, sig: signal.Signals) -> None:
        """One of ``IGNORED_SIGNALS`` arrived: the daemon flies on; the signal is logged and counted."""
        counts = self.counters.signals_ignored
        counts[sig.name] = counts.get(sig.name, 0) + 1
        log.warning(LogEvent.DAEMON_SIGNAL_IGNORED, signal=sig.name, count=counts[sig.name])

    # -- tasks ---------------------------------------------------------------------------------------
    async def _camera_ingest(self) -> None:
        async for frame in self._root.camera.frames():
            self.counters.frames_received += 1
            if not self._queue.put((frame, time.monotonic_ns())):
                log.debug(LogEvent.CAMERA_FRAME_DROPPED, seq=frame.seq, dropped_total=self._queue.dropped)

    async def _track_worker(self) -> None:
        tracker = self._root.tracker
        while True:
            captured, received_ns = await self._queue.get()
            admission = self._axis.admit_frame(captured.exposure_time_unix_usec)
            t_us = admission.exposure_time_unix_usec  # in the daemon's clock from here on
            if not admission.admitted:
                self.counters.frames_refused += 1
                reason = admission.reason.value if admission.reason is not None else "unknown"
                log.warning(
                    LogEvent.PIPELINE_FRAME_INVALID,
                    seq=captured.seq,
                    reason=reason,
                    ahead_of_clock_s=round(admission.ahead_s, 3),
                )
                self._root.fdr.record(
                    FdrKind.FRAME_REFUSED,
                    {
                        "frame_seq": captured.seq,
                        "exposure_time_unix_usec": t_us,
                        "stamp_unix_usec": captured.exposure_time_unix_usec,
                        "reason": reason,
                        "ahead_of_clock_s": admission.ahead_s,
                    },
                )
                continue
            # Vehicle state is sampled on the loop (single owner); the worker threads get values only.
            await self._await_attitude(t_us)
            attitude = tracker.attitude_at(t_us)
            alt_agl_m = tracker.alt_agl_at(t_us)
            timing = self._frame_timing(t_us, admission.stamp_offset_s)
            prior = self._prior(t_us)
            result = await self._track_thread.submit(
                self._track, captured, t_us, received_ns, attitude, alt_agl_m, prior, timing
            )
            if result is None:
                continue
            frame, outcome = result
            if prior is not None and self._axis.is_initialised:
                self._announce_prior(prior)
            self._note_tracked(outcome)
            if self._axis.is_initialised and not self._fix_mailbox.put(frame):
                self.counters.fix_frames_skipped += 1

    async def _fix_worker(self) -> None:
        while True:
            frame = await self._fix_mailbox.get()
            outcome = await self._fix_thread.submit(self._localise, frame)
            if outcome is not None:
                self._note_fix(outcome)

    def _prior(self, exposure_time_unix_usec: int) -> InitialPrior | None:
        """The start-up prior (F8 rules in ``c5_estimator.prior``); None while the autopilot has not
        told enough yet to decide (not known to be on the ground or in the air, or no HOME_POSITION, and no
        previous run to resume)."""
        if self._axis.is_initialised:
            return None
        handover = self._core.take_handover() if self._core is not None else None
        if handover is not None:
            cp = handover.checkpoint
            if handover.ltp == self._root.ltp and cp.time_usec is not None:
                lat, lon, _alt = self._root.ltp.to_geodetic(cp.x[:3, 0])
                return InitialPrior(
                    float(lat),
                    float(lon),
                    float(math.sqrt(max(cp.p_mat[0, 0], cp.p_mat[1, 1]))),
                    PriorSource.CORE_HANDOVER,
                    why="the navigator core's filter, carried on the IMU while this worker restarted",
                    confirmed=cp.map_confirmed,
                    handover=cp,
                )
            log.warning(LogEvent.WORKER_BAD_CORE_MESSAGE, error="handover in another local frame: not taken")
        tracker = self._root.tracker
        home = tracker.home() if self._cfg.init.use_home_position else None
        alt_agl_m = tracker.alt_agl_at(exposure_time_unix_usec)
        now_s = self._clock.now_unix_s()
        phase = tracker.flight_phase(now_s)
        air = in_the_air(self._cfg.init, alt_agl_m, phase)
        if self._asked_phase_s is None or now_s - self._asked_phase_s >= PHASE_ASK_PERIOD_S:
            # ArduPilot streams EXTENDED_SYS_STATE only where its stream rates say so: ask, at 1 Hz, until
            # the estimator has started.
            self._root.link.request_flight_phase()
            self._asked_phase_s = now_s
        tiles = self._root.tile_store
        _west, _south, east, north = tiles.bbox_lonlat
        centre_lon, centre_lat = tiles.center_lonlat
        radius_m = float(haversine_m(centre_lat, centre_lon, north, east))
        autopilot = None
        restarted = self._root.previous_run.last_record_unix_s is not None
        asked_s = self._asked_autopilot_last_s
        if air is False and tracker.ground_position() is None and (asked_s is None or now_s - asked_s >= 1.0):
            # On the ground: the autopilot's own position is the start points' witness (``prior``).
            self._root.link.request_autopilot_estimate()
            self._asked_autopilot_last_s = now_s
        # HOME_POSITION is a witness of the start points (``prior``): streamed only every few seconds,
        # it may not have come yet on a cold start that sees the vehicle in the air at its first frame.
        need_home = self._cfg.init.use_home_position and home is None and air is not False
        if (restarted or air or need_home) and self._cfg.init.autopilot_wait_s > 0:
            # A restart or a start in flight: ask the autopilot for its estimate, and wait a little for it.
            autopilot = tracker.autopilot_position(now_s) if restarted or air else None
            if autopilot is None or need_home:
                if self._asked_autopilot_first_s is None:
                    self._asked_autopilot_first_s = now_s
                last_s = self._asked_autopilot_last_s
                if last_s is None or now_s - last_s >= ESTIMATE_ASK_PERIOD_S:
                    self._root.link.request_autopilot_estimate()
                    self._asked_autopilot_last_s = now_s
                first_s = self._asked_autopilot_first_s
                answered = autopilot is not None or tracker.estimate_answered_since(first_s)
                # ... and its home, where the rules may use it (an autopilot without one never answers)
                answered = answered and not need_home
                if not answered and now_s - self._asked_autopilot_first_s < self._cfg.init.autopilot_wait_s:
                    return None  # no answer yet (an autopilot that has no position says so: no wait)
        prior = choose_prior(
            now_unix_usec=exposure_time_unix_usec,
            init=self._cfg.init,
            previous=self._root.previous_run,
            home=home,
            alt_agl_m=alt_agl_m,
            map_centre_lat_lon=(centre_lat, centre_lon),
            map_radius_m=radius_m,
            autopilot=autopilot,
            phase=phase,
            autopilot_ground=tracker.ground_position(),
            home_signed=tracker.home_signed(),
        )
        if prior.source == PriorSource.MAP_EXTENT and not restarted and not air:
            return None  # a cold start not known to be in the air: wait for HOME_POSITION and the ground
        return prior

    def _announce_prior(self, prior: InitialPrior) -> None:
        """Say where the estimator started and why: log, FDR, and the ground station."""
        log.warning(
            LogEvent.ESTIMATOR_PRIOR,
            source=prior.source,
            why=prior.why,
            sigma_m=round(prior.sigma_m, 1),
            lat_deg=prior.lat_deg,
            lon_deg=prior.lon_deg,
            confirmed=prior.confirmed,
            spread_m=prior.spread_m,
        )
        self._root.fdr.record(
            FdrKind.PRIOR,
            {
                "source": prior.source,
                "why": prior.why,
                "lat_deg": prior.lat_deg,
                "lon_deg": prior.lon_deg,
                "sigma_m": prior.sigma_m,
                "confirmed": prior.confirmed,
                "spread_m": prior.spread_m,
                # the core's filter this worker started from, whole: a replay starts from it too
                "handover": (
                    state_to_wire(prior.handover, self._root.ltp) if prior.handover is not None else None
                ),
            },
        )
        self.counters.prior_confirmed = prior.confirmed
        text = {
            PriorSource.RESUMED: f"GDN: resumed, sigma {prior.sigma_m:.0f} m",
            PriorSource.CORE_HANDOVER: f"GDN: vision resumed, sigma {prior.sigma_m:.0f} m",
            PriorSource.MAP_EXTENT: "GDN: no trusted prior, searching map",
            PriorSource.AUTOPILOT: "GDN: no trusted prior, searching map from AP estimate",
            PriorSource.DISPUTED: STATUSTEXT_PRIOR_DISPUTED.format(prior.spread_m or 0.0),
        }.get(prior.source, STATUSTEXT_PRIOR_UNCONFIRMED.format(prior.source))
        severity = (
            mavutil.mavlink.MAV_SEVERITY_INFO
            if prior.source in (PriorSource.HOME, PriorSource.CONFIG)
            else mavutil.mavlink.MAV_SEVERITY_WARNING
        )
        self._root.link.send_statustext(severity, text)

    def _frame_error(self, seq: int, stage: str, error: str, *, bad_input: bool) -> None:
        if bad_input:
            self.counters.frames_bad += 1
        else:
            self.counters.frame_errors += 1
        self._root.fdr.record(FdrKind.FRAME_ERROR, {"frame_seq": seq, "stage": stage, "error": error})

    async def _await_attitude(self, t_us: int) -> None:
        """Wait (at most ``ATTITUDE_WAIT_MAX_S``) until the autopilot's attitude covers the exposure and a
        little after it: a camera that stamps late, or a slow link, would otherwise pair the frame with
        an attitude extrapolated and held from before it (like with like, and the rate needs both sides)."""
        tracker = self._root.tracker
        need_usec = t_us + round(ATTITUDE_RATE_HALF_SPAN_S * 1e6)
        deadline = time.monotonic() + ATTITUDE_WAIT_MAX_S
        while time.monotonic() < deadline:
            latest = tracker.latest_attitude_unix_usec()
            # covered, or the stream has stopped (a link drop): waiting would only delay the frame
            if latest is None or latest >= need_usec or latest < t_us - ATTITUDE_WAIT_MAX_S * 1e6:
                return
            await asyncio.sleep(0.01)

    def _frame_timing(self, t_us: int, stamp_offset_s: float) -> FrameTiming | None:
        """How well the frame's exposure time is known: the camera's doubt and the autopilot clock's,
        with the rate world-down moved in the camera then (None without the attitude)."""
        tracker = self._root.tracker
        camera = self._axis.camera_offset
        span = np.array([-ATTITUDE_RATE_HALF_SPAN_S, ATTITUDE_RATE_HALF_SPAN_S])
        curve = tracker.down_cam_curve(t_us, span) if camera is not None else None
        if camera is None or curve is None:
            return None
        rate = (curve[1] - curve[0]) / (2 * ATTITUDE_RATE_HALF_SPAN_S)
        ap_sigma_s = tracker.autopilot_clock.sigma_s
        sigma_s = math.hypot(camera.sigma_s, ap_sigma_s if ap_sigma_s is not None else 0.0)
        ahrs = tracker.ahrs_doubt_rad(t_us)
        return FrameTiming((float(rate[0]), float(rate[1])), stamp_offset_s, sigma_s, ahrs or 0.0)

    def _check_camera_stamps(self) -> None:
        """Feed the camera-lateness fit the attitude that has arrived for its queued tilts; a change of
        the correction is logged, recorded and told to the ground station."""
        camera = self._axis.camera_offset
        tracker = self._root.tracker
        latest = tracker.latest_attitude_unix_usec()
        if camera is None or latest is None or not camera.complete(tracker.down_cam_curve, latest):
            return
        fit = camera.fit
        fields = {
            "applied_s": round(camera.applied_s, 4),
            "sigma_s": round(camera.sigma_s, 4),
            "fit_s": round(fit.offset_s, 4) if fit is not None else None,
            "fit_se_s": round(fit.se_s, 4) if fit is not None else None,
            "fit_explained": round(fit.explained, 3) if fit is not None else None,
            "samples": fit.samples if fit is not None else 0,
            "out_of_bounds": camera.out_of_bounds,
        }
        log.warning(LogEvent.CAMERA_STAMP_OFFSET, **fields)
        self._root.fdr.record(FdrKind.CAMERA_STAMP_OFFSET, fields)
        bound = " (beyond camera.max_stamp_offset_s)" if camera.out_of_bounds else ""
        self._root.link.send_statustext(
            mavutil.mavlink.MAV_SEVERITY_WARNING,
            f"GDN: camera stamps {camera.applied_s * 1000:+.0f} ms late{bound}",
        )

    def _track(
        self,
        captured: CapturedFrame,
        exposure_time_unix_usec: int,
        received_ns: int,
        attitude,
        alt_agl_m,  # type: ignore[no-untyped-def]
        prior: InitialPrior | None,
        timing: FrameTiming | None = None,
    ) -> tuple[NavCameraFrame, TrackOutcome] | None:
        """Runs on the track thread. A per-frame error is recorded and the daemon keeps flying."""
        try:
            image = captured.decode()
        except FrameStreamError as exc:
            log.warning(LogEvent.CAMERA_BAD_FRAME, seq=captured.seq, error=str(exc))
            self._frame_error(captured.seq, "decode", str(exc), bad_input=True)
            return None
        cal = self._root.calibration
        if image.shape[1] != cal.width_px or image.shape[0] != cal.height_px:
            got, want = f"{image.shape[1]}x{image.shape[0]}", f"{cal.width_px}x{cal.height_px}"
            msg = f"frame is {got}, calibration is for {want}"
            log.warning(LogEvent.CAMERA_BAD_FRAME, seq=captured.seq, error=msg)
            self._frame_error(captured.seq, "size", msg, bad_input=True)
            return None
        frame = NavCameraFrame(
            uuid.uuid4(),
            captured.seq,
            exposure_time_unix_usec,
            image,
            attitude,
            alt_agl_m,
            received_ns,
            timing,
        )
        try:
            outcome = self._root.pipeline.track(frame, prior)
        except Exception as exc:  # keep flying on any per-frame failure; it is recorded
            log.exception(LogEvent.PIPELINE_FRAME_ERROR, seq=captured.seq, stage="track", error=repr(exc))
            self._frame_error(captured.seq, "track", repr(exc), bad_input=False)
            return None
        every_n = self._cfg.fdr.frame_jpeg_every_n
        if every_n and captured.seq % every_n == 0:
            # After VO, so the encode (a few ms) never delays the estimate; the recorder never raises.
            self._root.fdr.record_frame_encoded(
                captured.seq,
                exposure_time_unix_usec,
                image,
                self._cfg.fdr.frames_format,
                quality=self._cfg.fdr.frame_jpeg_quality,
            )
        return frame, outcome

    def _localise(self, frame: NavCameraFrame) -> FixOutcome | None:
        """Runs on the fix thread. A per-frame error is recorded and the daemon keeps flying."""
        try:
            return self._root.pipeline.localise(frame)
        except Exception as exc:  # keep flying on any per-frame failure; it is recorded
            log.exception(LogEvent.PIPELINE_FRAME_ERROR, seq=frame.seq, stage="localise", error=repr(exc))
            self._frame_error(frame.seq, "localise", repr(exc), bad_input=False)
            return None

    def _note_tracked(self, outcome: TrackOutcome) -> None:
        self.counters.frames_processed += 1
        latency_ms = (self._clock.now_unix_usec() - outcome.exposure_time_unix_usec) / 1e3
        self.counters.last_latency_ms = latency_ms
        log.info(
            LogEvent.PIPELINE_FRAME,
            seq=outcome.seq,
            provenance=outcome.provenance.value,
            vo=outcome.vo_ok,
            vo_reason=outcome.vo_reason,
            sigma_m=round(outcome.state.horiz_sigma_m, 2) if outcome.state else None,
            latency_ms=round(latency_ms, 1),
            timings_ms={k: round(v, 1) for k, v in outcome.timings_ms.items()},
        )
        if outcome.ground_tilt is not None:
            self._note_attitude("vo", outcome.ground_tilt)

    def _note_fix(self, outcome: FixOutcome) -> None:
        self.counters.fix_attempts += 1
        self.counters.fixes_accepted += int(outcome.fix_accepted)
        if outcome.rung is not None:
            c = self.counters
            c.rung_attempts[outcome.rung] = c.rung_attempts.get(outcome.rung, 0) + 1
            c.rung_accepted[outcome.rung] = c.rung_accepted.get(outcome.rung, 0) + int(outcome.fix_accepted)
            c.last_fix_rung = outcome.rung
        verdict = outcome.integrity
        refused = self.counters.fixes_refused_integrity
        if verdict is not None and not verdict.accepted and verdict.reason is not None:
            refused[verdict.reason] = refused.get(verdict.reason, 0) + 1
        elif (outcome.no_fix_reason or "").startswith("consistency:"):
            reason = str(outcome.no_fix_reason).split(":", 1)[1]
            refused[reason] = refused.get(reason, 0) + 1
        elif outcome.attitude is not None and outcome.attitude.refused is not None:
            refused[outcome.attitude.refused] = refused.get(outcome.attitude.refused, 0) + 1
        elif (outcome.no_fix_reason or "").startswith("vo_attitude_"):
            reason = str(outcome.no_fix_reason)
            refused[reason] = refused.get(reason, 0) + 1
        if outcome.attitude is not None:
            self._note_attitude("fixes", outcome.attitude)
        if outcome.heading_height is not None:
            self._note_heading_height(outcome.heading_height)
        self._note_too_late(outcome)
        self._note_prior_doubt(outcome)
        self._last_fix = outcome
        self._last_fix_reason = outcome.no_fix_reason
        log.info(
            LogEvent.PIPELINE_FIX,
            seq=outcome.seq,
            accepted=outcome.fix_accepted,
            rung=outcome.rung,
            inliers=outcome.inliers,
            reason=outcome.no_fix_reason,
            fused_behind_s=round(outcome.fused_behind_s, 3),
            age_ms=round((self._clock.now_unix_usec() - outcome.exposure_time_unix_usec) / 1e3, 1),
            timings_ms={k: round(v, 1) for k, v in outcome.timings_ms.items()},
        )

    def _note_prior_doubt(self, outcome: FixOutcome) -> None:
        """The start prior's doubt for ``daemon.status``, and for the operator: its search grew (the first
        time at once, then at most every ``PRIOR_DOUBT_TEXT_INTERVAL_S``), and the map answered."""
        doubt = outcome.prior_doubt
        c = self.counters
        if outcome.fix_accepted:
            c.prior_confirmed = True
        if doubt is None:
            return
        c.prior_failures = doubt.failures
        if doubt.raise_to_sigma_m is not None:
            c.prior_widenings += 1
            c.prior_sigma_m = round(doubt.raise_to_sigma_m, 1)
            now_s = self._clock.now_unix_s()
            told = self._doubt_told_s
            if told is None or now_s - told >= PRIOR_DOUBT_TEXT_INTERVAL_S:
                self._doubt_told_s = now_s
                radius_m = self._cfg.vpr.prior_sigma_scale * doubt.raise_to_sigma_m
                self._root.link.send_statustext(
                    mavutil.mavlink.MAV_SEVERITY_WARNING,
                    STATUSTEXT_PRIOR_DOUBTED.format(doubt.failures, radius_m),
                )
        if doubt.reanchored_m is not None:
            c.prior_reanchored_m = round(doubt.reanchored_m, 1)
            self._root.link.send_statustext(
                mavutil.mavlink.MAV_SEVERITY_WARNING, STATUSTEXT_PRIOR_REANCHORED.format(doubt.reanchored_m)
            )

    def _note_too_late(self, outcome: FixOutcome) -> None:
        """Tell the operator, at the first of a run of them, that right fixes are dropped because they
        arrive later than the time axis can fuse them: a matcher slower than ``estimator.max_fix_delay_s``
        on this computer (DISK + LightGlue on a CPU takes 7-17 s) would otherwise fly VO-only with no
        word why. The run ends at the next fix fused."""
        if outcome.fix_accepted:
            self._fixes_late_run = False
            return
        if outcome.no_fix_reason != FIX_TOO_LATE_REASON:
            return
        self.counters.fixes_too_late += 1
        if self._fixes_late_run:
            return
        self._fixes_late_run = True
        limit_s = self._cfg.estimator.max_fix_delay_s
        log.warning(
            LogEvent.FIXES_TOO_LATE,
            seq=outcome.seq,
            behind_s=round(outcome.fused_behind_s, 2),
            max_fix_delay_s=limit_s,
            fixes_too_late=self.counters.fixes_too_late,
            hint="the matcher is slower than estimator.max_fix_delay_s allows: raise it, or use a faster "
            "matcher or computer",
        )
        self._root.link.send_statustext(
            mavutil.mavlink.MAV_SEVERITY_WARNING,
            f"GDN: fix {outcome.fused_behind_s:.1f} s late > {limit_s:g} s, dropped",
        )

    def _note_heading_height(self, check: HeadingHeightVerdict) -> None:
        """Tell the operator when the area fixes find the autopilot's heading or height off, and when it
        agrees again (``c4_pose/heading_height_check.py``): the correlation searches around both, so the
        fixes stay right, but the compass, the baro or ``terrain.ground_alt_amsl_m`` is off."""
        c = self.counters
        c.heading_offset_deg = check.heading_offset_deg
        c.height_scale = check.height_scale
        for what, off, was in (
            ("heading", check.heading_off, self._heading_off),
            ("height", check.height_off, self._height_off),
        ):
            if off == was:
                continue
            if what == "heading":
                self._heading_off = off
                text = (
                    f"GDN: AP heading {check.heading_offset_deg:+.0f} deg off the map"
                    if off
                    else "GDN: AP heading agrees with the map"
                )
            else:
                self._height_off = off
                text = (
                    f"GDN: AP height x{check.height_scale:.2f} of the map's"
                    if off
                    else "GDN: AP height agrees with the map"
                )
            log.warning(LogEvent.HEADING_HEIGHT_CHECK, what=what, off=off, **check.fdr_fields())
            severity = mavutil.mavlink.MAV_SEVERITY_WARNING if off else mavutil.mavlink.MAV_SEVERITY_INFO
            self._root.link.send_statustext(severity, text)

    def _note_attitude(self, source: str, check: AttitudeVerdict) -> None:
        """Tell the operator when a tilt check (``source``: ``fixes`` or ``vo``) finds the autopilot's
        tilt off, and when both agree again: an AHRS or camera-mount fault of the aircraft, not of
        this daemon."""
        was_off = any(self._attitude_off.values())
        self._attitude_off[source] = check.off
        if any(self._attitude_off.values()) == was_off:
            return
        if check.off:
            text = f"GDN: AP tilt {math.hypot(*check.bias_deg):.1f} deg off camera, no fixes"
            severity = mavutil.mavlink.MAV_SEVERITY_WARNING
        else:
            text = "GDN: AP tilt agrees with camera again"
            severity = mavutil.mavlink.MAV_SEVERITY_INFO
        self._root.link.send_statustext(severity, text)

    async def _estimate_output(self) -> None:
        """The steady estimate stream: the state propagated to the send time, at
        ``mavlink.estimate_rate_hz`` on absolute deadlines (``daemon.periodic``), whatever the frames do."""
        await on_deadlines(1.0 / self._cfg.mavlink.estimate_rate_hz, self._estimate_tick)

    def _estimate_tick(self) -> None:
        try:
            self._send_estimate()
        except Exception as exc:  # one estimate failing must not stop the stream; recorded
            self.counters.frame_errors += 1
            log.exception(LogEvent.PIPELINE_FRAME_ERROR, stage="estimate_output", error=repr(exc))
            self._root.fdr.record(
                FdrKind.FRAME_ERROR, {"frame_seq": None, "stage": "estimate_output", "error": repr(exc)}
            )

    def _send_estimate(self) -> None:
        state = self._axis.state_at()
        self._last_state = state
        fix_type = self._fix_gate.fix_type(state)
        if self._core is not None:
            sent = int(self._to_core())
        else:
            sent = self._root.link.send_estimate(
                state, time_unix_usec=state.time_unix_usec, gps_fix_type=fix_type
            )
        self.counters.estimates_sent += int(sent > 0)
        new = state.provenance
        if new is not self._provenance:
            old, self._provenance = self._provenance, new
            reason = self._last_fix_reason if new is not Provenance.SATELLITE_ANCHORED else None
            log.warning(LogEvent.PROVENANCE_CHANGED, old=old.value, new=new.value, reason=reason)
            self._root.fdr.record(
                FdrKind.PROVENANCE_CHANGED, {"old": old.value, "new": new.value, "reason": reason}
            )
            if self._core is None:  # under a core, the core tells the ground what it sends
                self._root.link.notify_provenance(old, new, f"GDN: {new.value}: {reason}" if reason else None)
        horiz = state.horiz_sigma_m if math.isfinite(state.lat_deg) else None
        speed = stated_speed_sigma_m_s(state)
        if fix_type == 3 and horiz is not None:
            resume = ResumeState(state.lat_deg, state.lon_deg, horiz, state.time_unix_usec)
            self._last_3d = (resume, new.value)
        self._root.fdr.record(
            FdrKind.ESTIMATE_SENT,
            {
                "time_unix_usec": state.time_unix_usec,
                "provenance": new.value,
                "fix_type": fix_type,
                "lat_deg": state.lat_deg if horiz is not None else None,
                "lon_deg": state.lon_deg if horiz is not None else None,
                "horiz_sigma_m": horiz,
                "speed_sigma_m_s": speed if math.isfinite(speed) else None,
                "last_fix_age_s": state.last_fix_age_s if math.isfinite(state.last_fix_age_s) else None,
                "sent": sent,
            },
        )

    def _to_core(self) -> bool:
        """The filter at its head to the navigator core, which predicts it to its send times (the core's
        worker only); before the estimator starts, that the worker is alive."""
        core = self._core
        assert core is not None
        link = self._root.link
        fields = {
            "system_status": self._system_status(),
            "no_fix_reason": self._last_fix_reason,
            "agp_hold": link.global_position_sensor_hold,
            "alt_distrust": link.altitude_distrust,
        }
        checkpoint = self._axis.head_checkpoint()
        if checkpoint is None:
            return core.send_alive(**fields)
        return core.send_estimate(checkpoint, self._root.ltp, **fields)

    async def _core_channel(self) -> None:
        """The navigator core's socket (its worker only): its handover and its relay's address read. When
        the core has gone, the pipeline runs on while this waits ``daemon.worker_orphan_s`` for the core's
        next start to adopt it (``daemon/core_channel.py``); returns when none does, which stops this
        worker."""
        core = self._core
        assert core is not None
        loop = asyncio.get_running_loop()
        readable = asyncio.Event()
        while True:
            fd = core.fileno()
            loop.add_reader(fd, readable.set)
            try:
                while True:
                    readable.clear()
                    if not core.poll():
                        break
                    if core.core_relay_port is not None:  # a new core: its relay speaks for the autopilot
                        self._root.link.follow_autopilot_at("127.0.0.1", core.core_relay_port)
                        core.core_relay_port = None
                    await readable.wait()
            finally:
                with contextlib.suppress(OSError, ValueError):
                    loop.remove_reader(fd)
            if not await self._await_next_core(core):
                log.warning(LogEvent.DAEMON_STOPPING, reason="the navigator core closed its socket")
                return

    async def _await_next_core(self, core: CoreChannel) -> bool:
        """This worker's core is gone: wait for its next start to adopt it. A worker stuck in native code
        meanwhile is ended by ``faulthandler``'s timer, which needs no Python to run."""
        wait_s = self._cfg.daemon.worker_orphan_s
        listener = core.rendezvous_fileno()
        log.warning(LogEvent.WORKER_ORPHANED, wait_s=wait_s, listening=listener is not None)
        self._root.fdr.record(FdrKind.WORKER_CORE, {"event": "orphaned", "wait_s": wait_s})
        if listener is None:
            return False
        faulthandler.dump_traceback_later(wait_s + ORPHAN_HARD_STOP_S, exit=True)
        loop = asyncio.get_running_loop()
        connecting = asyncio.Event()
        loop.add_reader(listener, connecting.set)
        deadline = time.monotonic() + wait_s
        try:
            while not core.adopt():
                left_s = deadline - time.monotonic()
                if left_s <= 0:
                    return False
                connecting.clear()
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(connecting.wait(), left_s)
        finally:
            with contextlib.suppress(OSError, ValueError):
                loop.remove_reader(listener)
            faulthandler.cancel_dump_traceback_later()
        log.warning(LogEvent.WORKER_ADOPTED, adoptions=core.adoptions)
        self._root.fdr.record(FdrKind.WORKER_CORE, {"event": "adopted", "adoptions": core.adoptions})
        return True

    async def _mavlink_rx(self) -> None:
        loop = asyncio.get_running_loop()
        link = self._root.link
        readable = asyncio.Event()
        fd: int | None = None
        try:
            while not self._stopping:
                current = link.fileno()
                if current != fd:
                    if fd is not None:
                        loop.remove_reader(fd)
                    fd = current
                    if fd is not None:
                        loop.add_reader(fd, readable.set)
                # Without a selectable fd (or while reconnecting) fall back to polling.
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(readable.wait(), 0.05 if fd is None else 0.5)
                readable.clear()
                link.poll()
        finally:
            if fd is not None:
                loop.remove_reader(fd)

    async def _mavlink_tx(self) -> None:
        period = 1.0 / self._cfg.mavlink.heartbeat_hz
        while True:
            self._root.link.send_heartbeat(self._system_status())
            await asyncio.sleep(period)

    def _system_status(self) -> int:
        if self._last_state is None or not self._axis.is_initialised:
            return mavutil.mavlink.MAV_STATE_STANDBY
        if self._provenance in (Provenance.SATELLITE_ANCHORED, Provenance.VISUAL_PROPAGATED):
            return mavutil.mavlink.MAV_STATE_ACTIVE
        return mavutil.mavlink.MAV_STATE_CRITICAL

    def _send_status_values(self) -> None:
        state = self._last_state
        fix = self._last_fix
        self._root.link.send_status_values(
            provenance=self._provenance,
            inliers=fix.inliers if fix is not None else 0,
            residual_px=fix.residual_px if fix is not None else None,
            horiz_sigma_m=state.horiz_sigma_m if state is not None else math.inf,
            frame_drops=self._queue.dropped,
            fdr_health=self._root.fdr.health().state,
            integrity_refused=sum(self.counters.fixes_refused_integrity.values()),
        )

    def _record_status(self, link_alive: bool, axis: TimeAxisStats, fdr: FdrHealth) -> None:
        """One ``daemon.status`` FDR record per status period: every counter a fault moves (refused and
        bad frames, camera reconnects, MAVLink bad packets and link state, FDR health), so the recorder
        alone shows when each fault happened and how the daemon took it."""
        link = self._root.link.stats()
        camera = self._root.camera
        self._root.fdr.record(
            FdrKind.STATUS,
            {
                "provenance": self._provenance.value,
                **vars(self.counters),
                "frames_dropped": self._queue.dropped,
                "camera_bad_frames": camera.bad_frames,
                "camera_connections": camera.connections,
                "time_axis_refused": axis.refused,
                "time_axis_rewinds": axis.rewinds,
                "link_alive": link_alive,
                "link_connected": link.connected,
                "mavlink_received": link.messages_received,
                "mavlink_bad_packets": link.bad_packets,
                "mavlink_sent": link.messages_sent,
                "mavlink_send_errors": link.send_errors,
                "mavlink_reconnects": link.reconnects,
                "mavlink_impostor_messages": link.impostor_messages,
                "mavlink_positions_withheld": link.positions_withheld,
                "mavlink_timesync_answered": link.timesync_answered,
                "mavlink_timesync_ignored": link.timesync_ignored,
                "fdr_state": fdr.state.value,
                "tiles_corrupt": self._root.tile_store.corrupt_cells,
                **self._timing_status(),
            },
        )

    def _timing_status(self) -> dict[str, object]:
        """The clocks' state for ``daemon.status``: the autopilot clock mapping and the camera lateness."""
        ap_clock = self._root.tracker.autopilot_clock
        rtt = ap_clock.rtt_usec
        camera = self._axis.camera_offset
        fit = camera.fit if camera is not None else None
        return {
            "autopilot_time_source": ap_clock.source.value,
            "autopilot_timesync_rtt_ms": round(rtt / 1000, 2) if rtt is not None else None,
            "autopilot_clock_resets": ap_clock.resets,
            "camera_stamp_offset_s": round(camera.applied_s, 4) if camera is not None else None,
            "camera_stamp_sigma_s": round(camera.sigma_s, 4) if camera is not None else None,
            "camera_stamp_fit_s": round(fit.offset_s, 4) if fit is not None else None,
            "camera_stamp_fit_se_s": round(fit.se_s, 4) if fit is not None else None,
            "camera_stamp_fit_explained": round(fit.explained, 3) if fit is not None else None,
            "camera_stamp_out_of_bounds": camera.out_of_bounds if camera is not None else None,
            "ground_alt_disagrees": self._ground_alt_off,
        }

    def _check_clock(self) -> None:
        """A step of the host's wall clock: logged, recorded, counted and told to the ground station. The
        daemon's clock (monotonic) does not follow it; camera stamps are mapped through the new offset."""
        step = self._clock.check_step()
        if step is None:
            return
        self.counters.clock_steps += 1
        log.warning(
            LogEvent.CLOCK_STEP,
            step_s=round(step.step_s, 3),
            wall_offset_s=round(step.wall_offset_s, 3),
            clock_steps=self.counters.clock_steps,
        )
        self._root.fdr.record(
            FdrKind.CLOCK_STEP,
            {
                "step_s": step.step_s,
                "wall_offset_s": step.wall_offset_s,
                "clock_steps": self.counters.clock_steps,
            },
        )
        self._root.link.send_statustext(
            mavutil.mavlink.MAV_SEVERITY_WARNING, f"GDN: host clock stepped {step.step_s:+.1f} s, ignored"
        )

    @staticmethod
    async def _idle_after(once: Coroutine[Any, Any, None]) -> None:
        """Run ``once``, then wait: a task of the service that ends stops the service."""
        await once
        await asyncio.Event().wait()

    async def _check_px4_parameters(self) -> None:
        """Before the first GLOBAL_POSITION_SENSOR, read PX4's ``EKF2_AGP0_*`` back and say what is wrong
        (``c8_mavlink.px4_params``): log, FDR, STATUSTEXT. The message is held while the check runs and
        while ``EKF2_AGP0_ID`` is not its id; an autopilot that is not PX4, or parameters PX4 never
        answers, release it (reported)."""
        link, tracker = self._root.link, self._root.tracker
        while tracker.autopilot_kind is None:
            await asyncio.sleep(PX4_PARAM_POLL_S)
        if tracker.autopilot_kind != mavutil.mavlink.MAV_AUTOPILOT_PX4:
            link.hold_global_position_sensor(None)
            log.warning(
                LogEvent.PX4_PARAMETERS,
                autopilot=tracker.autopilot_kind,
                reason="the autopilot is not PX4: its EKF2_AGP0 parameters are not checked",
            )
            return
        values: dict[str, float | None] = dict.fromkeys(PX4_AGP_PARAMS)
        for _ in range(PX4_PARAM_TRIES):
            link.request_params(tuple(name for name, value in values.items() if value is None))
            for _ in range(round(PX4_PARAM_WAIT_S / PX4_PARAM_POLL_S)):  # on the critical path of a restart
                await asyncio.sleep(PX4_PARAM_POLL_S)
                values = {name: tracker.param(name) for name in PX4_AGP_PARAMS}
                if all(value is not None for value in values.values()):
                    break
            if all(value is not None for value in values.values()):
                break
        problems = px4_agp_problems(values, sensor_id=self._cfg.mavlink.global_position_sensor_id)
        blocking = [p.detail for p in problems if p.blocks_output]
        link.hold_global_position_sensor(blocking[0] if blocking else None)
        fields = {"values": values, "problems": [p.detail for p in problems], "output_held": bool(blocking)}
        self._root.fdr.record(FdrKind.PX4_PARAMETERS, fields)
        if not problems:
            log.info(LogEvent.PX4_PARAMETERS, **fields)
            return
        log.error(LogEvent.PX4_PARAMETERS, **fields)
        for problem in problems:
            link.send_statustext(mavutil.mavlink.MAV_SEVERITY_ERROR, problem.statustext)

    def _check_ground_alt(self) -> None:
        """The autopilot's ground altitude against ``terrain.ground_alt_amsl_m``: beyond
        ``terrain.max_ground_alt_disagreement_m`` GPS_INPUT's altitude is flagged as ignored, and the
        change is logged, recorded, counted and told to the ground station (both ways)."""
        ap_ground = self._root.tracker.ground_alt_amsl_m()
        if ap_ground is None:
            return
        terrain = self._cfg.terrain
        diff_m = terrain.ground_alt_amsl_m - ap_ground
        off = abs(diff_m) > terrain.max_ground_alt_disagreement_m
        if off == self._ground_alt_off:
            return
        self._ground_alt_off = off
        fields = {
            "disagrees": off,
            "daemon_ground_alt_amsl_m": terrain.ground_alt_amsl_m,
            "autopilot_ground_alt_amsl_m": round(ap_ground, 2),
            "difference_m": round(diff_m, 2),
        }
        self._root.link.distrust_altitude("ground altitude disagrees with the autopilot's" if off else None)
        if off:
            self.counters.ground_alt_disagreements += 1
            log.error(LogEvent.GROUND_ALT_DISAGREEMENT, **fields)
            text = f"GDN: ground alt {diff_m:+.0f} m vs AP, alt not sent"
        else:
            log.info(LogEvent.GROUND_ALT_DISAGREEMENT, **fields)
            text = "GDN: ground alt agrees with AP again"
        self._root.fdr.record(FdrKind.GROUND_ALT_CHECK, fields)
        self._root.link.send_statustext(
            mavutil.mavlink.MAV_SEVERITY_ERROR if off else mavutil.mavlink.MAV_SEVERITY_INFO, text
        )

    async def _status(self) -> None:
        period = 1.0 / self._cfg.daemon.status_hz
        nv_period = 1.0 / self._cfg.mavlink.named_value_hz
        watchdog_s = self._notifier.watchdog_interval_s
        tick = min(period, nv_period, watchdog_s) if watchdog_s else min(period, nv_period)
        last_status = last_nv = 0.0
        while True:
            self._notifier.watchdog()
            self._check_clock()
            self._check_ground_alt()
            self._check_camera_stamps()
            now = time.monotonic()
            if now - last_nv >= nv_period:
                last_nv = now
                self._send_status_values()
            if now - last_status >= period:
                last_status = now
                c = self.counters
                alive = self._root.tracker.link_alive(self._clock.now_unix_s())
                axis = self._axis.stats()
                fdr = self._root.fdr.health()
                log.info(
                    LogEvent.DAEMON_STATUS,
                    provenance=self._provenance.value,
                    link_alive=alive,
                    dropped=self._queue.dropped,
                    bad_frames=c.frames_bad + self._root.camera.bad_frames,
                    time_axis_refused=axis.refused,
                    time_axis_rewinds=axis.rewinds,
                    fdr=fdr.state.value,
                    fdr_free_bytes=fdr.free_bytes,
                    fdr_records_dropped=fdr.records_dropped,
                    fdr_images_dropped=fdr.images_dropped,
                    fdr_write_errors=fdr.write_errors,
                    mavlink_impostor_messages=self._root.link.stats().impostor_messages,
                    **{k: v for k, v in vars(c).items() if k != "frames_bad"},
                )
                self._record_status(alive, axis, fdr)
                self._notifier.status(
                    f"{self._provenance.value} frames={c.frames_processed} "
                    f"fixes={c.fixes_accepted}/{c.fix_attempts} refused={c.frames_refused} "
                    f"drops={self._queue.dropped} fdr={fdr.state.value}"
                )
            await asyncio.sleep(tick)
