"""The navigation daemon: one asyncio service owning named tasks.

Tasks: ``camera_ingest`` (frames into a newest-wins queue), ``pipeline_worker`` (runs the OpenCV/ONNX
pipeline on a worker thread, sends the estimate), ``mavlink_rx`` (drains the link whenever its socket
is readable), ``mavlink_tx`` (own HEARTBEAT), ``status`` (status log, ground-station values, systemd
watchdog). Leaving ``run`` cancels and awaits every task; only CancelledError is swallowed. A failing
task is logged with its name and stops the daemon (systemd restarts it: F8).
"""

from __future__ import annotations

import asyncio
import contextlib
import signal
import time
import uuid
from dataclasses import dataclass

import structlog
from pymavlink import mavutil

from gps_denied_onboard.camera.sources import CapturedFrame
from gps_denied_onboard.camera.stream import FrameStreamError
from gps_denied_onboard.camera.types import NavCameraFrame
from gps_denied_onboard.constants import FdrKind, LogEvent, Provenance
from gps_denied_onboard.daemon.frame_queue import LatestQueue
from gps_denied_onboard.daemon.sd_notify import SdNotifier
from gps_denied_onboard.daemon.worker import WorkerThread
from gps_denied_onboard.pipeline import FrameOutcome, InitialPrior
from gps_denied_onboard.runtime_root import RuntimeRoot

log = structlog.get_logger(__name__)

#: Seconds allowed for cancelled tasks, then for the in-flight frame, when stopping (2 s budget in all).
_STOP_GRACE_S = 0.5
_FRAME_GRACE_S = 0.5


@dataclass
class DaemonCounters:
    frames_received: int = 0
    frames_processed: int = 0
    frames_stale: int = 0
    frames_bad: int = 0
    frame_errors: int = 0
    fixes_accepted: int = 0
    last_latency_ms: float | None = None


