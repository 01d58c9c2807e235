"""SITL scenarios: a YAML flight script, loaded strictly, resolved over a map into a truth trajectory.

A scenario says where and how the simulated aircraft flies and what its nav camera sees; the runner
resolves it over the map it was given (``Scenario.resolve``) into a ``Trajectory`` whose ``truth_at(t_s)``
is the ground truth that frames are rendered from and that the daemon's output is scored against.

Input: a YAML mapping (or a bundled scenario's name). Output: a frozen ``Scenario``, or a ``ScenarioError``
naming the key path (``waypoints.points[2][2].alt_agl_m``) and what was expected: an unknown key, a wrong
type (a string for a number, a bool for an integer) or an out-of-range value is refused; integers are
accepted where a number is expected.

The vocabulary: the flight (``duration_s``, ``frame_rate_hz``, ``speed_m_s``, ``accel_m_s2``,
``alt_agl_m``, ``climb_rate_m_s``, ``turn_rate_deg_s``, ``ground_alt_amsl_m``, ``start_delay_s``,
``waypoints`` in ``map_relative`` or ``wgs84`` frames), the clocks (``autopilot_unix_offset_s``,
``camera_stamp_offset_s``), the camera (``camera``, ``attitude_wobble``, ``photometric``), and what goes
wrong (``map_edits``, ``link_drops``, ``map_gaps``, ``daemon_restarts``, ``faults``, including the host
faults of ``sitl.host_faults``, ``timestamp_faults``, and ``spoofed_start``: the start points dragged off
before the flight).

Every key, its type, default and meaning: docs/sitl.md, "The scenario schema in full".
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any, Final

import numpy as np
import yaml

from gps_denied_onboard.camera.types import Attitude, CameraCalibration
from gps_denied_onboard.geo import LocalTangentPlane

from .photometric import GapKind, PhotometricParams

#: Where the scenarios shipped with the package live (``demo``, ``smoke``, ``nominal_real``).
BUILTIN_SCENARIOS_DIR: Path = Path(__file__).resolve().parent / "scenarios"

#: Extra clearance added to the automatic margin, m.
_AUTO_MARGIN_EXTRA_M = 5.0
#: Ratio of the pitch wobble period to the roll period: irrational, so the two never lock into a pattern.
_PITCH_PERIOD_RATIO = 1.618
_PITCH_PHASE_RAD = 0.7


class ScenarioError(ValueError):
    """Invalid scenario. ``key_path`` is dotted, with list indices (``waypoints.points[1][0]``)."""

    def __init__(self, key_path: str, message: str, *, source: str | None = None) -> None:
        where = f"{source}: " if source else ""
        super().__init__(f"scenario error: {where}{key_path}: {message}")
        self.key_path = key_path
        self.source = source


class WaypointFrame(str, Enum):
    """How waypoint coordinates are given."""

    MAP_RELATIVE = "map_relative"
    WGS84 = "wgs84"


@dataclass(frozen=True)
class CameraSpec:
    """Ideal pinhole nav camera: image size, px, and horizontal field of view, degrees."""

    width_px: int = 640
    height_px: int = 480
    hfov_deg: float = 70.0

    def calibration(self) -> CameraCalibration:
        """The camera as the ``CameraCalibration`` the renderer and the daemon use."""
        return CameraCalibration.from_hfov(self.width_px, self.height_px, self.hfov_deg)


@dataclass(frozen=True)
class WobbleSpec:
    """Roll/pitch oscillation amplitudes, degrees, and the roll period, s."""

    roll_amp_deg: float = 0.0
    pitch_amp_deg: float = 0.0
    period_s: float = 7.0

    def roll_pitch_rad(self, t_s: float) -> tuple[float, float]:
        """(roll_rad, pitch_rad) at time ``t_s``."""
        w = 2.0 * math.pi / self.period_s
        roll = math.radians(self.roll_amp_deg) * math.sin(w * t_s)
        pitch = math.radians(self.pitch_amp_deg) * math.sin(w / _PITCH_PERIOD_RATIO * t_s + _PITCH_PHASE_RAD)
        return roll, pitch

    @property
    def max_tilt_rad(self) -> float:
        """Upper bound of the camera axis tilt from nadir, radians."""
        return math.radians(self.roll_amp_deg) + math.radians(self.pitch_amp_deg)


@dataclass(frozen=True)
class Waypoint:
    """One waypoint: (a, b) = (u, v) map fractions for ``map_relative``, (lat_deg, lon_deg) for ``wgs84``.

    ``alt_agl_m`` overrides the scenario altitude for the leg ending here (None = the scenario default).
    """

    a: float
    b: float
    alt_agl_m: float | None = None


@dataclass(frozen=True)
class WaypointLayout:
    """The path's waypoints and how to read them. ``margin_m`` None = automatic (map_relative only)."""

    frame: WaypointFrame
    points: tuple[Waypoint, ...]
    margin_m: float | None = None


class MapEditKind(str, Enum):
    FEATURELESS = "featureless"
    LOOKALIKE = "lookalike"


@dataclass(frozen=True)
class MapEdit:
    """A change to the daemon's map along the path fractions [path_from, path_to] (see ``map_edits``)."""

    kind: MapEditKind
    path_from: float
    path_to: float
    offset_m: tuple[float, float] = (0.0, 0.0)
    half_width_m: float | None = None


@dataclass(frozen=True)
class LinkDrop:
    """The autopilot link is cut for ``[from_s, to_s)``."""

    from_s: float
    to_s: float


#: The most busy processes a ``cpu_hogs`` fault may start (a typo must not fork-bomb the host).
MAX_CPU_HOGS: Final = 64


class FaultKind(str, Enum):
    CAMERA_STALL = "camera_stall"
    ATTITUDE_NAN = "attitude_nan"
    ATTITUDE_ABSENT = "attitude_absent"
    MAVLINK_FLOOD = "mavlink_flood"
    #: One well-formed MAVLink datagram from each of many fresh source ports (``rate_hz`` of them).
    SOURCE_FLOOD = "source_flood"
    #: Another UDP source port claiming the autopilot's system and component ids: its HEARTBEAT, hostile
    #: ATTITUDE (NaN, huge, out of order), SYSTEM_TIME going back, TIMESYNC requests, ``rate_hz`` a second.
    IMPOSTOR = "impostor"
    CORRUPT_FRAME = "corrupt_frame"
    BOMB_FRAME = "bomb_frame"
    WRONG_SIZE_FRAME = "wrong_size_frame"
    CLOCK_JUMP = "clock_jump"
    ORT_FAULT = "ort_fault"
    TILE_CORRUPT = "tile_corrupt"
    FDR_FULL = "fdr_full"
    ATTITUDE_OFFSET = "attitude_offset"
    #: ``processes`` busy processes at nice 0 on the daemon's host for the window (``sitl.host_faults``):
    #: a companion computer is rarely idle.
    CPU_HOGS = "cpu_hogs"

    @property
    def instant(self) -> bool:
        return self in _INSTANT_FAULTS

    @property
    def bad_frame(self) -> bool:
        """A malformed frame the camera sends (the other instants happen on the companion computer)."""
        return self in _BAD_FRAME_FAULTS


