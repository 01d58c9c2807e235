"""The start-up beacon (``daemon.beacon``) and the composition root's first stage
(``runtime_root.link_first``): the link opens before anything heavy is imported, and the beacon keeps
the autopilot hearing the daemon, with nothing it could mistake for a position, until the tasks start.

Real UDP on loopback; the "autopilot" is a pymavlink endpoint.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from typing import Any

from gps_denied_onboard.clock import DaemonClock
from gps_denied_onboard.components.c8_mavlink.messages import DIALECT as D
from gps_denied_onboard.components.c8_mavlink.messages import mavutil
from gps_denied_onboard.config import config_from_mapping
from gps_denied_onboard.daemon.beacon import STARTING_TEXT, StartupBeacon
from gps_denied_onboard.geo import LocalTangentPlane
from gps_denied_onboard.runtime_root.link_first import open_link_first

#: What the first stage must not import: each costs 0.1-0.6 s of start-up on two cores.
HEAVY_MODULES = ("scipy", "cv2", "onnxruntime", "faiss", "rasterio", "torch")


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_the_first_stage_imports_nothing_heavy() -> None:
    """``gdnav run``'s first stage (CLI, config, link, beacon) in a fresh interpreter: none of the heavy
    libraries is loaded, so the link opens about a second before the rest; ``run``'s own parser does not
    load numpy (its BLAS threads are set from the config first)."""
    code = (
        "import sys\n"
        "import gps_denied_onboard.cli as cli\n"
        "cli.run_parser().parse_args(['run', '--config', 'x.yaml'])\n"
        "assert 'numpy' not in sys.modules, 'numpy before daemon.blas_threads is applied'\n"
        "import gps_denied_onboard.runtime_root.link_first\n"
        "import gps_denied_onboard.daemon.beacon\n"
        f"print(sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY_MODULES!r})))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == "[]", out.stdout


#: The navigator core's side of the daemon (issue 36): the link, the clocks, the estimator on its time
#: axis, the start-up prior and resume state, the flight data recorder, systemd's notifications.
CORE_MODULES = (
    "gps_denied_onboard.clock",
    "gps_denied_onboard.components.c8_mavlink",
    "gps_denied_onboard.components.c8_mavlink.px4_params",
    "gps_denied_onboard.components.c5_estimator.time_axis",
    "gps_denied_onboard.components.c5_estimator.ekf",
    "gps_denied_onboard.components.c5_estimator.prior",
    "gps_denied_onboard.components.c5_estimator.resume_state",
    "gps_denied_onboard.components.c13_fdr",
    "gps_denied_onboard.daemon.beacon",
    "gps_denied_onboard.daemon.sd_notify",
    "gps_denied_onboard.components.c5_estimator.wire",
    "gps_denied_onboard.daemon.core",
)


def test_the_navigator_cores_modules_import_nothing_heavy() -> None:
    """The estimator and everything else the core holds, in a fresh interpreter: no SciPy, OpenCV,
    ONNX Runtime, FAISS or torch comes with them (the VO and pose packages load their heavy parts only
    when those are asked for), so a core can start without the vision's imports."""
    code = "import sys\n" + "".join(f"import {m}\n" for m in CORE_MODULES)
    code += f"print(sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY_MODULES!r})))\n"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def _collect(ap: Any, seconds: float) -> dict[str, list[Any]]:
    got: dict[str, list[Any]] = {}
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        msg = ap.recv_match(blocking=True, timeout=0.05)
        if msg is not None and msg.get_type() != "BAD_DATA":
            got.setdefault(msg.get_type(), []).append(msg)
    return got


