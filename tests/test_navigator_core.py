"""The navigator core (``daemon/core.py``) with a scripted vision worker, over real sockets: the core's
MAVLink link to a pymavlink "autopilot" on loopback UDP, its Unix socket to a worker process it starts,
kills and restarts. The worker here is a script at the component boundary (it sends a filter state at
10 Hz and relays one STATUSTEXT); the real worker flies in tests/test_sitl_autopilot.py.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from gps_denied_onboard.clock import DaemonClock
from gps_denied_onboard.components.c8_mavlink.messages import DIALECT as D
from gps_denied_onboard.components.c8_mavlink.messages import mavutil
from gps_denied_onboard.components.c13_fdr import read_records
from gps_denied_onboard.config import config_from_mapping
from gps_denied_onboard.constants import CORE_FDR_SUBDIR, FdrKind
from gps_denied_onboard.daemon.core import NavigatorCore
from gps_denied_onboard.runtime_root.link_first import open_link_first

#: The scripted worker: argv = fd, the file it writes what it saw to. It takes the core's handover (or
#: starts a confident filter of its own), sends its state at 10 Hz, and on the first MAVLink message the
#: core relays to its link port, answers with a STATUSTEXT and a GPS_INPUT (which the core must not pass).
WORKER = r"""
import json, socket, sys, time
import numpy as np
from pymavlink import mavutil
from gps_denied_onboard.clock import DaemonClock
from gps_denied_onboard.components.c5_estimator.ekf import EstimatorCheckpoint, NavEstimator
from gps_denied_onboard.config import EstimatorConfig
from gps_denied_onboard.daemon.core_channel import CoreChannel
from gps_denied_onboard.geo import LocalTangentPlane

fd, out_path, port = int(sys.argv[1]), sys.argv[2], int(sys.argv[3])
clock = DaemonClock()
ch = CoreChannel(fd)
ch.poll()
handover = ch.take_handover()
ltp = LocalTangentPlane(17.59, 78.12, 500.0)
est = NavEstimator(EstimatorConfig(), ltp)
now = clock.now_unix_usec()
if handover is not None:
    est.restore(handover.checkpoint)
else:
    est.restore(EstimatorCheckpoint(
        x=np.array([[0.0], [0.0], [-80.0], [5.0], [0.0], [0.0]]),
        p_mat=np.diag([1.0, 1.0, 1.0, 0.04, 0.04, 0.04]),
        time_usec=now, last_fix_usec=now, last_no_fix_usec=None, last_vo_usec=now,
        consecutive_gated=0, yaw_rad=0.0, shared_sigma_m=0.0, map_confirmed=True,
    ))
seen = {"handover": None if handover is None else {
    "t": handover.checkpoint.time_usec, "x": handover.checkpoint.x.reshape(-1).tolist(),
    "p00": float(handover.checkpoint.p_mat[0, 0])}}
with open(out_path, "w") as f:
    json.dump(seen, f)
mav = mavutil.mavlink.MAVLink(None, srcSystem=1, srcComponent=197)
link = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
link.bind(("127.0.0.1", port))
link.setblocking(False)
answered = False
while True:
    # a worker that keeps fixing: the state moves on, its covariance stays where the fixes hold it
    t = clock.now_unix_usec()
    start = est.checkpoint()
    est.predict_to(t)
    cp = est.checkpoint()
    p = start.p_mat if handover is None else cp.p_mat
    cp = EstimatorCheckpoint(**{**cp.__dict__, "p_mat": p, "last_fix_usec": t, "last_vo_usec": t})
    est.restore(cp)
    if not ch.send_estimate(cp, ltp, system_status=4, no_fix_reason=None, agp_hold=None, alt_distrust=None):
        if ch.closed:
            break
    try:
        data, core_addr = link.recvfrom(4096)
        if not answered:
            link.sendto(mav.statustext_encode(6, b"GDN: from the worker").pack(mav), core_addr)
            gps = mav.gps_input_encode(0, 0, 0, 0, 0, 3, 0, 0, 0, 1, 1, 0, 0, 0, 0, 0, 0, 0, 10)
            link.sendto(gps.pack(mav), core_addr)
            answered = True
            seen["relayed_from_autopilot"] = True
            with open(out_path, "w") as f:
                json.dump(seen, f)
    except BlockingIOError:
        pass
    time.sleep(0.1)