_BAD_FRAME_FAULTS = frozenset({FaultKind.CORRUPT_FRAME, FaultKind.BOMB_FRAME, FaultKind.WRONG_SIZE_FRAME})
_INSTANT_FAULTS = _BAD_FRAME_FAULTS | {FaultKind.CLOCK_JUMP, FaultKind.ORT_FAULT}


@dataclass(frozen=True)
class Fault:
    """One injected fault: a window ``[from_s, to_s)``, or an instant (``from_s == to_s == at_s``)."""

    kind: FaultKind
    from_s: float
    to_s: float
    reconnect: bool = False
    rate_hz: float = 500.0
    #: ``clock_jump``: the wall clock's step, s.
    step_s: float = 0.0
    #: ``ort_fault``: ONNX Runtime runs to refuse.
    count: int = 0
    #: ``attitude_offset``: (roll, pitch, yaw) added to the autopilot's ATTITUDE, degrees.
    offset_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: ``cpu_hogs``: busy processes.
    processes: int = 0


class SpoofedSource(str, Enum):
    """What a spoofed start drags off (``SpoofedStart.sources``)."""

    #: HOME_POSITION, as the autopilot sends it (unsigned: the SITL link has no signing).
    HOME = "home"
    #: The autopilot's own position while on the ground (GLOBAL_POSITION_INT, GPS_RAW_INT, EKF_STATUS_REPORT).
    AUTOPILOT = "autopilot"
    #: The daemon's configured start (``init.lat_deg``/``lon_deg``, with ``init.sigma_m`` the stated sigma).
    CONFIG = "config"
    #: At each of the scenario's ``daemon_restarts``: the resume state file, rewritten after the kill as if
    #: the killed run's last 3D estimate had been there (the truth then, dragged), stating ``sigma_m``.
    RESUME = "resume"


@dataclass(frozen=True)
class SpoofedStart:
    """The start points dragged ``offset_ne_m`` (north, east) off the truth before the flight, each stating
    ``sigma_m``: a GNSS spoofed before the denial drags the autopilot's position, its HOME and the last
    fix an operator configures alike; a spoofed HOME_POSITION alone is an injection on the link."""

    offset_ne_m: tuple[float, float]
    sigma_m: float
    sources: frozenset[SpoofedSource]


@dataclass(frozen=True)
class TimestampFault:
    """The first frame exposed at or after ``at_s`` is stamped ``ahead_s`` seconds off the truth."""

    at_s: float
    ahead_s: float


@dataclass(frozen=True)
class MapGap:
    """Frames exposed in ``[from_s, to_s)`` are degraded as ``kind``."""

    from_s: float
    to_s: float
    kind: GapKind


@dataclass(frozen=True)
class TruthState:
    """Ground truth of the simulated aircraft at one instant.

    Position: WGS84 ``lat_deg``/``lon_deg``, ``alt_amsl_m`` above mean sea level and ``alt_agl_m`` above the
    flat ground. ``vel_ned_m_s``: (3,) float64 read-only, NED m/s. Attitude: body FRD in NED, ZYX
    roll/pitch/yaw in radians (MAVLink ATTITUDE convention), yaw in (-pi, pi], 0 = north, pi/2 = east.
    """

    t_s: float
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    alt_agl_m: float
    vel_ned_m_s: np.ndarray = field(compare=False)
    roll_rad: float
    pitch_rad: float
    yaw_rad: float

    @property
    def attitude(self) -> Attitude:
        return Attitude(self.roll_rad, self.pitch_rad, self.yaw_rad)


# --------------------------------------------------------------------------------------------------------
# Path geometry (local NED metres, horizontal only)


@dataclass(frozen=True)
class _Line:
    s0_m: float
    length_m: float
    start_ne: tuple[float, float]
    heading_rad: float

    def at(self, ds: float) -> tuple[float, float, float]:
        c, s = math.cos(self.heading_rad), math.sin(self.heading_rad)
        return self.start_ne[0] + ds * c, self.start_ne[1] + ds * s, self.heading_rad


@dataclass(frozen=True)
class _Arc:
    s0_m: float
    length_m: float
    centre_ne: tuple[float, float]
    radius_m: float
    heading0_rad: float
    #: +1 = right turn (heading increases), -1 = left turn.
    sign: float

    def at(self, ds: float) -> tuple[float, float, float]:
        psi = self.heading0_rad + self.sign * ds / self.radius_m
        # The centre lies on the right (sign +1) or left normal of the track; the aircraft is opposite.
        n = self.centre_ne[0] + self.sign * self.radius_m * math.sin(psi)
        e = self.centre_ne[1] - self.sign * self.radius_m * math.cos(psi)
        return n, e, psi


def _profile_duration_s(length_m: float, v_m_s: float, a_m_s2: float) -> float:
    """Time to fly ``length_m`` from rest to rest with cruise speed v and acceleration a, s."""
    ramp_m = v_m_s * v_m_s / (2.0 * a_m_s2)
    if length_m <= 2.0 * ramp_m:
        return 2.0 * math.sqrt(length_m / a_m_s2)
    return 2.0 * v_m_s / a_m_s2 + (length_m - 2.0 * ramp_m) / v_m_s


def _profile_at(tau_s: float, length_m: float, v_m_s: float, a_m_s2: float) -> tuple[float, float]:
    """(distance along the path m, speed m/s) at ``tau_s`` after leaving the hold: a trapezoidal speed
    profile (triangular when the path is shorter than the two ramps), at rest before and after."""
    if tau_s <= 0.0:
        return 0.0, 0.0
    v = min(v_m_s, math.sqrt(a_m_s2 * length_m))  # peak speed of a triangular profile
    t_ramp = v / a_m_s2
    d_ramp = 0.5 * a_m_s2 * t_ramp * t_ramp
    t_cruise = max(0.0, (length_m - 2.0 * d_ramp) / v)
    total = 2.0 * t_ramp + t_cruise
    if tau_s >= total:
        return length_m, 0.0
    if tau_s < t_ramp:
        return 0.5 * a_m_s2 * tau_s * tau_s, a_m_s2 * tau_s
    if tau_s < t_ramp + t_cruise:
        return d_ramp + v * (tau_s - t_ramp), v
    rest = total - tau_s
    return length_m - 0.5 * a_m_s2 * rest * rest, a_m_s2 * rest


