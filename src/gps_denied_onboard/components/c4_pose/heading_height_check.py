"""C4: the autopilot's heading and height, checked against what the area correlation measured.

An area fix (C3 ``orientation_corr``) rectifies the frame with the autopilot's yaw and height above ground,
and its winning hypothesis is the rotation and scale that brought the frame onto the map: a measurement of
the autopilot's heading error (a compass off, a GSF yaw not converged, the camera's mount in yaw) and of its
height error (baro drift, or ground that is not at ``terrain.ground_alt_amsl_m``). The correlation already
searches around both, so its fixes stay right; but the operator should know, and visual odometry turns its
displacements with that heading.

The rule: the accepted area fixes with full evidence (PSR at least ``integrity.full_evidence_psr``) feed a
window of the last ``HEADING_HEIGHT_SAMPLES``; once it holds ``HEADING_HEIGHT_MIN_SAMPLES``, the heading is
off while the median offset is at least ``HEADING_OFF_DEG`` (two grid steps: one is the grid's own
quantisation) and the height while the median scale is ``HEIGHT_OFF_FRAC`` or more from 1. A verdict that
changes is the daemon's to tell (STATUSTEXT, log, ``daemon.status``); every verdict is in the fix's FDR
record.
"""

from __future__ import annotations

import statistics
from collections import deque
from dataclasses import dataclass
from typing import Any, Final

from gps_denied_onboard.components.c4_pose.integrity import AreaEvidence

HEADING_HEIGHT_SAMPLES: Final = 15
HEADING_HEIGHT_MIN_SAMPLES: Final = 6
HEADING_OFF_DEG: Final = 2.0
HEIGHT_OFF_FRAC: Final = 0.04


@dataclass(frozen=True)
class HeadingHeightVerdict:
    """The window's medians (None before ``HEADING_HEIGHT_MIN_SAMPLES``) and whether each is off."""

    samples: int
    heading_offset_deg: float | None
    height_scale: float | None
    heading_off: bool
    height_off: bool

    def fdr_fields(self) -> dict[str, Any]:
        heading, scale = self.heading_offset_deg, self.height_scale
        return {
            "samples": self.samples,
            "heading_offset_deg": None if heading is None else round(heading, 2),
            "height_scale": None if scale is None else round(scale, 4),
            "heading_off": self.heading_off,
            "height_off": self.height_off,
        }


class HeadingHeightCheck:
    """See the module docstring. ``full_evidence_psr``: ``integrity.full_evidence_psr``."""

    def __init__(self, full_evidence_psr: float) -> None:
        self._min_psr = float(full_evidence_psr)
        self._window: deque[tuple[float, float]] = deque(maxlen=HEADING_HEIGHT_SAMPLES)

    def note(self, evidence: AreaEvidence) -> HeadingHeightVerdict | None:
        """Add an accepted area fix's measurement; the verdict after it, or None when its evidence is too
        weak to count."""
        if evidence.psr < self._min_psr:
            return None
        self._window.append((evidence.heading_offset_deg, evidence.height_scale))
        n = len(self._window)
        if n < HEADING_HEIGHT_MIN_SAMPLES:
            return HeadingHeightVerdict(n, None, None, False, False)
        heading = statistics.median(h for h, _ in self._window)
        scale = statistics.median(s for _, s in self._window)
        return HeadingHeightVerdict(
            n,
            heading,
            scale,
            heading_off=abs(heading) >= HEADING_OFF_DEG,
            height_off=abs(scale - 1.0) >= HEIGHT_OFF_FRAC,
        )
