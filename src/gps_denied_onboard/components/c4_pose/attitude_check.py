"""C4 attitude check: is the autopilot's tilt as good as the pose solver is told it is?

The solver leans on the autopilot's roll and pitch, weighed at ``pose.attitude_sigma_deg``, wherever the
image cannot pin the camera's tilt (``c4_pose/solver.py``). A wrong attitude (an AHRS gone wrong, a camera
mount knocked out of its calibration) then moves every fix by height x tilt error while each fix states
it is fine. Measured in SITL with 3 deg added to the autopilot's roll from 20 s on (XFeat, 70 s flights,
``docs/benchmarks.md``): same-source at 120 m AGL the fixes went 2-4 m off at a stated 1 m, across dates
at 1200 m AGL 35-72 m off at 10-27 m: 134 and 360 of 724 GPS_INPUT went out beyond 3 sigma.

The evidence: the image-only pose's world-down direction minus the autopilot's, on the camera's x and y
axes (the camera is fixed to the airframe, so a mount or AHRS error is constant there), kept for the
last ``pose.attitude_check_fixes`` solved fixes no older than ``pose.attitude_check_max_age_s``. One
frame across dates cannot tell (the image's own tilt is 1-3 deg off from frame to frame); a bias is the
same from frame to frame. Two tests, both on the scatter the fixes themselves show, never on the
solver's formal covariance (across dates that is several times too small). Consecutive frames see
mostly the same ground, and across dates the image's tilt error comes from that ground: measured over
NAIP 2009/2014 at 1200 m AGL, ten fixes in a row (15 s, 600 m) shared a 5 deg tilt error. A window's
fixes therefore count as ``1 + ground track / footprint`` independent ones (the footprint: the camera's
horizontal field of view at the fix's height), never more than there are. Unless its fixes pin the
tilt better than ``pose.attitude_sigma_deg`` (the image is then the better tilt sensor, as same-source
imagery is, a few hundredths of a degree from frame to frame; the jump test's criterion below), a
window needs two of them (``MIN_INDEPENDENT``), and its margin their degrees of freedom, before it can
prove anything. Within less ground the fixes' scatter is the image's noise over one stretch of it,
which says nothing of how far their mean strays: with the fix path on
every frame (an H100, ``docs/benchmarks.md``, 2026-11-26) the image-only tilts across dates at 1200 m
AGL strayed 1-4 deg together for tens of frames while scattering a few tenths among them, and windows
of a few seconds "proved" the attitude off in three of five flights, refused every fix and left the
autopilot without a position for 11 and 18 s, and in one for the rest of the flight.

- **Off**: over the newest 4, 8, ... fixes of the current state and over all of them, the mean is the
  bias; the attitude is off when, in any of them, the bias less its one-sided 99 % Student-t margin (on
  the independent fixes, with one fewer degrees of freedom) is beyond three times
  ``pose.attitude_sigma_deg`` (the prior claims one sigma; a bias proven beyond three makes its fixes
  lies). Once off it stays off until the newest evidence no longer shows a bias beyond the bound: the
  run of fixes that departed from the off state's own interval (below), else the newest window that
  spans enough ground; while no window of the off state says anything, it stays off. While off every
  fix is refused (``attitude_off``).
- **Jump**: where the state's fixes before pin the tilt better than ``pose.attitude_sigma_deg`` (their
  99 % prediction interval is narrower: the image is the better tilt sensor there), a fix whose tilt
  lies outside that interval and beyond the bound is held back (``attitude_jump``) until the next ones
  say whether it was one bad fix or a new attitude: the fixes that left the interval in a row are
  windows of their own (4, 8, ... of them; each against the same ground as the fixes before, so their
  scatter is their own) and 4 of them prove it off. This refuses the fixes between the attitude going
  wrong and the off test seeing it. A fix outside the interval but under the bound (a frame exposed
  across the step, with part of it) goes through, and is kept out of the interval the next fixes are
  judged by, as the held ones are. While off, the same run shows the attitude back: 4 fixes that left
  the off state's interval in a row, their bias within the bound, let go. Across dates the interval is
  the scatter of one fix, wider than the sigma, and nothing is held back (measured before this rule: 7
  of 52 cross-date fixes held back for nothing).
- **Each state's evidence is its own**: the windows, the runs and the interval are over the fixes since
  the check last changed its mind (the smallest window that proved the attitude off, or the run that
  showed it back, or else the fix it changed on). A window reaching into the state before mixes two
  tilts. Measured in CI (2026-11-27, 3 deg of roll for 25 s, same-source): judged against the fixes
  before the offset, whose autopilot error had wandered 0.5 deg since, the fixes after it kept
  "departing", the offset's fixes stayed part of the run, and the run held the check off 15 s after the
  attitude was back (44 of 69 fixes refused). And after a release, a second step was judged against an
  interval holding both tilts, too wide to see it: in the unit tests' draws its first three fixes went
  through 2.5 deg off.

What the estimate already holds leaned on the same attitude: the fixes fused before the check saw it,
and VO, which turns each frame's rays to the ground with the autopilot's attitude. A tilt error ``b``
fixed to the airframe puts every ray's ground point ``AGL tan b`` off towards a side that turns with
the aircraft, so VO's error over any stretch is the change of that offset: at most ``2 AGL tan b``
however long (measured: a 3 deg roll error through a 90 deg turn at 120 m AGL, 7 m). While the check
has shown a tilt error (``AttitudeVerdict.suspect_deg``) the pipeline raises the sigma of the
estimator's position to that bound (``c5_estimator/ekf.py``, ``raise_position_sigma``) and stops the
IMU, whose accelerations the same attitude rotates (3 deg leaks 0.5 m/s^2 of gravity into the
horizontal).

What it can see: where the image is sharp (same-source imagery, a few hundred metres up) the scatter
is a few hundredths of a degree and 4 fixes prove a bias of a degree or two, the fixes before held back
as jumps. Across dates from 1200 m AGL a footprint is 1.7 km, more ground than the 120 s window covers
at 12 m/s: there the fixes prove no bias at all (the unit tests find 10 deg once it spans more), the
image cannot tell the autopilot's error from its own, and VO's ground tilt (below) is the only check
left there (its reach at that height is not measured: its tests fly at 120 m).

What it cannot see in time from the fixes alone: their evidence is as quick as the matcher. Measured
with ALIKED and DISK on a 2-core CPU (a fix every 7-12 s, each landing 7-12 s after its exposure; 3 deg
of roll for 25 s, ``docs/benchmarks.md``): 3-4 fixes fell inside the offset, too few to prove it or to
pin the image's scatter for a jump, and VO and the IMU carried the estimate 5-8 m off at a stated 2 m
(about 220 of 790 GPS_INPUT beyond 3 sigma). Classical and XFeat, solving every 0.3 and 1.4 s, sent none.
A second instance of this check therefore runs on VO's ground tilt (``c1_vio/ground_tilt.py``: the
camera's tilt to the ground from each pair of frames, with no map, at the camera rate), built with
``ground_correlated=False``: a pair's tilt error comes from its own matches' noise (0.5 deg per axis at
120 m AGL, 12 m/s, 3 Hz), not from the ground it shares with the next pair. Its verdicts are answered
the same way (the pipeline refuses fixes as ``vo_attitude_off``, raises the position's sigma, leaves the
IMU out). What both read as tilt is the tilt to the ground the camera sees: over a hillside steeper than
the bound they call the attitude off and fixes are refused (the pose is solved against flat ground, so
those fixes would lean on the slope), VO's within seconds, the fixes' over more ground.

The image-only tilts keep coming while fixes are refused (they do not depend on the prior), so the check
clears by itself when the attitude comes back.
"""

