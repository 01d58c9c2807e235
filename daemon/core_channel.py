"""The vision worker's end of its socket to the navigator core (``daemon/core.py``).

The worker (``gdnav run --worker-fd N``, started by the core) sends its filter's state at every output
period (``estimate``; ``alive`` before its estimator has started) and reads what the core sends: the
``handover``, the core's filter to start from after a restart. End-of-file means the core is gone: the
worker then stops. Sends never block: a full socket drops the message and counts it (the core predicts
on from the previous one).
"""

from __future__ import annotations

import signal
import socket
from typing import Any

import structlog

from gps_denied_onboard.components.c5_estimator.ekf import EstimatorCheckpoint
from gps_denied_onboard.components.c5_estimator.wire import (
    WireError,
    WireState,
    pack,
    state_from_wire,
    state_to_wire,
    unpack,
)
from gps_denied_onboard.constants import LogEvent
from gps_denied_onboard.geo import LocalTangentPlane
from gps_denied_onboard.helpers.process import die_with_parent

log = structlog.get_logger(__name__)

def die_with_core() -> bool:
    """Have the kernel SIGKILL this worker the moment its core ends, as one process would have died
    whole; under systemd the unit's cgroup would end it too, but a core started otherwise must not leave
    a worker flying on. False where that is not available."""
    return die_with_parent(signal.SIGKILL)


#: The largest message the core sends (a handover is about 1 KiB), bytes.
MAX_MESSAGE_BYTES = 65536


class CoreChannel:
    """The worker's socket to the core (``fd``: inherited from the core)."""

    def __init__(self, fd: int) -> None:
        self._sock = socket.socket(fileno=fd)
        self._sock.setblocking(False)
        #: The core's filter to start from (None: none, or already taken).
        self.handover: WireState | None = None
        self.closed = False
        self.dropped = 0
        self.sent = 0

    def fileno(self) -> int:
        return self._sock.fileno()

    def poll(self) -> bool:
        """Read every waiting message; False once the core has closed its end."""
        while not self.closed:
            try:
                data = self._sock.recv(MAX_MESSAGE_BYTES)
            except (BlockingIOError, InterruptedError):
                return True
            except OSError:
                self.closed = True
                break
            if not data:
                self.closed = True
                break
            try:
                message = unpack(data)
                if message["kind"] == "handover":
                    self.handover = state_from_wire(message["state"])
                    log.info(LogEvent.WORKER_HANDOVER, time_unix_usec=self.handover.checkpoint.time_usec)
            except (WireError, KeyError) as exc:
                log.warning(LogEvent.WORKER_BAD_CORE_MESSAGE, error=str(exc))
        return not self.closed

    def take_handover(self) -> WireState | None:
        """The handover, once (the estimator starts from it at most once)."""
        handover, self.handover = self.handover, None
        return handover

    def send(self, message: dict[str, Any]) -> bool:
        if self.closed:
            return False
        try:
            self._sock.send(pack(message))
        except (BlockingIOError, InterruptedError):
            self.dropped += 1
            return False
        except OSError:
            self.closed = True
            return False
        self.sent += 1
        return True

    def send_estimate(self, checkpoint: EstimatorCheckpoint, ltp: LocalTangentPlane, **fields: Any) -> bool:
        """The filter at its head, in ``ltp``, with what the core should know (``fields``)."""
        return self.send({"kind": "estimate", "state": state_to_wire(checkpoint, ltp), **fields})

    def send_refusal(self, message: str) -> bool:
        """The one line this worker would print when it refuses its configuration or a file: its core
        prints it when it stops with the worker's exit code."""
        return self.send({"kind": "refusal", "text": message})

    def send_alive(self, **fields: Any) -> bool:
        return self.send({"kind": "alive", **fields})

    def close(self) -> None:
        self.closed = True
        self._sock.close()
