"""C5 start-up prior: where the estimator may honestly start, after a cold start or a restart (F8).

A restarted daemon must never claim an accuracy it cannot back. The rules, in order (:func:`choose_prior`):

1. **Resume** from the last estimate the previous run sent as a 3D fix (the newer of the FDR's and the
   resume state file's) when at most ``init.resume_max_age_s`` old, its sigma grown by
   ``init.max_speed_m_s`` times the time since.
2. **Configured position or HOME_POSITION** only while the autopilot says the vehicle is on the ground
   (``flight_phase``), or in the air when this run saw it on the ground, the sigma grown at top speed since.
   Cross-checked first: the configured position, HOME_POSITION and the autopilot's own position while
   on the ground (``GroundPosition``, with its stated accuracy) are compared with each other; two more
   than 3 combined sigmas apart make a wide prior that covers them all (source ``disputed``), not a
   pick. HOME_POSITION is a claim (unsigned, anyone on the link could send it), not a fact.
3. **Nothing trustworthy**: the whole map (the cache's centre, a sigma covering it, so fix_type 0 or 1), and
   a wide search until a fix re-anchors it.

None of these is a fact: until a map fix confirms the estimate it is never sent as a 3D fix (a resumed
estimate, the previous run's own 3D output, excepted: ``InitialPrior.confirmed``), and failed attempts
on frames that should match widen it (``prior_doubt``).

After a restart or a start in the air, the autopilot's own estimate (GLOBAL_POSITION_INT with a good
EKF_STATUS_REPORT) is asked for and used, never believed alone: it confirms a resumed estimate within 3
sigma, else the sigma grows to cover both, and with nothing of the daemon's own it centres the map-wide
search. The rules in full: docs/design.md, "`c5_estimator/prior.py`: the start-up prior".
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, Final

from gps_denied_onboard.components.c5_estimator.ekf import EstimatorCheckpoint
from gps_denied_onboard.components.c8_mavlink.messages import DIALECT
from gps_denied_onboard.components.c8_mavlink.vehicle_state import (
    AutopilotPosition,
    FlightPhase,
    GroundPosition,
)
from gps_denied_onboard.config import InitConfig
from gps_denied_onboard.constants import FdrKind
from gps_denied_onboard.geo import haversine_m

#: GPS_FIX_TYPE_3D: only estimates sent as a 3D fix are resumed from.
_FIX_3D: Final[int] = 3
#: MAV_LANDED_STATE values that mean the vehicle is flying.
_FLYING: Final[frozenset[int]] = frozenset(
    {DIALECT.MAV_LANDED_STATE_IN_AIR, DIALECT.MAV_LANDED_STATE_TAKEOFF, DIALECT.MAV_LANDED_STATE_LANDING}
)


class PriorSource:
    """Values of ``InitialPrior.source``."""

    RESUMED: Final = "fdr_resume"
    CONFIG: Final = "config"
    HOME: Final = "home_position"
    MAP_EXTENT: Final = "map_extent"
    #: The whole map, searched from the autopilot's own estimate (restart with nothing of our own).
    AUTOPILOT: Final = "autopilot_estimate"
    #: The start points (configured, HOME_POSITION, the autopilot's own position on the ground) disagree
    #: beyond their sigmas: a prior wide enough to cover them all.
    DISPUTED: Final = "disputed"
    #: The navigator core's own estimate, carried on the IMU while the vision worker restarted
    #: (``daemon/core.py``): the whole filter state, velocity and covariance included.
    CORE_HANDOVER: Final = "core_handover"


@dataclass(frozen=True)
class InitialPrior:
    """Where the estimator starts: position and its horizontal 1-sigma, and where that came from."""

    lat_deg: float
    lon_deg: float
    sigma_m: float
    source: str
    #: Why this source was chosen (and the others were not), for the log, the FDR and the operator.
    why: str = ""
    #: The previous run's own 3D output (resumed): it may be sent as a 3D fix before a map fix confirms
    #: it. Every other prior is a claim until one does (``EstimatorState.map_confirmed``).
    confirmed: bool = False
    #: ``disputed``: the largest distance between two start points, m (None otherwise).
    spread_m: float | None = None
    #: ``core_handover``: the filter state to start from as it is (None otherwise).
    handover: EstimatorCheckpoint | None = None


@dataclass(frozen=True)
class ResumeState:
    """The last estimate a previous run sent to the autopilot as a 3D fix."""

    lat_deg: float
    lon_deg: float
    horiz_sigma_m: float
    time_unix_usec: int


@dataclass(frozen=True)
class PreviousRun:
    """What the flight data recorder says about the daemon's previous run."""

    #: The last estimate it sent as a 3D fix, or None.
    last_3d: ResumeState | None
    #: Time of its newest record of any kind, Unix seconds, or None (no previous run recorded).
    last_record_unix_s: float | None


