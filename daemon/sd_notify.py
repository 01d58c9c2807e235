"""systemd notification protocol (sd_notify) over the ``NOTIFY_SOCKET`` datagram socket.

Only active when systemd (or a test) sets ``NOTIFY_SOCKET``; otherwise every call is a no-op. Sending
never raises: a missing supervisor must not take the daemon down.
"""

from __future__ import annotations

import os
import socket


class SdNotifier:
    def __init__(self, socket_path: str | None = None) -> None:
        path = socket_path if socket_path is not None else os.environ.get("NOTIFY_SOCKET")
        self._address: str | bytes | None = None
        if path:
            # A leading '@' means the Linux abstract namespace.
            self._address = b"\0" + path[1:].encode() if path.startswith("@") else path
        self._sock: socket.socket | None = None
        self.errors = 0

    @property
    def enabled(self) -> bool:
        return self._address is not None

    @property
    def watchdog_interval_s(self) -> float | None:
        """Half of systemd's WatchdogSec (the recommended ping period), or None when not enabled."""
        usec = os.environ.get("WATCHDOG_USEC")
        if not self.enabled or not usec or not usec.isdigit():
            return None
        return int(usec) / 2e6

    def notify(self, *fields: str) -> None:
        if self._address is None:
            return
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
                self._sock.setblocking(False)
            self._sock.sendto("\n".join(fields).encode(), self._address)
        except OSError:
            self.errors += 1

    def ready(self, status: str) -> None:
        self.notify("READY=1", f"STATUS={status}")

    def watchdog(self) -> None:
        self.notify("WATCHDOG=1")

    def status(self, status: str) -> None:
        self.notify(f"STATUS={status}")

    def stopping(self) -> None:
        self.notify("STOPPING=1")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
