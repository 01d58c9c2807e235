"""What the CI autopilot emulators share: the UDP MAVLink server loop and the point-mass vehicle.

Both emulators (:mod:`~gps_denied_onboard.sitl.ap_emulator` for ArduPilot,
:mod:`~gps_denied_onboard.sitl.px4_emulator` for PX4) are test doubles of an autopilot's MAVLink side,
not autopilots. What they have in common is no autopilot's rule, only the plumbing of a double:

- :class:`UdpEmulator`: one MAVLink channel per UDP port on loopback, each answering the last address
  that sent it a datagram (like a serial port), broadcasts forwarded between channels, a handler per
  message type, and a fixed-rate loop in which the vehicle moves with the wall clock;
- :class:`PointMassVehicle`: a point mass with speed and acceleration limits whose tilt follows the
  commanded horizontal acceleration with a first-order lag, flat ground, no wind. Roll and pitch are the
  tilt that gives that acceleration; HIGHRES_IMU's specific force follows from it.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import select
import signal
import socket
import time
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Final

import numpy as np

GRAVITY_M_S2: Final[float] = 9.80665
#: Physics and fast-telemetry rate, Hz.
PHYSICS_HZ: Final[float] = 50.0
#: Time constant of the tilt (and so the acceleration) following the commanded acceleration, s
#: (ArduCopter ATC_INPUT_TC default; used for both doubles: nothing was measured on PX4's).
TILT_TAU_S: Final[float] = 0.15
#: Yaw rate towards the next target, rad/s.
YAW_RATE_RAD_S: Final[float] = math.radians(90.0)
#: Closer than this to its target, the vehicle keeps its heading, m.
YAW_HOLD_DISTANCE_M: Final[float] = 2.0


def wrap_pi(a: float) -> float:
    """``a`` in (-pi, pi]."""
    return math.atan2(math.sin(a), math.cos(a))


def param_id(raw: Any) -> str:
    """A MAVLink ``param_id`` (bytes or str, NUL-padded) as a str."""
    s = raw.decode("ascii", "replace") if isinstance(raw, bytes) else str(raw)
    return s.split("\x00", 1)[0]


def parse_home(text: str) -> tuple[float, float, float, float]:
    """``LAT,LON,ALT,HEADING`` as ArduPilot SITL's ``--home`` takes it."""
    parts = text.split(",")
    if len(parts) != 4:
        raise ValueError(f"--home {text!r}: expected LAT,LON,ALT_AMSL_M,HEADING_DEG (4 numbers)")
    try:
        lat, lon, alt, hdg = (float(p) for p in parts)
    except ValueError as exc:
        raise ValueError(f"--home {text!r}: expected 4 numbers") from exc
    if not (abs(lat) <= 90 and abs(lon) <= 180 and all(map(math.isfinite, (alt, hdg)))):
        raise ValueError(f"--home {text!r}: latitude/longitude out of range")
    return lat, lon, alt, hdg


def add_common_arguments(ap: argparse.ArgumentParser) -> None:
    """The options every emulator takes: where it stands, its channels, its boot parameters, its events."""
    ap.add_argument(
        "--home", required=True, help="LAT,LON,ALT_AMSL_M,HEADING_DEG (as ArduPilot SITL's --home)"
    )
    ap.add_argument("--port", type=int, action="append", help="UDP port of one MAVLink channel (repeatable)")
    ap.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a parameter as stored before boot (e.g. GPS2_TYPE=14; PX4: EKF2_AGP0_ID=1)",
    )
    ap.add_argument("--events", type=Path, default=None, help="write the events (JSON) here on exit")
    ap.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    ap.add_argument("--quiet", action="store_true")


def parse_params(texts: Sequence[str], known: Collection[str]) -> dict[str, float]:
    """``--param NAME=VALUE`` options as a mapping; ValueError names an unknown or malformed one."""
    params = {}
    for p in texts:
        name, _, value = p.partition("=")
        if name not in known:
            raise ValueError(f"--param {p!r}: unknown parameter; known: {', '.join(sorted(known))}")
        try:
            params[name] = float(value)
        except ValueError as exc:
            raise ValueError(f"--param {p!r}: the value is not a number") from exc
    return params


def serve(emu: UdpEmulator, duration_s: float | None, **announce: Any) -> int:
    """Run ``emu`` until SIGTERM/SIGINT or ``duration_s``, after one JSON line with its ports."""
    signal.signal(signal.SIGTERM, lambda *_: emu.stop())
    signal.signal(signal.SIGINT, lambda *_: emu.stop())
    print(json.dumps({"kind": "listening", "ports": emu.ports, **announce}), flush=True)
    try:
        emu.run(duration_s)
    finally:
        emu.close()
    return 0


