"""Who hears the daemon: a listening link (udpin/tcpin) writes only to the autopilot's address, learned
from its valid messages, then moved only by its HEARTBEAT from a new address once the old one has been
silent past ``mavlink.link_timeout_s``, whatever else sends to it; an impostor (another address with the
autopilot's ids) is ignored, counted and reported; TIMESYNC answers are bounded. Real pymavlink and
sockets on 127.0.0.1."""

from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gps_denied_onboard.components.c5_estimator.types import EstimatorState
from gps_denied_onboard.components.c8_mavlink import MavlinkLink, VehicleStateTracker, transport
from gps_denied_onboard.components.c8_mavlink.messages import DIALECT as D
from gps_denied_onboard.components.c8_mavlink.messages import mavutil
from gps_denied_onboard.config import MavlinkConfig
from gps_denied_onboard.constants import TIMESYNC_ANSWER_MIN_INTERVAL_S, FdrHealthState, FdrKind, Provenance

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


class _RecordingFdr:
    """The FDR at the link's boundary: keeps what is recorded."""

    def __init__(self) -> None:
        self.records: list[tuple[str, dict[str, Any]]] = []

    def record(self, kind: str, fields: Mapping[str, object]) -> None:
        self.records.append((kind, dict(fields)))


def _link(
    url: str,
    signing_key_file: str | None = None,
    *,
    link_timeout_s: float = 3.0,
    fdr: _RecordingFdr | None = None,
) -> MavlinkLink:
    tracker = VehicleStateTracker(
        1, attitude_max_age_s=0.3, altitude_max_age_s=1.0, link_timeout_s=link_timeout_s
    )
    config = MavlinkConfig(url=url, signing_key_file=signing_key_file, link_timeout_s=link_timeout_s)
    link = MavlinkLink(config, tracker, fdr=fdr)
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


