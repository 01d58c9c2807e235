"""``gdnav sitl run`` owns the daemon it starts: SIGTERM to the runner (or its sudden death) stops the
daemon too (issue 26: a SIGTERM left it running, still holding its ports)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from daemon_harness import build_small_cache
from gps_denied_onboard.sitl.host_faults import child_pids

pytestmark = pytest.mark.sitl


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
        daemons = [c for c in child_pids(runner.pid) if b"run" in Path(f"/proc/{c}/cmdline").read_bytes()]
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


def test_runner_sigterm_in_an_autopilot_flight_stops_the_mission_and_the_daemon_at_once(
    tmp_path: Path,
) -> None:
    """`gdnav sitl run --autopilot` flying on the emulator, GNSS off: SIGTERM ends the runner (130) and
    its daemon within 5 s, the mission driver sends nothing more but the GNSS switched back on (issue 36:
    the mission flew on without frames until LAND, the daemon lived on, the runner exited only at the
    disarm)."""
    from daemon_harness import free_udp_port
    from gps_denied_onboard.sitl.render import MapRenderer

    map_path, _cache = build_small_cache(tmp_path)
    west, south, east, north = MapRenderer(map_path).bbox_lonlat
    port = free_udp_port()
    events = tmp_path / "emulator_events.json"
    emulator = subprocess.Popen(
        [
            sys.executable, "-m", "gps_denied_onboard.sitl.ap_emulator",
            "--home", f"{(south + north) / 2},{(west + east) / 2},400,0", "--port", str(port),
            "--ekf-origin-delay-s", "2", "--ekf-using-gps-delay-s", "4", "--events", str(events), "--quiet",
        ],
    )  # fmt: skip
    log = tmp_path / "runner.log"
    with log.open("wb") as out:
        runner = subprocess.Popen(
            [
                sys.executable, "-m", "gps_denied_onboard.cli", "sitl", "run",
                "--autopilot", f"udpout:127.0.0.1:{port}", "--map", str(map_path), "--scenario", "smoke",
                "--report", str(tmp_path / "out" / "report.json"), "--workdir", str(tmp_path / "work"),
                "--set", "matcher.strategy=classical",
            ],
            stdout=out,
            stderr=subprocess.STDOUT,
        )  # fmt: skip
    daemon_pid = None
    try:
        deadline = time.time() + 180.0
        while "mission: gnss_off" not in log.read_text() and time.time() < deadline:
            assert runner.poll() is None, log.read_text()[-3000:]
            daemons = [c for c in child_pids(runner.pid) if b"run" in Path(f"/proc/{c}/cmdline").read_bytes()]
            daemon_pid = daemons[0] if daemons else daemon_pid
            time.sleep(0.2)
        assert "mission: gnss_off" in log.read_text(), log.read_text()[-3000:]
        assert daemon_pid is not None and _alive(daemon_pid)
        t_term = time.time()
        os.kill(runner.pid, signal.SIGTERM)
        code = runner.wait(30)
        runner_s = time.time() - t_term
        while _alive(daemon_pid) and time.time() - t_term < 30.0:
            time.sleep(0.1)
        daemon_s = time.time() - t_term
    finally:
        if runner.poll() is None:
            runner.kill()
        if daemon_pid is not None and _alive(daemon_pid):
            os.kill(daemon_pid, signal.SIGKILL)
        emulator.send_signal(signal.SIGTERM)
        emulator.wait(10)
    assert code == 130, log.read_text()[-3000:]
    assert runner_s < 5.0 and daemon_s < 5.0, (runner_s, daemon_s)
    assert "mission: stopped {'gnss_restored': True}" in log.read_text()
    # what the driver made the autopilot do after the SIGTERM (a mode command already on its way may
    # still land in the first moment): the GNSS back on, nothing else
    after = [e for e in json.loads(events.read_text())["events"] if e["t_unix_s"] > t_term]
    params = [(e["name"], e["value"]) for e in after if e["kind"] == "param_set"]
    modes = [e for e in after if e["kind"] == "mode" and e["t_unix_s"] > t_term + 0.5]
    assert params == [("SIM_GPS1_ENABLE", 1.0)] and not modes, after
