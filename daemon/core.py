"""The navigator core: the light process that keeps the autopilot fed while the vision works, crashes or
restarts (``daemon.vision_worker``; docs/design.md, "The navigator core and the vision worker").

What it holds, and what the vision worker (``gdnav run`` under it, the whole pipeline) holds:

- **The MAVLink link** to the autopilot. Every message the autopilot sends that the link's tracker takes
  (never an impostor's) is relayed to the worker's own link on loopback UDP; what the worker sends is
  relayed to the autopilot, except what the core says itself: the estimate (GPS_INPUT,
  GLOBAL_POSITION_SENSOR, VISION_POSITION_ESTIMATE), HEARTBEAT, the vision frame's origin and TIMESYNC
  answers. The worker signs as link id 1, the core as 0.
- **The estimate.** The worker fuses (VO, fixes, the time axis with its rewinds) and sends its filter's
  state at every output period over a Unix ``SOCK_SEQPACKET`` socket in msgpack
  (``c5_estimator/wire.py``; chosen by ``tools/ipc_bench.py``). The core restores it into its own
  ``NavEstimator`` and predicts it to each send time with the autopilot's IMU, on absolute deadlines.
  When the worker is gone, nothing else changes: the same filter goes on predicting on the IMU, its
  sigma grows as the filter's process noise says, its provenance and ``fix_type`` follow the same rules
  (``Fix3dGate``), and no deadline is missed. A restarted worker starts from the core's filter as it is
  at the worker's first frame (the handover, offered at every output period until the worker's first
  estimate: position, velocity and covariance), so fusion resumes where the core had got to.
- **The worker itself.** Started with its nice value ``daemon.worker_nice_offset`` above the core's;
  or, at the core's start, adopted: a worker left running by the core's previous process (killed,
  crashed, stopped by the watchdog) waits at its rendezvous for ``daemon.worker_orphan_s``
  (``daemon/core_channel.py``), and the new core takes it over with its filter, its VO and its map
  already running, so a core restart costs the core's own start and no vision start-up.
  Every message is its heartbeat; end-of-file on the socket is its death (a kill, a segfault, the OOM
  killer), seen at once. Silent for ``daemon.worker_silence_s`` (or with no first message within
  ``daemon.worker_start_s``) it is killed. Restarted after a back-off that doubles from
  ``WORKER_BACKOFF_MIN_S`` to ``WORKER_BACKOFF_MAX_S`` and starts again after ``WORKER_HEALTHY_S`` of
  good running; one that exits 2 or 3 (its configuration, or a file it needs, refused) is not started
  again: the core stops with that code, as one process would. The ground hears when it is lost and when
  it is back (STATUSTEXT); the log
  (``core.*``) and the core's FDR (``<fdr.dir>/core``, ``core.worker`` and ``mavlink.estimate``
  records) keep both.
- **The resume state file**, from what the core sent as 3D; systemd's ``sd_notify`` and its watchdog.

Imports stay light (no OpenCV, ONNX Runtime, SciPy, FAISS, torch): tests/test_startup_beacon.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import math
import os
import select
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import structlog
from pymavlink import mavutil

from gps_denied_onboard import __version__
from gps_denied_onboard.clock import DaemonClock
from gps_denied_onboard.components.c5_estimator.ekf import NavEstimator
from gps_denied_onboard.components.c5_estimator.prior import ResumeState
from gps_denied_onboard.components.c5_estimator.resume_state import ResumeStateFile, default_path
from gps_denied_onboard.components.c5_estimator.types import EstimatorState
from gps_denied_onboard.components.c5_estimator.wire import (
    WireError,
    pack,
    state_from_wire,
    state_to_wire,
    unpack,
)
from gps_denied_onboard.components.c8_mavlink import MavlinkLink
from gps_denied_onboard.components.c8_mavlink.messages import DIALECT, Fix3dGate
from gps_denied_onboard.components.c13_fdr.recorder import FlightDataRecorder
from gps_denied_onboard.config import Config
from gps_denied_onboard.constants import (
    CORE_FDR_SUBDIR,
    EXIT_CONFIG,
    EXIT_RESOURCE,
    STATUSTEXT_WORKER_ADOPTED,
    STATUSTEXT_WORKER_BACK,
    STATUSTEXT_WORKER_LOST,
    FdrKind,
    LogEvent,
    Provenance,
)
from gps_denied_onboard.daemon.core_channel import peer_credentials, rendezvous_address
from gps_denied_onboard.daemon.periodic import keep_resume_state, on_deadlines
from gps_denied_onboard.daemon.sd_notify import SdNotifier
from gps_denied_onboard.daemon.signals import IGNORED_SIGNALS
from gps_denied_onboard.geo import LocalTangentPlane

log = structlog.get_logger(__name__)

#: The MAVLink 2 signing link ids of the core's own messages and of the worker's, relayed.
CORE_SIGNING_LINK_ID: Final = 0
WORKER_SIGNING_LINK_ID: Final = 1
#: What the worker sends that the core never relays: it says these itself.
CORE_OWN_MESSAGES: Final = frozenset(
    {"GPS_INPUT", "GLOBAL_POSITION_SENSOR", "VISION_POSITION_ESTIMATE", "HEARTBEAT", "SET_GPS_GLOBAL_ORIGIN"}
)
#: The restart back-off: the first pause, the longest, and the good running after which it starts over, s.
WORKER_BACKOFF_MIN_S: Final = 0.2
WORKER_BACKOFF_MAX_S: Final = 10.0
WORKER_HEALTHY_S: Final = 30.0
#: How often the supervisor looks at the worker, and how long a worker whose socket closed may live on, s.
SUPERVISE_PERIOD_S: Final = 0.05
WORKER_EOF_GRACE_S: Final = 0.5
#: The worker's grace between SIGTERM and SIGKILL when the core stops, s.
WORKER_STOP_GRACE_S: Final = 1.2
#: The largest message on the socket (a state is about 1 KiB), bytes.
MAX_MESSAGE_BYTES: Final = 65536
#: The environment variable that carries a worker's ``launch_id`` from the core that started it.
LAUNCH_ID_ENV: Final = "GDNAV_WORKER_LAUNCH_ID"
#: An adopted worker's exit status, which only its parent could read (``_exit_text``: "ended").
EXIT_UNKNOWN: Final = 256
#: The core's share of ``fdr.max_bytes`` for its own records (at least two segments); the worker gets the
#: rest.
CORE_FDR_SHARE: Final = 0.1


class AdoptedWorker:
    """A worker this core did not start (left running by the core's previous process): not this
    process's child, so it is watched and signalled through a pidfd (Linux 5.3), which cannot reach a
    later process given the same pid. The ``Popen`` methods the core uses; its exit status is unknown."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self._fd: int | None = os.pidfd_open(pid)
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None and self._fd is not None:
            ended, _, _ = select.select([self._fd], [], [], 0.0)
            if ended:
                self._ended()
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if self.returncode is None and self._fd is not None:
            ended, _, _ = select.select([self._fd], [], [], timeout)
            if not ended:
                raise subprocess.TimeoutExpired(f"pid {self.pid}", timeout or 0.0)
            self._ended()
        return EXIT_UNKNOWN if self.returncode is None else self.returncode

    def _ended(self) -> None:
        self.returncode = EXIT_UNKNOWN
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def send_signal(self, sig: signal.Signals) -> None:
        if self.poll() is None and self._fd is not None:
            signal.pidfd_send_signal(self._fd, sig)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)