"""


class _ScriptedCore(NavigatorCore):
    def __init__(self, *args: Any, out_dir: Path, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.out_dir = out_dir

    def _worker_command(self, fd: int) -> list[str]:
        out = self.out_dir / f"worker{self._worker.starts + 1}.json"
        return [sys.executable, "-c", WORKER, str(fd), str(out), str(self._worker.port)]


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class _Autopilot(threading.Thread):
    """A pymavlink endpoint with the autopilot's ids: HEARTBEAT at 2 Hz, and everything it hears."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.conn = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{port}", source_system=1, source_component=1
        )
        self.got: list[tuple[float, Any]] = []
        self.stop = threading.Event()

    def run(self) -> None:
        next_hb = 0.0
        while not self.stop.is_set():
            now = time.monotonic()
            if now >= next_hb:
                self.conn.mav.heartbeat_send(D.MAV_TYPE_QUADROTOR, D.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0)
                next_hb = now + 0.5
            msg = self.conn.recv_match(blocking=True, timeout=0.05)
            if msg is not None and msg.get_type() != "BAD_DATA":
                self.got.append((time.monotonic(), msg))


@pytest.mark.sitl
def test_a_killed_worker_leaves_no_gap_and_the_new_one_starts_from_the_cores_filter(tmp_path: Path) -> None:
    port = _free_udp_port()
    cfg = config_from_mapping(
        {
            "mavlink": {"url": f"udpin:127.0.0.1:{port}"},
            "fdr": {"dir": str(tmp_path / "fdr")},
            "daemon": {"vision_worker": True},
        }
    )
    clock = DaemonClock()
    link = open_link_first(cfg, clock)
    core = _ScriptedCore(cfg, tmp_path / "unused.yaml", [], link=link, clock=clock, out_dir=tmp_path)
    ap = _Autopilot(port)
    ap.start()
    marks: dict[str, float] = {}

    async def choreography(stop: asyncio.Event) -> None:
        await asyncio.sleep(4.0)
        proc = core._worker.proc
        assert proc is not None
        marks["kill"] = time.monotonic()
        os.kill(proc.pid, signal.SIGKILL)
        await asyncio.sleep(5.0)
        stop.set()

    async def main() -> int:
        stop = asyncio.Event()
        task = asyncio.create_task(choreography(stop))
        code = await core.run(stop)
        await task
        return code

    try:
        assert asyncio.run(main()) == 0
    finally:
        ap.stop.set()
        ap.join(2.0)
    gps = [(t, m) for t, m in ap.got if m.get_type() == "GPS_INPUT"]
    times = [t for t, _ in gps]
    gaps_ms = [1000 * (b - a) for a, b in itertools.pairwise(times)]
    # the stream never paused, through the kill and the restart (ArduPilot's bound: 245 ms)
    assert len(gps) >= 70 and max(gaps_ms) <= 245.0, max(gaps_ms)
    kill = marks["kill"]
    before = [m for t, m in gps if kill - 1.0 <= t < kill]
    assert before and all(m.fix_type == 3 for m in before), [(m.fix_type, m.horiz_accuracy) for m in before]
    # after the kill the core predicts on alone (no IMU here: constant velocity): the stated accuracy
    # grows, and the fix is given up rather than held at an accuracy it no longer has
    after = [m for t, m in gps if kill < t < kill + 0.6]
    acc = [m.horiz_accuracy for m in after if m.fix_type == 3]
    assert len(acc) >= 2 and all(b >= a for a, b in itertools.pairwise(acc)) and acc[-1] > acc[0], acc
    # the worker came back from the core's own filter, and the ground heard both
    first = json.loads((tmp_path / "worker1.json").read_text())
    second = json.loads((tmp_path / "worker2.json").read_text())
    assert first["handover"] is None
    assert second["handover"] is not None and second["handover"]["p00"] > 1.0, second
    texts = [m.text for _, m in ap.got if m.get_type() == "STATUSTEXT"]
    assert any(t.startswith("GDN: vision lost (SIGKILL)") for t in texts), texts
    assert any(t.startswith("GDN: vision back after") for t in texts), texts
    # what the autopilot sent reached the worker's link; what the worker sent reached the autopilot,
    # except its GPS_INPUT: the only GPS_INPUT the autopilot heard is the core's (none with fix_type 3 and
    # the worker's all-zero position)
    assert first.get("relayed_from_autopilot") and "GDN: from the worker" in texts
    assert not any(m.lat == 0 and m.fix_type == 3 for _, m in gps)
    # the core recorded both ends of the worker's loss
    events = [
        r["event"]
        for r in read_records(tmp_path / "fdr" / CORE_FDR_SUBDIR)
        if r["kind"] == FdrKind.CORE_WORKER
    ]
    assert events[:4] == ["started", "lost", "started", "back"], events


