"""Photometric model of the simulated nav camera, and the map-gap degradations.

The renderer gives the map's own radiometry; a real camera sees the same ground with a different exposure,
tone curve, white balance, sensor noise and now and then motion/defocus blur. ``PhotometricModel`` draws
those per frame from a seeded generator keyed by ``(seed, frame_index)``, so frame ``k`` of a run is the
same whatever order frames are rendered in and however many runs came before.

Images are (H, W, 3) uint8 BGR throughout; "DN" is one 8-bit digital number.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum
from statistics import NormalDist

import cv2
import numpy as np

#: Standard normal quantiles at the centres of 256 equal-probability bins: uint8 uniform -> N(0, 1).
_NORMAL_QUANTILES = np.array([NormalDist().inv_cdf((k + 0.5) / 256.0) for k in range(256)], dtype=np.float32)


class GapKind(str, Enum):
    """How the nav image is degraded inside a scenario's map gap.

    ``featureless``: the ground looks uniform (water, snow, fog, smoke): the frame keeps its mean colours but
    loses every feature. ``blackout``: the camera sees almost nothing (lens covered, night, sensor fault).
    """

    FEATURELESS = "featureless"
    BLACKOUT = "blackout"


@dataclass(frozen=True)
class PhotometricParams:
    """Ranges from which the per-frame photometric changes are drawn (uniformly).

    ``gain_range``: multiplicative exposure gain (lo, hi), 1 = unchanged.
    ``gamma_range``: tone-curve exponent (lo, hi) applied to normalised intensity, 1 = linear.
    ``colour_shift_dn``: largest per-channel additive offset, DN (white-balance error), drawn in
        [-colour_shift_dn, +colour_shift_dn] independently for B, G and R.
    ``noise_sigma_dn``: standard deviation of additive Gaussian sensor noise, DN.
    ``blur_prob``: probability that a frame is blurred; ``blur_sigma_px``: the largest Gaussian blur sigma
        (the frame's sigma is drawn in [0.5, 1] x this).
    ``seed``: seed of the per-frame generator.
    """

    gain_range: tuple[float, float] = (1.0, 1.0)
    gamma_range: tuple[float, float] = (1.0, 1.0)
    colour_shift_dn: float = 0.0
    noise_sigma_dn: float = 0.0
    blur_prob: float = 0.0
    blur_sigma_px: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("gain_range", "gamma_range"):
            lo, hi = getattr(self, name)
            if not (0.0 < lo <= hi) or not math.isfinite(hi):
                raise ValueError(f"{name} must be (lo, hi) with 0 < lo <= hi, got {(lo, hi)!r}")
        for name in ("colour_shift_dn", "noise_sigma_dn", "blur_sigma_px"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if not 0.0 <= self.blur_prob <= 1.0:
            raise ValueError(f"blur_prob must be in [0, 1], got {self.blur_prob!r}")

    @property
    def is_identity(self) -> bool:
        """True when no frame is ever changed."""
        return (
            self.gain_range == (1.0, 1.0)
            and self.gamma_range == (1.0, 1.0)
            and self.colour_shift_dn == 0.0
            and self.noise_sigma_dn == 0.0
            and (self.blur_prob == 0.0 or self.blur_sigma_px == 0.0)
        )


@dataclass(frozen=True)
class FrameDraw:
    """The photometric change drawn for one frame (logged by the runner to explain a bad frame)."""

    gain: float
    gamma: float
    colour_shift_bgr_dn: tuple[float, float, float]
    blur_sigma_px: float


class PhotometricModel:
    """Applies seeded, per-frame photometric changes to rendered frames."""

    def __init__(self, params: PhotometricParams, seed: int | None = None) -> None:
        self.params = params
        self.seed = params.seed if seed is None else int(seed)
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")

    def _rng(self, frame_index: int) -> np.random.Generator:
        if frame_index < 0:
            raise ValueError(f"frame_index must be >= 0, got {frame_index}")
        # A generator per (seed, frame): frames are independent of render order.
        return np.random.default_rng([self.seed, int(frame_index)])

    def draw(self, frame_index: int) -> FrameDraw:
        """The change that ``apply`` makes to frame ``frame_index`` (without the noise field)."""
        p = self.params
        rng = self._rng(frame_index)
        gain = float(rng.uniform(*p.gain_range))
        gamma = float(rng.uniform(*p.gamma_range))
        shift = rng.uniform(-p.colour_shift_dn, p.colour_shift_dn, size=3)
        blurred = bool(rng.random() < p.blur_prob) and p.blur_sigma_px > 0.0
        sigma = float(p.blur_sigma_px * rng.uniform(0.5, 1.0)) if blurred else 0.0
        return FrameDraw(gain, gamma, (float(shift[0]), float(shift[1]), float(shift[2])), sigma)

    def apply(self, img: np.ndarray, frame_index: int) -> np.ndarray:
        """Return a changed copy of ``img`` ((H, W, 3) uint8 BGR) for frame ``frame_index``."""
        if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"expected an (H, W, 3) uint8 image, got {img.shape} {img.dtype}")
        if self.params.is_identity:
            return img.copy()
        d = self.draw(frame_index)
        # Draw the noise from a generator separate from draw()'s so draw() stays cheap and both agree.
        noise_rng = np.random.default_rng([self.seed, int(frame_index), 1])
        # Exposure, tone curve and white balance as one 256-entry table per channel (one cv2.LUT pass).
        x = np.arange(256, dtype=np.float64) / 255.0
        curve = 255.0 * np.clip(d.gain * x, 0.0, 1.0) ** d.gamma
        lut = np.stack([curve + s for s in d.colour_shift_bgr_dn], axis=-1)
        lut_u8 = np.clip(np.rint(lut), 0, 255).astype(np.uint8).reshape(256, 1, 3)
        out = cv2.LUT(img, lut_u8)
        if d.blur_sigma_px > 0.0:
            out = cv2.GaussianBlur(out, (0, 0), d.blur_sigma_px)
        if self.params.noise_sigma_dn > 0.0:
            # Gaussian noise from uniform bytes through the inverse normal CDF (256 levels, tails at
            # +-2.7 sigma): statistically the same for 8-bit frames and 3x cheaper than standard_normal.
            uniform = np.asarray(noise_rng.integers(0, 256, size=img.shape, dtype=np.uint8))
            noise = cv2.LUT(uniform, _NORMAL_QUANTILES * np.float32(self.params.noise_sigma_dn))
            out = cv2.add(out, noise, dtype=cv2.CV_8U)
        return out


def degrade_for_gap(img: np.ndarray, kind: GapKind | str) -> np.ndarray:
    """Return ``img`` ((H, W, 3) uint8 BGR) as the camera would see it inside a map gap of ``kind``.

    ``featureless`` keeps only the frame's very low frequencies (a smooth colour field, no corners or
    edges a matcher could use); ``blackout`` leaves a near-black frame (DN <= 6) with the faint structure a
    real underexposed sensor keeps. Deterministic: the same input gives the same output.
    """
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) uint8 image, got {img.shape} {img.dtype}")
    try:
        gap = GapKind(kind)
    except ValueError as exc:
        valid = ", ".join(k.value for k in GapKind)
        raise ValueError(f"unknown map gap kind {kind!r}; expected one of: {valid}") from exc
    h, w = img.shape[:2]
    if gap is GapKind.FEATURELESS:
        # Down to a 4x3 grid of means and back up with a smooth interpolator: no feature survives.
        small = cv2.resize(img, (4, 3), interpolation=cv2.INTER_AREA)
        smooth = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
        return cv2.GaussianBlur(smooth, (0, 0), max(h, w) / 16.0)
    scaled = img.astype(np.float32) * np.float32(0.025)
    return np.clip(np.rint(scaled), 0, 255).astype(np.uint8)
