"""The daemon as a real process: start-up, READY, MAVLink heartbeat, bad frames, clean SIGTERM exit."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import struct
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from daemon_harness import build_small_cache, daemon_command, start_daemon, wait_for
from gps_denied_onboard.camera.stream import encode_frame
from gps_denied_onboard.components.c13_fdr import read_records
from gps_denied_onboard.constants import CORE_FDR_SUBDIR, FdrKind
from gps_denied_onboard.sitl.autopilot import SimAutopilot

pytestmark = pytest.mark.sitl


@pytest.fixture(scope="module")
def small_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_small_cache(tmp_path_factory.mktemp("cache"))[1]


def _autopilot_until_heartbeat(port: int, timeout_s: float = 60.0) -> SimAutopilot:
    ap = SimAutopilot(daemon_port=port)

    def beat() -> bool:
        ap.send_heartbeat()
        ap.poll()
        return bool(ap.of_type("HEARTBEAT"))

    assert wait_for(beat, timeout_s, 0.2), "no HEARTBEAT from the daemon"
    return ap


def test_daemon_sigterm_exits_cleanly_within_2s(tmp_path: Path, small_cache: Path) -> None:
    """After READY and its first HEARTBEAT, SIGTERM stops the daemon with code 0 in under 2 s."""
    notify = tmp_path / "notify.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sd:
        sd.bind(str(notify))
        sd.settimeout(60.0)
        d = start_daemon(tmp_path, small_cache, extra_env={"NOTIFY_SOCKET": str(notify)})
        try:
            ready = sd.recv(4096).decode()
            assert "READY=1" in ready.split("\n")
            ap = _autopilot_until_heartbeat(d.mav_port)
            hb = ap.of_type("HEARTBEAT")[0].fields
            assert hb["type"] == 18 and hb["autopilot"] == 8  # ONBOARD_CONTROLLER, AUTOPILOT_INVALID
            t0 = time.monotonic()
            d.proc.terminate()
            code = d.proc.wait(10)
            elapsed = time.monotonic() - t0
        finally:
            d.stop()
    assert code == 0, d.log_text()[-2000:]
    assert elapsed < 2.0, f"stop took {elapsed:.2f} s"
    events = [json.loads(line).get("event") for line in d.log_text().splitlines() if line.startswith("{")]
    assert "daemon.stopping" in events and "daemon.stopped" in events


def test_daemon_survives_sighup_sigusr1_sigusr2_and_keeps_the_autopilot_fed(
    tmp_path: Path, small_cache: Path
) -> None:
    """SIGHUP during start-up, then SIGHUP, SIGUSR1 and SIGUSR2 once running: the daemon neither dies (by
    default each ended it at once; after SIGHUP, rc 129, systemd did not restart it) nor stops its
    GPS_INPUT; each is logged and counted in daemon.status; SIGTERM still stops it cleanly."""
    d = start_daemon(tmp_path, small_cache)
    try:
        assert wait_for(lambda: "daemon.config" in d.log_text() or d.proc.poll() is not None, 60.0)
        os.kill(d.proc.pid, signal.SIGHUP)  # before ready: the start-up must survive it too
        ap = _autopilot_until_heartbeat(d.mav_port)
        assert wait_for(lambda: "daemon.ready" in d.log_text() or d.proc.poll() is not None, 60.0)
        for sig in (signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2):
            os.kill(d.proc.pid, sig)
            time.sleep(0.2)
        before = len(ap.of_type("GPS_INPUT"))

        def fed() -> bool:
            ap.send_heartbeat()
            ap.poll()
            return len(ap.of_type("GPS_INPUT")) >= before + 10

        assert wait_for(fed, 10.0, 0.1), "GPS_INPUT stopped after the signals"
        assert d.proc.poll() is None, f"daemon died with {d.proc.returncode}"
        time.sleep(1.5)  # one more daemon.status period
    finally:
        code = d.stop()
    assert code == 0, d.log_text()[-2000:]
    events = [json.loads(ln) for ln in d.log_text().splitlines() if ln.startswith("{")]
    ignored = [e["signal"] for e in events if e.get("event") == "daemon.signal_ignored"]
    assert ignored == ["SIGHUP", "SIGUSR1", "SIGUSR2"], ignored
    # the signals reach the service's main process, the navigator core: its own status record counts them
    status = [r for r in read_records(d.fdr_dir / CORE_FDR_SUBDIR) if r["kind"] == FdrKind.CORE_STATUS][-1]
    assert status["signals_ignored"] == {"SIGHUP": 1, "SIGUSR1": 1, "SIGUSR2": 1}


def test_daemon_keeps_running_and_records_bad_frames(tmp_path: Path, small_cache: Path) -> None:
    """A corrupt image and a wrong-size frame are recorded in the FDR and counted; the daemon keeps going."""
    d = start_daemon(tmp_path, small_cache)
    try:
        ap = _autopilot_until_heartbeat(d.mav_port)

        async def stream() -> None:
            sent = asyncio.Event()

            async def on_client(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
                if sent.is_set():  # the daemon reconnects after we hang up; send the bad frames once
                    return
                sent.set()
                now_us = int(time.time() * 1e6)
                good = encode_frame(np.zeros((480, 640, 3), np.uint8), seq=1, exposure_time_unix_usec=now_us)
                corrupt = bytearray(good)
                (hlen,) = struct.unpack(">I", good[4:8])
                body = 8 + hlen + 4
                corrupt[body : body + 64] = b"\x00" * 64  # valid header, JPEG payload destroyed
                wrong_size = encode_frame(  # a later exposure: the time axis refuses a repeated stamp
                    np.zeros((100, 100, 3), np.uint8), seq=2, exposure_time_unix_usec=now_us + 1000
                )
                writer.write(bytes(corrupt))
                writer.write(wrong_size)
                await writer.drain()
                await asyncio.sleep(2.0)
                writer.close()

            server = await asyncio.start_server(on_client, "127.0.0.1", d.cam_port)
            async with server:
                await asyncio.sleep(4.0)

        asyncio.run(stream())
        ap.send_heartbeat()
        assert d.proc.poll() is None, "daemon died on bad frames"
    finally:
        code = d.stop()
    assert code == 0
    errors = [r for r in read_records(d.fdr_dir) if r["kind"] == "pipeline.frame_error"]
    stages = {r["stage"] for r in errors}
    assert {"decode", "size"} <= stages, errors
    assert any("100x100" in r["error"] for r in errors)
    stopped = next(json.loads(ln) for ln in d.log_text().splitlines() if '"daemon.stopped"' in ln)
    assert stopped["frames_bad"] == 2


def _gone(pid: int) -> bool:
    """Ended (a zombie waiting for its reaper is ended too)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[-1].split()[0] == "Z"
    except FileNotFoundError:
        return True


