"""C8 link: one pymavlink connection to the autopilot, driven by the daemon's event loop.

Input: the configured URL (``udpin:``/``udpout:``/``udp:``/``tcp:``/``tcpin:``/serial), the tracker to feed,
the estimates and status to send. Output: every decoded message to the tracker (each stamped at its own
arrival), GPS_INPUT / GLOBAL_POSITION_SENSOR / VISION_POSITION_ESTIMATE, HEARTBEAT, NAMED_VALUE,
STATUSTEXT, TIMESYNC requests (and answers to the autopilot's), SET_GPS_GLOBAL_ORIGIN.

Rules:
- ``poll()`` never blocks; it drains input, drives reconnects (capped exponential backoff with jitter,
  ``c8.mavlink.link_lost`` once per outage), TIMESYNC and the STATUSTEXT queue; sends never raise.
- Provenance STATUSTEXT: at most one per ``STATUSTEXT_MIN_INTERVAL_S``, the newest pending one kept.
- Signing when ``signing_key_file`` is set: unsigned or wrongly signed input is refused (RADIO_STATUS
  excepted).
- Listening links write only to the autopilot (``transport``): first where any of its valid messages came
  from (a restarted daemon hears its 50 Hz ATTITUDE before its 1 Hz HEARTBEAT). Once known, the address
  moves only when it has been silent past ``link_timeout_s`` and the new one sends the autopilot's valid
  HEARTBEAT (signed when signing is on). Meanwhile another address claiming the autopilot's system and
  component ids is an impostor: its messages are ignored (never reach the tracker, never answered),
  counted, and reported at most once per ``IMPOSTOR_REPORT_INTERVAL_S`` (log, FDR, STATUSTEXT).
- TIMESYNC: only the autopilot's own requests, from its address, are answered, at most one per
  ``TIMESYNC_ANSWER_MIN_INTERVAL_S``.
- What leaves as a position follows one rule (``messages.withheld_reason``): GPS_INPUT says "do not use"
  with its fix_type; GLOBAL_POSITION_SENSOR and VISION_POSITION_ESTIMATE, which have no such form their
  receiver honours, are not sent at all for a state the daemon cannot back. Each stretch of withheld
  messages is recorded once when it starts and once when it ends (``mavlink.link_event``
  ``output_withheld`` / ``output_resumed``) and counted (``LinkStats.positions_withheld``).
- GLOBAL_POSITION_SENSOR also waits for a finite altitude, and while the altitude is distrusted
  (``distrust_altitude``) it waits until the autopilot reports an origin: PX4 takes its origin's altitude
  from the first message it fuses. It waits too while held (``hold_global_position_sensor``: PX4's
  parameters not yet checked, or a wrong ``EKF2_AGP0_ID``).
- VISION_POSITION_ESTIMATE goes out only in a frame the autopilot shares (its GPS_GLOBAL_ORIGIN, or ours
  offered with SET_GPS_GLOBAL_ORIGIN until it reports one).
- GPS_INPUT's altitude is flagged as ignored while the ground altitude disagrees (``distrust_altitude``).

The rules in full: docs/design.md, "`c8_mavlink/link.py`: the link".
"""

from __future__ import annotations

import contextlib
import errno
import random
import socket
import stat
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np
import structlog

from gps_denied_onboard.components.c5_estimator.types import EstimatorState
from gps_denied_onboard.components.c8_mavlink import messages
from gps_denied_onboard.components.c8_mavlink.messages import DIALECT, mavutil
from gps_denied_onboard.components.c8_mavlink.transport import AutopilotTcpIn, AutopilotUdpIn, open_transport
from gps_denied_onboard.components.c8_mavlink.vehicle_state import AUTOPILOT_COMPONENT_ID, VehicleStateTracker
from gps_denied_onboard.components.c13_fdr.protocol import FdrClient
from gps_denied_onboard.config import MavlinkConfig, check_mavlink_url
from gps_denied_onboard.constants import (
    IMPOSTOR_REPORT_INTERVAL_S,
    IMPOSTOR_STATUSTEXT,
    LINK_EVENT_IMPOSTOR,
    NV_FDR_HEALTH,
    NV_FRAME_DROPS,
    NV_HORIZ_SIGMA_M,
    NV_INLIERS,
    NV_INTEGRITY_REFUSED,
    NV_PROVENANCE,
    NV_RESIDUAL_PX,
    SET_GPS_GLOBAL_ORIGIN_INTERVAL_S,
    STATUSTEXT_MIN_INTERVAL_S,
    TIMESYNC_ANSWER_MIN_INTERVAL_S,
    FdrHealthState,
    FdrKind,
    LogEvent,
    Provenance,
)
from gps_denied_onboard.geo import LocalTangentPlane

_log = structlog.get_logger(__name__)

#: Reconnect backoff: first delay, cap, and relative jitter (+-).
RECONNECT_BACKOFF_INITIAL_S: Final[float] = 0.5
RECONNECT_BACKOFF_MAX_S: Final[float] = 10.0
RECONNECT_JITTER_FRAC: Final[float] = 0.2
#: At most this many messages are handled per poll() (keeps one callback short under a flood).
MAX_MESSAGES_PER_POLL: Final[int] = 1000
#: TIMESYNC requests to the autopilot (``clock.AutopilotClock``): fast until this many answers, then slow.
TIMESYNC_FAST_INTERVAL_S: Final[float] = 0.25
TIMESYNC_SLOW_INTERVAL_S: Final[float] = 1.0
TIMESYNC_FAST_ANSWERS: Final[int] = 8
#: send_error logs are emitted at most once per this interval (the count is always kept).
SEND_ERROR_LOG_INTERVAL_S: Final[float] = 5.0
#: Message ids accepted unsigned when signing is on (RADIO_STATUS is injected by SiK radios).
UNSIGNED_ALLOWED_MSG_IDS: Final[frozenset[int]] = frozenset({DIALECT.MAVLINK_MSG_ID_RADIO_STATUS})
#: The autopilot's reported origin is "ours" when it lies this close to the daemon's (degE7/mm rounding
#: of SET_GPS_GLOBAL_ORIGIN is about 1 cm), m.
ORIGIN_MATCH_TOLERANCE_M: Final[float] = 0.05
_VISION_OUTPUT: Final[str] = "vision_position_estimate"