def _time_at_distance_s(s_m: float, length_m: float, v_m_s: float, a_m_s2: float) -> float:
    """Inverse of ``_profile_at`` (bisection; the profile is monotonic)."""
    lo, hi = 0.0, _profile_duration_s(length_m, v_m_s, a_m_s2)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if _profile_at(mid, length_m, v_m_s, a_m_s2)[0] < s_m:
            lo = mid
        else:
            hi = mid
    return hi


def _wrap_pi(angle_rad: float) -> float:
    """Angle to (-pi, pi]."""
    a = math.fmod(angle_rad + math.pi, 2.0 * math.pi)
    if a <= 0.0:
        a += 2.0 * math.pi
    return a - math.pi


def _build_path(
    points_ne: np.ndarray, turn_radius_m: float
) -> tuple[tuple[_Line | _Arc, ...], list[float], float]:
    """Lines joined by tangent arcs at the interior waypoints.

    Returns the segments, the along-path distance at which each waypoint is "passed" (start, middle of its
    arc, end), and the total length, m.
    """
    n_pts = len(points_ne)
    legs = np.diff(points_ne, axis=0)
    leg_len = np.hypot(legs[:, 0], legs[:, 1])
    headings = np.arctan2(legs[:, 1], legs[:, 0])
    # Tangent distance and radius of each corner; a corner may use at most half of each adjacent leg.
    cut = np.zeros(n_pts)
    corners: dict[int, tuple[float, float, float]] = {}
    for i in range(1, n_pts - 1):
        turn = _wrap_pi(float(headings[i] - headings[i - 1]))
        if abs(turn) < 1e-9:
            continue
        tan_half = math.tan(abs(turn) / 2.0)
        tangent = min(turn_radius_m * tan_half, 0.5 * leg_len[i - 1], 0.5 * leg_len[i])
        radius = tangent / tan_half
        if radius < 1e-6:
            continue
        cut[i] = tangent
        corners[i] = (turn, radius, tangent)

    segments: list[_Line | _Arc] = []
    passed_s = [0.0]
    s = 0.0
    for i in range(n_pts - 1):
        psi = float(headings[i])
        d = np.array([math.cos(psi), math.sin(psi)])
        start = points_ne[i] + d * cut[i]
        length = float(leg_len[i] - cut[i] - cut[i + 1])
        if length > 1e-9:
            segments.append(_Line(s, length, (float(start[0]), float(start[1])), psi))
            s += length
        j = i + 1
        if j in corners:
            turn, radius, _tangent = corners[j]
            sign = 1.0 if turn > 0 else -1.0
            arc_start = points_ne[j] - d * cut[j]
            centre = arc_start + sign * radius * np.array([-math.sin(psi), math.cos(psi)])
            arc_len = radius * abs(turn)
            segments.append(_Arc(s, arc_len, (float(centre[0]), float(centre[1])), radius, psi, sign))
            passed_s.append(s + arc_len / 2.0)
            s += arc_len
        else:
            passed_s.append(s)
    return tuple(segments), passed_s, s