@dataclass
class WorkerState:
    """The vision worker as the core sees it."""

    proc: subprocess.Popen[bytes] | AdoptedWorker | None = None
    sock: socket.socket | None = None
    started_s: float = 0.0
    #: Its newest message of any kind (None: none since this start), core clock s.
    heard_s: float | None = None
    #: Its newest estimate (None: none since this start), core clock s.
    estimate_s: float | None = None
    #: When it was lost (None: it is running), core clock s.
    lost_s: float | None = None
    #: Its first message due within this long of its start (or adoption), s.
    first_message_s: float = 60.0
    starts: int = 0
    adoptions: int = 0
    losses: int = 0
    kills: int = 0
    bad_messages: int = 0
    #: When its socket closed (None: open), core clock s; why the core killed it (how, the ground's words).
    eof_s: float | None = None
    kill_reason: tuple[str, str] | None = None
    #: The pause before the restart after this loss, and the one after the next (doubling), s.
    restart_in_s: float = WORKER_BACKOFF_MIN_S
    backoff_s: float = WORKER_BACKOFF_MIN_S
    #: The loopback UDP port its link listens on (a fresh one for each start).
    port: int = 0
    #: What it last said of itself: its HEARTBEAT's system status, why there is no fix, and the holds on
    #: the outputs its own checks set (PX4's parameters, the autopilot's ground altitude).
    system_status: int = mavutil.mavlink.MAV_STATE_BOOT
    no_fix_reason: str | None = None
    exits: list[str] = field(default_factory=list)