def test_link_udpin_an_impostor_never_takes_a_heard_autopilots_output(
    udp_link: tuple[MavlinkLink, int],
) -> None:
    """Another port claiming the autopilot's ids (HEARTBEAT, ATTITUDE) while the autopilot is heard moves
    nothing and receives nothing; the autopilot gets every GPS_INPUT (issue 36: two hostile flights lost
    GPS_INPUT for 19.9 s and 35.8 s when the output followed the impostor's HEARTBEAT)."""
    link, port = udp_link
    ap, impostor = _ap(port), _ap(port)
    try:
        ap.mav.send(_heartbeat(ap.mav))
        assert _pump(link, lambda: link.tracker.autopilot_seen)
        for _ in range(5):
            impostor.mav.send(_heartbeat(impostor.mav))
            impostor.mav.attitude_send(1000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
            ap.mav.attitude_send(1000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
            _pump(link, lambda: False, timeout_s=0.05)
        _send_everything(link, 3)
        assert _count(ap, "GPS_INPUT") == 3
        assert _count(impostor, None, 0.2) == 0
        assert link.stats().impostor_messages == 10
    finally:
        ap.close()
        impostor.close()


def test_link_udpin_impostor_is_reported_to_the_ground_rate_limited() -> None:
    """An impostor is counted, logged and recorded in the FDR, and a CRITICAL STATUSTEXT goes to the
    autopilot (which forwards it to the ground), at most once per IMPOSTOR_REPORT_INTERVAL_S; its
    TIMESYNC requests and its answers to ours are not answered or used."""
    port = _free_port(socket.SOCK_DGRAM)
    fdr = _RecordingFdr()
    link = _link(f"udpin:127.0.0.1:{port}", fdr=fdr)
    ap, impostor = _ap(port), _ap(port)
    try:
        ap.mav.send(_heartbeat(ap.mav))
        assert _pump(link, lambda: link.tracker.autopilot_seen)
        for _ in range(50):
            impostor.mav.send(_heartbeat(impostor.mav))
            impostor.mav.timesync_send(0, 555)
        _pump(link, lambda: link.stats().impostor_messages >= 100)
        texts = [m.text for m in _recv_all_of(ap, "STATUSTEXT", 0.4)]
        assert texts == [f"GDN: impostor 127.0.0.1:{_local_port(impostor)} x1"]
        reports = [f for kind, f in fdr.records if kind == FdrKind.LINK_EVENT and f["event"] == "impostor"]
        assert len(reports) == 1 and reports[0]["source"] == f"127.0.0.1:{_local_port(impostor)}"
        assert link.stats().impostor_messages == 100 and link.stats().timesync_answered == 0
        assert _count(impostor, None, 0.1) == 0
    finally:
        ap.close()
        impostor.close()
        link.close()


def test_link_udpin_moves_only_after_the_old_address_is_silent_and_on_a_heartbeat() -> None:
    """The autopilot on a new port (a reboot, a new router): its HEARTBEAT there moves nothing while the
    old address is heard; once the old one has been silent past link_timeout_s, its ATTITUDE there still
    moves nothing, its HEARTBEAT does; a HEARTBEAT of another system id never does."""
    port = _free_port(socket.SOCK_DGRAM)
    link = _link(f"udpin:127.0.0.1:{port}", link_timeout_s=0.5)
    old, new = _ap(port), _ap(port)
    other_sys = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=2, source_component=1)
    try:
        old.mav.send(_heartbeat(old.mav))
        assert _pump(link, lambda: link.tracker.autopilot_seen)
        new.mav.send(_heartbeat(new.mav))
        _pump(link, lambda: False, timeout_s=0.1)
        _send_everything(link, 3)
        assert _count(old, "GPS_INPUT") == 3 and _count(new, None, 0.1) == 0
        time.sleep(0.7)  # the old address falls silent past the timeout
        new.mav.attitude_send(1000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        other_sys.mav.send(_heartbeat(other_sys.mav))  # a quadrotor autopilot, but not ours
        _pump(link, lambda: False, timeout_s=0.1)
        _send_everything(link, 3)
        assert _count(old, "GPS_INPUT") == 3 and _count(new, None, 0.1) == 0
        new.mav.send(_heartbeat(new.mav))
        _pump(link, lambda: False, timeout_s=0.1)
        _send_everything(link, 5)
        assert _count(new, "GPS_INPUT") == 5
        assert _count(old, None, 0.2) == 0 and _count(other_sys, None, 0.1) == 0
    finally:
        for conn in (old, new, other_sys):
            conn.close()
        link.close()


def test_link_udpin_signed_moves_only_on_a_signed_heartbeat(tmp_path: Path) -> None:
    """With signing on, after the autopilot's old address falls silent, an unsigned HEARTBEAT with its ids
    from a new port moves nothing; the autopilot's signed HEARTBEAT from a new port does."""
    key_path = tmp_path / "key"
    key_path.write_text(KEY_HEX)
    os.chmod(key_path, 0o600)
    port = _free_port(socket.SOCK_DGRAM)
    link = _link(f"udpin:127.0.0.1:{port}", signing_key_file=str(key_path), link_timeout_s=0.5)
    old, new, spoof = _ap(port), _ap(port), _ap(port)
    try:
        for signed in (old, new):
            signed.setup_signing(bytes.fromhex(KEY_HEX), sign_outgoing=True)
        old.mav.send(_heartbeat(old.mav))
        assert _pump(link, lambda: link.tracker.autopilot_seen)
        time.sleep(0.7)
        spoof.mav.send(_heartbeat(spoof.mav))
        _pump(link, lambda: False, timeout_s=0.1)
        _send_everything(link, 3)
        assert _count(spoof, None, 0.2) == 0 and _count(old, "GPS_INPUT") == 3
        new.mav.send(_heartbeat(new.mav))
        _pump(link, lambda: False, timeout_s=0.1)
        _send_everything(link, 3)
        assert _count(new, "GPS_INPUT") == 3 and _count(spoof, None, 0.1) == 0
    finally:
        for conn in (old, new, spoof):
            conn.close()
        link.close()


def test_link_udpin_timesync_answers_are_bounded_and_only_to_the_autopilot(
    udp_link: tuple[MavlinkLink, int],
) -> None:
    """A flood of TIMESYNC requests from the autopilot's own address draws at most one answer per
    TIMESYNC_ANSWER_MIN_INTERVAL_S, none from another system or address, and the 10 Hz GPS_INPUT stream
    stays whole (issue 36: 75,000 requests/s drew 50,538 answers in 10 s and cut GPS_INPUT to 4.6/s)."""
    link, port = udp_link
    ap = _ap(port)
    stranger = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
    flood_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        ap.mav.send(_heartbeat(ap.mav))
        assert _pump(link, lambda: link.tracker.autopilot_seen)
        # the autopilot's own requests, from its own socket: one datagram of 40 requests each time
        mav = D.MAVLink(None, srcSystem=1, srcComponent=1)
        burst = b"".join(bytes(mav.timesync_encode(0, 1000 + i).pack(mav)) for i in range(40))
        t0 = time.monotonic()
        sent = got = answers = 0
        next_send = t0
        while time.monotonic() - t0 < 2.0:
            for _ in range(20):
                ap.port.sendto(burst, ("127.0.0.1", port))
                stranger.mav.timesync_send(0, 42)
            link.poll()
            now = time.monotonic()
            if now >= next_send:
                link.send_estimate(_state(), time_unix_usec=T0_UNIX_USEC)
                sent += 1
                next_send += 0.1
            while (msg := ap.recv_match(type=["GPS_INPUT", "TIMESYNC"], blocking=False)) is not None:
                got += msg.get_type() == "GPS_INPUT"
                answers += msg.get_type() == "TIMESYNC" and msg.tc1 != 0
            time.sleep(0.002)
        elapsed = time.monotonic() - t0
        for msg in _recv_all_of(ap, None, 0.3):
            got += msg.get_type() == "GPS_INPUT"
            answers += msg.get_type() == "TIMESYNC" and msg.tc1 != 0
        stats = link.stats()
        assert stats.timesync_ignored > 1000, stats
        assert 1 <= answers == stats.timesync_answered <= elapsed / TIMESYNC_ANSWER_MIN_INTERVAL_S + 2
        assert got == sent
        assert _count(stranger, None, 0.1) == 0
    finally:
        ap.close()
        stranger.close()
        flood_sock.close()


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


def _local_port(conn: Any) -> int:
    """The source port a pymavlink udpout connection sends from."""
    return int(conn.port.getsockname()[1])


def _recv_all_of(conn: Any, msg_type: str | None, wait_s: float) -> list[Any]:
    """Every message (of ``msg_type``) ``conn`` receives within ``wait_s``."""
    out = []
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        msg = conn.recv_match(type=msg_type, blocking=True, timeout=0.05)
        if msg is not None and msg.get_type() != "BAD_DATA":
            out.append(msg)
    return out


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
    """Many idle connections never exceed TCP_MAX_CLIENTS and never push out the autopilot's; a second
    connection's HEARTBEAT with its ids takes nothing while the autopilot's is open; once that closes, the
    autopilot connecting again gets the stream."""
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
        ap2.mav.send(_heartbeat(ap2.mav))  # while the first connection is open and heard: an impostor
        _pump(link, lambda: False, timeout_s=0.3)
        _send_everything(link, 5)
        assert _count(ap, "GPS_INPUT") == 5 and _count(ap2, None, 0.2) == 0
        ap.close()  # the autopilot's connection closes: the next HEARTBEAT of its ids takes the output
        _pump(link, lambda: False, timeout_s=0.3)
        ap2.mav.send(_heartbeat(ap2.mav))
        _pump(link, lambda: False, timeout_s=0.3)
        _send_everything(link, 5)
        assert _count(ap2, "GPS_INPUT") == 5
    finally:
        for s in idle:
            s.close()
        for c in (ap, ap2):
            if c is not None:
                c.close()
        link.close()