def test_beacon_speaks_to_the_autopilot_without_a_position_until_stopped() -> None:
    """Once the autopilot is heard: HEARTBEAT in MAV_STATE_BOOT, GPS_INPUT at the estimate rate with
    fix_type 0 and no position, "GDN: starting" once. After ``stop`` it sends nothing more, and the
    same link takes its FDR and frame (``attach``) for the daemon's tasks."""
    port = _free_udp_port()
    config = config_from_mapping({"mavlink": {"url": f"udpin:127.0.0.1:{port}", "estimate_rate_hz": 10.0}})
    clock = DaemonClock()
    link = open_link_first(config, clock)
    ap = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    beacon = StartupBeacon(link, config.mavlink, clock.now_unix_s)
    try:
        beacon.start()
        quad, ardupilot = D.MAV_TYPE_QUADROTOR, D.MAV_AUTOPILOT_ARDUPILOTMEGA
        hb = ap.mav.heartbeat_encode(quad, ardupilot, 0, 0, D.MAV_STATE_ACTIVE)
        ap.mav.send(hb)  # the link writes only to the autopilot's address, learned from it
        got = _collect(ap, 1.5)
        gps = got.get("GPS_INPUT", [])
        assert len(gps) >= 8, {k: len(v) for k, v in got.items()}  # ~10 Hz for ~1.5 s, after the address
        assert all(m.fix_type == 0 and (m.lat, m.lon) == (0, 0) for m in gps)
        assert all(m.system_status == D.MAV_STATE_BOOT for m in got["HEARTBEAT"])
        texts = [m.text for m in got.get("STATUSTEXT", [])]
        assert texts == [STARTING_TEXT], texts
        # what the start-up prior needs is asked for before the first frame: estimate and home at 4 Hz,
        # the landed state at 1 Hz
        asks = _requested(got)
        for wanted in ("GLOBAL_POSITION_INT", "EKF_STATUS_REPORT", "HOME_POSITION", "GPS_RAW_INT"):
            assert 4 <= asks.count(wanted) <= 7, asks
        assert 1 <= asks.count("EXTENDED_SYS_STATE") <= 2, asks
        asked = beacon.asked
        assert asked.estimate_first_unix_s is not None and asked.estimate_last_unix_s is not None
        assert asked.phase_last_unix_s is not None
        assert 0.75 <= asked.estimate_last_unix_s - asked.estimate_first_unix_s <= 1.5, asked
        beacon.stop()
        sent = beacon.estimates_sent
        assert sent >= len(gps)
        assert _collect(ap, 0.4).get("GPS_INPUT", []) == []
        assert beacon.estimates_sent == sent
        link.attach(None, LocalTangentPlane(47.0, 8.0, 400.0))
        link.open()  # already open: the daemon's call is a no-op, the port stays ours
        assert link.connected
    finally:
        beacon.stop()
        ap.close()
        link.close()


def _requested(got: dict[str, list[Any]]) -> list[str]:
    """The messages asked for by MAV_CMD_REQUEST_MESSAGE among ``got``'s COMMAND_LONGs, by name."""
    names = {
        v: k.removeprefix("MAVLINK_MSG_ID_") for k, v in vars(D).items() if k.startswith("MAVLINK_MSG_ID_")
    }
    return [
        names[int(m.param1)] for m in got.get("COMMAND_LONG", []) if m.command == D.MAV_CMD_REQUEST_MESSAGE
    ]


def test_beacon_asks_only_for_the_landed_state_where_the_autopilot_is_not_to_be_asked() -> None:
    """``init.autopilot_wait_s`` 0 ("do not ask"): the beacon asks for the landed state only."""
    port = _free_udp_port()
    config = config_from_mapping({"mavlink": {"url": f"udpin:127.0.0.1:{port}"}})
    clock = DaemonClock()
    link = open_link_first(config, clock)
    ap = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    beacon = StartupBeacon(link, config.mavlink, clock.now_unix_s, ask_estimate=False)
    try:
        beacon.start()
        hb = ap.mav.heartbeat_encode(D.MAV_TYPE_QUADROTOR, D.MAV_AUTOPILOT_PX4, 0, 0, D.MAV_STATE_ACTIVE)
        ap.mav.send(hb)
        asks = _requested(_collect(ap, 1.2))
        assert asks and set(asks) == {"EXTENDED_SYS_STATE"}, asks
        assert beacon.asked.estimate_first_unix_s is None
    finally:
        beacon.stop()
        ap.close()
        link.close()


def test_the_sitl_waits_for_a_heartbeat_out_of_boot_not_the_beacons() -> None:
    """The flights start their clock when the daemon is ready: its beacon's HEARTBEATs (MAV_STATE_BOOT)
    do not count, the daemon's own (STANDBY before its first estimate) do."""
    from gps_denied_onboard.sitl.autopilot import ReceivedMessage
    from gps_denied_onboard.sitl.runner import daemon_ready

    boot = ReceivedMessage(1.0, "HEARTBEAT", {"system_status": D.MAV_STATE_BOOT})
    standby = ReceivedMessage(2.0, "HEARTBEAT", {"system_status": D.MAV_STATE_STANDBY})
    gps = ReceivedMessage(1.5, "GPS_INPUT", {"fix_type": 0})
    assert not daemon_ready([boot, gps])
    assert daemon_ready([boot, gps, standby])
