"""Who hears the daemon: a listening link (udpin/tcpin) writes only to the autopilot's address, learned
from its valid messages (then moved by its HEARTBEAT only), whatever else sends to it. Real pymavlink
and sockets on 127.0.0.1."""

from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gps_denied_onboard.components.c5_estimator.types import EstimatorState
from gps_denied_onboard.components.c8_mavlink import MavlinkLink, VehicleStateTracker, transport
from gps_denied_onboard.components.c8_mavlink.messages import DIALECT as D
from gps_denied_onboard.components.c8_mavlink.messages import mavutil
from gps_denied_onboard.config import MavlinkConfig
from gps_denied_onboard.constants import FdrHealthState, Provenance

KEY_HEX = "00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff"
T0_UNIX_USEC = 1_717_000_000_000_000
#: Distinct source ports in the flood test (the probe used 20,000; this keeps the test short on 2 cores).
FLOOD_SENDERS = 5000


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _state() -> EstimatorState:
    return EstimatorState(
        time_unix_usec=T0_UNIX_USEC,
        provenance=Provenance.SATELLITE_ANCHORED,
        pos_ned_m=np.array([10.0, 20.0, -100.0]),
        vel_ned_m_s=np.array([5.0, -2.0, 0.5]),
        cov_pos_ned_m2=np.diag([9.0, 16.0, 25.0]),
        cov_vel_ned_m2_s2=np.diag([0.25, 0.16, 0.09]),
        lat_deg=50.4501234,
        lon_deg=30.5234567,
        alt_amsl_m=250.0,
        yaw_rad=0.5,
        last_fix_age_s=0.2,
        shared_sigma_m=1.0,
    )


def _heartbeat(mav: Any, mav_type: int = D.MAV_TYPE_QUADROTOR) -> Any:
    autopilot = D.MAV_AUTOPILOT_INVALID if mav_type == D.MAV_TYPE_GCS else D.MAV_AUTOPILOT_ARDUPILOTMEGA
    return mav.heartbeat_encode(mav_type, autopilot, 0, 0, D.MAV_STATE_ACTIVE)


def _link(url: str, signing_key_file: str | None = None) -> MavlinkLink:
    tracker = VehicleStateTracker(1, attitude_max_age_s=0.3, altitude_max_age_s=1.0, link_timeout_s=3.0)
    link = MavlinkLink(MavlinkConfig(url=url, signing_key_file=signing_key_file), tracker)
    link.open()
    return link


