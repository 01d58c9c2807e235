"""F8 through a real daemon process: restarted in flight with nothing of its own to resume from, the
daemon asks the autopilot for its estimate over UDP (MAV_CMD_REQUEST_MESSAGE) and searches the map from
it; it never turns that estimate into a fix (issue 9, "asks the autopilot for its current estimate")."""

from __future__ import annotations

import asyncio
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil

from daemon_harness import build_small_cache, start_daemon, wait_for
from gps_denied_onboard.camera.stream import encode_frame
from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.components.c13_fdr import FlightDataRecorder, read_records
from gps_denied_onboard.sitl.autopilot import SimAutopilot

pytestmark = pytest.mark.sitl

M = mavutil.mavlink
EKF_GOOD = M.EKF_ATTITUDE | M.EKF_VELOCITY_HORIZ | M.EKF_POS_HORIZ_REL | M.EKF_POS_HORIZ_ABS


def _previous_run(fdr_dir: Path, lat_deg: float, lon_deg: float) -> None:
    """What a run killed a moment ago left: its last 3D estimate is 10 minutes old (too old to resume
    from), its last record is from now (so this start is a restart in flight)."""
    with FlightDataRecorder(fdr_dir, max_bytes=1 << 22, segment_bytes=1 << 20) as fdr:
        old_usec = int((time.time() - 600.0) * 1e6)
        fdr.record(
            "mavlink.estimate",
            {
                "time_unix_usec": old_usec,
                "fix_type": 3,
                "lat_deg": lat_deg,
                "lon_deg": lon_deg,
                "horiz_sigma_m": 2.0,
            },
        )
        fdr.record("pipeline.frame", {"frame_seq": 41})


def test_restart_in_flight_searches_from_the_autopilot_estimate(tmp_path: Path) -> None:
    _map, cache = build_small_cache(tmp_path)
    store = TileStore.open(cache)
    lon_c, lat_c = store.center_lonlat
    ap_lat, ap_lon = lat_c + 100.0 / 111_195.0, lon_c  # 100 m north of the map's centre
    fdr_dir = tmp_path / "fdr"
    _previous_run(fdr_dir, lat_c, lon_c)

    d = start_daemon(tmp_path, cache)
    ap = SimAutopilot(daemon_port=d.mav_port)
    requests: list[int] = []
    stop = threading.Event()

    def autopilot() -> None:
        """HEARTBEAT and SYSTEM_TIME at 5 Hz; GLOBAL_POSITION_INT and EKF_STATUS_REPORT only when asked."""
        while not stop.is_set():
            now = time.time()
            ap.send_heartbeat()
            ap.send_system_time(now)
            n = len(ap.received)
            ap.poll()
            for msg in ap.received[n:]:
                f = msg.fields
                if msg.type == "COMMAND_LONG" and f["command"] == M.MAV_CMD_REQUEST_MESSAGE:
                    requests.append(int(f["param1"]))
                    if int(f["param1"]) == M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
                        ap.mav.global_position_int_send(
                            ap._boot_ms(now),
                            round(ap_lat * 1e7),
                            round(ap_lon * 1e7),
                            0,
                            120_000,
                            1500,
                            0,
                            0,
                            0,
                        )
                    elif int(f["param1"]) == M.MAVLINK_MSG_ID_EKF_STATUS_REPORT:
                        ap.mav.ekf_status_report_send(EKF_GOOD, 0.1, 0.1, 0.1, 0.1, 0.0)
            time.sleep(0.2)

    async def camera() -> None:
        async def on_client(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            for seq in range(1, 16):
                image = np.zeros((480, 640, 3), np.uint8)
                writer.write(encode_frame(image, seq=seq, exposure_time_unix_usec=int(time.time() * 1e6)))
                await writer.drain()
                await asyncio.sleep(1 / 3)
            writer.close()

        server = await asyncio.start_server(on_client, "127.0.0.1", d.cam_port)
        async with server:
            await asyncio.sleep(8.0)

    thread = threading.Thread(target=autopilot, daemon=True)
    thread.start()
    try:
        assert wait_for(lambda: bool(ap.of_type("HEARTBEAT")), 60.0, 0.2), d.log_text()[-2000:]
        asyncio.run(camera())
    finally:
        stop.set()
        thread.join(5.0)
        code = d.stop()
        ap.close()
    assert code == 0, d.log_text()[-2000:]
    assert M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT in requests and M.MAVLINK_MSG_ID_EKF_STATUS_REPORT in requests
    records = list(read_records(fdr_dir))
    priors = [r for r in records if r["kind"] == "estimator.prior"]
    assert [p["source"] for p in priors] == ["autopilot_estimate"], priors
    assert (priors[0]["lat_deg"], priors[0]["lon_deg"]) == pytest.approx((ap_lat, ap_lon))
    assert priors[0]["sigma_m"] > 300.0  # the whole map from there: never a fix
    sent = [r for r in records if r["kind"] == "mavlink.estimate" and r["t_unix_s"] > priors[0]["t_unix_s"]]
    assert sent and all(r["fix_type"] != 3 for r in sent), sent[:3]