_FOREIGN_UID = 65534  # nobody


def _as_nobody(code: str) -> subprocess.Popen[str]:
    """``code`` in a Python child that has dropped to uid ``_FOREIGN_UID`` first (needs root)."""
    prelude = f"import os, socket, sys, time; os.setgid({_FOREIGN_UID}); os.setuid({_FOREIGN_UID}); "
    return subprocess.Popen([sys.executable, "-c", prelude + code], stdout=subprocess.PIPE, text=True)


@pytest.mark.skipif(os.geteuid() != 0, reason="dropping a child to another user needs root")
def test_the_rendezvous_takes_only_a_peer_of_the_same_user(tmp_path: Path) -> None:
    """An abstract socket has no file permissions: a worker refuses a core of another user, and a core
    refuses a rendezvous another user holds (it starts a worker of its own instead)."""
    from gps_denied_onboard.daemon.core_channel import CoreChannel, rendezvous_address

    # the worker's side: another user's connection is refused, its own core's is taken
    name = rendezvous_address(tmp_path / "worker_side")
    core_end, worker_end = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    channel = CoreChannel(worker_end.detach(), rendezvous=name, hello={"pid": os.getpid()})
    core_end.close()
    try:
        intruder = _as_nobody(
            f"s = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET); s.connect({name!r}); "
            "print('in', flush=True); time.sleep(5)"
        )
        assert intruder.stdout is not None and intruder.stdout.readline().strip() == "in"
        assert not channel.adopt() and channel.foreign_peers == 1
        intruder.kill()
        with socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET) as own:
            own.connect(name)
            assert channel.adopt() and channel.adoptions == 1
            own.settimeout(5.0)
            assert b"hello" in own.recv(65536)
    finally:
        channel.close()

    # the core's side: a name held by another user is not a worker to adopt
    fdr = tmp_path / "core_side"
    squatter = _as_nobody(
        f"s = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET); s.bind({rendezvous_address(fdr)!r}); "
        "s.listen(1); print('bound', flush=True); time.sleep(30)"
    )
    try:
        assert squatter.stdout is not None and squatter.stdout.readline().strip() == "bound"
        port = _free_udp_port()
        cfg = config_from_mapping({"mavlink": {"url": f"udpin:127.0.0.1:{port}"}, "fdr": {"dir": str(fdr)}})
        clock = DaemonClock()
        link = open_link_first(cfg, clock)
        core = NavigatorCore(cfg, tmp_path / "unused.yaml", [], link=link, clock=clock)
        try:
            assert not core._adopt_worker()
            assert core._worker.proc is None and core._worker.adoptions == 0
        finally:
            link.close()
    finally:
        squatter.kill()


def test_a_worker_whose_rendezvous_is_held_runs_on_without_one(tmp_path: Path) -> None:
    """The name held by another process (a worker its core did not adopt): the new worker's channel to its
    own core still works, only no later core can adopt it."""
    from gps_denied_onboard.daemon.core_channel import CoreChannel, rendezvous_address

    name = rendezvous_address(tmp_path)
    with socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET) as holder:
        holder.bind(name)
        holder.listen(1)
        core_end, worker_end = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        channel = CoreChannel(worker_end.detach(), rendezvous=name)
        try:
            assert channel.rendezvous_fileno() is None and not channel.adopt()
            assert channel.send_alive(system_status=3)
            core_end.settimeout(5.0)
            assert b"alive" in core_end.recv(65536)
        finally:
            channel.close()
            core_end.close()
