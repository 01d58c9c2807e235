"""sd_notify: READY/WATCHDOG datagrams reach NOTIFY_SOCKET."""

from __future__ import annotations

import socket
from pathlib import Path

from gps_denied_onboard.daemon.sd_notify import SdNotifier


def test_sd_notify_sends_ready_and_watchdog(tmp_path: Path) -> None:
    """With a socket configured, READY=1 and WATCHDOG=1 arrive as datagrams."""
    path = str(tmp_path / "notify.sock")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as srv:
        srv.bind(path)
        srv.settimeout(2.0)
        n = SdNotifier(path)
        n.ready("ok")
        n.watchdog()
        first, second = srv.recv(1024).decode(), srv.recv(1024).decode()
        n.close()
    assert "READY=1" in first.split("\n") and "STATUS=ok" in first.split("\n")
    assert second == "WATCHDOG=1"


def test_sd_notify_without_socket_is_noop() -> None:
    """Without NOTIFY_SOCKET nothing is sent and nothing fails."""
    n = SdNotifier("")
    n.ready("x")
    assert not n.enabled and n.errors == 0
