"""``gdnav sitl run`` owns the daemon it starts: SIGTERM to the runner (or its sudden death) stops the
daemon too (issue 26: a SIGTERM left it running, still holding its ports)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from daemon_harness import build_small_cache

pytestmark = pytest.mark.sitl


def _children(pid: int) -> list[int]:
    """The direct children of ``pid`` (Linux /proc)."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        # "pid (comm) state ppid ...": comm may hold spaces, so split after the last ')'
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
            out.append(int(entry.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _start_runner(tmp_path: Path) -> tuple[subprocess.Popen[bytes], int]:
    map_path, _cache = build_small_cache(tmp_path)
    runner = subprocess.Popen(
        [
            sys.executable, "-m", "gps_denied_onboard.cli", "sitl", "run", "--map", str(map_path),
            "--scenario", "smoke", "--report", str(tmp_path / "out" / "report.json"),
            "--workdir", str(tmp_path / "work"), "--set", "matcher.strategy=classical", "--quiet",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )  # fmt: skip
    deadline = time.time() + 120.0
    while time.time() < deadline:
        daemons = [c for c in _children(runner.pid) if b"run" in Path(f"/proc/{c}/cmdline").read_bytes()]
        if daemons:
            return runner, daemons[0]
        if runner.poll() is not None:
            pytest.fail(f"the runner exited with {runner.returncode} before starting the daemon")
        time.sleep(0.2)
    runner.kill()
    pytest.fail("the runner started no daemon in 120 s")


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_runner_signal_stops_its_daemon(tmp_path: Path, sig: signal.Signals) -> None:
    """SIGTERM: the runner unwinds and stops the daemon; SIGKILL (no cleanup possible): the kernel
    sends the daemon SIGTERM as its parent dies (PR_SET_PDEATHSIG). Either way, no daemon is left."""
    runner, daemon_pid = _start_runner(tmp_path)
    time.sleep(2.0)  # flying
    os.kill(runner.pid, sig)
    runner.wait(30)
    deadline = time.time() + 15.0
    while _alive(daemon_pid) and time.time() < deadline:
        time.sleep(0.2)
    left = _alive(daemon_pid)
    if left:
        os.kill(daemon_pid, signal.SIGKILL)
    assert not left, f"daemon {daemon_pid} still running 15 s after the runner got {sig.name}"