class NavDaemon:
    def __init__(self, root: RuntimeRoot, *, notifier: SdNotifier | None = None) -> None:
        self._root = root
        self._cfg = root.config
        self._notifier = notifier or SdNotifier()
        self._queue: LatestQueue[tuple[CapturedFrame, int]] = LatestQueue(self._cfg.camera.queue_depth)
        self._worker = WorkerThread("pipeline")
        self._provenance = Provenance.NO_ESTIMATE
        self._last_outcome: FrameOutcome | None = None
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
        self._root.link.open()
        bodies = {
            "camera_ingest": self._camera_ingest(),
            "pipeline_worker": self._pipeline_worker(),
            "mavlink_rx": self._mavlink_rx(),
            "mavlink_tx": self._mavlink_tx(),
            "status": self._status(),
        }
        tasks = {name: asyncio.create_task(body, name=name) for name, body in bodies.items()}
        stopper = asyncio.create_task(stop.wait(), name="stop")
        self._notifier.ready(f"matcher={self._cfg.matcher.strategy} tiles={len(self._root.tile_store)}")
        log.info(LogEvent.DAEMON_READY, tasks=sorted(tasks), matcher=self._cfg.matcher.strategy)
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
                log.error(
                    LogEvent.DAEMON_TASK_STUCK,
                    task=task.get_name(),
                    stack=[f"{f.f_code.co_filename}:{f.f_lineno}" for f in task.get_stack()],
                )
            # The worker may be inside one frame: a bounded grace, then it is abandoned (daemon thread).
            if not await self._worker.stop(_FRAME_GRACE_S):
                log.warning(LogEvent.DAEMON_TASK_STUCK, task="pipeline_thread", grace_s=_FRAME_GRACE_S)
            self._root.close()
            self._notifier.close()
            log.info(LogEvent.DAEMON_STOPPED, exit_code=exit_code, **vars(self.counters))
        return exit_code

    # -- tasks ---------------------------------------------------------------------------------------
    async def _camera_ingest(self) -> None:
        async for frame in self._root.camera.frames():
            self.counters.frames_received += 1
            if not self._queue.put((frame, time.monotonic_ns())):
                log.debug(LogEvent.CAMERA_FRAME_DROPPED, seq=frame.seq, dropped_total=self._queue.dropped)

    async def _pipeline_worker(self) -> None:
        tracker = self._root.tracker
        while True:
            captured, received_ns = await self._queue.get()
            t_us = captured.exposure_time_unix_usec
            age_s = time.time() - t_us / 1e6
            if age_s > self._cfg.daemon.max_frame_age_s:
                self.counters.frames_stale += 1
                log.warning(
                    LogEvent.PIPELINE_FRAME_INVALID, seq=captured.seq, reason="stale", age_s=round(age_s, 3)
                )
                continue
            # Vehicle state is sampled on the loop (single owner); the pipeline thread gets values only.
            attitude = tracker.attitude_at(t_us)
            alt_agl_m = tracker.alt_agl_at(t_us)
            prior = self._prior()
            outcome = await self._worker.submit(
                self._process, captured, received_ns, attitude, alt_agl_m, prior
            )
            if outcome is not None:
                try:
                    self._publish(outcome)
                except Exception as exc:  # one frame's output failing must not stop the daemon; recorded
                    self.counters.frame_errors += 1
                    log.exception(
                        LogEvent.PIPELINE_FRAME_ERROR, seq=outcome.seq, stage="publish", error=repr(exc)
                    )
                    self._root.fdr.record(
                        FdrKind.FRAME_ERROR,
                        {"frame_seq": outcome.seq, "stage": "publish", "error": repr(exc)},
                    )

    def _prior(self) -> InitialPrior | None:
        init = self._cfg.init
        if init.lat_deg is not None and init.lon_deg is not None:
            return InitialPrior(init.lat_deg, init.lon_deg, init.sigma_m, "config")
        home = self._root.tracker.home() if init.use_home_position else None
        if home is not None:
            return InitialPrior(home[0], home[1], init.sigma_m, "home_position")
        return None

    def _process(
        self,
        captured: CapturedFrame,
        received_ns: int,
        attitude,
        alt_agl_m,  # type: ignore[no-untyped-def]
        prior: InitialPrior | None,
    ) -> FrameOutcome | None:
        """Runs on the pipeline thread. A per-frame error is recorded and the daemon keeps flying."""
        try:
            image = captured.decode()
        except FrameStreamError as exc:
            self.counters.frames_bad += 1
            log.warning(LogEvent.CAMERA_BAD_FRAME, seq=captured.seq, error=str(exc))
            self._root.fdr.record(
                FdrKind.FRAME_ERROR, {"frame_seq": captured.seq, "stage": "decode", "error": str(exc)}
            )
            return None
        cal = self._root.calibration
        if image.shape[1] != cal.width_px or image.shape[0] != cal.height_px:
            self.counters.frames_bad += 1
            got, want = f"{image.shape[1]}x{image.shape[0]}", f"{cal.width_px}x{cal.height_px}"
            msg = f"frame is {got}, calibration is for {want}"
            log.warning(LogEvent.CAMERA_BAD_FRAME, seq=captured.seq, error=msg)
            self._root.fdr.record(
                FdrKind.FRAME_ERROR, {"frame_seq": captured.seq, "stage": "size", "error": msg}
            )
            return None
        frame = NavCameraFrame(
            uuid.uuid4(),
            captured.seq,
            captured.exposure_time_unix_usec,
            image,
            attitude,
            alt_agl_m,
            received_ns,
        )
        try:
            return self._root.pipeline.process(frame, prior)
        except Exception as exc:  # keep flying on any per-frame failure; it is recorded
            self.counters.frame_errors += 1
            log.exception(LogEvent.PIPELINE_FRAME_ERROR, seq=captured.seq, error=repr(exc))
            self._root.fdr.record(
                FdrKind.FRAME_ERROR, {"frame_seq": captured.seq, "stage": "pipeline", "error": repr(exc)}
            )
            return None

    def _publish(self, outcome: FrameOutcome) -> None:
        self.counters.frames_processed += 1
        self.counters.fixes_accepted += int(outcome.fix_accepted)
        self._last_outcome = outcome
        latency_ms = (time.time() * 1e6 - outcome.exposure_time_unix_usec) / 1e3
        self.counters.last_latency_ms = latency_ms
        log.info(
            LogEvent.PIPELINE_FRAME,
            seq=outcome.seq,
            provenance=outcome.provenance.value,
            inliers=outcome.inliers,
            fix=outcome.fix_accepted,
            reason=outcome.no_fix_reason,
            sigma_m=round(outcome.state.horiz_sigma_m, 2) if outcome.state else None,
            latency_ms=round(latency_ms, 1),
            timings_ms={k: round(v, 1) for k, v in outcome.timings_ms.items()},
        )
        new = outcome.provenance
        if new is not self._provenance:
            old, self._provenance = self._provenance, new
            log.warning(
                LogEvent.PROVENANCE_CHANGED, old=old.value, new=new.value, reason=outcome.no_fix_reason
            )
            self._root.fdr.record(
                FdrKind.PROVENANCE_CHANGED,
                {"old": old.value, "new": new.value, "reason": outcome.no_fix_reason},
            )
            self._root.link.notify_provenance(old, new, outcome.no_fix_reason)
        if outcome.state is not None:
            self._root.link.send_estimate(
                outcome.state,
                time_unix_usec=outcome.exposure_time_unix_usec,
                inliers=outcome.inliers,
                residual_px=outcome.residual_px,
                frame_drops=self._queue.dropped,
            )

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
        if self._last_outcome is None:
            return mavutil.mavlink.MAV_STATE_STANDBY
        if self._provenance in (Provenance.SATELLITE_ANCHORED, Provenance.VISUAL_PROPAGATED):
            return mavutil.mavlink.MAV_STATE_ACTIVE
        return mavutil.mavlink.MAV_STATE_CRITICAL

    async def _status(self) -> None:
        period = 1.0 / self._cfg.daemon.status_hz
        watchdog_s = self._notifier.watchdog_interval_s
        tick = min(period, watchdog_s) if watchdog_s else period
        last_status = 0.0
        while True:
            self._notifier.watchdog()
            now = time.monotonic()
            if now - last_status >= period:
                last_status = now
                c = self.counters
                alive = self._root.tracker.link_alive(time.time())
                log.info(
                    LogEvent.DAEMON_STATUS,
                    provenance=self._provenance.value,
                    link_alive=alive,
                    dropped=self._queue.dropped,
                    bad_frames=c.frames_bad + self._root.camera.bad_frames,
                    **{k: v for k, v in vars(c).items() if k != "frames_bad"},
                )
                self._notifier.status(
                    f"{self._provenance.value} frames={c.frames_processed} "
                    f"fixes={c.fixes_accepted} drops={self._queue.dropped}"
                )
            await asyncio.sleep(tick)