from __future__ import annotations

import functools
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

import numpy as np
from scipy.stats import t as student_t

from gps_denied_onboard.components.c4_pose.types import PoseFix
from gps_denied_onboard.config import PoseConfig

#: Solved fixes needed before the check can find the attitude off (a scatter from fewer says little).
MIN_FIXES: Final[int] = 4
#: One-sided confidence of the lower bound on the bias.
CONFIDENCE: Final[float] = 0.99
#: Independent fixes a window of ground-correlated tilts needs before it can prove anything: with fewer,
#: the scatter of its fixes is the image's noise over one stretch of ground, not how far its mean can
#: stray (module docstring).
MIN_INDEPENDENT: Final[float] = 2.0


@dataclass(frozen=True)
class AttitudeVerdict:
    """The check after one fix: the bias (deg, camera x and y) of the window that says most, its lower
    and upper bounds (deg), the bound the prior allows (deg), how many fixes that window holds, whether
    the attitude is off, whether this fix's tilt jumped from the ones before it (then it is held
    back; see the module docstring), and ``suspect_deg``: the tilt error the estimate may carry from
    the autopilot's attitude, deg, when the check has shown one (off: the bias' upper bound; a jump:
    the jumped tilt), else None."""

    bias_deg: tuple[float, float]
    bias_lower_deg: float
    bias_upper_deg: float
    allowed_deg: float
    fixes: int
    off: bool
    jump: bool = False
    suspect_deg: float | None = None
    #: This fix's own image-only tilt minus the autopilot's, deg, camera x and y.
    tilt_off_deg: tuple[float, float] = (0.0, 0.0)
    #: The oldest exposure (us, Unix) the verdict's evidence reaches back to: while off, the oldest
    #: tilt kept (any window may be the one that proved it); else this tilt's own. A fix exposed from
    #: here on may lean on the tilt error the check has shown.
    since_unix_usec: int = 0

    @property
    def refused(self) -> str | None:
        """The fix's refusal reason, or None: ``attitude_off`` or ``attitude_jump``."""
        return "attitude_off" if self.off else "attitude_jump" if self.jump else None

    def fdr_fields(self) -> dict[str, object]:
        return {
            "bias_deg": [round(self.bias_deg[0], 3), round(self.bias_deg[1], 3)],
            "bias_lower_deg": round(self.bias_lower_deg, 3),
            "bias_upper_deg": round(self.bias_upper_deg, 3),
            "allowed_deg": round(self.allowed_deg, 3),
            "fixes": self.fixes,
            "off": self.off,
            "jump": self.jump,
            "suspect_deg": round(self.suspect_deg, 3) if self.suspect_deg is not None else None,
            "tilt_off_deg": [round(self.tilt_off_deg[0], 3), round(self.tilt_off_deg[1], 3)],
        }