def read_previous_run(records_newest_first: Iterable[Mapping[str, Any]]) -> PreviousRun:
    """Scan FDR records newest first (``read_records_newest_first``) up to the last 3D estimate."""
    last_record: float | None = None
    for r in records_newest_first:
        t = r.get("t_unix_s")
        if last_record is None and isinstance(t, (int, float)) and not isinstance(t, bool):
            with contextlib.suppress(OverflowError):  # an integer too large for a float
                last_record = float(t) if math.isfinite(float(t)) else None
        if r.get("kind") != FdrKind.ESTIMATE_SENT or r.get("fix_type") != _FIX_3D:
            continue
        try:
            state = ResumeState(
                float(r["lat_deg"]), float(r["lon_deg"]), float(r["horiz_sigma_m"]), int(r["time_unix_usec"])
            )
        except (KeyError, TypeError, ValueError, OverflowError):  # int(inf): OverflowError
            continue
        if all(math.isfinite(v) for v in (state.lat_deg, state.lon_deg, state.horiz_sigma_m)):
            return PreviousRun(state, last_record)
    return PreviousRun(None, last_record)


def with_resume_state(previous: PreviousRun, state: ResumeState | None) -> PreviousRun:
    """``previous`` (the FDR's view) with the resume state file's estimate where that one is newer: the
    recorder may have dropped what the state file kept (a full disk)."""
    if state is None:
        return previous
    last_3d = previous.last_3d
    if last_3d is None or state.time_unix_usec > last_3d.time_unix_usec:
        last_3d = state
    t_s = state.time_unix_usec / 1e6
    last = previous.last_record_unix_s
    return PreviousRun(last_3d, t_s if last is None else max(last, t_s))


def in_the_air(init: InitConfig, alt_agl_m: float | None, phase: FlightPhase | None) -> bool | None:
    """True when anything the autopilot says means flying (landed_state IN_AIR/TAKEOFF/LANDING, or
    higher than ``init.on_ground_max_alt_agl_m`` above home); False when something says on the ground
    (landed_state ON_GROUND, disarmed, or that low) and nothing says flying; None when nothing is known."""
    landed = phase.landed_state if phase is not None else None
    armed = phase.armed if phase is not None else None
    low = None if alt_agl_m is None else alt_agl_m <= init.on_ground_max_alt_agl_m
    if landed in _FLYING or low is False:
        return True
    if landed == DIALECT.MAV_LANDED_STATE_ON_GROUND or armed is False or low:
        return False
    return None


