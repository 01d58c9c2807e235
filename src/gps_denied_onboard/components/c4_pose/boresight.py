"""C4 boresight: the camera's mount as a flight's own images measured it (``gdnav fdr boresight``).

A mount a fraction of a degree off nadir (or an AHRS a little off level: from the camera the two are the
same) moves every fix by height x tan(offset), the same way each time. ``pose.attitude_sigma_deg`` must
cover it until the mount is measured and set (``camera.mount_roll_deg``, ``camera.mount_pitch_deg``).

Input: a flight's FDR records: every VO pair's tilt to the ground minus the autopilot's (``pipeline.frame``
``ground_tilt_check.tilt_off_deg``, after the mount in use; each pair's error its own) and the fixes'
image-only tilts (``pipeline.fix`` ``attitude_check.tilt_off_deg``). Output: the offset still left per
axis with a 99 % Student-t interval from the VO tilts, the fixes' mean beside it as a check (no interval:
their errors are shared and carry the autopilot's wander), and the mount to set (the one in use plus the
offset), or why not.

Rule: a mount is settable when at least ``MIN_SAMPLES`` tilts pin both axes to ``max_half_width_deg``
(about 330 pairs, 2 minutes at 3 Hz, at 120 m AGL for 0.1 deg). Calibrate low over flat, textured ground:
a slope reads as tilt. A yaw offset of the mount is not measured (the fixes solve the heading).

Why, and what it changed: docs/design.md, "The camera boresight"; docs/benchmarks.md, "Camera boresight".
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import numpy as np
from scipy.special import stdtrit

#: Fewest VO tilts a mount is ever set from.
MIN_SAMPLES: Final[int] = 30
#: Two-sided confidence of the intervals.
CONFIDENCE: Final[float] = 0.99
#: Default of the widest 99 % half-interval per axis a settable mount may have, deg.
DEFAULT_MAX_HALF_WIDTH_DEG: Final[float] = 0.1


@dataclass(frozen=True)
class TiltOffset:
    """The mean of some image-minus-camera tilts (deg, camera x and y), its 99 % half-interval per axis
    (deg; independent samples assumed), their scatter (deg, per axis) and how many there were."""

    mean_deg: tuple[float, float]
    half_width_deg: tuple[float, float]
    scatter_deg: tuple[float, float]
    samples: int

    @classmethod
    def of(cls, tilts_deg: np.ndarray) -> TiltOffset | None:
        """Over ``tilts_deg`` ((N, 2), deg); None for fewer than 2 (no scatter, no interval)."""
        tilts = np.asarray(tilts_deg, dtype=np.float64).reshape(-1, 2)
        tilts = tilts[np.all(np.isfinite(tilts), axis=1)]
        n = tilts.shape[0]
        if n < 2:
            return None
        scatter = tilts.std(axis=0, ddof=1)
        half = float(stdtrit(n - 1, 0.5 + CONFIDENCE / 2.0)) * scatter / math.sqrt(n)  # Student t quantile
        mean = tilts.mean(axis=0)
        return cls(
            (float(mean[0]), float(mean[1])),
            (float(half[0]), float(half[1])),
            (float(scatter[0]), float(scatter[1])),
            n,
        )


@dataclass(frozen=True)
class BoresightEstimate:
    """What a flight says about the mount: ``mount_used_deg`` (roll, pitch) it flew with, the VO tilts
    left after it (``vo``) and the fixes' (``fixes``, a check), the mount to set (``mount_deg``: used
    plus VO's mean; None without VO tilts), and whether the evidence is enough to set it (``settable``,
    with ``why`` when not)."""

    mount_used_deg: tuple[float, float]
    vo: TiltOffset | None
    fixes: TiltOffset | None
    mount_deg: tuple[float, float] | None
    settable: bool
    why: str | None

    def as_dict(self) -> dict[str, object]:
        def offset(o: TiltOffset | None, *, interval: bool) -> dict[str, object] | None:
            if o is None:
                return None
            return {
                "mean_deg": [round(v, 4) for v in o.mean_deg],
                # The fixes' errors are shared over the ground and the attitude's wander: an interval
                # that counts each as independent would claim far more than they pin.
                **({"half_width_99_deg": [round(v, 4) for v in o.half_width_deg]} if interval else {}),
                "scatter_deg": [round(v, 4) for v in o.scatter_deg],
                "samples": o.samples,
            }

        return {
            "mount_used_deg": list(self.mount_used_deg),
            "vo_ground_tilt": offset(self.vo, interval=True),
            "fixes": offset(self.fixes, interval=False),
            "mount_deg": [round(v, 3) for v in self.mount_deg] if self.mount_deg is not None else None,
            "settable": self.settable,
            "why_not": self.why,
        }


def estimate_boresight(
    vo_tilts_deg: np.ndarray,
    fix_tilts_deg: np.ndarray,
    mount_used_deg: tuple[float, float],
    *,
    max_half_width_deg: float = DEFAULT_MAX_HALF_WIDTH_DEG,
) -> BoresightEstimate:
    """The mount a flight's tilts ask for (module docstring). ``vo_tilts_deg``, ``fix_tilts_deg``:
    (N, 2) image-minus-camera tilts, deg, camera x and y, measured with ``mount_used_deg`` (roll,
    pitch, deg) in use."""
    if not max_half_width_deg > 0:
        raise ValueError(f"max_half_width_deg must be > 0, got {max_half_width_deg!r}")
    vo = TiltOffset.of(vo_tilts_deg)
    fixes = TiltOffset.of(fix_tilts_deg)
    if vo is None:
        return BoresightEstimate(mount_used_deg, None, fixes, None, False, "no VO ground tilts recorded")
    mount = (mount_used_deg[0] + vo.mean_deg[0], mount_used_deg[1] + vo.mean_deg[1])
    why = None
    if vo.samples < MIN_SAMPLES:
        why = f"{vo.samples} VO ground tilts, at least {MIN_SAMPLES} needed"
    elif max(vo.half_width_deg) > max_half_width_deg:
        why = (
            f"99 % interval +/-{max(vo.half_width_deg):.3f} deg, wider than {max_half_width_deg:g} deg: "
            "fly longer, lower or over more texture"
        )
    return BoresightEstimate(mount_used_deg, vo, fixes, mount, why is None, why)