class AttitudeCheck:
    """The running check of the module docstring; one caller at a time (the fix thread)."""

    def __init__(
        self,
        config: PoseConfig,
        *,
        samples: int | None = None,
        max_age_s: float | None = None,
        ground_correlated: bool = True,
    ) -> None:
        """``samples``, ``max_age_s``: how many tilts are kept and for how long (default: the fixes'
        ``pose.attitude_check_fixes`` and ``pose.attitude_check_max_age_s``). ``ground_correlated``:
        the tilts' errors are shared over a footprint of ground (the fixes' image-only tilts, module
        docstring); False for tilts whose errors are each their own (VO's ground tilt from two frames
        of the same camera, ``c1_vio/ground_tilt.py``: the matches' noise)."""
        self._sigma_deg = config.attitude_sigma_deg
        self._allowed_deg = 3.0 * config.attitude_sigma_deg
        age_s = config.attitude_check_max_age_s if max_age_s is None else max_age_s
        self._max_age_usec = int(age_s * 1e6)
        self._recent: deque[_Seen] = deque(maxlen=config.attitude_check_fixes if samples is None else samples)
        self._ground_correlated = ground_correlated
        self._off = False
        #: Fixes in a row, the newest last, whose tilt left the interval the fixes before them pin
        #: (``_departs``): held back as jumps where beyond the bound, and kept out of the baseline either way.
        self._held = 0
        #: Exposure (us) of the first fix of the current state (on or off): its windows, runs and interval
        #: are over this state's fixes only (module docstring, "Each state's evidence is its own").
        self._state_since_usec = 0
        #: While off, the upper bound on the bias from the newest verdict that had a window (deg).
        self._off_upper_deg = 0.0

    def note(self, fix: PoseFix, footprint_m: float) -> AttitudeVerdict:
        """Add ``fix``'s image-only tilt and say whether the autopilot's attitude is off.
        ``footprint_m``: the ground the frame covers across, m (its fixes' errors are correlated)."""
        return self.note_tilt(
            fix.exposure_time_unix_usec,
            fix.image_tilt_off_cam_rad,
            (float(fix.pos_ned_m[0]), float(fix.pos_ned_m[1])),
            footprint_m,
        )

    def note_tilt(
        self,
        time_unix_usec: int,
        tilt_off_cam_rad: tuple[float, float],
        ne_m: tuple[float, float] = (0.0, 0.0),
        footprint_m: float = 1.0,
    ) -> AttitudeVerdict:
        """Add one image-only tilt minus the autopilot's (camera x and y, rad) seen at
        ``time_unix_usec`` and say whether the autopilot's attitude is off. ``ne_m`` (north, east, m)
        and ``footprint_m`` (m) place it on the ground; they count only when ``ground_correlated``."""
        t = int(time_unix_usec)
        dx, dy = tilt_off_cam_rad
        if self._recent and t < self._recent[-1].t_usec:
            self._recent.clear()  # time went back (a replay, a restart of the axis): begin again
            self._held = 0
            self._state_since_usec = t
        self._recent.append(
            _Seen(
                t,
                (math.degrees(dx), math.degrees(dy)),
                (float(ne_m[0]), float(ne_m[1])),
                max(float(footprint_m), 1e-3),
            )
        )
        while self._recent and t - self._recent[0].t_usec > self._max_age_usec:
            self._recent.popleft()
        seen = list(self._recent)
        offs = np.array([s.off_deg for s in seen])
        # Every window, run and baseline is over the current state's own fixes (module docstring, "Each
        # state's evidence is its own"): a window reaching into the state before mixes two tilts.
        in_state = sum(1 for s in seen if s.t_usec >= self._state_since_usec)
        independent = _independent(seen) if self._ground_correlated else None
        windows = [
            w
            for n in _window_sizes(in_state)
            if (w := _Window.of(offs[-n:], self._sigma_deg, None if independent is None else independent(n)))
            is not None
        ]
        # The fixes that left the interval the ones before them pin, in a row: a step of the autopilot's
        # tilt where the image is the sharper sensor, their own evidence (each against the same ground).
        departed = self._departs(offs[-in_state:])
        self._held = self._held + 1 if departed else 0
        run = [
            w
            for n in _window_sizes(self._held)
            if (w := _Window.of(offs[-n:], self._sigma_deg, None)) is not None
        ]
        proofs = windows + run
        was_off = self._off
        if self._off and run:
            # Fixes that left the off state's own interval in a row: the tilt has moved, and they alone
            # say where to.
            self._off = any(w.bias_norm_deg > self._allowed_deg for w in run)
            new_state_fixes = self._held
        elif self._off:
            # Off until the newest evidence no longer shows the bias beyond the bound, not just unproven:
            # every window where tilts are each their own; else the newest that spans a footprint of
            # ground. While no window of the state's fixes says anything yet it stays off, unless the
            # fixes that proved it have left the window (older than the window's age: nothing is known).
            holding = windows if not self._ground_correlated else windows[:1]
            if holding:
                self._off = any(w.bias_norm_deg > self._allowed_deg for w in holding)
            else:
                self._off = seen[0].t_usec <= self._state_since_usec
            new_state_fixes = 1
        else:
            proving = [w.fixes for w in proofs if w.lower_deg > self._allowed_deg]
            self._off = bool(proving)
            new_state_fixes = min(proving, default=1)
        if self._off != was_off:
            # A new state begins with the fixes that showed it: the smallest window that proved the
            # attitude off, the run that showed it back, or else this fix alone.
            self._state_since_usec = seen[-new_state_fixes].t_usec
            self._held = 0
        jump = departed and not self._off and float(np.hypot(*offs[-1])) > self._allowed_deg
        suspect = float(np.hypot(*offs[-1])) if jump else None
        if not proofs:  # too few fixes, or too little ground: nothing is proven either way
            bias = offs[-in_state:].mean(axis=0)
            return AttitudeVerdict(
                (float(bias[0]), float(bias[1])),
                0.0,
                float(np.hypot(*bias)),
                self._allowed_deg,
                in_state,
                self._off,
                jump,
                # Off on the evidence before: the error it showed is still what the estimate may carry.
                self._off_upper_deg if self._off else suspect,
                seen[-1].off_deg,
                seen[0].t_usec if self._off else t,
            )
        worst = max(proofs, key=lambda w: w.lower_deg)
        if self._off:
            self._off_upper_deg = worst.upper_deg
        return AttitudeVerdict(
            (float(worst.bias_deg[0]), float(worst.bias_deg[1])),
            worst.lower_deg,
            worst.upper_deg,
            self._allowed_deg,
            worst.fixes,
            self._off,
            jump,
            worst.upper_deg if self._off else suspect,
            seen[-1].off_deg,
            seen[0].t_usec if self._off else t,
        )

    def _departs(self, offs_deg: np.ndarray) -> bool:
        """The current state's fixes (``offs_deg``, the newest last) before the ones that departed in a
        row (``_held``) pin the tilt better than the autopilot's own sigma (their 99 % prediction
        interval is narrower), and the newest tilt lies outside that interval: the image is then the
        better tilt sensor, and the autopilot's tilt has moved (while on, a jump where it is beyond the
        bound; while off, back or further). A departure under the bound is let through but kept out of
        the baseline: a frame exposed across an attitude step gets part of it (measured in CI: 1.24 of
        3.2 deg), and in the baseline that one fix widened the interval past the sigma, so the next three
        at 3.2 deg were not held back. Across dates the interval is wider than the sigma (the scatter of
        one fix) and nothing departs."""
        newest = offs_deg[-1]
        before = offs_deg[: offs_deg.shape[0] - 1 - self._held]
        n = before.shape[0]
        if n < MIN_FIXES:
            return False
        margin = _prediction_margin_deg(before)
        if margin > self._sigma_deg:
            return False
        return float(np.hypot(*(newest - before.mean(axis=0)))) > margin