def _pump(link: MavlinkLink, until: Callable[[], bool], timeout_s: float = 2.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        link.poll()
        if until():
            return True
        time.sleep(0.005)
    return until()


def _send_everything(link: MavlinkLink, n_estimates: int) -> None:
    """What the daemon sends: estimates, its HEARTBEAT, the NAMED_VALUE set and a STATUSTEXT."""
    for _ in range(n_estimates):
        link.send_estimate(_state(), time_unix_usec=T0_UNIX_USEC)
    link.send_heartbeat()
    link.send_status_values(
        provenance=Provenance.SATELLITE_ANCHORED,
        inliers=50,
        residual_px=1.0,
        horiz_sigma_m=5.0,
        frame_drops=0,
        fdr_health=FdrHealthState.OK,
    )
    link.send_statustext(D.MAV_SEVERITY_INFO, "GDN: test")


def _count(conn: Any, msg_type: str | None, wait_s: float = 0.4) -> int:
    n = 0
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        msg = conn.recv_match(type=msg_type, blocking=True, timeout=0.05)
        if msg is not None and msg.get_type() != "BAD_DATA":
            n += 1
    return n


def _datagrams_waiting(sock: socket.socket, wait_s: float = 0.0) -> int:
    """How many datagrams ``sock`` has received (read without blocking after ``wait_s``)."""
    time.sleep(wait_s)
    sock.setblocking(False)
    n = 0
    while True:
        try:
            sock.recv(65535)
        except BlockingIOError:
            return n
        n += 1


@pytest.fixture
def udp_link() -> Iterator[tuple[MavlinkLink, int]]:
    port = _free_port(socket.SOCK_DGRAM)
    link = _link(f"udpin:127.0.0.1:{port}")
    try:
        yield link, port
    finally:
        link.close()


def _ap(port: int, scheme: str = "udpout") -> Any:
    return mavutil.mavlink_connection(f"{scheme}:127.0.0.1:{port}", source_system=1, source_component=1)


def test_link_udpin_stranger_receives_nothing(udp_link: tuple[MavlinkLink, int]) -> None:
    """A ground station and a raw UDP sender that talk to the daemon's port get none of its messages;
    the autopilot gets them all."""
    link, port = udp_link
    gcs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
    raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ap = _ap(port)
    try:
        gcs.mav.send(_heartbeat(gcs.mav, D.MAV_TYPE_GCS))
        ap.mav.send(_heartbeat(ap.mav))
        assert _pump(link, lambda: link.tracker.autopilot_seen)
        gcs.mav.send(_heartbeat(gcs.mav, D.MAV_TYPE_GCS))  # the newest senders are not the autopilot
        raw.sendto(b"hello", ("127.0.0.1", port))
        _pump(link, lambda: False, timeout_s=0.1)
        _send_everything(link, 20)
        assert _count(ap, "GPS_INPUT") == 20
        assert _count(gcs, None, 0.2) == 0
        assert _datagrams_waiting(raw) == 0
    finally:
        for conn in (gcs, ap):
            conn.close()
        raw.close()


def test_link_udpin_a_strangers_partial_packet_does_not_eat_the_autopilots_next_datagram(
    udp_link: tuple[MavlinkLink, int],
) -> None:
    """A datagram ending in the start of a packet is not completed with the autopilot's next datagram
    (which would turn the autopilot's HEARTBEAT into bad data): each datagram is parsed on its own."""
    link, port = udp_link
    ap = _ap(port)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
        try:
            raw.sendto(b"\xfd\x09\x00", ("127.0.0.1", port))  # a MAVLink 2 header of a 9-byte payload
            _pump(link, lambda: False, timeout_s=0.1)
            ap.mav.send(_heartbeat(ap.mav))
            assert _pump(link, lambda: link.tracker.autopilot_seen)
        finally:
            ap.close()


def test_link_udpin_nothing_goes_out_before_the_autopilot_is_heard(
    udp_link: tuple[MavlinkLink, int],
) -> None:
    """Nothing is written before the autopilot is heard; then, before its first HEARTBEAT, any valid
    message of its own (ATTITUDE at 50 Hz: a restarted daemon need not wait up to 1 s for the 1 Hz
    HEARTBEAT) gives its address. The same message from another system id, or from the autopilot's
    system id but another component, gives nothing (issue 27, item 5)."""
    link, port = udp_link
    ap = _ap(port)
    other_sys = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=2, source_component=1)
    other_comp = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=2)
    try:
        _send_everything(link, 3)
        assert _count(ap, None, 0.2) == 0
        for stranger in (other_sys, other_comp):
            stranger.mav.attitude_send(1000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        _pump(link, lambda: False, timeout_s=0.2)
        _send_everything(link, 3)
        assert _count(other_sys, None, 0.2) == 0 and _count(other_comp, None, 0.1) == 0
        ap.mav.attitude_send(1000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        _pump(link, lambda: False, timeout_s=0.2)
        assert not link.tracker.autopilot_seen  # no HEARTBEAT yet, but its address is known
        _send_everything(link, 3)
        assert _count(ap, "GPS_INPUT") == 3
        assert _count(other_sys, None, 0.1) == 0 and _count(other_comp, None, 0.1) == 0
    finally:
        for conn in (ap, other_sys, other_comp):
            conn.close()


def test_link_udpin_only_a_heartbeat_moves_a_known_autopilot_address(
    udp_link: tuple[MavlinkLink, int],
) -> None:
    """Once the output follows the autopilot, a message other than HEARTBEAT with its ids from another
    port moves nothing; its HEARTBEAT from there does."""
    link, port = udp_link
    old, new = _ap(port), _ap(port)
    try:
        old.mav.send(_heartbeat(old.mav))
        assert _pump(link, lambda: link.tracker.autopilot_seen)
        new.mav.attitude_send(1000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        _pump(link, lambda: False, timeout_s=0.2)
        _send_everything(link, 3)
        assert _count(old, "GPS_INPUT") == 3
        assert _count(new, None, 0.2) == 0
        new.mav.send(_heartbeat(new.mav))
        _pump(link, lambda: False, timeout_s=0.2)
        _send_everything(link, 3)
        assert _count(new, "GPS_INPUT") == 3
    finally:
        old.close()
        new.close()


def test_link_udpin_follows_the_autopilots_newest_address(udp_link: tuple[MavlinkLink, int]) -> None:
    """After the autopilot's HEARTBEAT comes from a new port (a reboot), the output goes there only; a
    HEARTBEAT from another system id or a ground station moves nothing."""
    link, port = udp_link
    old, new = _ap(port), _ap(port)
    other_sys = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=2, source_component=1)
    try:
        old.mav.send(_heartbeat(old.mav))
        assert _pump(link, lambda: link.tracker.autopilot_seen)
        _send_everything(link, 5)
        assert _count(old, "GPS_INPUT") == 5
        new.mav.send(_heartbeat(new.mav))
        other_sys.mav.send(_heartbeat(other_sys.mav))  # a quadrotor autopilot, but not ours
        _pump(link, lambda: False, timeout_s=0.2)
        _send_everything(link, 5)
        assert _count(new, "GPS_INPUT") == 5
        assert _count(old, None, 0.2) == 0
        assert _count(other_sys, None, 0.1) == 0
    finally:
        for conn in (old, new, other_sys):
            conn.close()


def test_link_udpin_signed_ignores_an_unsigned_autopilot_heartbeat(tmp_path: Path) -> None:
    """With signing on, an unsigned HEARTBEAT that claims the autopilot's ids neither takes the output nor
    receives anything, before or after the signed autopilot is heard."""
    key_path = tmp_path / "key"
    key_path.write_text(KEY_HEX)
    os.chmod(key_path, 0o600)
    port = _free_port(socket.SOCK_DGRAM)
    link = _link(f"udpin:127.0.0.1:{port}", signing_key_file=str(key_path))
    ap, spoof = _ap(port), _ap(port)
    try:
        ap.setup_signing(bytes.fromhex(KEY_HEX), sign_outgoing=True)
        spoof.mav.send(_heartbeat(spoof.mav))
        _pump(link, lambda: False, timeout_s=0.2)
        assert not link.tracker.autopilot_seen
        ap.mav.send(_heartbeat(ap.mav))
        assert _pump(link, lambda: link.tracker.autopilot_seen)
        spoof.mav.send(_heartbeat(spoof.mav))
        _pump(link, lambda: False, timeout_s=0.2)
        _send_everything(link, 10)
        assert _count(ap, "GPS_INPUT") == 10
        assert _count(spoof, None, 0.2) == 0
    finally:
        ap.close()
        spoof.close()
        link.close()


def test_link_udpin_signed_ignores_unsigned_autopilot_messages_before_its_heartbeat(tmp_path: Path) -> None:
    """With signing on, an unsigned ATTITUDE claiming the autopilot's ids gives no address; the signed
    autopilot's ATTITUDE does, before any HEARTBEAT."""
    key_path = tmp_path / "key"
    key_path.write_text(KEY_HEX)
    os.chmod(key_path, 0o600)
    port = _free_port(socket.SOCK_DGRAM)
    link = _link(f"udpin:127.0.0.1:{port}", signing_key_file=str(key_path))
    ap, spoof = _ap(port), _ap(port)
    try:
        ap.setup_signing(bytes.fromhex(KEY_HEX), sign_outgoing=True)
        spoof.mav.attitude_send(1000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        _pump(link, lambda: False, timeout_s=0.2)
        _send_everything(link, 3)
        assert _count(spoof, None, 0.2) == 0
        ap.mav.attitude_send(1000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        _pump(link, lambda: False, timeout_s=0.2)
        spoof.mav.attitude_send(1000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        _pump(link, lambda: False, timeout_s=0.2)
        _send_everything(link, 3)
        assert _count(ap, "GPS_INPUT") == 3
        assert _count(spoof, None, 0.2) == 0
    finally:
        ap.close()
        spoof.close()
        link.close()


def _flood(port: int, payload: bytes, n: int, keep: list[socket.socket], done: threading.Event) -> None:
    """``n`` datagrams, each from a fresh socket (a fresh source port); the last 20 sockets are kept open
    in ``keep`` so that what reaches them can be counted."""
    for i in range(n):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.sendto(payload, ("127.0.0.1", port))
        if i >= n - 20:
            keep.append(s)
        else:
            s.close()
    done.set()


def test_link_udpin_source_port_flood_keeps_table_bounded_and_stream_whole(
    udp_link: tuple[MavlinkLink, int],
) -> None:
    """FLOOD_SENDERS one-datagram senders during a 10 Hz GPS_INPUT stream: the link writes to one address,
    the autopilot gets every GPS_INPUT, and the flood's senders get nothing."""
    link, port = udp_link
    ap = _ap(port)
    gcs = D.MAVLink(None, srcSystem=255, srcComponent=190)
    payload = bytes(_heartbeat(gcs, D.MAV_TYPE_GCS).pack(gcs))
    keep: list[socket.socket] = []
    done = threading.Event()
    try:
        ap.mav.send(_heartbeat(ap.mav))
        assert _pump(link, lambda: link.tracker.autopilot_seen)
        flood = threading.Thread(target=_flood, args=(port, payload, FLOOD_SENDERS, keep, done), daemon=True)
        t0 = time.monotonic()
        flood.start()
        sent, got, arrivals = 0, 0, []
        next_send = t0
        next_hb = t0 + 1.0
        while time.monotonic() - t0 < 3.0 or (not done.is_set() and time.monotonic() - t0 < 30.0):
            link.poll()
            now = time.monotonic()
            if now >= next_send:
                link.send_estimate(_state(), time_unix_usec=T0_UNIX_USEC)
                sent += 1
                next_send += 0.1
            if now >= next_hb:
                ap.mav.send(_heartbeat(ap.mav))
                next_hb += 1.0
            while (msg := ap.recv_match(type="GPS_INPUT", blocking=False)) is not None:
                got += 1
                arrivals.append(msg._timestamp)
            time.sleep(0.002)
        assert done.is_set(), "the flood did not finish within 30 s"
        flood_s = time.monotonic() - t0
        got += _count(ap, "GPS_INPUT", 0.3)
        conn = link._conn
        assert conn is not None and len(conn.clients) <= 1
        assert got == sent
        assert sum(_datagrams_waiting(s) for s in keep) == 0
        gaps_ms = np.diff(arrivals) * 1000 if len(arrivals) > 2 else np.array([0.0])
        print(
            f"flood of {FLOOD_SENDERS} senders in {flood_s:.1f} s: {got}/{sent} GPS_INPUT, interval p99 "
            f"{np.percentile(gaps_ms, 99):.0f} ms, max {gaps_ms.max():.0f} ms"
        )
    finally:
        ap.close()
        for s in keep:
            s.close()


def test_link_tcpin_silent_first_client_does_not_block_the_autopilot(monkeypatch: pytest.MonkeyPatch) -> None:
    """A client that connects first and sends nothing neither keeps the autopilot's connection out nor
    receives anything, and is closed after the hello bound; the autopilot gets the stream."""
    monkeypatch.setattr(transport, "TCP_CLIENT_HELLO_TIMEOUT_S", 1.0)
    port = _free_port(socket.SOCK_STREAM)
    link = _link(f"tcpin:127.0.0.1:{port}")
    silent = socket.create_connection(("127.0.0.1", port), timeout=2.0)
    ap = None
    try:
        _pump(link, lambda: False, timeout_s=0.2)  # the silent client is accepted first
        ap = _ap(port, "tcp")
        ap.mav.send(_heartbeat(ap.mav))
        assert _pump(link, lambda: link.tracker.autopilot_seen), "the autopilot's heartbeat was never read"
        _send_everything(link, 10)
        assert _count(ap, "GPS_INPUT") == 10
        silent.settimeout(2.0)
        t0 = time.monotonic()
        closed = threading.Event()

        def read_silent() -> None:
            if silent.recv(4096) == b"":  # EOF, nothing received before it
                closed.set()

        reader = threading.Thread(target=read_silent, daemon=True)
        reader.start()
        _pump(link, lambda: closed.is_set(), timeout_s=2.5)
        reader.join(timeout=1.0)
        assert closed.is_set(), "the silent client was not closed (or was sent something)"
        assert time.monotonic() - t0 < 2.5
        _send_everything(link, 5)
        assert _count(ap, "GPS_INPUT") == 5  # the autopilot's connection stays
    finally:
        silent.close()
        if ap is not None:
            ap.close()
        link.close()


def test_link_tcpin_holds_a_bounded_number_of_clients_and_follows_a_reconnecting_autopilot() -> None:
    """Many idle connections never exceed TCP_MAX_CLIENTS and never push out the autopilot's; when the
    autopilot connects again, the stream moves to the new connection."""
    port = _free_port(socket.SOCK_STREAM)
    link = _link(f"tcpin:127.0.0.1:{port}")
    ap = _ap(port, "tcp")
    idle: list[socket.socket] = []
    ap2 = None
    try:
        ap.mav.send(_heartbeat(ap.mav))
        assert _pump(link, lambda: link.tracker.autopilot_seen)
        for _ in range(3 * transport.TCP_MAX_CLIENTS):
            idle.append(socket.create_connection(("127.0.0.1", port), timeout=2.0))
            _pump(link, lambda: False, timeout_s=0.01)
        conn = link._conn
        assert conn is not None and conn.client_count <= transport.TCP_MAX_CLIENTS
        _send_everything(link, 5)
        assert _count(ap, "GPS_INPUT") == 5
        ap2 = _ap(port, "tcp")
        ap2.mav.send(_heartbeat(ap2.mav))
        _pump(link, lambda: False, timeout_s=0.3)
        _send_everything(link, 5)
        assert _count(ap2, "GPS_INPUT") == 5
        assert _count(ap, "GPS_INPUT", 0.2) == 0
    finally:
        for s in idle:
            s.close()
        for c in (ap, ap2):
            if c is not None:
                c.close()
        link.close()
