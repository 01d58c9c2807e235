"""What the ground station sees: the daemon's STATUSTEXT and NAMED_VALUE at a MAVProxy `--out` port.

All real processes on loopback: the ArduPilot emulator (a test double, two MAVLink channels like
ArduPilot SITL's SERIAL0/SERIAL1), MAVProxy on channel 0 (`--master`) with a ground-station `--out`, and
the daemon on channel 1 (a companion computer on the autopilot's TELEM2). The daemon's messages reach
the ground station because the autopilot forwards broadcast messages between its channels (MAVLink
routing) and MAVProxy passes everything its master sends to every `--out`. MAVProxy does NOT pass what
one `--out` sends to another `--out` (mavproxy.py ``process_mavlink``: messages from an output go to
the master only), so a daemon placed on a MAVProxy `--out` is heard by the autopilot but not by a
ground station on another `--out`: docs/ardupilot.md, "Routing", says so.

MAVProxy (PyPI ``mavproxy``) is installed by ``scripts/_venv.sh`` with the dev extra, ``--no-deps``: it
declares ``opencv-python`` (the GUI build, which clashes with the project's ``opencv-python-headless``:
both install ``cv2``) and ``vtk``, which only its GUI modules use. The test uses ``$GDNAV_MAVPROXY``, else
``mavproxy.py`` beside the running interpreter or on PATH, and is skipped with that reason otherwise.
"""

from __future__ import annotations

import asyncio
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from daemon_harness import build_small_cache, free_udp_port

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil

pytestmark = [pytest.mark.sitl]


def _mavproxy() -> str:
    beside = Path(sys.executable).parent / "mavproxy.py"
    exe = (
        os.environ.get("GDNAV_MAVPROXY")
        or (str(beside) if beside.exists() else None)
        or shutil.which("mavproxy.py")
    )
    if not exe:
        pytest.skip(
            "MAVProxy not found: run scripts/test.sh (it installs mavproxy --no-deps) "
            "or set GDNAV_MAVPROXY to a mavproxy.py"
        )
    return exe


def _camera(map_path: Path, lat: float, lon: float, stop: threading.Event) -> int:
    """A nav camera on the ground at (lat, lon): frames at 3 Hz from a TCP frame server; returns its port."""
    from gps_denied_onboard.camera.stream import encode_frame
    from gps_denied_onboard.camera.types import Attitude, CameraCalibration
    from gps_denied_onboard.sitl.frame_server import FrameServer
    from gps_denied_onboard.sitl.render import MapRenderer

    renderer = MapRenderer(map_path)
    calib = CameraCalibration.from_hfov(640, 480, 70.0)
    ready: list[int] = []

    async def serve() -> None:
        server = FrameServer()
        ready.append(await server.start())
        seq = 0
        while not stop.is_set():
            img = renderer.render(calib, lat, lon, 0.3, Attitude(0.0, 0.0, 0.0))
            await server.send(encode_frame(img, seq=seq, exposure_time_unix_usec=int(time.time() * 1e6)))
            seq += 1
            await asyncio.sleep(1 / 3)
        await server.close()

    threading.Thread(target=lambda: asyncio.run(serve()), daemon=True).start()
    while not ready:
        time.sleep(0.05)
    return ready[0]


def test_statustext_and_named_value_reach_a_mavproxy_ground_station_port(tmp_path: Path) -> None:
    mavproxy = _mavproxy()
    _map, cache = build_small_cache(tmp_path)
    from gps_denied_onboard.sitl.render import MapRenderer

    west, south, east, north = MapRenderer(_map).bbox_lonlat
    home = f"{(south + north) / 2},{(west + east) / 2},400,0"
    ch0, ch1, gcs_port = free_udp_port(), free_udp_port(), free_udp_port()
    stop = threading.Event()
    cam_port = _camera(_map, (south + north) / 2, (west + east) / 2, stop)
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{gcs_port}", source_system=254)
    procs: list[subprocess.Popen[bytes]] = []
    log = (tmp_path / "procs.log").open("wb")
    try:
        procs.append(
            subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "gps_denied_onboard.sitl.ap_emulator",
                    "--home",
                    home,
                    "--port",
                    str(ch0),
                    "--port",
                    str(ch1),
                    "--ekf-origin-delay-s",
                    "1",
                    "--ekf-using-gps-delay-s",
                    "2",
                    "--quiet",
                ],
                stdout=log,
                stderr=log,
            )
        )
        procs.append(
            subprocess.Popen(
                [
                    mavproxy,
                    f"--master=udpout:127.0.0.1:{ch0}",
                    f"--out=udp:127.0.0.1:{gcs_port}",
                    "--daemon",
                    "--non-interactive",
                    f"--state-basedir={tmp_path}",
                    "--default-modules=",
                    "--nowait",
                ],
                stdout=log,
                stderr=log,
                cwd=tmp_path,
                stdin=subprocess.DEVNULL,
            )
        )
        # the ground station hears the autopilot first (a STATUSTEXT sent before it connects is not replayed)
        hb = gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=30.0)
        assert hb is not None, (tmp_path / "procs.log").read_text(errors="replace")[-3000:]
        procs.append(
            subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "gps_denied_onboard.cli",
                    "run",
                    "--config",
                    str(Path(__file__).resolve().parents[1] / "config" / "sitl.yaml"),
                    "--set",
                    f"mavlink.url=udpout:127.0.0.1:{ch1}",
                    "--set",
                    f"cache.dir={cache}",
                    "--set",
                    f"fdr.dir={tmp_path / 'fdr'}",
                    "--set",
                    f"camera.source=tcp://127.0.0.1:{cam_port}",
                ],
                stdout=log,
                stderr=log,
            )
        )
        seen: dict[str, object] = {}
        autopilot_seen = False
        deadline = time.time() + 60.0
        while time.time() < deadline and not (
            {"STATUSTEXT", "NAMED_VALUE_INT", "NAMED_VALUE_FLOAT"} <= set(seen)
        ):
            m = gcs.recv_match(blocking=True, timeout=0.2)
            if m is None:
                continue
            if m.get_srcComponent() == 1 and m.get_type() == "HEARTBEAT":
                autopilot_seen = True
            if m.get_srcComponent() == 197 and m.get_srcSystem() == 1:
                seen.setdefault(m.get_type(), m)
    finally:
        stop.set()
        for p in reversed(procs):
            p.send_signal(signal.SIGTERM)
        for p in reversed(procs):
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
        gcs.close()
        log.close()
    assert autopilot_seen, (tmp_path / "procs.log").read_text(errors="replace")[-3000:]
    assert {"STATUSTEXT", "NAMED_VALUE_INT", "NAMED_VALUE_FLOAT"} <= set(seen), (
        sorted(seen),
        (tmp_path / "procs.log").read_text(errors="replace")[-3000:],
    )
    names = {str(seen["NAMED_VALUE_INT"].name)}  # type: ignore[attr-defined]
    assert names & {"GDN_PROV", "GDN_INL", "GDN_DROP", "GDN_FDR"}, names
    assert str(seen["STATUSTEXT"].text)  # type: ignore[attr-defined]