def choose_prior(
    *,
    now_unix_usec: int,
    init: InitConfig,
    previous: PreviousRun,
    home: tuple[float, float, float] | None,
    alt_agl_m: float | None,
    map_centre_lat_lon: tuple[float, float],
    map_radius_m: float,
    autopilot: AutopilotPosition | None = None,
    phase: FlightPhase | None = None,
    autopilot_ground: GroundPosition | None = None,
    home_signed: bool = False,
) -> InitialPrior:
    """The start-up prior by the rules in the module docstring.

    ``previous``: the FDR's view of the previous run; a record of it within ``init.resume_max_age_s``
    means this start is a restart in flight, unless the vehicle is on the ground. ``home``:
    HOME_POSITION (lat, lon, alt) or None. ``alt_agl_m``: the autopilot's height above home now, or None
    when unknown. ``map_centre_lat_lon``/``map_radius_m``: the cache's extent. ``autopilot``: the
    autopilot's own estimate; used after a restart in flight only, and only when its EKF says its
    absolute horizontal position is good. ``phase``: the autopilot's armed and landed states
    (``in_the_air``) and when this run last saw the vehicle on the ground. ``autopilot_ground``: the
    autopilot's own position while on the ground in this run, the start points' witness;
    ``home_signed``: whether HOME_POSITION came signed (said in ``why``).
    """
    now_s = now_unix_usec / 1e6
    notes: list[str] = []
    resume = previous.last_3d
    if resume is not None:
        age_s = now_s - resume.time_unix_usec / 1e6
        if 0.0 <= age_s <= init.resume_max_age_s:
            sigma = math.hypot(resume.horiz_sigma_m, init.max_speed_m_s * age_s)
            why = (
                f"last 3D estimate {age_s:.1f} s ago, sigma {resume.horiz_sigma_m:.1f} m grown at "
                f"{init.max_speed_m_s:g} m/s"
            )
            ap = _usable(autopilot)
            if ap is not None:
                # The autopilot's estimate may be up to its own age apart in time from ``now``.
                slack = init.max_speed_m_s * abs(now_s - ap.time_unix_usec / 1e6)
                d = float(haversine_m(resume.lat_deg, resume.lon_deg, ap.lat_deg, ap.lon_deg))
                if d <= 3.0 * sigma + slack:
                    why += f"; the autopilot's estimate agrees ({d:.0f} m away)"
                else:
                    sigma += d + slack
                    why += f"; the autopilot's estimate is {d:.0f} m away: sigma covers both"
            return InitialPrior(
                resume.lat_deg, resume.lon_deg, sigma, PriorSource.RESUMED, why, confirmed=True
            )
        notes.append(f"last 3D estimate {age_s:.0f} s old (limit {init.resume_max_age_s:g} s)")
    restarted = (
        previous.last_record_unix_s is not None
        and 0.0 <= now_s - previous.last_record_unix_s <= init.resume_max_age_s
    )
    air = in_the_air(init, alt_agl_m, phase)
    start_point: tuple[float, float, str] | None = None
    if init.lat_deg is not None and init.lon_deg is not None:
        start_point = (init.lat_deg, init.lon_deg, PriorSource.CONFIG)
    elif init.use_home_position and home is not None:
        start_point = (home[0], home[1], PriorSource.HOME)
    if start_point is not None:
        lat0, lon0, source = start_point
        sigma0, check = init.sigma_m, _cross_check(init, home, home_signed, autopilot_ground)
        if check.disputed:
            lat0, lon0, sigma0, source = check.lat_deg, check.lon_deg, check.sigma_m, PriorSource.DISPUTED
        spread = check.spread_m if check.disputed else None
        if air is False:
            return InitialPrior(lat0, lon0, sigma0, source, "on the ground" + check.why, spread_m=spread)
        ground_s = phase.last_on_ground_unix_s if phase is not None else None
        if air and ground_s is not None and now_s >= ground_s:
            since_s = now_s - ground_s
            sigma = math.hypot(sigma0, init.max_speed_m_s * since_s)
            why = f"in the air, on the ground {since_s:.1f} s ago: sigma grown at {init.max_speed_m_s:g} m/s"
            return InitialPrior(lat0, lon0, sigma, source, why + check.why, spread_m=spread)
        if air:
            notes.append(f"{source} ignored: in the air" + (" after a restart" if restarted else ""))
        else:
            notes.append(f"{source} ignored: not known to be on the ground")
    elif air:
        notes.append("in the air, no start point")
    lat, lon = map_centre_lat_lon
    why = "; ".join(notes) or "no previous estimate, no start point"
    ap = _usable(autopilot) if restarted or air else None
    if ap is not None:
        # Centred on the autopilot's estimate, still covering the whole map from there.
        d = float(haversine_m(lat, lon, ap.lat_deg, ap.lon_deg))
        return InitialPrior(
            ap.lat_deg,
            ap.lon_deg,
            max(map_radius_m + d, init.sigma_m),
            PriorSource.AUTOPILOT,
            why + "; searching the map from the autopilot's estimate",
        )
    return InitialPrior(lat, lon, max(map_radius_m, init.sigma_m), PriorSource.MAP_EXTENT, why)