def test_a_killed_core_leaves_its_vision_worker_to_the_next_core_and_an_unclaimed_one_ends(
    tmp_path: Path, small_cache: Path
) -> None:
    """kill -9 of the navigator core: its vision worker runs on, the core's next start (same FDR
    directory) takes it over instead of starting another, and tells it where its relay is; killed again
    with no core to follow, the worker ends itself after ``daemon.worker_orphan_s``."""
    orphan_s = 2.0
    overrides = (f"daemon.worker_orphan_s={orphan_s}",)
    d = start_daemon(tmp_path, small_cache, overrides=overrides)
    second: subprocess.Popen[bytes] | None = None
    worker = -1
    try:
        _autopilot_until_heartbeat(d.mav_port)
        assert wait_for(lambda: '"daemon.ready"' in d.log_text() or d.proc.poll() is not None, 60.0)
        (started,) = [
            r for r in read_records(d.fdr_dir / CORE_FDR_SUBDIR) if r["kind"] == FdrKind.CORE_WORKER
        ]
        worker = int(started["pid"])
        d.proc.kill()
        d.proc.wait(10)
        assert wait_for(lambda: '"worker.orphaned"' in d.log_text(), 10.0), d.log_text()[-2000:]
        assert not _gone(worker)
        mav_port = d.mav_port  # the same command line, as systemd starts it again
        cmd = daemon_command(mav_port, d.cam_port, d.fdr_dir, f"cache.dir={small_cache}", *overrides)
        with (tmp_path / "second.log").open("wb") as log:
            second = subprocess.Popen(cmd, stdout=log, stderr=log)
        _autopilot_until_heartbeat(mav_port)
        # the worker's own log line goes to the first core's log (its stdout): it was taken over
        assert wait_for(lambda: '"worker.adopted"' in d.log_text(), 15.0), d.log_text()[-2000:]
        events = [
            r
            for r in read_records(d.fdr_dir / CORE_FDR_SUBDIR)
            if r["kind"] == FdrKind.CORE_WORKER and r["event"] in ("started", "adopted")
        ]
        assert [(r["event"], r["pid"]) for r in events] == [("started", worker), ("adopted", worker)]
        told = [json.loads(ln) for ln in d.log_text().splitlines() if '"told": true' in ln]
        assert told and told[-1]["event"] == "c8.mavlink.autopilot_address", told
        second.kill()
        second.wait(10)
        assert wait_for(lambda: _gone(worker), orphan_s + 8.0), "an unclaimed worker outlived its wait"
        # it stopped itself, in order (not by faulthandler's hard stop)
        assert "the navigator core closed its socket" in d.log_text()
        assert "Timeout (" not in d.log_text()
    finally:
        if second is not None and second.poll() is None:
            second.kill()
        d.stop()
        if not _gone(worker):
            os.kill(worker, signal.SIGKILL)


def test_a_core_started_with_another_configuration_replaces_the_worker_it_finds(
    tmp_path: Path, small_cache: Path
) -> None:
    """The core killed, then started again with a changed setting: the worker still running was started
    with the old one, so the new core does not keep it (what the operator set must take effect): it
    replaces it with a worker of its own."""
    d = start_daemon(tmp_path, small_cache, overrides=("daemon.worker_orphan_s=5.0",))
    second: subprocess.Popen[bytes] | None = None
    try:
        _autopilot_until_heartbeat(d.mav_port)
        assert wait_for(lambda: '"daemon.ready"' in d.log_text() or d.proc.poll() is not None, 60.0)
        d.proc.kill()
        d.proc.wait(10)
        assert wait_for(lambda: '"worker.orphaned"' in d.log_text(), 10.0), d.log_text()[-2000:]
        mav_port = d.mav_port
        changed = ("daemon.worker_orphan_s=6.0",)
        cmd = daemon_command(mav_port, d.cam_port, d.fdr_dir, f"cache.dir={small_cache}", *changed)
        second_log = tmp_path / "second.log"
        with second_log.open("wb") as log:
            second = subprocess.Popen(cmd, stdout=log, stderr=log)
        _autopilot_until_heartbeat(mav_port)

        def events() -> list[str]:
            records = read_records(d.fdr_dir / CORE_FDR_SUBDIR)
            return [r["event"] for r in records if r["kind"] == FdrKind.CORE_WORKER]

        assert wait_for(lambda: events()[-1:] == ["started"] and len(events()) >= 4, 20.0), events()
        assert events()[:4] == ["started", "adopted", "lost", "started"], events()
        assert '"core.worker_stale"' in second_log.read_text(errors="replace")
    finally:
        if second is not None:
            second.terminate()
            second.wait(10)
        d.stop()