def approach_velocity_ne(d_ne: np.ndarray, vmax_m_s: float, accel_m_s2: float) -> np.ndarray:
    """The horizontal velocity towards a target ``d_ne`` (north, east m) away: at most ``vmax_m_s``,
    slowing so that ``accel_m_s2`` stops it there, and at most 1.5 x the distance per second near it."""
    dist = float(np.hypot(*d_ne))
    if dist <= 1e-6:
        return np.zeros(2)
    speed = min(vmax_m_s, math.sqrt(2.0 * accel_m_s2 * dist), 1.5 * dist)
    return np.asarray(d_ne, dtype=float) / dist * speed


def geodetic(ltp: Any, ned: np.ndarray) -> tuple[float, float, float]:
    """(lat_deg, lon_deg, alt_m) of a NED point of ``ltp`` (a ``geo.LocalTangentPlane``)."""
    lat, lon, alt = ltp.to_geodetic(np.asarray(ned, dtype=float))
    return float(lat), float(lon), float(alt)


def send_highres_imu(mav: Any, time_usec: int, f_body: np.ndarray) -> None:
    """HIGHRES_IMU with the specific force ``f_body`` (m/s^2, FRD), no rates, standard pressure."""
    mav.highres_imu_send(
        time_usec, *(float(x) for x in f_body), 0, 0, 0, 0, 0, 0, 1013.25, 0, 0, 20.0, 0b111111
    )


def send_global_position_int(
    mav: Any,
    time_boot_ms: int,
    lat_lon_alt: tuple[float, float, float],
    height_m: float,
    vel_ned_m_s: np.ndarray,
    yaw_rad: float,
) -> None:
    """GLOBAL_POSITION_INT of a position (deg, deg, m AMSL), its height above home and velocity."""
    lat, lon, alt = lat_lon_alt
    v = vel_ned_m_s
    mav.global_position_int_send(
        time_boot_ms,
        round(lat * 1e7),
        round(lon * 1e7),
        round(alt * 1000),
        round(height_m * 1000),
        round(v[0] * 100),
        round(v[1] * 100),
        round(v[2] * 100),
        round(math.degrees(yaw_rad) % 360.0 * 100),
    )


@dataclass
class Channel:
    """One MAVLink channel: a UDP socket and the last address that sent it a datagram."""

    sock: socket.socket
    port: int
    peer: tuple[str, int] | None = None
    parser: Any = None


class PointMassVehicle:
    """The vehicle's truth (module docstring): NED at home, down = -height. Mixed into an emulator."""

    def _reset_vehicle(self, heading_deg: float) -> None:
        self.pos_ned = np.zeros(3)
        self.vel_ned = np.zeros(3)
        self.accel_ned = np.zeros(3)
        self.tilt_accel_ne = np.zeros(2)  # horizontal acceleration the current tilt gives, m/s^2
        self.yaw_rad = math.radians(heading_deg)
        self.roll_rad = self.pitch_rad = 0.0

    @property
    def on_ground(self) -> bool:
        return bool(self.pos_ned[2] >= -1e-3)

    def _turn_toward(self, d_ne: np.ndarray, dt: float) -> None:
        """Yaw towards ``d_ne`` at ``YAW_RATE_RAD_S`` while farther than ``YAW_HOLD_DISTANCE_M``."""
        if float(np.hypot(*d_ne)) > YAW_HOLD_DISTANCE_M:
            step = YAW_RATE_RAD_S * dt
            self.yaw_rad += float(np.clip(wrap_pi(math.atan2(d_ne[1], d_ne[0]) - self.yaw_rad), -step, step))

    def _integrate(
        self, want_v: np.ndarray, dt: float, accel_h_m_s2: float, accel_v_m_s2: float
    ) -> np.ndarray:
        """Move the vehicle ``dt`` s towards the velocity ``want_v`` (NED, m/s); returns the change of
        (roll, pitch) it made, rad.

        The commanded horizontal acceleration closes the velocity error in two tilt time constants (a
        damping of 0.7 with the tilt's lag), at most ``accel_h_m_s2``; the tilt, and with it the
        acceleration, follows it with a first-order lag. The vertical acceleration is at most
        ``accel_v_m_s2``. On the ground the vehicle stands still."""
        dv = want_v - self.vel_ned
        cmd_h = dv[:2] / max(2.0 * TILT_TAU_S, dt)
        n = float(np.hypot(*cmd_h))
        if n > accel_h_m_s2:
            cmd_h = cmd_h / n * accel_h_m_s2
        self.tilt_accel_ne = self.tilt_accel_ne + (cmd_h - self.tilt_accel_ne) * min(1.0, dt / TILT_TAU_S)
        dv_h = self.tilt_accel_ne * dt
        dv_z = float(np.clip(dv[2], -accel_v_m_s2 * dt, accel_v_m_s2 * dt))
        self.accel_ned = np.array([dv_h[0], dv_h[1], dv_z]) / dt
        self.vel_ned = self.vel_ned + self.accel_ned * dt
        self.pos_ned = self.pos_ned + self.vel_ned * dt
        if self.pos_ned[2] > 0.0:  # the ground
            self.pos_ned[2] = 0.0
            self.vel_ned[2] = min(self.vel_ned[2], 0.0)
            self.vel_ned[:2] = 0.0
            self.accel_ned[:] = 0.0
            self.tilt_accel_ne[:] = 0.0
        # roll/pitch from the horizontal acceleration, in the body frame
        cy, sy = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        a_fwd = cy * self.accel_ned[0] + sy * self.accel_ned[1]
        a_right = -sy * self.accel_ned[0] + cy * self.accel_ned[1]
        prev = np.array([self.roll_rad, self.pitch_rad])
        self.pitch_rad = -math.atan2(a_fwd, GRAVITY_M_S2)
        self.roll_rad = math.atan2(a_right, GRAVITY_M_S2)
        return np.array([self.roll_rad, self.pitch_rad]) - prev

    def _specific_force_body(self) -> np.ndarray:
        """What an accelerometer on the vehicle reads (body FRD, m/s^2): acceleration minus gravity."""
        from gps_denied_onboard.camera.types import Attitude

        r = Attitude(self.roll_rad, self.pitch_rad, self.yaw_rad).R_ned_body()
        return np.asarray(r.T @ (self.accel_ned - np.array([0.0, 0.0, GRAVITY_M_S2])))