@dataclass(frozen=True)
class _CrossCheck:
    """The start points compared (``_cross_check``): whether they disagree, and if so the prior that
    covers them all; ``why`` is appended to the prior's."""

    disputed: bool
    why: str
    lat_deg: float = math.nan
    lon_deg: float = math.nan
    sigma_m: float = math.nan
    spread_m: float = 0.0


def _cross_check(
    init: InitConfig,
    home: tuple[float, float, float] | None,
    home_signed: bool,
    autopilot_ground: GroundPosition | None,
) -> _CrossCheck:
    """The configured position, HOME_POSITION (where ``init.use_home_position``) and the autopilot's own
    position on the ground, each with its sigma (``init.sigma_m`` for the first two and for an autopilot
    that states no accuracy), compared two by two: farther apart than 3 combined sigmas, they disagree,
    and the prior is centred on their mean with a sigma that puts every one of them within one sigma of
    it (each one's distance plus its own sigma). One of them may be right; the fix path then searches
    them all. Agreeing, they say so (the pick stays the configured position, else HOME_POSITION)."""
    points: list[tuple[str, float, float, float]] = []
    if init.lat_deg is not None and init.lon_deg is not None:
        points.append((PriorSource.CONFIG, init.lat_deg, init.lon_deg, init.sigma_m))
    if init.use_home_position and home is not None:
        label = "HOME_POSITION" + ("" if home_signed else " (unsigned)")
        points.append((label, home[0], home[1], init.sigma_m))
    if autopilot_ground is not None:
        sigma = autopilot_ground.sigma_m if autopilot_ground.sigma_m is not None else init.sigma_m
        points.append(("the autopilot's position", autopilot_ground.lat_deg, autopilot_ground.lon_deg, sigma))
    if len(points) < 2:
        return _CrossCheck(False, "")
    worst: tuple[float, str] | None = None
    spread = 0.0
    for i, (name_i, lat_i, lon_i, sig_i) in enumerate(points):
        for name_j, lat_j, lon_j, sig_j in points[i + 1 :]:
            d = float(haversine_m(lat_i, lon_i, lat_j, lon_j))
            spread = max(spread, d)
            bound = 3.0 * math.hypot(sig_i, sig_j)
            if d > bound and (worst is None or d / bound > worst[0]):
                worst = (d / bound, f"{name_i} {d:.0f} m from {name_j} (3 sigma {bound:.0f} m)")
    names = ", ".join(p[0] for p in points)
    if worst is None:
        return _CrossCheck(False, f"; {names} agree (within {spread:.0f} m)")
    lat = sum(p[1] for p in points) / len(points)
    lon = sum(p[2] for p in points) / len(points)
    sigma = max(float(haversine_m(lat, lon, p[1], p[2])) + p[3] for p in points)
    why = f"; start points disagree: {worst[1]}: sigma {sigma:.0f} m covers {names}"
    return _CrossCheck(True, why, lat, lon, sigma, spread)


def _usable(autopilot: AutopilotPosition | None) -> AutopilotPosition | None:
    """The autopilot's estimate when its EKF vouches for the absolute horizontal position."""
    if autopilot is None or not autopilot.horizontal_position_valid:
        return None
    return autopilot