_NAMED_VALUE_NAMES: Final[tuple[str, ...]] = (
    NV_PROVENANCE,
    NV_INLIERS,
    NV_RESIDUAL_PX,
    NV_HORIZ_SIGMA_M,
    NV_FRAME_DROPS,
    NV_FDR_HEALTH,
    NV_INTEGRITY_REFUSED,
)
#: pymavlink schemes that bind a UDP port to listen on (``udp:`` is pymavlink's alias of ``udpin:``).
_UDP_LISTEN_SCHEMES: Final[tuple[str, ...]] = ("udpin:", "udp:")


class MavlinkError(RuntimeError):
    """Base of C8 errors. ``url`` names the connection."""

    def __init__(self, message: str, *, url: str | None = None) -> None:
        super().__init__(f"{message} (url={url})" if url else message)
        self.url = url


class MavlinkConfigError(MavlinkError):
    """The MAVLink configuration cannot be used (bad URL, unusable signing key file, a UDP port that
    another process already listens on)."""

    def __init__(self, message: str, *, url: str | None = None, path: str | None = None) -> None:
        super().__init__(f"{path}: {message}" if path else message, url=url)
        self.path = path


class _PeerClosed(ConnectionError):
    """Raised from pymavlink's TCP EOF/reset hooks so that poll() sees the loss."""


def load_signing_key(path: str | Path) -> bytes:
    """Read a MAVLink 2 signing key: 32 raw bytes or 64 hex characters (surrounding whitespace allowed).

    The file must not be readable or writable by group or others (mode & 0o077 == 0).
    """
    p = Path(path)
    try:
        st = p.stat()
    except OSError as exc:
        raise MavlinkConfigError(f"signing key file cannot be read: {exc.strerror}", path=str(p)) from exc
    if not stat.S_ISREG(st.st_mode):
        raise MavlinkConfigError("signing key file is not a regular file", path=str(p))
    if st.st_mode & 0o077:
        raise MavlinkConfigError(
            f"signing key file has mode {stat.S_IMODE(st.st_mode):04o}; it must not be accessible to group "
            "or others (chmod 600)",
            path=str(p),
        )
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise MavlinkConfigError(f"signing key file cannot be read: {exc.strerror}", path=str(p)) from exc
    if len(raw) == 32:
        return raw
    text = raw.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError) as exc:
            raise MavlinkConfigError(
                "signing key file has 64 characters but they are not hex", path=str(p)
            ) from exc
    raise MavlinkConfigError(
        f"signing key must be 32 raw bytes or 64 hex characters, got {len(raw)} bytes", path=str(p)
    )


def _validate_url(url: str) -> None:
    try:
        check_mavlink_url(url)
    except ValueError as exc:
        raise MavlinkConfigError(str(exc), url=url) from exc


def _refuse_taken_udp_port(url: str) -> None:
    """Refuse a ``udpin:``/``udp:`` address that another socket on this machine has bound.

    pymavlink binds UDP inputs with SO_REUSEADDR, so a second daemon on the same port starts without an
    error and Linux then delivers each datagram from the autopilot to only one of the two sockets (the
    newest): the second process silently takes the first one's input. A probe bind without SO_REUSEADDR
    fails with EADDRINUSE whenever any socket holds the port. Other bind errors (an address not up yet)
    are left to the connect, which retries them like any transport failure.
    """
    if not url.startswith(_UDP_LISTEN_SCHEMES):
        return
    host, _, port = url.split(":", 1)[1].rpartition(":")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.bind((host, int(port)))
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise MavlinkConfigError(
                    f"UDP port {port} on {host} is already bound by another process (another gdnav, or a "
                    "MAVLink router/ground station listening there); refusing to share the autopilot's input",
                    url=url,
                ) from exc


@dataclass(frozen=True)
class LinkStats:
    """Counters since open()."""

    connected: bool
    messages_received: int
    bad_packets: int
    messages_sent: int
    send_errors: int
    sends_dropped_link_down: int
    reconnects: int
    statustext_sent: int
    statustext_coalesced: int
    #: SET_GPS_GLOBAL_ORIGIN messages handed to the transport.
    global_origin_sent: int = 0
    #: VISION_POSITION_ESTIMATEs not sent because no frame shared with the autopilot was known yet.
    vision_withheld: int = 0
    #: GLOBAL_POSITION_SENSORs and VISION_POSITION_ESTIMATEs not sent because the daemon could not back
    #: the state (``messages.withheld_reason``; for GLOBAL_POSITION_SENSOR also its altitude).
    positions_withheld: int = 0
    #: Messages ignored from an impostor: another address claiming the autopilot's ids.
    impostor_messages: int = 0
    #: The autopilot's TIMESYNC requests answered, and requests not answered (rate limit, another address
    #: or another sender).
    timesync_answered: int = 0
    timesync_ignored: int = 0


@dataclass
class _PendingStatus:
    severity: int
    text: str
    coalesced: int


def severity_for(new: Provenance) -> int:
    """STATUSTEXT severity for a transition to ``new``: INFO anchored, WARNING VIO/dead reckoning,
    CRITICAL no estimate."""
    if new is Provenance.SATELLITE_ANCHORED:
        return DIALECT.MAV_SEVERITY_INFO
    if new is Provenance.NO_ESTIMATE:
        return DIALECT.MAV_SEVERITY_CRITICAL
    return DIALECT.MAV_SEVERITY_WARNING