@dataclass(frozen=True)
class _Seen:
    """One solved fix as the check keeps it: exposure (us), image-only tilt minus the autopilot's (deg,
    camera x and y), ground position (NED north, east, m) and the frame's footprint across (m)."""

    t_usec: int
    off_deg: tuple[float, float]
    ne_m: tuple[float, float]
    footprint_m: float


def _independent(seen: list[_Seen]) -> Callable[[int], float]:
    """How many independent fixes the newest ``n`` of ``seen`` are worth: 1 + their ground track / their
    mean footprint, at most ``n``."""
    ne = np.array([s.ne_m for s in seen])
    track_m = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(ne, axis=0).T))])
    footprint_m = np.concatenate([[0.0], np.cumsum([s.footprint_m for s in seen])])

    def of_newest(n: int) -> float:
        track = float(track_m[-1] - track_m[-n])
        footprint = float(footprint_m[-1] - footprint_m[-n - 1]) / n
        return min(float(n), 1.0 + track / footprint)

    return of_newest


@dataclass(frozen=True)
class _Window:
    """The bias over some recent fixes: mean (deg, x and y), its norm and the norm's bounds."""

    fixes: int
    bias_deg: np.ndarray
    bias_norm_deg: float
    lower_deg: float
    upper_deg: float

    @classmethod
    def of(cls, offs_deg: np.ndarray, sigma_deg: float, independent: float | None) -> _Window | None:
        """The bias over ``offs_deg`` (deg, camera x and y). ``independent``: how many independent fixes
        ground-correlated tilts are worth (None: each is its own); None where they pin the tilt no better
        than ``sigma_deg`` (deg) and are worth fewer than ``MIN_INDEPENDENT`` (module docstring)."""
        n = offs_deg.shape[0]
        bias = offs_deg.mean(axis=0)
        norm = float(np.hypot(*bias))
        # The mean's error over the independent fixes only.
        ground_correlated = independent is not None
        independent = float(n) if independent is None else independent
        dof = n - 1.0
        if ground_correlated and _prediction_margin_deg(offs_deg) > sigma_deg:
            # The image is not the better tilt sensor here: its error is the ground's, shared over a
            # footprint, and only the independent stretches of ground say how far the mean strays.
            if independent < MIN_INDEPENDENT:
                return None
            dof = independent - 1.0
        std_err = math.sqrt(float(np.sum(offs_deg.var(axis=0, ddof=1))) / independent)
        margin = _t_quantile(dof) * std_err
        return cls(n, bias, norm, max(0.0, norm - margin), norm + margin)