def _altitude_knots(
    start_agl_m: float, events: Sequence[tuple[float, float]], climb_rate_m_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Knots (t_s, alt_agl_m) of the piecewise-linear altitude: at each event time the target changes and
    the altitude ramps towards it at ``climb_rate_m_s`` (an unfinished ramp continues to the new target)."""
    knots_t = [0.0]
    knots_z = [start_agl_m]
    t, z, target = 0.0, start_agl_m, start_agl_m
    for t_event, new_target in [*events, (math.inf, math.nan)]:
        if z != target:
            if knots_t[-1] < t:
                knots_t.append(t)  # the ramp starts here; until now the altitude was level
                knots_z.append(z)
            t_reach = t + abs(target - z) / climb_rate_m_s
            if t_reach <= t_event:
                t, z = t_reach, target
            else:
                z = z + math.copysign(climb_rate_m_s * (t_event - t), target - z)
                t = t_event
            knots_t.append(t)
            knots_z.append(z)
        if math.isinf(t_event):
            break
        t = max(t, t_event)
        target = new_target
    return np.asarray(knots_t), np.asarray(knots_z)


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A resolved flight: the scenario's path placed on one map, at one ground height.

    ``origin``: local NED frame (at ground level) in which the path was built. ``duration_s``: run
    length; ``start_delay_s``: hold before the path; ``path_length_m``: horizontal path length.
    ``waypoints_lat_lon_deg``: (N, 2) float64, the resolved waypoints. ``footprint_radius_m``: largest
    ground distance from the nadir point that the camera can see on this flight (used for the margin).
    """

    origin: LocalTangentPlane
    ground_alt_amsl_m: float
    speed_m_s: float
    accel_m_s2: float
    start_delay_s: float
    duration_s: float
    frame_rate_hz: float
    path_length_m: float
    waypoints_lat_lon_deg: np.ndarray
    footprint_radius_m: float
    wobble: WobbleSpec
    _segments: tuple[_Line | _Arc, ...] = field(repr=False)
    _alt_knots_t_s: np.ndarray = field(repr=False)
    _alt_knots_agl_m: np.ndarray = field(repr=False)

    @property
    def flight_end_s(self) -> float:
        """Time at which the aircraft reaches the last waypoint, s."""
        return self.start_delay_s + _profile_duration_s(self.path_length_m, self.speed_m_s, self.accel_m_s2)

    def point_at_distance(self, s_m: float) -> tuple[float, float]:
        """(lat_deg, lon_deg) of the path point ``s_m`` metres from its start (clamped to the path)."""
        s_m = min(max(s_m, 0.0), self.path_length_m)
        seg = self._segments[-1]
        for candidate in self._segments:
            if s_m <= candidate.s0_m + candidate.length_m:
                seg = candidate
                break
        n, e, _psi = seg.at(min(max(s_m - seg.s0_m, 0.0), seg.length_m))
        lat, lon, _alt = self.origin.to_geodetic(np.array([n, e, 0.0]))
        return float(lat), float(lon)

    def frame_times_s(self) -> np.ndarray:
        """Exposure times of the run's frames, s: (n,) float64, ``k / frame_rate_hz`` < ``duration_s``."""
        n = math.ceil(self.duration_s * self.frame_rate_hz - 1e-9)
        return np.arange(n, dtype=np.float64) / self.frame_rate_hz

    def _horizontal(self, t_s: float) -> tuple[float, float, float, bool]:
        """(north_m, east_m, heading_rad, moving) at ``t_s``."""
        s, _speed = _profile_at(t_s - self.start_delay_s, self.path_length_m, self.speed_m_s, self.accel_m_s2)
        moving = 0.0 < s < self.path_length_m
        seg = self._segments[-1]
        for candidate in self._segments:
            if s <= candidate.s0_m + candidate.length_m:
                seg = candidate
                break
        n, e, psi = seg.at(min(max(s - seg.s0_m, 0.0), seg.length_m))
        return n, e, psi, moving

    def _altitude(self, t_s: float) -> tuple[float, float]:
        """(alt_agl_m, climb_rate_m_s up-positive) at ``t_s``."""
        kt, kz = self._alt_knots_t_s, self._alt_knots_agl_m
        z = float(np.interp(t_s, kt, kz))
        i = int(np.searchsorted(kt, t_s, side="right"))
        if 0 < i < len(kt):
            dt = kt[i] - kt[i - 1]
            rate = float((kz[i] - kz[i - 1]) / dt) if dt > 0 else 0.0
        else:
            rate = 0.0
        return z, rate

    def truth_at(self, t_s: float) -> TruthState:
        """Truth at ``t_s`` (s since the start of the run). Before 0 and after the path it holds position."""
        t = float(t_s)
        if not math.isfinite(t):
            raise ValueError(f"t_s must be finite, got {t_s!r}")
        n, e, psi, _moving = self._horizontal(t)
        alt_agl, climb = self._altitude(max(t, 0.0))
        lat, lon, _alt = self.origin.to_geodetic(np.array([n, e, 0.0]))
        _s, speed = _profile_at(t - self.start_delay_s, self.path_length_m, self.speed_m_s, self.accel_m_s2)
        vel = np.array([speed * math.cos(psi), speed * math.sin(psi), -climb])
        vel.setflags(write=False)
        roll, pitch = self.wobble.roll_pitch_rad(t)
        return TruthState(
            t_s=t,
            lat_deg=float(lat),
            lon_deg=float(lon),
            alt_amsl_m=self.ground_alt_amsl_m + alt_agl,
            alt_agl_m=alt_agl,
            vel_ned_m_s=vel,
            roll_rad=roll,
            pitch_rad=pitch,
            yaw_rad=_wrap_pi(psi),
        )


# --------------------------------------------------------------------------------------------------------
# The scenario


@dataclass(frozen=True)
class Scenario:
    """A loaded scenario (see the module docstring for every key's meaning and unit)."""

    name: str
    alt_agl_m: float
    waypoints: WaypointLayout
    description: str = ""
    duration_s: float | None = None
    frame_rate_hz: float = 3.0
    speed_m_s: float = 12.0
    accel_m_s2: float = 2.5
    climb_rate_m_s: float = 2.0
    turn_rate_deg_s: float = 15.0
    ground_alt_amsl_m: float | None = None
    start_delay_s: float = 2.0
    autopilot_unix_offset_s: float = 0.0
    camera_stamp_offset_s: float = 0.0
    camera: CameraSpec = field(default_factory=CameraSpec)
    attitude_wobble: WobbleSpec = field(default_factory=WobbleSpec)
    photometric: PhotometricParams = field(default_factory=PhotometricParams)
    map_gaps: tuple[MapGap, ...] = ()
    map_edits: tuple[MapEdit, ...] = ()
    link_drops: tuple[LinkDrop, ...] = ()
    timestamp_faults: tuple[TimestampFault, ...] = ()
    faults: tuple[Fault, ...] = ()
    #: Flight times at which the daemon is killed (SIGKILL) and restarted, s.
    daemon_restarts_s: tuple[float, ...] = ()
    #: The restarts (by time) before which the FDR directory is deleted.
    daemon_restarts_wipe_fdr: frozenset[float] = frozenset()
    #: The daemon runs as a navigator core and its vision worker (``daemon.vision_worker``); None: as its
    #: configuration says (the default: it does).
    vision_worker: bool | None = None
    #: Flight times at which the vision worker is killed (SIGKILL; its core restarts it), s.
    worker_kills_s: tuple[float, ...] = ()
    #: The start points dragged off before the flight (None: they are true).
    spoofed_start: SpoofedStart | None = None
    #: File the scenario was read from (None when built from a mapping).
    source: str | None = field(default=None, compare=False)

    def calibration(self) -> CameraCalibration:
        """The nav camera's calibration."""
        return self.camera.calibration()

    def link_down_at(self, t_s: float) -> bool:
        """Whether the autopilot link is cut at ``t_s``."""
        return any(d.from_s <= t_s < d.to_s for d in self.link_drops)

    def fault_at(self, kind: FaultKind, t_s: float) -> Fault | None:
        """The window fault of ``kind`` active at ``t_s``, or None."""
        return next((f for f in self.faults if f.kind is kind and f.from_s <= t_s < f.to_s), None)

    def instant_faults(self, t0_s: float, t1_s: float) -> list[Fault]:
        """Bad-frame instant faults due in ``(t0_s, t1_s]`` (the frames between two exposures)."""
        return [f for f in self.faults if f.kind.bad_frame and t0_s < f.from_s <= t1_s]

    def faults_of(self, kind: FaultKind) -> list[Fault]:
        """Every fault of ``kind``, in time order."""
        return sorted((f for f in self.faults if f.kind is kind), key=lambda f: f.from_s)

    def wall_step_s(self, t_s: float) -> float:
        """The companion computer's wall clock minus true time at ``t_s`` (sum of ``clock_jump`` steps)."""
        return sum(f.step_s for f in self.faults if f.kind is FaultKind.CLOCK_JUMP and f.from_s <= t_s)

    def stamp_offset_s(self, t_s: float) -> float:
        """Seconds to add to the stamp of the frame exposed at ``t_s`` (0 for a truthful stamp)."""
        period = 1.0 / self.frame_rate_hz
        one_off = sum(f.ahead_s for f in self.timestamp_faults if f.at_s <= t_s < f.at_s + period)
        return self.camera_stamp_offset_s + one_off

    def gap_at(self, t_s: float) -> GapKind | None:
        """The map-gap degradation for a frame exposed at ``t_s``, or None."""
        for gap in self.map_gaps:
            if gap.from_s <= t_s < gap.to_s:
                return gap.kind
        return None

    @property
    def max_alt_agl_m(self) -> float:
        alts = [p.alt_agl_m for p in self.waypoints.points if p.alt_agl_m is not None]
        return max([self.alt_agl_m, *alts])

    def footprint_radius_m(self, alt_agl_m: float | None = None) -> float:
        """Largest ground distance from the nadir point to what an image corner sees, m, at ``alt_agl_m``
        (default: the highest waypoint altitude) with the largest wobble tilt."""
        alt = self.max_alt_agl_m if alt_agl_m is None else alt_agl_m
        calib = self.calibration()
        half_diag_px = math.hypot(calib.width_px / 2.0, calib.height_px / 2.0)
        angle = math.atan2(half_diag_px, calib.fx_px) + self.attitude_wobble.max_tilt_rad
        if angle >= math.radians(80.0):
            raise ScenarioError(
                "camera",
                f"camera half-diagonal FOV + wobble tilt = {math.degrees(angle):.1f} deg sees the horizon",
            )
        return alt * math.tan(angle)

    def resolve(
        self, map_bbox_lonlat: tuple[float, float, float, float], ground_alt_amsl_m: float | None = None
    ) -> Trajectory:
        """Place the scenario on a map whose usable area is ``map_bbox_lonlat`` = (W, S, E, N) degrees.

        ``ground_alt_amsl_m`` (the daemon's terrain height) is used when the scenario's own is null.
        Raises ``ScenarioError`` when the map is too small for the margin or a wgs84 waypoint is off it.
        """
        west, south, east, north = (float(v) for v in map_bbox_lonlat)
        if not (west < east and south < north):
            raise ScenarioError(
                "<map>", f"map bbox must be (W, S, E, N) with W < E and S < N, got {map_bbox_lonlat}"
            )
        ground = self.ground_alt_amsl_m if self.ground_alt_amsl_m is not None else ground_alt_amsl_m
        if ground is None:
            raise ScenarioError("ground_alt_amsl_m", "null in the scenario and not given by the runner")
        footprint = self.footprint_radius_m()
        lat_c, lon_c = (south + north) / 2.0, (west + east) / 2.0
        origin = LocalTangentPlane(lat_c, lon_c, float(ground))
        pts = self.waypoints.points

        if self.waypoints.frame is WaypointFrame.MAP_RELATIVE:
            corner_lat = np.array([south, north, south, north, north, south])
            corner_lon = np.array([east, east, west, west, lon_c, lon_c])
            ned = origin.to_ned(corner_lat, corner_lon, np.full(6, float(ground)))
            # Conservative half-sizes: the narrower of the north and south edges (meridians converge).
            half_e = float(min(ned[0, 1], ned[1, 1], -ned[2, 1], -ned[3, 1]))
            half_n = float(min(ned[4, 0], -ned[5, 0]))
            margin = self.waypoints.margin_m
            if margin is None:
                margin = footprint + _AUTO_MARGIN_EXTRA_M
            if half_e - margin <= 0.0 or half_n - margin <= 0.0:
                raise ScenarioError(
                    "waypoints.margin_m",
                    f"map is {2 * half_e:.0f} m x {2 * half_n:.0f} m (E x N), too small for a margin of "
                    f"{margin:.0f} m on each side (camera footprint radius {footprint:.0f} m at "
                    f"{self.max_alt_agl_m:g} m AGL)",
                    source=self.source,
                )
            points_ne = np.array(
                [
                    [
                        -(half_n - margin) + p.b * 2.0 * (half_n - margin),
                        -(half_e - margin) + p.a * 2.0 * (half_e - margin),
                    ]
                    for p in pts
                ]
            )
        else:
            for i, p in enumerate(pts):
                if not (south <= p.a <= north and west <= p.b <= east):
                    raise ScenarioError(
                        f"waypoints.points[{i}]",
                        f"({p.a}, {p.b}) is off the map "
                        f"(lat {south:.6f}..{north:.6f}, lon {west:.6f}..{east:.6f})",
                        source=self.source,
                    )
            ned = origin.to_ned(
                np.array([p.a for p in pts]), np.array([p.b for p in pts]), np.full(len(pts), float(ground))
            )
            points_ne = ned[:, :2]

        leg = np.hypot(*np.diff(points_ne, axis=0).T)
        if np.any(leg < 1e-3):
            i = int(np.argmax(leg < 1e-3)) + 1
            raise ScenarioError(
                f"waypoints.points[{i}]", "same position as the previous point", source=self.source
            )

        turn_radius = self.speed_m_s / math.radians(self.turn_rate_deg_s)
        segments, passed_s, length = _build_path(points_ne, turn_radius)
        alts = [self.alt_agl_m if p.alt_agl_m is None else p.alt_agl_m for p in pts]
        v, a = self.speed_m_s, self.accel_m_s2
        events = [
            (self.start_delay_s + _time_at_distance_s(passed_s[i - 1], length, v, a), alts[i])
            for i in range(1, len(pts))
        ]
        knots_t, knots_z = _altitude_knots(alts[0], events, self.climb_rate_m_s)
        duration = (
            self.duration_s
            if self.duration_s is not None
            else self.start_delay_s + _profile_duration_s(length, self.speed_m_s, self.accel_m_s2)
        )
        wp_lat, wp_lon, _ = origin.to_geodetic(np.column_stack([points_ne, np.zeros(len(pts))]))
        return Trajectory(
            origin=origin,
            ground_alt_amsl_m=float(ground),
            speed_m_s=self.speed_m_s,
            accel_m_s2=self.accel_m_s2,
            start_delay_s=self.start_delay_s,
            duration_s=float(duration),
            frame_rate_hz=self.frame_rate_hz,
            path_length_m=length,
            waypoints_lat_lon_deg=np.column_stack([wp_lat, wp_lon]),
            footprint_radius_m=footprint,
            wobble=self.attitude_wobble,
            _segments=segments,
            _alt_knots_t_s=knots_t,
            _alt_knots_agl_m=knots_z,
        )


# --------------------------------------------------------------------------------------------------------
# Strict YAML reading

_REQUIRED: Any = object()


def _type_name(value: object) -> str:
    return "null" if value is None else type(value).__name__


class _Block:
    """A mapping being read; tracks which keys were consumed so that the rest can be reported."""

    def __init__(self, data: object, path: str, source: str | None) -> None:
        if not isinstance(data, Mapping):
            raise ScenarioError(
                path or "<root>", f"expected a mapping, got {_type_name(data)}", source=source
            )
        for key in data:
            if not isinstance(key, str):
                raise ScenarioError(path or "<root>", f"keys must be strings, got {key!r}", source=source)
        self.data: dict[str, Any] = dict(data)
        self.path = path
        self.source = source
        self.known: list[str] = []

    def key_path(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def error(self, key: str, message: str) -> ScenarioError:
        return ScenarioError(self.key_path(key), message, source=self.source)

    def get(self, key: str, default: Any = _REQUIRED) -> Any:
        self.known.append(key)
        if key not in self.data:
            if default is _REQUIRED:
                raise self.error(key, "required key is missing")
            return default
        return self.data[key]

    def number(
        self,
        key: str,
        default: Any = _REQUIRED,
        *,
        ge: float | None = None,
        gt: float | None = None,
        lt: float | None = None,
        le: float | None = None,
        nullable: bool = False,
    ) -> Any:
        value = self.get(key, default)
        if value is None and nullable:
            return None
        return _check_number(value, self.key_path(key), self.source, ge=ge, gt=gt, lt=lt, le=le)

    def integer(self, key: str, default: Any = _REQUIRED, *, ge: int) -> int:
        value = self.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(key, f"expected an integer, got {_type_name(value)} {value!r}")
        if value < ge:
            raise self.error(key, f"expected an integer >= {ge}, got {value}")
        return value

    def string(self, key: str, default: Any = _REQUIRED) -> str:
        value = self.get(key, default)
        if not isinstance(value, str):
            raise self.error(key, f"expected a string, got {_type_name(value)} {value!r}")
        return value

    def block(self, key: str) -> _Block:
        return _Block(self.get(key, {}), self.key_path(key), self.source)

    def finish(self) -> None:
        unknown = sorted(set(self.data) - set(self.known))
        if unknown:
            valid = ", ".join(self.known)
            raise self.error(unknown[0], f"unknown key; expected one of: {valid}")


def _check_number(
    value: object,
    path: str,
    source: str | None,
    *,
    ge: float | None = None,
    gt: float | None = None,
    lt: float | None = None,
    le: float | None = None,
) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ScenarioError(path, f"expected a number, got {_type_name(value)} {value!r}", source=source)
    x = float(value)
    bounds = [
        (ge is not None and not x >= ge, f">= {ge}"),
        (gt is not None and not x > gt, f"> {gt}"),
        (lt is not None and not x < lt, f"< {lt}"),
        (le is not None and not x <= le, f"<= {le}"),
    ]
    if not math.isfinite(x):
        raise ScenarioError(path, f"expected a finite number, got {value!r}", source=source)
    for failed, what in bounds:
        if failed:
            raise ScenarioError(path, f"expected a number {what}, got {value!r}", source=source)
    return x


def _range_pair(block: _Block, key: str) -> tuple[float, float]:
    value = block.get(key, [1.0, 1.0])
    path = block.key_path(key)
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise ScenarioError(path, f"expected [lo, hi], got {value!r}", source=block.source)
    lo = _check_number(value[0], f"{path}[0]", block.source, gt=0.0)
    hi = _check_number(value[1], f"{path}[1]", block.source, gt=0.0)
    if lo > hi:
        raise ScenarioError(path, f"expected lo <= hi, got {value!r}", source=block.source)
    return lo, hi


def _read_waypoints(block: _Block) -> WaypointLayout:
    frame_raw = block.string("frame")
    try:
        frame = WaypointFrame(frame_raw)
    except ValueError as exc:
        valid = ", ".join(f.value for f in WaypointFrame)
        raise block.error("frame", f"expected one of: {valid}; got {frame_raw!r}") from exc
    margin_raw = block.get("margin_m", "auto")
    margin: float | None
    if frame is WaypointFrame.WGS84:
        if "margin_m" in block.data:
            raise block.error("margin_m", "only applies to frame: map_relative")
        margin = None
    elif margin_raw == "auto":
        margin = None
    else:
        margin = _check_number(margin_raw, block.key_path("margin_m"), block.source, ge=0.0)
    raw_points = block.get("points")
    points_path = block.key_path("points")
    if not isinstance(raw_points, list) or len(raw_points) < 2:
        raise ScenarioError(
            points_path, f"expected a list of at least 2 points, got {raw_points!r}", source=block.source
        )
    if frame is WaypointFrame.MAP_RELATIVE:
        ranges = [(0.0, 1.0), (0.0, 1.0)]
    else:
        ranges = [(-90.0, 90.0), (-180.0, 180.0)]
    points = []
    for i, raw in enumerate(raw_points):
        path = f"{points_path}[{i}]"
        if not isinstance(raw, list) or len(raw) not in (2, 3):
            raise ScenarioError(
                path, f"expected [a, b] or [a, b, {{alt_agl_m: H}}], got {raw!r}", source=block.source
            )
        a, b = (
            _check_number(raw[k], f"{path}[{k}]", block.source, ge=ranges[k][0], le=ranges[k][1])
            for k in range(2)
        )
        alt = None
        if len(raw) == 3:
            opts = _Block(raw[2], f"{path}[2]", block.source)
            # Optional here so that a misspelt key is reported as unknown rather than as a missing alt_agl_m.
            alt = opts.number("alt_agl_m", None, gt=0.0, nullable=True)
            opts.finish()
        points.append(Waypoint(a, b, alt))
    block.finish()
    return WaypointLayout(frame, tuple(points), margin)


def _read_map_edits(value: object, source: str | None) -> tuple[MapEdit, ...]:
    if not isinstance(value, list):
        raise ScenarioError("map_edits", f"expected a list, got {_type_name(value)}", source=source)
    edits = []
    for i, raw in enumerate(value):
        b = _Block(raw, f"map_edits[{i}]", source)
        kind_raw = b.string("kind")
        try:
            kind = MapEditKind(kind_raw)
        except ValueError as exc:
            valid = ", ".join(k.value for k in MapEditKind)
            raise b.error("kind", f"expected one of: {valid}; got {kind_raw!r}") from exc
        start = b.number("path_from", ge=0.0, lt=1.0)
        end = b.number("path_to", gt=start, le=1.0)
        half = b.number("half_width_m", None, gt=0.0, nullable=True)
        offset: tuple[float, float] = (0.0, 0.0)
        if kind is MapEditKind.LOOKALIKE:
            raw_off = b.get("offset_m")
            path = b.key_path("offset_m")
            if not isinstance(raw_off, (list, tuple)) or len(raw_off) != 2:
                raise ScenarioError(path, f"expected [north_m, east_m], got {raw_off!r}", source=source)
            offset = (
                _check_number(raw_off[0], f"{path}[0]", source),
                _check_number(raw_off[1], f"{path}[1]", source),
            )
            if offset == (0.0, 0.0):
                raise ScenarioError(path, "a look-alike needs a non-zero offset", source=source)
        b.finish()
        edits.append(MapEdit(kind, start, end, offset, half))
    return tuple(edits)


def _read_link_drops(value: object, source: str | None) -> tuple[LinkDrop, ...]:
    if not isinstance(value, list):
        raise ScenarioError("link_drops", f"expected a list, got {_type_name(value)}", source=source)
    drops = []
    for i, raw in enumerate(value):
        b = _Block(raw, f"link_drops[{i}]", source)
        start = b.number("from_s", ge=0.0)
        end = b.number("to_s", gt=start)
        b.finish()
        drops.append(LinkDrop(start, end))
    return tuple(drops)


def _read_timestamp_faults(value: object, source: str | None) -> tuple[TimestampFault, ...]:
    if not isinstance(value, list):
        raise ScenarioError("timestamp_faults", f"expected a list, got {_type_name(value)}", source=source)
    faults = []
    for i, raw in enumerate(value):
        b = _Block(raw, f"timestamp_faults[{i}]", source)
        at = b.number("at_s", ge=0.0)
        ahead = b.number("ahead_s")
        if ahead == 0.0:
            raise b.error("ahead_s", "expected a non-zero offset in seconds, got 0")
        b.finish()
        faults.append(TimestampFault(at, ahead))
    return tuple(faults)


def _read_faults(value: object, source: str | None) -> tuple[Fault, ...]:
    if not isinstance(value, list):
        raise ScenarioError("faults", f"expected a list, got {_type_name(value)}", source=source)
    faults = []
    for i, raw in enumerate(value):
        b = _Block(raw, f"faults[{i}]", source)
        kind_raw = b.string("kind")
        try:
            kind = FaultKind(kind_raw)
        except ValueError as exc:
            valid = ", ".join(k.value for k in FaultKind)
            raise b.error("kind", f"expected one of: {valid}; got {kind_raw!r}") from exc
        if kind is FaultKind.CLOCK_JUMP:
            at = b.number("at_s", ge=0.0)
            if at != round(at):
                # libfaketime re-reads the daemon's offset at whole seconds (sitl.host_faults), and the
                # flight starts on a whole second, so a step lands at its at_s only on a whole second.
                raise b.error("at_s", f"expected a whole number of seconds, got {at}")
            step = b.number("step_s")
            if step == 0.0:
                raise b.error("step_s", "expected a non-zero step in seconds, got 0")
            faults.append(Fault(kind, at, at, step_s=step))
        elif kind is FaultKind.ORT_FAULT:
            at = b.number("at_s", ge=0.0)
            faults.append(Fault(kind, at, at, count=b.integer("count", 3, ge=1)))
        elif kind.instant:
            at = b.number("at_s", ge=0.0)
            faults.append(Fault(kind, at, at))
        else:
            start = b.number("from_s", ge=0.0)
            end = b.number("to_s", gt=start)
            reconnect = b.get("reconnect", False) if kind is FaultKind.CAMERA_STALL else False
            if not isinstance(reconnect, bool):
                raise b.error("reconnect", f"expected true or false, got {reconnect!r}")
            floods = (FaultKind.MAVLINK_FLOOD, FaultKind.SOURCE_FLOOD, FaultKind.IMPOSTOR)
            rate = b.number("rate_hz", 500.0, gt=0.0, le=5000.0) if kind in floods else 500.0
            offset = (0.0, 0.0, 0.0)
            if kind is FaultKind.ATTITUDE_OFFSET:
                offset = (
                    b.number("roll_deg", 0.0, ge=-30.0, le=30.0),
                    b.number("pitch_deg", 0.0, ge=-30.0, le=30.0),
                    b.number("yaw_deg", 0.0, ge=-30.0, le=30.0),
                )
                if offset == (0.0, 0.0, 0.0):
                    raise b.error(
                        "roll_deg", "expected a non-zero roll_deg, pitch_deg or yaw_deg, got all three 0"
                    )
            processes = b.integer("processes", 2, ge=1) if kind is FaultKind.CPU_HOGS else 0
            if processes > MAX_CPU_HOGS:
                raise b.error("processes", f"expected at most {MAX_CPU_HOGS} busy processes, got {processes}")
            faults.append(Fault(kind, start, end, reconnect, rate, offset_deg=offset, processes=processes))
        b.finish()
    return tuple(faults)


def _read_restarts(value: object, source: str | None) -> tuple[tuple[float, ...], frozenset[float]]:
    """(restart times, sorted; the times of those with ``wipe_fdr``)."""
    if not isinstance(value, list):
        raise ScenarioError("daemon_restarts", f"expected a list, got {_type_name(value)}", source=source)
    times = []
    wipes = set()
    for i, raw in enumerate(value):
        b = _Block(raw, f"daemon_restarts[{i}]", source)
        at_s = b.number("at_s", gt=0.0)
        wipe = b.get("wipe_fdr", False)
        if not isinstance(wipe, bool):
            raise b.error("wipe_fdr", f"expected true or false, got {wipe!r}")
        times.append(at_s)
        if wipe:
            wipes.add(at_s)
        b.finish()
    return tuple(sorted(times)), frozenset(wipes)


def _read_worker_kills(value: object, vision_worker: bool | None, source: str | None) -> tuple[float, ...]:
    """The worker kill times, sorted (a scenario with kills runs the vision worker)."""
    if not isinstance(value, list):
        raise ScenarioError("worker_kills", f"expected a list, got {_type_name(value)}", source=source)
    if value and vision_worker is not True:
        raise ScenarioError("worker_kills", "needs vision_worker: true (no worker to kill)", source=source)
    times = []
    for i, raw in enumerate(value):
        b = _Block(raw, f"worker_kills[{i}]", source)
        times.append(b.number("at_s", gt=0.0))
        b.finish()
    return tuple(sorted(times))


def _read_gaps(value: object, source: str | None) -> tuple[MapGap, ...]:
    if not isinstance(value, list):
        raise ScenarioError("map_gaps", f"expected a list, got {_type_name(value)}", source=source)
    gaps = []
    for i, raw in enumerate(value):
        b = _Block(raw, f"map_gaps[{i}]", source)
        start = b.number("from_s", ge=0.0)
        end = b.number("to_s", gt=start)
        kind_raw = b.string("kind")
        try:
            kind = GapKind(kind_raw)
        except ValueError as exc:
            valid = ", ".join(k.value for k in GapKind)
            raise b.error("kind", f"expected one of: {valid}; got {kind_raw!r}") from exc
        b.finish()
        gaps.append(MapGap(start, end, kind))
    return tuple(gaps)


def _read_spoofed_start(value: object, source: str | None) -> SpoofedStart | None:
    if value is None:
        return None
    b = _Block(value, "spoofed_start", source)
    raw = b.get("offset_m")
    path = b.key_path("offset_m")
    if not isinstance(raw, (list, tuple)) or len(raw) != 2:
        raise ScenarioError(path, f"expected [north_m, east_m], got {raw!r}", source=source)
    offset = (_check_number(raw[0], f"{path}[0]", source), _check_number(raw[1], f"{path}[1]", source))
    if math.hypot(*offset) > 100_000.0:
        raise ScenarioError(path, f"expected an offset of at most 100 km, got {raw!r}", source=source)
    sigma = b.number("sigma_m", 5.0, gt=0.0, le=1000.0)
    names = b.get("sources", [s.value for s in SpoofedSource if s is not SpoofedSource.RESUME])
    path = b.key_path("sources")
    if not isinstance(names, list) or not names:
        raise ScenarioError(path, f"expected a non-empty list, got {names!r}", source=source)
    sources = set()
    for i, name in enumerate(names):
        try:
            sources.add(SpoofedSource(name))
        except ValueError:
            valid = ", ".join(s.value for s in SpoofedSource)
            message = f"expected one of: {valid}; got {name!r}"
            raise ScenarioError(f"{path}[{i}]", message, source=source) from None
    b.finish()
    return SpoofedStart(offset, sigma, frozenset(sources))


def spoofed_start_from_yaml(text: str, source: str) -> SpoofedStart | None:
    """A ``spoofed_start`` mapping given as YAML text (``gdnav sitl run --spoofed-start``); ``null`` is
    none. Raises ``ScenarioError`` naming ``source`` and the key."""
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        message = f"not valid YAML: {exc}".replace("\n", " ")
        raise ScenarioError("spoofed_start", message, source=source) from exc
    return _read_spoofed_start(value, source)


def scenario_from_mapping(data: Mapping[str, Any], *, source: str | None = None) -> Scenario:
    """Build a ``Scenario`` from parsed YAML, strictly (see the module docstring)."""
    root = _Block(data, "", source)
    name = root.string("name")
    description = root.string("description", "")
    duration = root.number("duration_s", None, gt=0.0, nullable=True)
    frame_rate = root.number("frame_rate_hz", 3.0, gt=0.0)
    speed = root.number("speed_m_s", 12.0, gt=0.0)
    accel = root.number("accel_m_s2", 2.5, gt=0.0)
    alt = root.number("alt_agl_m", gt=0.0)
    climb = root.number("climb_rate_m_s", 2.0, gt=0.0)
    turn = root.number("turn_rate_deg_s", 15.0, gt=0.0)
    ground = root.number("ground_alt_amsl_m", None, nullable=True)
    delay = root.number("start_delay_s", 2.0, ge=0.0)
    ap_unix_offset = root.number("autopilot_unix_offset_s", 0.0)
    cam_offset = root.number("camera_stamp_offset_s", 0.0, ge=-1.0, le=1.0)

    cam = root.block("camera")
    camera = CameraSpec(
        cam.integer("width_px", 640, ge=16),
        cam.integer("height_px", 480, ge=16),
        cam.number("hfov_deg", 70.0, gt=1, lt=179),
    )
    cam.finish()

    wob = root.block("attitude_wobble")
    wobble = WobbleSpec(
        wob.number("roll_amp_deg", 0.0, ge=0.0, lt=45.0),
        wob.number("pitch_amp_deg", 0.0, ge=0.0, lt=45.0),
        wob.number("period_s", 7.0, gt=0.0),
    )
    wob.finish()

    ph = root.block("photometric")
    photometric = PhotometricParams(
        gain_range=_range_pair(ph, "gain_range"),
        gamma_range=_range_pair(ph, "gamma_range"),
        colour_shift_dn=ph.number("colour_shift_dn", 0.0, ge=0.0),
        noise_sigma_dn=ph.number("noise_sigma_dn", 0.0, ge=0.0),
        blur_prob=ph.number("blur_prob", 0.0, ge=0.0, le=1.0),
        blur_sigma_px=ph.number("blur_sigma_px", 0.0, ge=0.0),
        seed=ph.integer("seed", 0, ge=0),
    )
    ph.finish()

    waypoints = _read_waypoints(root.block("waypoints"))
    gaps = _read_gaps(root.get("map_gaps", []), source)
    edits = _read_map_edits(root.get("map_edits", []), source)
    drops = _read_link_drops(root.get("link_drops", []), source)
    stamp_faults = _read_timestamp_faults(root.get("timestamp_faults", []), source)
    restarts, restart_wipes = _read_restarts(root.get("daemon_restarts", []), source)
    vision_worker = root.get("vision_worker", None)
    if vision_worker is not None and not isinstance(vision_worker, bool):
        raise ScenarioError("vision_worker", f"expected true or false, got {vision_worker!r}", source=source)
    worker_kills = _read_worker_kills(root.get("worker_kills", []), vision_worker, source)
    faults = _read_faults(root.get("faults", []), source)
    spoofed = _read_spoofed_start(root.get("spoofed_start", None), source)
    root.finish()
    scenario = Scenario(
        name=name,
        alt_agl_m=alt,
        waypoints=waypoints,
        description=description,
        duration_s=duration,
        frame_rate_hz=frame_rate,
        speed_m_s=speed,
        accel_m_s2=accel,
        climb_rate_m_s=climb,
        turn_rate_deg_s=turn,
        ground_alt_amsl_m=ground,
        start_delay_s=delay,
        autopilot_unix_offset_s=ap_unix_offset,
        camera_stamp_offset_s=cam_offset,
        camera=camera,
        attitude_wobble=wobble,
        photometric=photometric,
        map_gaps=gaps,
        map_edits=edits,
        link_drops=drops,
        timestamp_faults=stamp_faults,
        daemon_restarts_s=restarts,
        daemon_restarts_wipe_fdr=restart_wipes,
        vision_worker=vision_worker,
        worker_kills_s=worker_kills,
        faults=faults,
        spoofed_start=spoofed,
        source=source,
    )
    scenario.footprint_radius_m()  # rejects a camera + wobble that would see the horizon
    return scenario


def load_scenario(path: str | Path) -> Scenario:
    """Load a scenario YAML file. A bare name (``demo``) loads the built-in scenario of that name."""
    p = Path(path)
    if not p.suffix and not p.exists():
        p = BUILTIN_SCENARIOS_DIR / f"{p.name}.yaml"
    source = str(p)
    if not p.is_file():
        builtin = ", ".join(sorted(f.stem for f in BUILTIN_SCENARIOS_DIR.glob("*.yaml")))
        raise ScenarioError(
            "<file>", f"scenario file not found (built-in scenarios: {builtin})", source=source
        )
    try:
        data = yaml.safe_load(p.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise ScenarioError("<file>", f"not valid YAML: {exc}".replace("\n", " "), source=source) from exc
    return scenario_from_mapping(data, source=source)