class NavigatorCore:
    """The core's tasks on one asyncio loop (see the module docstring). ``config_path`` and
    ``overrides``: how the worker is started (``gdnav run --config ... --set ...``)."""

    def __init__(
        self,
        config: Config,
        config_path: str | Path,
        overrides: Sequence[str],
        *,
        link: MavlinkLink,
        clock: DaemonClock,
        notifier: SdNotifier | None = None,
    ) -> None:
        self._cfg = config
        self._config_path = str(config_path)
        self._overrides = list(overrides)
        #: What this core starts its workers with; an orphan started with anything else is not adopted.
        self._launch_id = launch_id(self._config_path, self._overrides)
        self._link = link
        self._clock = clock
        self._notifier = notifier or SdNotifier()
        self._worker = WorkerState()
        self._est: NavEstimator | None = None
        self._ltp: LocalTangentPlane | None = None
        self._gate = Fix3dGate()
        self._provenance = Provenance.NO_ESTIMATE
        self._last_3d: tuple[ResumeState, str] | None = None
        self._parser = DIALECT.MAVLink(None)
        self._parser.robust_parsing = True
        self._relay_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._relay_sock.bind(("127.0.0.1", 0))
        self._relay_sock.setblocking(False)
        self.relayed_to_worker = 0
        self.relayed_to_autopilot = 0
        self.estimates_sent = 0
        #: The worker's exit code when it refused its configuration or a file (2 or 3): the core's too.
        self.refused_exit: int | None = None
        #: SIGHUP, SIGUSR1, SIGUSR2 survived, by name (``daemon.signals``).
        self.signals_ignored: dict[str, int] = {}
        #: The worker's refusal line, when it said one (``gdnav run`` prints it last).
        self.worker_refusal: str | None = None
        fdr_dir = Path(config.fdr.dir)
        with contextlib.suppress(OSError):  # a full or read-only disk: the recorder counts what it loses
            (fdr_dir / CORE_FDR_SUBDIR).mkdir(parents=True, exist_ok=True)
        self._fdr_bytes = max(int(config.fdr.max_bytes * CORE_FDR_SHARE), config.fdr.segment_bytes * 2)
        self._fdr = FlightDataRecorder(
            fdr_dir / CORE_FDR_SUBDIR,
            max_bytes=self._fdr_bytes,
            segment_bytes=config.fdr.segment_bytes,
            clock=clock.now_unix_s,
            images_max_bytes=0,
            min_free_bytes=config.fdr.min_free_bytes,
        )
        link.attach_fdr(self._fdr)  # its events (impostors, link lost, TIMESYNC) in the core's records
        state_path = config.init.resume_state_path or default_path(fdr_dir)
        self._rendezvous = rendezvous_address(fdr_dir)
        self._resume = ResumeStateFile(state_path)
        if "global_position_sensor" in config.mavlink.outputs:
            link.hold_global_position_sensor(
                "the vision worker has not checked PX4's EKF2_AGP0 parameters yet"
            )

    # -- lifecycle ------------------------------------------------------------------------------------
    async def run(self, stop: asyncio.Event | None = None) -> int:
        stop = stop or asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
                loop.add_signal_handler(sig, stop.set)
        for sig in IGNORED_SIGNALS:
            with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
                loop.add_signal_handler(sig, self._signal_ignored, sig)
        self._link.relay_autopilot_to(self._relay_to_worker)
        bodies = {
            "output": self._output(),
            "mavlink_rx": self._mavlink_rx(),
            "relay_rx": self._relay_rx(),
            "heartbeat": self._heartbeat(),
            "supervise": self._supervise(),
            "resume_state": keep_resume_state(self._resume, lambda: self._last_3d, self._clock.now_unix_s),
            "status": self._status(),
        }
        tasks = {name: asyncio.create_task(body, name=name) for name, body in bodies.items()}
        stopper = asyncio.create_task(stop.wait(), name="stop")
        self._notifier.ready("navigator core; vision worker starting")
        log.info(
            LogEvent.CORE_READY,
            relay_port=self._relay_sock.getsockname()[1],
            nice=os.getpriority(os.PRIO_PROCESS, 0),
        )
        exit_code = 0
        try:
            done, _ = await asyncio.wait([stopper, *tasks.values()], return_when=asyncio.FIRST_COMPLETED)
            if self.refused_exit is not None:
                exit_code = self.refused_exit
            for task in done:
                if task is not stopper and not task.cancelled() and task.exception() is not None:
                    log.error(LogEvent.DAEMON_TASK_FAILED, task=task.get_name(), error=repr(task.exception()))
                    exit_code = 1
        finally:
            log.info(LogEvent.DAEMON_STOPPING)
            for sig in (signal.SIGTERM, signal.SIGINT, *IGNORED_SIGNALS):
                with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
                    loop.remove_signal_handler(sig)
            self._notifier.stopping()
            sock = self._worker.sock
            if sock is not None:  # its end at the stop is no loss to report
                with contextlib.suppress(OSError, ValueError):
                    loop.remove_reader(sock.fileno())
            proc = self._worker.proc
            if proc is not None and proc.poll() is None:  # the worker's own stop runs beside the core's
                with contextlib.suppress(OSError):
                    proc.terminate()
            for task in [stopper, *tasks.values()]:
                task.cancel()
            await asyncio.wait([stopper, *tasks.values()], timeout=0.5)
            await asyncio.to_thread(self._stop_worker)
            self._link.relay_autopilot_to(None)
            self._link.close()
            self._relay_sock.close()
            self._fdr.close()
            self._notifier.close()
            log.info(
                LogEvent.DAEMON_STOPPED,
                exit_code=exit_code,
                signals_ignored=dict(self.signals_ignored),
                worker_starts=self._worker.starts,
                worker_losses=self._worker.losses,
                estimates_sent=self.estimates_sent,
            )
        return exit_code

    def _signal_ignored(self, sig: signal.Signals) -> None:
        """One of ``IGNORED_SIGNALS``: the core flies on (``daemon.signals``); logged and counted."""
        self.signals_ignored[sig.name] = self.signals_ignored.get(sig.name, 0) + 1
        log.warning(LogEvent.DAEMON_SIGNAL_IGNORED, signal=sig.name, count=self.signals_ignored[sig.name])

    # -- the worker -----------------------------------------------------------------------------------
    def _worker_command(self, fd: int) -> list[str]:
        command = [sys.executable, "-m", "gps_denied_onboard.cli", "run", "--config", self._config_path]
        for item in self._overrides:
            command += ["--set", item]
        worker_fdr_bytes = self._cfg.fdr.max_bytes - self._fdr_bytes
        if worker_fdr_bytes >= 2 * self._cfg.fdr.segment_bytes:  # the two recorders within fdr.max_bytes
            command += ["--set", f"fdr.max_bytes={worker_fdr_bytes}"]
        command += ["--set", f"mavlink.url=udpin:127.0.0.1:{self._worker.port}", "--worker-fd", str(fd)]
        return command

    def _start_worker(self) -> None:
        w = self._worker
        w.port = _free_udp_port()
        core_end, worker_end = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        handover = self._handover()
        if handover is not None:
            core_end.send(pack(handover))  # waits in the socket for the worker's first read
        env = dict(os.environ)
        env[LAUNCH_ID_ENV] = self._launch_id
        env.pop("NOTIFY_SOCKET", None)  # systemd hears the core only (NotifyAccess=main)
        env.pop("WATCHDOG_USEC", None)
        env.pop("WATCHDOG_PID", None)
        try:
            proc = subprocess.Popen(
                self._worker_command(worker_end.fileno()), pass_fds=(worker_end.fileno(),), env=env
            )
        finally:
            worker_end.close()
        with contextlib.suppress(OSError):  # behind the core: its nice value above the core's
            nice = os.getpriority(os.PRIO_PROCESS, 0) + self._cfg.daemon.worker_nice_offset
            os.setpriority(os.PRIO_PROCESS, proc.pid, min(19, nice))
        core_end.setblocking(False)
        self._take_worker(proc, core_end, first_message_s=self._cfg.daemon.worker_start_s)
        w.starts += 1
        fields = {"pid": proc.pid, "start": w.starts, "handover": handover is not None, "port": w.port}
        log.info(LogEvent.CORE_WORKER_STARTED, **fields)
        self._fdr.record(FdrKind.CORE_WORKER, {"event": "started", **fields})

    def _take_worker(
        self, proc: subprocess.Popen[bytes] | AdoptedWorker, sock: socket.socket, *, first_message_s: float
    ) -> None:
        """``proc`` is this core's worker from now on (started or adopted), heard on ``sock``."""
        w = self._worker
        w.proc, w.sock = proc, sock
        w.started_s = time.monotonic()
        w.first_message_s = first_message_s
        w.heard_s = w.estimate_s = w.eof_s = None
        w.kill_reason = None
        w.system_status = mavutil.mavlink.MAV_STATE_BOOT

    def _adopt_worker(self) -> bool:
        """Take over a worker of this daemon left running by the core's previous process, if one waits
        at the rendezvous (``daemon/core_channel.py``): its pid from the socket's peer credentials, its
        link's port from its ``hello``; told where this core's relay is. False when none waits."""
        w = self._worker
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            sock.connect(self._rendezvous)
            pid, uid, _ = peer_credentials(sock)
            if uid != os.getuid():  # another user's process holds the name: not a worker of ours
                log.warning(LogEvent.CORE_RENDEZVOUS_FOREIGN, pid=pid, uid=uid)
                sock.close()
                return False
            proc = AdoptedWorker(pid)
            sock.setblocking(False)
            sock.send(pack({"kind": "core", "relay_port": self._relay_sock.getsockname()[1]}))
        except OSError:  # nobody listens (refused, or gone meanwhile): no worker of this daemon runs
            sock.close()
            return False
        w.port = 0  # the port comes with its hello
        # it runs already: it answers at once
        self._take_worker(proc, sock, first_message_s=self._cfg.daemon.worker_silence_s)
        w.adoptions += 1
        fields = {"pid": pid, "adoptions": w.adoptions}
        log.warning(LogEvent.CORE_WORKER_ADOPTED, **fields)
        self._fdr.record(FdrKind.CORE_WORKER, {"event": "adopted", **fields})
        self._link.send_statustext(mavutil.mavlink.MAV_SEVERITY_NOTICE, STATUSTEXT_WORKER_ADOPTED)
        return True

    def _handover(self) -> dict[str, Any] | None:
        """The core's filter predicted to now, for a restarted worker to start from (None: no estimate)."""
        if self._est is None or self._ltp is None or not self._est.is_initialised:
            return None
        self._est.predict_to(self._clock.now_unix_usec())
        state = state_to_wire(self._est.checkpoint(), self._ltp, clock_anchor_ns=self._clock.anchor_unix_ns)
        return {"kind": "handover", "state": state}

    def _close_socket(self) -> None:
        w = self._worker
        sock, w.sock = w.sock, None
        if sock is not None:
            with contextlib.suppress(OSError, ValueError, RuntimeError):
                asyncio.get_running_loop().remove_reader(sock.fileno())
            sock.close()

    def _kill_worker(self, how: str, short: str) -> None:
        """Kill the worker for ``how`` (the ground hears ``short``); ``_supervise`` reaps and reports it."""
        w = self._worker
        if w.proc is None or w.kill_reason is not None:
            return
        w.kills += 1
        w.kill_reason = (how, short)
        with contextlib.suppress(OSError):
            w.proc.kill()

    def _lose_worker(self) -> None:
        """The worker has exited: reaped, counted, reported; the output goes on on the IMU."""
        w = self._worker
        proc = w.proc
        assert proc is not None
        self._close_socket()
        w.proc = None
        exit_text = _exit_text(proc.returncode)
        how, short = w.kill_reason or ("it ended" if w.eof_s is None else "its socket closed", exit_text)
        w.kill_reason = None
        w.eof_s = None
        ran_s = time.monotonic() - w.started_s
        w.losses += 1
        w.lost_s = time.monotonic()
        w.exits.append(exit_text)
        if ran_s >= WORKER_HEALTHY_S:
            w.backoff_s = WORKER_BACKOFF_MIN_S  # it had been running well: this loss starts the count over
        w.restart_in_s = w.backoff_s
        w.backoff_s = min(WORKER_BACKOFF_MAX_S, w.backoff_s * 2)
        fields = {"how": how, "exit": exit_text, "ran_s": round(ran_s, 2), "restart_in_s": w.restart_in_s}
        log.error(LogEvent.CORE_WORKER_LOST, **fields)
        self._fdr.record(FdrKind.CORE_WORKER, {"event": "lost", **fields})
        self._link.send_statustext(
            mavutil.mavlink.MAV_SEVERITY_CRITICAL, STATUSTEXT_WORKER_LOST.format(short)
        )

    def _stop_worker(self) -> None:
        """At the core's stop (off the loop): SIGTERM, then SIGKILL after ``WORKER_STOP_GRACE_S``."""
        proc = self._worker.proc
        if proc is None or proc.poll() is not None:
            return
        with contextlib.suppress(OSError):
            proc.terminate()
        try:
            proc.wait(timeout=WORKER_STOP_GRACE_S)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(OSError):
                proc.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=1.0)

    async def _supervise(self) -> None:
        """Start the worker, watch it, and start it again after each loss (see the module docstring).
        Nothing here blocks the loop: an end is reaped by polling, every ``SUPERVISE_PERIOD_S``."""
        loop = asyncio.get_running_loop()
        cfg = self._cfg.daemon
        while True:
            w = self._worker
            if w.proc is None:
                if w.lost_s is not None:
                    await asyncio.sleep(max(0.0, w.lost_s + w.restart_in_s - time.monotonic()))
                if not self._adopt_worker():
                    self._start_worker()
                assert w.sock is not None
                loop.add_reader(w.sock.fileno(), self._read_worker)
            await asyncio.sleep(SUPERVISE_PERIOD_S)
            proc = w.proc
            assert proc is not None
            now = time.monotonic()
            if proc.poll() is not None:
                self._read_worker()  # what it said last
                self._lose_worker()
                if proc.returncode in (EXIT_CONFIG, EXIT_RESOURCE):
                    # its configuration or a file it needs is refused: starting it again cannot help
                    log.error(LogEvent.CORE_WORKER_REFUSED, exit=proc.returncode)
                    self.refused_exit = proc.returncode
                    return
            elif w.eof_s is not None and now - w.eof_s > WORKER_EOF_GRACE_S:
                self._kill_worker("its socket closed, and it lived on", "socket closed")
            elif w.heard_s is None and now - w.started_s > w.first_message_s:
                self._kill_worker(f"nothing within {w.first_message_s:.0f} s of its start", "no start")
            elif w.heard_s is not None and now - w.heard_s > cfg.worker_silence_s:
                self._kill_worker(f"silent for {now - w.heard_s:.1f} s", "stalled")

    def _read_worker(self) -> None:
        """Every message waiting on the worker's socket; at its end-of-file, the socket is closed and the
        process left for ``_supervise`` to reap."""
        w = self._worker
        while w.sock is not None:
            try:
                data = w.sock.recv(MAX_MESSAGE_BYTES)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                data = b""
            if not data:
                w.eof_s = time.monotonic()
                self._close_socket()
                return
            w.heard_s = time.monotonic()
            try:
                self._on_message(unpack(data))
            except WireError as exc:
                w.bad_messages += 1
                log.warning(LogEvent.CORE_WORKER_BAD_MESSAGE, error=str(exc), count=w.bad_messages)

    def _on_message(self, message: dict[str, Any]) -> None:
        w = self._worker
        status = message.get("system_status")
        if isinstance(status, int):
            w.system_status = status
        if message["kind"] == "refusal" and isinstance(message.get("text"), str):
            self.worker_refusal = message["text"]
            return
        if message["kind"] == "hello":  # an adopted worker: where its link listens, what it was started with
            w.port = _udpin_port(message.get("mavlink_url"))
            if message.get("launch_id") != self._launch_id:
                # another configuration or version than this core's (changed, then the core crashed):
                # what the operator set now must take effect, so it is replaced, not adopted
                theirs = message.get("launch_id")
                log.warning(LogEvent.CORE_WORKER_STALE, launch_id=theirs, own=self._launch_id)
                self._kill_worker("started with another configuration or version", "config changed")
            return
        if message["kind"] != "estimate" or w.kill_reason is not None:
            return  # "alive": loading, or waiting for its first prior; or a worker being killed
        ws = state_from_wire(message["state"], clock_anchor_ns=self._clock.anchor_unix_ns)
        if self._est is None or self._ltp != ws.ltp:
            self._est = NavEstimator(self._cfg.estimator, ws.ltp, accel_source=self._link.tracker)
            self._ltp = ws.ltp
            self._link.attach(self._fdr, ws.ltp)
        self._est.restore(ws.checkpoint)
        reason = message.get("no_fix_reason")
        w.no_fix_reason = reason if isinstance(reason, str) else None
        agp, alt = message.get("agp_hold"), message.get("alt_distrust")
        self._link.hold_global_position_sensor(agp if isinstance(agp, str) else None)
        self._link.distrust_altitude(alt if isinstance(alt, str) else None)
        now = time.monotonic()
        if w.estimate_s is None and w.lost_s is not None:
            gap_s = now - w.lost_s
            log.warning(LogEvent.CORE_WORKER_BACK, after_s=round(gap_s, 2), start=w.starts)
            self._fdr.record(FdrKind.CORE_WORKER, {"event": "back", "after_s": round(gap_s, 3)})
            self._link.send_statustext(
                mavutil.mavlink.MAV_SEVERITY_NOTICE, STATUSTEXT_WORKER_BACK.format(gap_s)
            )
            w.lost_s = None
        w.estimate_s = now

    # -- MAVLink ----------------------------------------------------------------------------------------
    def _relay_to_worker(self, msg: Any) -> None:
        """The autopilot's own messages to the worker's link (what other systems say, a ground station's or
        a flood's, the worker does not need: relaying it would double the core's work under a flood)."""
        if msg.get_srcSystem() != self._cfg.mavlink.autopilot_system_id or not self._worker.port:
            return
        with contextlib.suppress(OSError):
            self._relay_sock.sendto(msg.get_msgbuf(), ("127.0.0.1", self._worker.port))
            self.relayed_to_worker += 1

    async def _mavlink_rx(self) -> None:
        loop = asyncio.get_running_loop()
        readable = asyncio.Event()
        fd: int | None = None
        try:
            while True:
                current = self._link.fileno()
                if current != fd:
                    if fd is not None:
                        loop.remove_reader(fd)
                    fd = current
                    if fd is not None:
                        loop.add_reader(fd, readable.set)
                readable.clear()  # before the poll: a datagram arriving during it sets it again
                self._link.poll()
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(readable.wait(), 0.05)
        finally:
            if fd is not None:
                with contextlib.suppress(OSError, ValueError):
                    loop.remove_reader(fd)

    async def _relay_rx(self) -> None:
        loop = asyncio.get_running_loop()
        readable = asyncio.Event()
        loop.add_reader(self._relay_sock.fileno(), readable.set)
        try:
            while True:
                readable.clear()
                self._relay_from_worker()
                await readable.wait()
        finally:
            with contextlib.suppress(OSError, ValueError):
                loop.remove_reader(self._relay_sock.fileno())

    def _relay_from_worker(self) -> None:
        """What the worker's link sent, to the autopilot as it was encoded (and signed), but for what the
        core says itself."""
        while True:
            try:
                data, address = self._relay_sock.recvfrom(MAX_MESSAGE_BYTES)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            if address != ("127.0.0.1", self._worker.port):
                continue  # only the worker's link speaks on this socket
            try:
                messages = self._parser.parse_buffer(data) or []
            except Exception:  # a malformed datagram: dropped
                continue
            for msg in messages:
                name = msg.get_type()
                if name == "BAD_DATA" or name in CORE_OWN_MESSAGES:
                    continue
                if name == "TIMESYNC" and msg.tc1 != 0:
                    continue  # the core answers the autopilot's TIMESYNC itself
                if self._link.send_raw(msg.get_msgbuf()):
                    self.relayed_to_autopilot += 1

    async def _heartbeat(self) -> None:
        period = 1.0 / self._cfg.mavlink.heartbeat_hz
        while True:
            self._link.send_heartbeat(self._system_status())
            self._notifier.watchdog()
            await asyncio.sleep(min(period, self._notifier.watchdog_interval_s or period))

    def _system_status(self) -> int:
        w = self._worker
        if w.estimate_s is not None:
            return w.system_status
        if self._est is not None and self._est.is_initialised:
            return mavutil.mavlink.MAV_STATE_CRITICAL  # navigating on the IMU alone until the worker is back
        if w.heard_s is not None:
            return w.system_status  # its tasks run (STANDBY until its estimator starts)
        return mavutil.mavlink.MAV_STATE_BOOT

    # -- the output -----------------------------------------------------------------------------------
    async def _output(self) -> None:
        await on_deadlines(1.0 / self._cfg.mavlink.estimate_rate_hz, self._output_tick)

    def _output_tick(self) -> None:
        try:
            self._send_estimate()
        except Exception as exc:  # one estimate failing must not stop the stream; recorded
            log.exception(LogEvent.PIPELINE_FRAME_ERROR, stage="core_output", error=repr(exc))
            self._fdr.record(
                FdrKind.FRAME_ERROR, {"frame_seq": None, "stage": "core_output", "error": repr(exc)}
            )

    def _offer_handover(self) -> None:
        """Until a started worker sends its first estimate, the core's filter at every output period: the
        worker starts from the newest at its first frame, so it need not predict the time it took to
        start again without the IMU the core had (its own link hears the IMU only from its start)."""
        w = self._worker
        if w.sock is None or w.estimate_s is not None:
            return
        handover = self._handover()
        if handover is not None:
            with contextlib.suppress(BlockingIOError, InterruptedError, OSError):
                w.sock.send(pack(handover))

    def _send_estimate(self) -> None:
        self._offer_handover()
        now_usec = self._clock.now_unix_usec()
        est = self._est
        state = est.state(now_usec) if est is not None else EstimatorState.no_estimate(now_usec)
        fix_type = self._gate.fix_type(state) if est is not None else 0
        sent = self._link.send_estimate(state, time_unix_usec=state.time_unix_usec, gps_fix_type=fix_type)
        self.estimates_sent += int(sent > 0)
        new = state.provenance
        if new is not self._provenance:
            old, self._provenance = self._provenance, new
            reason = None
            if new is not Provenance.SATELLITE_ANCHORED:
                reason = (
                    self._worker.no_fix_reason
                    if self._worker.estimate_s is not None
                    else "vision worker lost"
                )
            log.warning(LogEvent.PROVENANCE_CHANGED, old=old.value, new=new.value, reason=reason)
            self._fdr.record(
                FdrKind.PROVENANCE_CHANGED, {"old": old.value, "new": new.value, "reason": reason}
            )
            self._link.notify_provenance(old, new, f"GDN: {new.value}: {reason}" if reason else None)
        horiz = state.horiz_sigma_m if math.isfinite(state.lat_deg) else None
        if fix_type == 3 and horiz is not None:
            self._last_3d = (
                ResumeState(state.lat_deg, state.lon_deg, horiz, state.time_unix_usec),
                new.value,
            )
        self._fdr.record(
            FdrKind.ESTIMATE_SENT,
            {
                "time_unix_usec": state.time_unix_usec,
                "provenance": new.value,
                "fix_type": fix_type,
                "lat_deg": state.lat_deg if horiz is not None else None,
                "lon_deg": state.lon_deg if horiz is not None else None,
                "horiz_sigma_m": horiz,
                "worker": self._worker.estimate_s is not None,
                "sent": sent,
            },
        )

    async def _status(self) -> None:
        period = 1.0 / self._cfg.daemon.status_hz
        while True:
            await asyncio.sleep(period)
            w = self._worker
            now = time.monotonic()
            link = self._link.stats()
            fields = {
                "worker_pid": w.proc.pid if w.proc is not None else None,
                "worker_running": w.proc is not None,
                "worker_estimating": w.estimate_s is not None,
                "worker_starts": w.starts,
                "worker_adoptions": w.adoptions,
                "worker_losses": w.losses,
                "worker_kills": w.kills,
                "worker_bad_messages": w.bad_messages,
                "worker_last_heard_s": None if w.heard_s is None else round(now - w.heard_s, 3),
                "provenance": self._provenance.value,
                "estimates_sent": self.estimates_sent,
                "relayed_to_worker": self.relayed_to_worker,
                "relayed_to_autopilot": self.relayed_to_autopilot,
                "signals_ignored": dict(self.signals_ignored),
                "link_alive": link.connected,
                "mavlink_received": link.messages_received,
                "mavlink_bad_packets": link.bad_packets,
                "mavlink_sent": link.messages_sent,
                "mavlink_send_errors": link.send_errors,
                "mavlink_impostor_messages": link.impostor_messages,
                "timesync_answered": link.timesync_answered,
                "timesync_ignored": link.timesync_ignored,
            }
            log.info(LogEvent.CORE_STATUS, **fields)
            self._fdr.record(FdrKind.CORE_STATUS, fields)
            self._notifier.status(
                f"worker {'up' if w.estimate_s is not None else 'down'}; {self._provenance.value}; "
                f"restarts {max(0, w.starts - 1)}"
            )


