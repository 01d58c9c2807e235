"""C5 prior doubt: a start prior that every fix attempt contradicts is found out, and the search widens.

A start prior (a configured position, HOME_POSITION, a resumed estimate) has nothing behind it but its
stated sigma. GNSS denial often starts with spoofing, so the last position the autopilot trusted can be
hundreds of metres or kilometres off while its sigma says a few tens. The fix path searches around the
prior, so a prior outside its own 3 sigma is never looked past: on the demo map, a configured start 300 m
off at 33 m failed all 129 attempts of a 45 s flight while the output said "3D fix, 33 m".

Rule (:meth:`PriorDoubt.note`, once per fix attempt, inside the attempt's unit of the time axis):

1. While no map fix has been accepted since the estimator started, a failed attempt **counts** against
   the prior when the frame should have matched: the matcher ran and failed (too few inliers, a pose
   rejected, the integrity rule's refusal, the estimator's gate; not a missing attitude, an attitude
   fault, a matcher or VPR error, a fix too late, nor a fix held back to be confirmed), the frame has
   texture (``helpers/texture.py``: at least ``init.doubt_min_texture``) and so does the map where the
   search started (its first candidate: the footprint at the prior is on the map, and the map there
   has something to match). An attempt that does not count leaves the run as it is.
2. From the ``init.doubt_after_failures``-th counted failure in a row on, each one raises the state's
   position sigma to ``init.doubt_growth`` times the sigma that attempt searched with, up to one that
   covers the whole map from where the state is (``cover_sigma_m``): the search region (VPR's, and the
   area correlation's disc) grows with it, and the fix path sweeps it outward, the prior's own place
   kept in every attempt (``pipeline.py``, ``_sweep``).
3. The first accepted fix confirms the state and ends the rule; when the prior had been doubted, how far
   the fix was from it is said (``reanchored_m``).

What the autopilot is told meanwhile: nothing of a state no map fix has confirmed goes out as a 3D fix
(``EstimatorState.map_confirmed``, ``c8_mavlink/messages.py``), so the output is fix_type 1 (0 above
``estimator.max_output_sigma_m``) until the map answers. Why, and what was measured: docs/design.md, "A
wrong prior is found out".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Final

from gps_denied_onboard.config import InitConfig

#: ``no_fix_reason`` values (and prefixes) of attempts where the matcher ran on the frame and the map did
#: not answer: what counts against the prior (rule 1).
_MATCH_FAILURES: Final = ("insufficient_inliers",)
_MATCH_FAILURE_PREFIXES: Final = ("integrity:", "pose_rejected:", "gated:")
#: ... except these: a fix solved but too late to fuse is no evidence about the place.
_NOT_EVIDENCE: Final = frozenset({"gated:too_late"})


def is_match_failure(reason: str | None) -> bool:
    """Whether an attempt that ended with ``no_fix_reason`` ``reason`` is the map not answering there
    (rule 1 of the module docstring); None (a fix) is not."""
    if reason is None or reason in _NOT_EVIDENCE:
        return False
    return reason in _MATCH_FAILURES or reason.startswith(_MATCH_FAILURE_PREFIXES)


@dataclass(frozen=True)
class DoubtVerdict:
    """What one attempt did to the doubt on the start prior."""

    #: Whether this attempt counted against the prior, and if not, why not (``counted`` when it did).
    counted: bool
    why: str
    #: Counted failures in a row against the prior after this attempt.
    failures: int
    #: The sigma (m) the state's position is to be raised to, or None (unchanged).
    raise_to_sigma_m: float | None = None
    #: The first accepted fix after the prior was doubted: its distance from the state before it, m.
    reanchored_m: float | None = None

    def fdr_fields(self) -> dict[str, Any]:
        return {
            "counted": self.counted,
            "why": self.why,
            "failures": self.failures,
            "raise_to_sigma_m": None if self.raise_to_sigma_m is None else round(self.raise_to_sigma_m, 1),
            "reanchored_m": None if self.reanchored_m is None else round(self.reanchored_m, 1),
        }


class PriorDoubt:
    """The rule of the module docstring, for one estimator run (``start`` at each initialisation).
    Single-threaded: the fix half of the pipeline owns it."""

    def __init__(self, config: InitConfig) -> None:
        self._after = config.doubt_after_failures
        self._growth = config.doubt_growth
        self._min_texture = config.doubt_min_texture
        self._active = False
        self._failures = 0
        self._widenings = 0
        self._sigma_m: float | None = None

    def start(self) -> None:
        """The estimator started from a prior no map fix has confirmed in this run."""
        self._active = self._after > 0
        self._failures = 0
        self._widenings = 0
        self._sigma_m = None

    @property
    def active(self) -> bool:
        """Whether the rule still applies (no accepted fix since the start)."""
        return self._active

    @property
    def doubted(self) -> bool:
        """Whether the prior has been widened and not yet confirmed: the fix path sweeps."""
        return self._active and self._widenings > 0

    @property
    def failures(self) -> int:
        return self._failures

    @property
    def widenings(self) -> int:
        """How many times the prior's sigma was raised in this run."""
        return self._widenings

    @property
    def sigma_m(self) -> float | None:
        """The sigma the prior was last raised to (None: never)."""
        return self._sigma_m

    def note(
        self,
        *,
        accepted: bool,
        reason: str | None,
        frame_texture: float | None,
        map_texture: float | None,
        searched_sigma_m: float,
        cover_sigma_m: float,
        moved_m: float | None = None,
    ) -> DoubtVerdict:
        """One attempt's outcome: ``accepted`` (a fix fused) or ``reason`` (its ``no_fix_reason``); the
        edge shares of the frame and of the map where the search started (None: not measured, no map
        there); the horizontal sigma the attempt searched with, m; the sigma that covers the whole map
        from the state, m; ``moved_m``: how far an accepted fix moved the state, m."""
        if not self._active:
            return DoubtVerdict(False, "confirmed", 0)
        if accepted:
            self._active = False
            reanchored = moved_m if self._widenings > 0 else None
            return DoubtVerdict(False, "confirmed", 0, reanchored_m=reanchored)
        why = self._why_not(reason, frame_texture, map_texture)
        if why is not None:
            return DoubtVerdict(False, why, self._failures)
        self._failures += 1
        if self._failures < self._after:
            return DoubtVerdict(True, "counted", self._failures)
        target = min(self._growth * searched_sigma_m, cover_sigma_m)
        if target <= searched_sigma_m:
            return DoubtVerdict(True, "counted", self._failures)  # already covers the map: the sweep goes on
        self._widenings += 1
        self._sigma_m = target
        return DoubtVerdict(True, "counted", self._failures, raise_to_sigma_m=target)

    def _why_not(
        self, reason: str | None, frame_texture: float | None, map_texture: float | None
    ) -> str | None:
        if not is_match_failure(reason):
            return f"not a match failure: {reason}"
        if frame_texture is None or frame_texture < self._min_texture:
            return f"frame texture {_fmt(frame_texture)} < {self._min_texture:g}"
        if map_texture is None:
            return "no map where the search started"
        if map_texture < self._min_texture:
            return f"map texture {map_texture:.3f} < {self._min_texture:g}"
        return None


def _fmt(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3f}"