class UdpEmulator:
    """The server side of a double (module docstring). Subclasses set ``_handlers`` (message type ->
    ``handler(self, msg, now_s)``) and implement :meth:`_before_physics`, :meth:`_step`, :meth:`_send_tick`
    and :meth:`_write_events`; :meth:`run` serves until :meth:`stop` or the duration."""

    _handlers: ClassVar[dict[str, Callable[[Any, Any, float], None]]] = {}

    def __init__(self, dialect: Any, ports: Sequence[int], *, quiet: bool) -> None:
        self._quiet = quiet
        self.events: list[dict[str, Any]] = []
        self._mav = dialect.MAVLink(self, srcSystem=1, srcComponent=1)
        self._mav.robust_parsing = True
        self._channels: list[Channel] = []
        for port in ports:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.bind(("127.0.0.1", port))
            sock.setblocking(False)
            parser = dialect.MAVLink(None, srcSystem=1, srcComponent=1)
            parser.robust_parsing = True
            self._channels.append(Channel(sock, int(sock.getsockname()[1]), parser=parser))
        self._out: Channel | None = None  # None = all channels
        self._running = True
        self._upload: dict[str, Any] | None = None
        #: Messages received that this double has no handler for, by type (PX4's GPS_INPUT, e.g.).
        self.unhandled: dict[str, int] = {}
        self.boot_unix_s = time.time()

    # --- transport ------------------------------------------------------------------------------
    def write(self, buf: bytes) -> None:
        """pymavlink's file interface: send to one channel (a reply) or to every channel with a peer."""
        targets = [self._out] if self._out is not None else self._channels
        for ch in targets:
            if ch.peer is not None:
                with contextlib.suppress(OSError):
                    ch.sock.sendto(buf, ch.peer)

    @property
    def ports(self) -> list[int]:
        return [c.port for c in self._channels]

    def stop(self) -> None:
        self._running = False

    def close(self) -> None:
        for c in self._channels:
            c.sock.close()

    # --- time, events, texts --------------------------------------------------------------------
    def now_s(self) -> float:
        """Seconds since boot."""
        return time.time() - self.boot_unix_s

    def boot_s(self) -> float:
        """The autopilot's own boot clock, s: what its messages and TIMESYNC answers are stamped with
        (``now_s`` runs the physics). The host's rate here; an emulator whose autopilot's clock runs
        otherwise says so by overriding it."""
        return self.now_s()

    def _boot_ms(self) -> int:
        return int(self.boot_s() * 1000) & 0xFFFFFFFF

    def _event(self, kind: str, **data: Any) -> None:
        ev = {"t_unix_s": round(time.time(), 3), "kind": kind, **data}
        self.events.append(ev)
        if not self._quiet:
            print(json.dumps(ev), flush=True)

    def _text(self, severity: int, text: str) -> None:
        """STATUSTEXT to every channel, also while answering one."""
        out, self._out = self._out, None
        try:
            self._mav.statustext_send(severity, text.encode()[:50])
        finally:
            self._out = out
        self._event("statustext", text=text)

    # --- the mission protocol: upload ------------------------------------------------------------
    def _on_mission_count(self, msg: Any) -> None:
        """MISSION_COUNT: ask for each item in turn (MISSION_REQUEST_INT); another mission type is refused."""
        if int(getattr(msg, "mission_type", 0)) != 0:
            self._mav.mission_ack_send(msg.get_srcSystem(), msg.get_srcComponent(), 1, msg.mission_type)
            return
        self._upload = {
            "count": int(msg.count),
            "items": [],
            "sys": msg.get_srcSystem(),
            "comp": msg.get_srcComponent(),
        }
        self._request_next()

    def _request_next(self) -> None:
        assert self._upload is not None
        seq = len(self._upload["items"])
        self._upload["asked_s"] = time.time()
        self._mav.mission_request_int_send(self._upload["sys"], self._upload["comp"], seq, 0)

    def _on_mission_item(self, msg: Any) -> None:
        """MISSION_ITEM_INT: the next item, or the last one (then MISSION_ACK accepted)."""
        up = self._upload
        if up is None or int(msg.seq) != len(up["items"]):
            return
        up["items"].append(msg)
        if len(up["items"]) < up["count"]:
            self._request_next()
            return
        self._upload = None
        self._mission_uploaded(list(up["items"]))
        self._mav.mission_ack_send(msg.get_srcSystem(), msg.get_srcComponent(), 0, 0)  # MAV_MISSION_ACCEPTED
        self._event("mission_uploaded", items=up["count"])

    def _upload_retry(self) -> None:
        """Ask again for an item not received within 1 s."""
        if self._upload is not None and time.time() - self._upload.get("asked_s", 0.0) > 1.0:
            self._request_next()

    def _mission_uploaded(self, items: list[Any]) -> None:
        """The whole mission has arrived (MISSION_ITEM_INT messages, by seq)."""
        raise NotImplementedError

    # --- the loop -------------------------------------------------------------------------------
    def _dispatch(self, ch: Channel, data: bytes, now: float) -> None:
        try:
            msgs = ch.parser.parse_buffer(data) or []
        except Exception:
            return
        for msg in msgs:
            mtype = msg.get_type()
            if mtype == "BAD_DATA":
                continue
            # MAVLink routing: a broadcast from one channel goes on to the others
            if getattr(msg, "target_system", 0) in (0, None) and len(self._channels) > 1:
                for other in self._channels:
                    if other is not ch and other.peer is not None:
                        with contextlib.suppress(OSError):
                            other.sock.sendto(msg.get_msgbuf(), other.peer)
            target = getattr(msg, "target_system", 0)
            if target not in (0, 1, None):
                continue
            handler = self._handlers.get(mtype)
            if handler is None:
                self.unhandled[mtype] = self.unhandled.get(mtype, 0) + 1
                continue
            self._out = ch
            try:
                handler(self, msg, now)
            finally:
                self._out = None

    def _before_physics(self, now: float) -> None:
        """Once a tick, before the vehicle moves."""

    def _step(self, dt: float, now: float) -> None:
        """Move the vehicle ``dt`` s."""
        raise NotImplementedError

    def _send_tick(self, k: int, now: float) -> None:
        """Once a tick (``k`` counts them at ``PHYSICS_HZ``), after the vehicle moved: the telemetry."""
        raise NotImplementedError

    def _write_events(self) -> None:
        """On exit."""

    def run(self, duration_s: float | None = None) -> None:
        dt = 1.0 / PHYSICS_HZ
        next_t = time.time()
        k = 0
        end = None if duration_s is None else time.time() + duration_s
        socks = {c.sock: c for c in self._channels}
        last_step = time.time()
        while self._running and (end is None or time.time() < end):
            timeout = max(0.0, next_t - time.time())
            ready, _, _ = select.select(list(socks), [], [], timeout)
            now = self.now_s()
            for s in ready:
                ch = socks[s]
                while True:
                    try:
                        data, addr = s.recvfrom(65535)
                    except (BlockingIOError, InterruptedError):
                        break
                    except OSError:
                        break
                    ch.peer = addr
                    self._dispatch(ch, data, now)
            if time.time() < next_t:
                continue
            # The vehicle moves with the wall clock: after a stall of this process (a loaded machine) it
            # is where its velocity took it, in sub-steps, so that the truth and the IMU stay consistent;
            # one catch-up burst of fixed steps would move it without any acceleration the IMU reported.
            wall = time.time()
            elapsed = min(max(wall - last_step, 0.0), 1.0)
            last_step = wall
            next_t += dt
            if next_t < wall:
                next_t = wall + dt  # behind: the next tick a full period from now, not a burst
            self._before_physics(now)
            n_sub = math.ceil(elapsed / dt - 1e-9)
            for _ in range(n_sub):
                self._step(elapsed / n_sub, now)
            self._send_tick(k, now)
            k += 1
        self._write_events()