def _prediction_margin_deg(offs_deg: np.ndarray) -> float:
    """Half the one-sided ``CONFIDENCE`` prediction interval of one more tilt after ``offs_deg`` (deg,
    two axes together): how well these tilts pin the next."""
    n = offs_deg.shape[0]
    spread = math.sqrt(float(np.sum(offs_deg.var(axis=0, ddof=1))) * (1.0 + 1.0 / n))
    return _t_quantile(n - 1.0) * spread


@functools.lru_cache(maxsize=4096)
def _student_t(dof_hundredths: int) -> float:
    return float(student_t.ppf(CONFIDENCE, dof_hundredths / 100.0))


def _t_quantile(dof: float) -> float:
    """Student's t at ``CONFIDENCE`` for ``dof`` degrees of freedom, taken down to a hundredth (fewer
    degrees of freedom, a wider margin) so that the few values a flight needs are computed once."""
    return _student_t(math.floor(dof * 100.0 + 1e-9))


def _window_sizes(available: int) -> list[int]:
    """The windows of recent fixes tested: MIN_FIXES, twice that, ... and all that are kept."""
    sizes = []
    n = MIN_FIXES
    while n < available:
        sizes.append(n)
        n *= 2
    if available >= MIN_FIXES:
        sizes.append(available)
    return sizes
