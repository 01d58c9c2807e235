"""The vision worker's end of its socket to the navigator core (``daemon/core.py``).

The worker (``gdnav run --worker-fd N``, started by the core) sends its filter's state at every output
period (``estimate``; ``alive`` before its estimator has started) and reads what the core sends: the
``handover``, the core's filter to start from after a restart. Sends never block: a full socket drops the
message and counts it (the core predicts on from the previous one).

**A core's crash does not take the vision with it.** The worker listens at its daemon's rendezvous (a
Linux abstract Unix socket named from the FDR directory: one daemon per directory, bound while the worker
lives, nothing on disk to go stale). End-of-file on the socket means its core is gone: the worker keeps
its pipeline running and waits up to ``daemon.worker_orphan_s`` for the core's next start, which connects
to the rendezvous and takes it over (``adopt``: the worker says ``hello`` with its pid and its link's
port; the core says where its relay is). A worker never speaks to the autopilot itself, so one waiting
for a core sends nothing anyone could fly on; one whose core does not come back ends itself.

An abstract socket has no file permissions: each side takes the other only when the kernel's peer
credentials (``SO_PEERCRED``) show the same user as its own. A name another user holds costs the
adoption, never the vision: the worker then runs without a rendezvous, and its core starts a new one when
it dies, as before.
"""

from __future__ import annotations

import errno
import hashlib
import os
import socket
import struct
from pathlib import Path
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

log = structlog.get_logger(__name__)


def rendezvous_address(fdr_dir: str | Path) -> bytes:
    """The abstract Unix socket name where the vision worker of the daemon that records into ``fdr_dir``
    waits for a core (the leading NUL: Linux's abstract namespace)."""
    digest = hashlib.sha256(str(Path(fdr_dir).resolve()).encode()).hexdigest()[:24]
    return b"\0gdnav-worker-" + digest.encode()


def peer_credentials(sock: socket.socket) -> tuple[int, int, int]:
    """The pid, uid and gid of the process at the other end of a connected Unix socket (the kernel's
    record of who called ``connect`` or ``listen``; it cannot be forged)."""
    pid, uid, gid = struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, 12))
    return int(pid), int(uid), int(gid)


def _listen(rendezvous: bytes) -> socket.socket | None:
    """The worker's listener at ``rendezvous``; None, logged, where the name cannot be had (held by a
    worker its core did not adopt, or by another user's process): the vision runs all the same, only
    no later core can adopt it."""
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    try:
        listener.bind(rendezvous)
        listener.listen(1)
    except OSError as exc:
        listener.close()
        held = exc.errno == errno.EADDRINUSE
        name = rendezvous[1:].decode()
        log.warning(LogEvent.WORKER_NO_RENDEZVOUS, rendezvous=name, held=held, error=str(exc))
        return None
    listener.setblocking(False)
    return listener


#: The largest message the core sends (a handover is about 1 KiB), bytes.
MAX_MESSAGE_BYTES = 65536


class CoreChannel:
    """The worker's socket to the core (``fd``: inherited from the core that started it). With
    ``rendezvous`` it listens there for a later core (``adopt``) and says ``hello`` to it. With
    ``clock_anchor_ns`` (this worker's ``DaemonClock.anchor_unix_ns``) the states it sends carry it, and
    a handover's times are mapped onto this worker's clock."""

    def __init__(
        self,
        fd: int,
        *,
        rendezvous: bytes | None = None,
        hello: dict[str, Any] | None = None,
        clock_anchor_ns: int | None = None,
    ) -> None:
        self._anchor_ns = clock_anchor_ns
        self._sock = socket.socket(fileno=fd)
        self._sock.setblocking(False)
        self._listener = None if rendezvous is None else _listen(rendezvous)
        self._hello = dict(hello or {})
        #: The core's filter to start from (None: none, or already taken).
        self.handover: WireState | None = None
        self.closed = False
        self.dropped = 0
        self.sent = 0
        #: Cores that took this worker over after the one that started it.
        self.adoptions = 0
        #: Where the newest adopting core's relay is (its loopback UDP port; None: not told).
        self.core_relay_port: int | None = None
        #: Connections at the rendezvous from another user's process, refused.
        self.foreign_peers = 0

    def fileno(self) -> int:
        return self._sock.fileno()

    def rendezvous_fileno(self) -> int | None:
        """The rendezvous listener (readable when a core connects; None: not listening)."""
        return None if self._listener is None else self._listener.fileno()

    def adopt(self) -> bool:
        """Take a core waiting at the rendezvous as this worker's core (the previous one is gone), and
        say ``hello``; False when none is waiting."""
        if self._listener is None:
            return False
        try:
            sock, _ = self._listener.accept()
        except (BlockingIOError, InterruptedError):
            return False
        pid, uid, _ = peer_credentials(sock)
        if uid != os.getuid():
            sock.close()
            self.foreign_peers += 1
            log.warning(LogEvent.WORKER_FOREIGN_PEER, pid=pid, uid=uid, refused=self.foreign_peers)
            return False
        sock.setblocking(False)
        old, self._sock = self._sock, sock
        old.close()
        self.closed = False
        self.adoptions += 1
        self.send({"kind": "hello", **self._hello})
        return True

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
                    self.handover = state_from_wire(message["state"], clock_anchor_ns=self._anchor_ns)
                    log.info(LogEvent.WORKER_HANDOVER, time_unix_usec=self.handover.checkpoint.time_usec)
                elif message["kind"] == "core":
                    port = message["relay_port"]
                    if not isinstance(port, int) or not 0 < port < 65536:
                        raise WireError(f"relay_port must be a UDP port number, got {port!r}")
                    self.core_relay_port = port
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
        state = state_to_wire(checkpoint, ltp, clock_anchor_ns=self._anchor_ns)
        return self.send({"kind": "estimate", "state": state, **fields})

    def send_refusal(self, message: str) -> bool:
        """The one line this worker would print when it refuses its configuration or a file: its core
        prints it when it stops with the worker's exit code."""
        return self.send({"kind": "refusal", "text": message})

    def send_alive(self, **fields: Any) -> bool:
        return self.send({"kind": "alive", **fields})

    def close(self) -> None:
        self.closed = True
        self._sock.close()
        if self._listener is not None:
            self._listener.close()