def _free_udp_port() -> int:
    """A loopback UDP port free now (the worker's link listens there)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def launch_id(config_path: str | Path, overrides: Sequence[str]) -> str:
    """What a worker is started with, in 16 hex digits: the package's version, the configuration file's
    bytes and the overrides (``LAUNCH_ID_ENV`` in its environment; it says it back in its ``hello``)."""
    digest = hashlib.sha256(__version__.encode())
    with contextlib.suppress(OSError):
        digest.update(Path(config_path).read_bytes())
    for item in overrides:
        digest.update(b"\0" + item.encode())
    return digest.hexdigest()[:16]


def _udpin_port(url: object) -> int:
    """The port of a worker's ``udpin:127.0.0.1:PORT`` link (0: not such a URL, so nothing is relayed)."""
    if isinstance(url, str) and url.startswith("udpin:127.0.0.1:"):
        port = url.rsplit(":", 1)[1]
        if port.isdigit() and 0 < int(port) < 65536:
            return int(port)
    return 0


def _exit_text(code: int | None) -> str:
    """How a process ended, in few words (``SIGKILL``, ``exit 1``): the operator's STATUSTEXT has 50."""
    if code is None:
        return "unknown"
    if code == EXIT_UNKNOWN:
        return "ended"  # an adopted worker: only its parent could read how
    if code < 0:
        with contextlib.suppress(ValueError):
            return signal.Signals(-code).name
        return f"signal {-code}"
    return f"exit {code}"
