"""C4 attitude check: is the autopilot's tilt as good as the pose solver is told it is?

The solver leans on the autopilot's roll and pitch (``pose.attitude_sigma_deg``) wherever the image cannot
pin the camera's tilt, and so do VO and the IMU prediction; a wrong attitude (an AHRS fault, a knocked
camera mount) would move every fix by height x tilt error while each fix states it is fine.

Input: per solved fix (or, in a second instance built with ``ground_correlated=False``, per VO pair from
``c1_vio/ground_tilt.py``), the image-only world-down direction minus the autopilot's on the camera's x
and y axes, with the fix's height and ground position. Output: an :class:`AttitudeVerdict` (``off``,
``jump``, the bias and ``suspect_deg``) that the pipeline answers by refusing fixes (``attitude_off``,
``attitude_jump``, ``vo_attitude_off``), raising the estimator's position sigma to ``2 AGL tan b`` and
leaving the IMU out.

Rule, on the scatter the tilts themselves show (never the solver's formal covariance):
- **off**: over the newest 4, 8, ... tilts of the current state and all of them, the mean bias less its
  one-sided 99 % Student-t margin exceeds 3 x ``pose.attitude_sigma_deg``; a window's tilts count as
  ``1 + ground track / footprint`` independent ones and it needs ``MIN_INDEPENDENT`` of them, unless
  they pin the tilt better than the sigma. Off holds until the newest evidence shows no bias beyond it;
- **jump**: where the state's tilts pin the tilt better than the sigma, a tilt outside their 99 %
  prediction interval and beyond the bound is held back; 4 such in a row prove it off (and, while off,
  4 back within the bound let go);
- each state's windows, runs and interval are over the tilts since the check last changed its mind.

Why each part, and what it can and cannot see: docs/design.md, "`c4_pose/attitude_check.py`: the
attitude check"; measured: docs/benchmarks.md, "When the autopilot's attitude is wrong".
"""

from __future__ import annotations

import functools
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

import numpy as np
from scipy.special import stdtrit

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

    @property
    def sigma_deg(self) -> float:
        """The autopilot's tilt sigma the check holds it to (``pose.attitude_sigma_deg``), deg."""
        return self._sigma_deg

    def note(self, fix: PoseFix, footprint_m: float) -> AttitudeVerdict:
        """Add ``fix``'s image-only tilt and say whether the autopilot's attitude is off.
        ``footprint_m``: the ground the frame covers across, m (its fixes' errors are correlated).
        A fix that measured no tilt (``image_tilt_off_cam_rad`` None) is a ValueError: it has nothing to
        add, and the caller must not feed it."""
        if fix.image_tilt_off_cam_rad is None:
            raise ValueError("a fix that measured no tilt of its own cannot feed the attitude check")
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
    return float(stdtrit(dof_hundredths / 100.0, CONFIDENCE))  # Student t quantile


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