def _no_frame(config: MavlinkConfig) -> MavlinkConfigError:
    return MavlinkConfigError(
        "mavlink.outputs has vision_position_estimate but the link was given no local frame (ltp) "
        "to offer the autopilot as its origin",
        url=config.url,
    )


class MavlinkLink:
    """The daemon's MAVLink endpoint (see the module docstring). Thread-safe: sends may come from the
    pipeline thread while the event loop polls."""

    def __init__(
        self,
        config: MavlinkConfig,
        tracker: VehicleStateTracker,
        fdr: FdrClient | None = None,
        clock: Callable[[], float] = time.time,
        rng: random.Random | None = None,
        *,
        ltp: LocalTangentPlane | None = None,
        frame_later: bool = False,
        signing_link_id: int = 0,
    ) -> None:
        """``ltp``: the daemon's local tangent plane (the frame of ``EstimatorState.pos_ned_m``); required
        when ``vision_position_estimate`` is among ``config.outputs``. ``frame_later``: the link starts
        before the map is open (the start-up beacon); ``attach`` then gives it the frame and the FDR.
        ``signing_link_id``: the MAVLink 2 signing link id of what this link signs (the navigator core
        signs as 0 and its vision worker, relayed through it, as 1: each keeps its own timestamps)."""
        if _VISION_OUTPUT in config.outputs and ltp is None and not frame_later:
            raise _no_frame(config)
        self._config = config
        self._ltp = ltp
        self._tracker = tracker
        self._fdr = fdr
        self._clock = clock
        self._rng = rng or random.Random()
        self._lock = threading.RLock()
        self._conn: Any = None
        self._signing_link_id = signing_link_id
        #: Called with each message the tracker took from the autopilot (``relay_autopilot_to``).
        self._relay: Callable[[Any], None] | None = None
        self._opened = False
        self._signing_key: bytes | None = None
        self._boot_monotonic = time.monotonic()
        # reconnect state
        self._backoff_s = RECONNECT_BACKOFF_INITIAL_S
        self._next_reconnect_s: float | None = None
        self._outage = False  # a link_lost was logged and no recovery seen yet
        self._was_alive = False
        # counters
        self._received = 0
        self._bad = 0
        self._sent = 0
        self._send_errors = 0
        self._dropped_down = 0
        self._reconnects = 0
        self._last_send_error_log_s = -float("inf")
        self._suppressed_send_errors = 0
        # statustext
        self._last_status_s = -float("inf")
        self._pending: _PendingStatus | None = None
        self._status_sent = 0
        self._status_coalesced = 0
        self._vision_reset_counter = 0
        self._last_provenance: Provenance | None = None
        # vision frame (see the module docstring)
        self._origin_sent_at: float | None = None
        self._origin_sent = 0
        self._vision_withheld = 0
        # positions not sent (see the module docstring): the count, and the reason of the current stretch
        self._positions_withheld = 0
        self._withheld_now: dict[str, str | None] = {}
        self._ap_origin: tuple[float, float, float] | None = None
        self._ap_frame: LocalTangentPlane | None = None  # the autopilot's frame, or our ltp when they agree
        self._last_vision_frame: LocalTangentPlane | None = None
        self._last_vision_state: EstimatorState | None = None
        self._last_timesync_s = -float("inf")
        #: Why the altitude is not given to the autopilot (None: it is); ``distrust_altitude``.
        self._alt_distrust: str | None = None
        #: Why GLOBAL_POSITION_SENSOR is held back whatever the state (None: it is not);
        #: ``hold_global_position_sensor``.
        self._agp_hold: str | None = None
        # the autopilot's address on a listening link (see the module docstring)
        self._ap_address_followed = False  # an address was followed on this transport
        self._ap_heard_s = -float("inf")  # its last valid message with the autopilot's ids (clock)
        self._impostor_messages = 0
        self._impostor_unreported = 0
        self._impostor_reported_s = -float("inf")
        # TIMESYNC answers
        self._timesync_answered_s = -float("inf")
        self._timesync_answered = 0
        self._timesync_ignored = 0

    # --- lifecycle ----------------------------------------------------------------------------------
    def attach(self, fdr: FdrClient | None, ltp: LocalTangentPlane | None) -> None:
        """Give a link made with ``frame_later`` the daemon's FDR and local frame, once they exist."""
        if _VISION_OUTPUT in self._config.outputs and ltp is None:
            raise _no_frame(self._config)
        with self._lock:
            self._fdr = fdr
            self._ltp = ltp

    def attach_fdr(self, fdr: FdrClient | None) -> None:
        """Give a link made with ``frame_later`` its FDR alone (the navigator core's, before it knows the
        frame its worker's filter is in)."""
        with self._lock:
            self._fdr = fdr

    def open(self) -> None:
        """Validate the config (URL, signing key, a UDP listen port nobody else holds) and connect.
        Raises ``MavlinkConfigError`` for a configuration that cannot work; a transport failure only
        schedules a reconnect. A second call (the link opened before start-up finished) does nothing."""
        if self._opened:
            return
        _validate_url(self._config.url)
        if self._config.signing_key_file is not None:
            self._signing_key = load_signing_key(self._config.signing_key_file)
        _refuse_taken_udp_port(self._config.url)
        with self._lock:
            self._opened = True
            self._connect(self._clock())

    def _connect(self, now: float) -> bool:
        cfg = self._config
        try:
            conn = open_transport(
                cfg.url, baud=cfg.baud, source_system=cfg.system_id, source_component=cfg.component_id
            )
        except (OSError, ValueError) as exc:
            self._schedule_reconnect(now, reason=f"connect failed: {exc}")
            return False
        if isinstance(conn, mavutil.mavtcp):
            # pymavlink prints and swallows EOF/reset on TCP; turn them into an exception poll() sees.
            conn.handle_eof = _raise_peer_closed
            conn.handle_disconnect = _raise_peer_closed
        if isinstance(conn, mavutil.mavudp) and conn.udp_server:
            # pymavlink bound with SO_REUSEADDR; clearing it now makes any later bind of this port fail
            # (EADDRINUSE) instead of silently taking the autopilot's datagrams from us.
            with contextlib.suppress(OSError):
                conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 0)
        if self._signing_key is not None:
            conn.setup_signing(
                self._signing_key,
                sign_outgoing=True,
                allow_unsigned_callback=_allow_unsigned,
                link_id=self._signing_link_id,
            )
        self._conn = conn
        self._ap_address_followed = False  # a new transport learns the autopilot's address afresh
        self._backoff_s = RECONNECT_BACKOFF_INITIAL_S
        self._next_reconnect_s = None
        _log.info(LogEvent.MAVLINK_CONNECTED, url=cfg.url, signed=self._signing_key is not None)
        self._record_event("connected", url=cfg.url, signed=self._signing_key is not None)
        return True

    def close(self) -> None:
        """Close the connection; later sends are dropped and polls return 0."""
        with self._lock:
            self._opened = False
            self._drop_connection()
            self._next_reconnect_s = None

    def _drop_connection(self) -> None:
        conn, self._conn = self._conn, None
        if conn is not None:
            with contextlib.suppress(OSError):
                conn.close()

    def fileno(self) -> int | None:
        """File descriptor to watch for input (changes after a reconnect), or None while down."""
        with self._lock:
            conn = self._conn
        if conn is None:
            return None
        fd = getattr(conn, "fd", None)
        if fd is None and hasattr(conn, "port") and hasattr(conn.port, "fileno"):
            with contextlib.suppress(OSError, ValueError):
                fd = conn.port.fileno()
        return fd if isinstance(fd, int) and fd >= 0 else None

    @property
    def connected(self) -> bool:
        return self._conn is not None

    @property
    def tracker(self) -> VehicleStateTracker:
        return self._tracker

    def relay_autopilot_to(self, relay: Callable[[Any], None] | None) -> None:
        """Hand every message the tracker takes from the autopilot (an impostor's never) to ``relay`` as
        well, on the polling thread, after the tracker (the navigator core relays them to its vision
        worker). None: stop."""
        self._relay = relay

    # --- receive ------------------------------------------------------------------------------------
    def poll(self) -> int:
        """Handle every pending input message without blocking; returns how many were decoded.

        Also: reconnect when due, report heartbeat loss/recovery, send a due coalesced STATUSTEXT.
        """
        now = self._clock()
        count = 0
        with self._lock:
            reconnect_due = self._next_reconnect_s is not None and now >= self._next_reconnect_s
            if self._opened and self._conn is None and reconnect_due:
                self._reconnects += 1
                self._connect(now)
            conn = self._conn
            if conn is not None:
                listening = isinstance(conn, (AutopilotUdpIn, AutopilotTcpIn))
                try:
                    for _ in range(MAX_MESSAGES_PER_POLL):
                        msg = conn.recv_msg()
                        if msg is None:
                            break
                        if msg.get_type() == "BAD_DATA":
                            self._bad += 1
                            continue
                        count += 1
                        recv_s = self._clock()  # each message at its own arrival: the clock's bound
                        if listening and self._claims_autopilot(msg):
                            if not self._autopilot_message(conn, msg, recv_s):
                                continue  # an impostor's: ignored, counted, reported
                        else:
                            self._tracker.handle(msg, recv_s)
                        if self._relay is not None:
                            self._relay(msg)
                        if msg.get_type() == "TIMESYNC":
                            self._answer_timesync(msg, recv_s, from_autopilot=self._from_autopilot(conn))
                except (OSError, _PeerClosed) as exc:
                    self._drop_connection()
                    self._schedule_reconnect(now, reason=f"receive failed: {exc}")
            self._received += count
        self._check_liveness(now)
        self._maybe_request_timesync(now)
        self._maybe_send_origin(now)
        self._flush_pending_status(now)
        return count

    def hold_global_position_sensor(self, reason: str | None) -> None:
        """Send no GLOBAL_POSITION_SENSOR while ``reason`` (None: send as the rule allows): PX4's
        parameters not checked yet, or an ``EKF2_AGP0_ID`` that is not the message's id
        (``px4_params``)."""
        self._agp_hold = reason

    @property
    def global_position_sensor_hold(self) -> str | None:
        """Why GLOBAL_POSITION_SENSOR is held back now (None: it is not)."""
        return self._agp_hold

    @property
    def altitude_distrust(self) -> str | None:
        """Why GPS_INPUT's altitude is flagged as ignored now (None: it is not)."""
        return self._alt_distrust

    def distrust_altitude(self, reason: str | None) -> None:
        """Flag GPS_INPUT's altitude as ignored while ``reason`` (None: give it again)."""
        self._alt_distrust = reason

    def _maybe_request_timesync(self, now: float) -> None:
        """Keep the autopilot's clock mapped: a TIMESYNC request while its link is alive."""
        ap_clock = self._tracker.autopilot_clock
        fast = ap_clock.answers < TIMESYNC_FAST_ANSWERS
        interval = TIMESYNC_FAST_INTERVAL_S if fast else TIMESYNC_SLOW_INTERVAL_S
        if now - self._last_timesync_s < interval or not self._tracker.link_alive(now):
            return
        self._last_timesync_s = now
        ts1_ns = ap_clock.request(int(self._clock() * 1e6))
        self._build_and_send(lambda mav: messages.timesync(mav, tc1_ns=0, ts1_ns=ts1_ns))

    def _answer_timesync(self, msg: Any, recv_s: float, *, from_autopilot: bool) -> None:
        """Answer the autopilot's own TIMESYNC request (ArduPilot sends one every 10 s and logs the
        round trip), with our receive time: only one from its system and component ids and its address,
        at most one per ``TIMESYNC_ANSWER_MIN_INTERVAL_S`` (a flood of requests must not crowd out the
        estimates). Answers to our own requests (``tc1`` != 0) are the tracker's."""
        if int(msg.tc1) != 0:
            return
        if (
            not from_autopilot
            or not self._claims_autopilot(msg)
            or recv_s - self._timesync_answered_s < TIMESYNC_ANSWER_MIN_INTERVAL_S
        ):
            self._timesync_ignored += 1
            return
        self._timesync_answered_s = recv_s
        self._timesync_answered += 1
        ts1 = int(msg.ts1)
        self._build_and_send(lambda mav: messages.timesync(mav, tc1_ns=int(recv_s * 1e9), ts1_ns=ts1))

    def _claims_autopilot(self, msg: Any) -> bool:
        """``msg`` carries the configured autopilot's system id and component 1."""
        return bool(
            msg.get_srcSystem() == self._config.autopilot_system_id
            and msg.get_srcComponent() == AUTOPILOT_COMPONENT_ID
        )

    @staticmethod
    def _from_autopilot(conn: Any) -> bool:
        """The last message came from the autopilot's address (a link with one peer: always)."""
        if isinstance(conn, (AutopilotUdpIn, AutopilotTcpIn)):
            return conn.source_is_autopilot()
        return True

    def _autopilot_message(self, conn: AutopilotUdpIn | AutopilotTcpIn, msg: Any, recv_s: float) -> bool:
        """A message with the autopilot's ids on a listening link: handled when it is the autopilot's
        (from its address; the first address; or a new one after the old fell silent, on its HEARTBEAT),
        and True; an impostor's is counted and reported, and False (module docstring)."""
        if conn.source_is_autopilot():
            self._ap_heard_s = recv_s
            self._tracker.handle(msg, recv_s)
            return True
        if not self._ap_address_followed:
            # no address yet: the first valid message of the autopilot's gives it
            if self._tracker.handle(msg, recv_s):
                self._follow_autopilot(conn, msg, recv_s)
            return True
        silent_s = recv_s - self._ap_heard_s
        if (
            (not conn.autopilot_known or silent_s > self._config.link_timeout_s)
            and msg.get_type() == "HEARTBEAT"
            and (self._signing_key is None or msg.get_signed())
            and self._tracker.handle(msg, recv_s)
        ):
            self._follow_autopilot(conn, msg, recv_s)
            return True
        self._impostor(conn, msg, recv_s)
        return False

    def _follow_autopilot(self, conn: AutopilotUdpIn | AutopilotTcpIn, msg: Any, recv_s: float) -> None:
        """Send to where ``msg``, a message the tracker used from the configured autopilot, came from (a
        signed one when signing is on); logged and recorded when that moves."""
        if self._signing_key is not None and not msg.get_signed():
            return
        address = conn.follow_source()
        self._ap_address_followed = True
        self._ap_heard_s = recv_s
        if address is not None:
            _log.info(LogEvent.MAVLINK_AUTOPILOT_ADDRESS, url=self._config.url, address=address)
            self._record_event("autopilot_address", address=address)

    def follow_autopilot_at(self, host: str, port: int) -> bool:
        """The autopilot speaks from ``host:port`` from now on (a listening UDP link; False otherwise):
        what a trusted side channel says, never a datagram. A vision worker's new navigator core tells
        its relay's address over the worker's Unix socket (``daemon/core.py``), so the worker need not
        wait out ``link_timeout_s`` of the dead core's silence. Logged and recorded."""
        with self._lock:
            conn = self._conn
            if not isinstance(conn, AutopilotUdpIn):
                return False
            address = conn.follow((host, port))
            self._ap_address_followed = True
            self._ap_heard_s = self._clock()
        if address is not None:
            _log.info(LogEvent.MAVLINK_AUTOPILOT_ADDRESS, url=self._config.url, address=address, told=True)
            self._record_event("autopilot_address", address=address)
        return True

    def _impostor(self, conn: AutopilotUdpIn | AutopilotTcpIn, msg: Any, recv_s: float) -> None:
        """Count a message from another address that claims the autopilot's ids; report them at most once
        per ``IMPOSTOR_REPORT_INTERVAL_S`` (log, FDR, STATUSTEXT to the ground through the autopilot)."""
        self._impostor_messages += 1
        self._impostor_unreported += 1
        if recv_s - self._impostor_reported_s < IMPOSTOR_REPORT_INTERVAL_S:
            return
        self._impostor_reported_s = recv_s
        source = conn.source_label()
        fields = {
            "source": source,
            "msg_type": msg.get_type(),
            "messages": self._impostor_messages,
            "since_last_report": self._impostor_unreported,
            "autopilot_silent_s": round(min(recv_s - self._ap_heard_s, 1e6), 3),
        }
        self._impostor_unreported = 0
        _log.warning(LogEvent.MAVLINK_IMPOSTOR, url=self._config.url, **fields)
        self._record_event(LINK_EVENT_IMPOSTOR, **fields)
        text = IMPOSTOR_STATUSTEXT.format(source=source, messages=self._impostor_messages)
        self.send_statustext(DIALECT.MAV_SEVERITY_CRITICAL, text)

    def _schedule_reconnect(self, now: float, *, reason: str) -> None:
        delay = self._backoff_s * (1.0 + self._rng.uniform(-RECONNECT_JITTER_FRAC, RECONNECT_JITTER_FRAC))
        self._next_reconnect_s = now + delay
        self._backoff_s = min(self._backoff_s * 2.0, RECONNECT_BACKOFF_MAX_S)
        self._report_lost(reason=reason, retry_in_s=round(delay, 3))

    def _report_lost(self, **fields: object) -> None:
        if self._outage:
            return
        self._outage = True
        _log.warning(LogEvent.MAVLINK_LINK_LOST, url=self._config.url, **fields)
        self._record_event("link_lost", **fields)

    def _check_liveness(self, now: float) -> None:
        alive = self._tracker.link_alive(now)
        if alive and not self._was_alive:
            if self._outage:
                _log.info(LogEvent.MAVLINK_LINK_RESTORED, url=self._config.url)
                self._record_event("link_restored")
            self._outage = False
        elif not alive and self._was_alive:
            with self._lock:
                self._report_lost(reason="heartbeat timeout")
        self._was_alive = alive

    # --- send ---------------------------------------------------------------------------------------
    def _send(self, msg: Any) -> bool:
        """Send one message; never raises. Returns True when handed to the transport."""
        return self._transmit(lambda conn: conn.mav.send(msg), msg)

    def send_raw(self, buf: bytes) -> bool:
        """Send an already encoded (and, on a signed link, signed) MAVLink message as it is: what the
        navigator core relays from its vision worker. Never raises; True when handed to the transport."""
        return self._transmit(lambda conn: conn.write(buf), "relayed")

    def _transmit(self, write: Callable[[Any], object], what: Any) -> bool:
        """``write(conn)`` under the lock, counted; a transport failure drops the connection and schedules
        a reconnect, any other (an encoding bug) is counted and logged: never raised."""
        with self._lock:
            conn = self._conn
            if conn is None:
                self._dropped_down += 1
                return False
            try:
                write(conn)
            except (OSError, _PeerClosed) as exc:
                self._drop_connection()
                self._schedule_reconnect(self._clock(), reason=f"send failed: {exc}")
                self._count_send_error(exc, what)
                return False
            except Exception as exc:  # an encoding bug must not take the pipeline down; counted + logged
                self._count_send_error(exc, what)
                return False
            self._sent += 1
            return True

    def _count_send_error(self, exc: BaseException, msg: Any) -> None:
        self._send_errors += 1
        now = self._clock()
        if now - self._last_send_error_log_s >= SEND_ERROR_LOG_INTERVAL_S:
            _log.warning(
                LogEvent.MAVLINK_SEND_ERROR,
                msg_type=getattr(msg, "msgname", type(msg).__name__),
                error=repr(exc),
                suppressed=self._suppressed_send_errors,
                total=self._send_errors,
            )
            self._last_send_error_log_s = now
            self._suppressed_send_errors = 0
        else:
            self._suppressed_send_errors += 1

    def _build_and_send(self, build: Callable[[Any], Any]) -> bool:
        with self._lock:
            conn = self._conn
            if conn is None:
                self._dropped_down += 1
                return False
            try:
                msg = build(conn.mav)
            except Exception as exc:  # bad input to a builder: counted + logged, never raised
                self._count_send_error(exc, build)
                return False
            return self._send(msg)

    def time_boot_ms(self) -> int:
        """Milliseconds since this link object was created (our own "boot" for NAMED_VALUE times)."""
        return int((time.monotonic() - self._boot_monotonic) * 1000) & 0xFFFFFFFF

    def send_heartbeat(self, system_status: int = DIALECT.MAV_STATE_ACTIVE) -> bool:
        """Our HEARTBEAT (onboard controller, no autopilot, component ``config.component_id``)."""
        ok = self._build_and_send(lambda mav: messages.heartbeat(mav, system_status))
        self._flush_pending_status(self._clock())
        return ok

    def send_estimate(
        self, state: EstimatorState, *, time_unix_usec: int, gps_fix_type: int | None = None
    ) -> int:
        """Send ``config.outputs`` for ``state`` stamped ``time_unix_usec`` (the time the state is valid
        for); returns the number of messages handed to the transport (0 while the link is down).
        ``gps_fix_type``: GPS_INPUT's fix_type as the output stream decided it (``messages.Fix3dGate``);
        None: the pure rule for this state alone."""
        sent = 0
        with self._lock:
            if (
                self._last_provenance is Provenance.NO_ESTIMATE
                and state.provenance is not Provenance.NO_ESTIMATE
            ):
                self.reset_vision_counter()  # re-initialised
            self._last_provenance = state.provenance
        processing_usec = max(0, int(self._clock() * 1e6) - int(state.time_unix_usec))
        for output in self._config.outputs:
            if output == "gps_input":
                sent += self._build_and_send(
                    lambda mav: messages.gps_input(
                        mav,
                        state,
                        time_unix_usec=time_unix_usec,
                        fix_type=gps_fix_type,
                        gps_id=self._config.gps_input_gps_id,
                        alt_trusted=self._alt_distrust is None,
                    )
                )
            elif output == "global_position_sensor":
                reason = self._global_position_sensor_withheld(state)
                if reason is not None:
                    self._note_withheld(output, reason)
                    continue
                sent += self._build_and_send(
                    lambda mav: messages.global_position_sensor(
                        mav,
                        state,
                        time_unix_usec=time_unix_usec,
                        processing_time_usec=processing_usec,
                        target_system=self._config.autopilot_system_id,
                        sensor_id=self._config.global_position_sensor_id,
                    )
                )
                self._note_withheld(output, None)
            elif output == _VISION_OUTPUT:
                reason = messages.withheld_reason(state)
                if reason is not None:
                    with self._lock:
                        self._last_vision_state = None
                    self._note_withheld(output, reason)
                    continue
                sent += self._send_vision(state, time_unix_usec)
                self._note_withheld(output, None)
        return sent

    def _global_position_sensor_withheld(self, state: EstimatorState) -> str | None:
        """Why GLOBAL_POSITION_SENSOR waits for ``state`` (None: it goes; see the module docstring)."""
        reason = messages.global_position_sensor_withheld(state)
        if reason is None and self._agp_hold is not None:
            reason = self._agp_hold
        if reason is None and self._alt_distrust is not None and self._tracker.gps_origin() is None:
            reason = f"altitude distrusted ({self._alt_distrust}) and the autopilot reports no origin yet"
        return reason

    def _note_withheld(self, output: str, reason: str | None) -> None:
        """Count a position message not sent (``reason``), and record a stretch's start and end once."""
        with self._lock:
            if reason is not None:
                self._positions_withheld += 1
            if reason == self._withheld_now.get(output):
                return
            self._withheld_now[output] = reason
        if reason is None:
            _log.info(LogEvent.MAVLINK_OUTPUT_WITHHELD, output=output, withheld=False)
            self._record_event("output_resumed", output=output)
        else:
            _log.warning(LogEvent.MAVLINK_OUTPUT_WITHHELD, output=output, withheld=True, reason=reason)
            self._record_event("output_withheld", output=output, reason=reason)

    def _send_vision(self, state: EstimatorState, time_unix_usec: int) -> int:
        """One VISION_POSITION_ESTIMATE in the frame shared with the autopilot, or none (see the module
        docstring); bumps reset_counter on a frame change or a jump (``messages.vision_position_jumped``)."""
        self._maybe_send_origin(self._clock())
        with self._lock:
            position_ok = bool(np.all(np.isfinite(np.asarray(state.pos_ned_m, dtype=np.float64))))
            if not position_ok or self._ltp is None:
                self._last_vision_state = None
                return 0
            frame = self._vision_frame()
            if frame is None:
                self._vision_withheld += 1
                self._last_vision_state = None
                return 0
            frame_changed = self._last_vision_frame is not None and frame != self._last_vision_frame
            previous = self._last_vision_state
            if frame_changed or (previous is not None and messages.vision_position_jumped(previous, state)):
                self.reset_vision_counter()
            self._last_vision_frame = frame
            self._last_vision_state = state
            pos = messages.ned_in_frame(state.pos_ned_m, self._ltp, frame)
            counter = self._vision_reset_counter
        return int(
            self._build_and_send(
                lambda mav: messages.vision_position_estimate(
                    mav, state, time_usec=time_unix_usec, reset_counter=counter, pos_ned_m=pos
                )
            )
        )

    def _sync_autopilot_origin(self) -> tuple[float, float, float] | None:
        """Follow the autopilot's reported GPS_GLOBAL_ORIGIN; returns it (None while unknown)."""
        reported = self._tracker.gps_origin()
        with self._lock:
            if reported == self._ap_origin:
                return reported
            if reported is None:  # forgotten after an autopilot reboot: offer ours again, at once
                self._ap_origin, self._ap_frame, self._origin_sent_at = None, None, None
                return None
            own = self._ltp
            if own is None:  # no vision output configured: nothing to re-express
                return reported
            theirs = LocalTangentPlane(*reported)
            offset_m = float(np.linalg.norm(own.to_ned(*reported)))
            self._ap_origin = reported
            self._ap_frame = own if offset_m <= ORIGIN_MATCH_TOLERANCE_M else theirs
            fields = {
                "lat_deg": reported[0],
                "lon_deg": reported[1],
                "alt_amsl_m": reported[2],
                "offset_from_ours_m": round(offset_m, 3),
                "frame": "daemon" if self._ap_frame is own else "autopilot",
            }
            if self._ap_frame is own:
                _log.info(LogEvent.MAVLINK_VISION_FRAME, **fields)
            else:
                _log.warning(
                    LogEvent.MAVLINK_VISION_FRAME,
                    reason="the autopilot already has another origin; positions are re-expressed in it",
                    **fields,
                )
            self._record_event("vision_frame", **fields)
            return reported

    def _vision_frame(self) -> LocalTangentPlane | None:
        """The frame VISION_POSITION_ESTIMATE goes out in now, or None when none is shared yet."""
        if self._sync_autopilot_origin() is not None:
            return self._ap_frame
        return self._ltp if self._origin_sent_at is not None else None

    def _maybe_send_origin(self, now: float) -> None:
        """Offer our origin (SET_GPS_GLOBAL_ORIGIN + a request for GPS_GLOBAL_ORIGIN) when due."""
        if self._ltp is None or _VISION_OUTPUT not in self._config.outputs:
            return
        if self._sync_autopilot_origin() is not None or not self._tracker.link_alive(now):
            return
        ltp = self._ltp
        cfg = self._config
        with self._lock:
            last = self._origin_sent_at
            if last is not None and now - last < SET_GPS_GLOBAL_ORIGIN_INTERVAL_S:
                return
            sent = self._build_and_send(
                lambda mav: messages.set_gps_global_origin(
                    mav, ltp, target_system=cfg.autopilot_system_id, time_usec=int(now * 1e6)
                )
            )
            if not sent:
                return
            self._build_and_send(
                lambda mav: messages.request_message(
                    mav,
                    target_system=cfg.autopilot_system_id,
                    target_component=AUTOPILOT_COMPONENT_ID,
                    message_id=DIALECT.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN,
                )
            )
            self._origin_sent_at = now
            self._origin_sent += 1
            fields = {
                "lat_deg": ltp.origin_lat_deg,
                "lon_deg": ltp.origin_lon_deg,
                "alt_amsl_m": ltp.origin_alt_m,
                "count": self._origin_sent,
            }
        _log.info(LogEvent.MAVLINK_ORIGIN_SENT, **fields)
        self._record_event("origin_sent", **fields)

    def request_autopilot_estimate(self) -> bool:
        """Ask the autopilot for its position estimate, EKF status, GNSS accuracy and home now
        (MAV_CMD_REQUEST_MESSAGE for GPS_RAW_INT, GLOBAL_POSITION_INT, EKF_STATUS_REPORT and HOME_POSITION):
        the start-up rules and cross-checks in ``c5_estimator.prior`` (HOME_POSITION is otherwise streamed
        only every few seconds)."""
        target = self._config.autopilot_system_id

        def request(message_id: int) -> Callable[[Any], Any]:
            return lambda mav: messages.request_message(
                mav, target_system=target, target_component=AUTOPILOT_COMPONENT_ID, message_id=message_id
            )

        sent = [
            self._build_and_send(request(message_id))
            for message_id in (
                DIALECT.MAVLINK_MSG_ID_GPS_RAW_INT,
                DIALECT.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
                DIALECT.MAVLINK_MSG_ID_EKF_STATUS_REPORT,
                DIALECT.MAVLINK_MSG_ID_HOME_POSITION,
            )
        ]
        return all(sent)

    def request_params(self, names: tuple[str, ...]) -> bool:
        """Ask the autopilot for each parameter in ``names`` (PARAM_REQUEST_READ); the answers reach the
        tracker (``VehicleStateTracker.param``)."""
        target = self._config.autopilot_system_id

        def request(name: str) -> Callable[[Any], Any]:
            return lambda mav: mav.param_request_read_encode(
                target, AUTOPILOT_COMPONENT_ID, name.encode("ascii"), -1
            )

        return all([self._build_and_send(request(name)) for name in names])

    def request_flight_phase(self) -> bool:
        """Ask the autopilot for EXTENDED_SYS_STATE (its landed state) now (MAV_CMD_REQUEST_MESSAGE): the
        start-up rules in ``c5_estimator.prior`` must know whether the vehicle is in the air."""
        target = self._config.autopilot_system_id
        return self._build_and_send(
            lambda mav: messages.request_message(
                mav,
                target_system=target,
                target_component=AUTOPILOT_COMPONENT_ID,
                message_id=DIALECT.MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
            )
        )

    def send_status_values(
        self,
        *,
        provenance: Provenance,
        inliers: int,
        residual_px: float | None,
        horiz_sigma_m: float,
        frame_drops: int,
        fdr_health: FdrHealthState,
        integrity_refused: int = 0,
    ) -> int:
        """Send the NAMED_VALUE set the ground station shows (``messages.named_values``); returns the
        number handed to the transport."""
        with self._lock:
            conn = self._conn
            if conn is None:
                self._dropped_down += len(_NAMED_VALUE_NAMES)
                return 0
        sent = 0
        for msg in messages.named_values(
            conn.mav,
            time_boot_ms=self.time_boot_ms(),
            provenance=provenance,
            inliers=inliers,
            residual_px=residual_px,
            horiz_sigma_m=horiz_sigma_m,
            frame_drops=frame_drops,
            fdr_health=fdr_health,
            integrity_refused=integrity_refused,
        ):
            sent += self._send(msg)
        return sent

    def reset_vision_counter(self) -> int:
        """Bump VISION_POSITION_ESTIMATE.reset_counter (call when the estimate jumps); returns it."""
        with self._lock:
            self._vision_reset_counter = (self._vision_reset_counter + 1) & 0xFF
            return self._vision_reset_counter

    # --- status text --------------------------------------------------------------------------------
    def send_statustext(self, severity: int, text: str) -> bool:
        """One STATUSTEXT, not rate-limited (for one-off events such as start-up)."""
        return self._build_and_send(lambda mav: messages.statustext(mav, severity, text))

    def notify_provenance(self, old: Provenance | None, new: Provenance, text: str | None = None) -> None:
        """Report a provenance transition as STATUSTEXT, rate-limited to STATUSTEXT_MIN_INTERVAL_S; a
        transition inside the interval is coalesced (latest wins, count kept) and sent when allowed."""
        if text is None:
            text = f"GDN: {old.value if old else 'start'} -> {new.value}"
        severity = severity_for(new)
        now = self._clock()
        with self._lock:
            if self._pending is not None:
                self._pending = _PendingStatus(severity, text, self._pending.coalesced + 1)
                self._status_coalesced += 1
            else:
                self._pending = _PendingStatus(severity, text, 0)
        self._flush_pending_status(now)

    def _flush_pending_status(self, now: float) -> None:
        with self._lock:
            pending = self._pending
            if pending is None or now - self._last_status_s < STATUSTEXT_MIN_INTERVAL_S:
                return
            text = pending.text
            if pending.coalesced:
                suffix = f" (+{pending.coalesced})"
                text = messages.clip_statustext(text, messages.STATUSTEXT_MAX_BYTES - len(suffix)).decode()
                text += suffix
            if self._conn is None:
                return  # keep it pending until the link is back
            if self._build_and_send(lambda mav: messages.statustext(mav, pending.severity, text)):
                self._pending = None
                self._last_status_s = now
                self._status_sent += 1
                self._record_event("statustext", severity=pending.severity, text=text)

    # --- misc ---------------------------------------------------------------------------------------
    def _record_event(self, event: str, **fields: object) -> None:
        if self._fdr is not None:
            self._fdr.record(FdrKind.LINK_EVENT, {"event": event, **fields})

    def stats(self) -> LinkStats:
        with self._lock:
            return LinkStats(
                connected=self._conn is not None,
                messages_received=self._received,
                bad_packets=self._bad,
                messages_sent=self._sent,
                send_errors=self._send_errors,
                sends_dropped_link_down=self._dropped_down,
                reconnects=self._reconnects,
                statustext_sent=self._status_sent,
                statustext_coalesced=self._status_coalesced,
                global_origin_sent=self._origin_sent,
                vision_withheld=self._vision_withheld,
                positions_withheld=self._positions_withheld,
                impostor_messages=self._impostor_messages,
                timesync_answered=self._timesync_answered,
                timesync_ignored=self._timesync_ignored,
            )


def _raise_peer_closed(*_args: object) -> None:
    raise _PeerClosed("peer closed the connection")


def _allow_unsigned(_mav: Any, msg_id: int) -> bool:
    return msg_id in UNSIGNED_ALLOWED_MSG_IDS
