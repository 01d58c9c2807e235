"""Area correlation: where a whole rectified frame lies in a window of the map's orientation field.

The numerical core of ``orientation_corr`` (no georeference, no config): a frame already warped north-up at
the map's GSD (``helpers/frame_rectifier.py``) differs from the map by a 2-D shift, plus the heading and
height errors the autopilot's yaw and AGL leave in it. The search:

1. **Coarse, every hypothesis.** At level 2 (half the map's resolution) each hypothesis (a rotation and a
   scale about the frame's nadir point) is correlated with the map window by FFT, normalised by the
   template's energy and the map's energy under it (a cosine, at most 1). Only shifts within the search
   disc whose footprint lies at least ``MIN_COVERAGE`` on map data are candidates.
2. **Fine, the best hypothesis.** At level 1 (the map's resolution) within a few pixels of the coarse
   peak; the peak is refined to a sub-pixel by a parabola through its neighbours on each axis.

The evidence it returns is the integrity rule's to judge (``c4_pose/integrity.py``):
- ``psr``: peak-to-sidelobe ratio of the best hypothesis's coarse surface, the sidelobes being the disc
  beyond ``EXCLUSION_PX`` of the peak: how far the peak stands out of everything else the window offers;
- ``peak``: the fine peak's normalised value: how much of the frame's structure the map explains;
- ``secondary_ratio``: the highest sidelobe over the peak: a second place that looks almost as right.

Levels are relative to the template: level 1 is its GSD, level 2 half of it. A caller matching a large
footprint hands a coarser pair of the map's levels (:class:`LevelView`), so the work per fix does not grow
with the map's resolution. Pixel conventions: OpenCV's (x right, y down, (0, 0) the centre of the
top-left pixel); one level down, pixel centres are ``x2 = (x1 + 0.5) / 2 - 0.5``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Final, Protocol

import cv2
import numpy as np
import scipy.fft as sfft

from gps_denied_onboard.helpers.orientation_field import downsample2, orientation_field

#: The share of the footprint that must lie on map data for a shift to be a candidate.
MIN_COVERAGE: Final = 0.95
#: Radius around the coarse peak left out of the sidelobes, level-2 px (the peak's own width is 1-3 px).
EXCLUSION_PX: Final = 10
#: Fewest sidelobe pixels for a peak-to-sidelobe ratio that means something.
MIN_SIDELOBE_PX: Final = 64
#: Half-width of the fine search around the coarse peak, level-1 px (the coarse peak is good to 1 px,
#: 2 level-1 px).
FINE_RADIUS_PX: Final = 4
#: Local patches: the aligned footprint is cut into about this many cells per side, each a patch of
#: ``PATCH_MIN_PX``..``PATCH_MAX_PX`` level-1 px, placed by its own peak within ``PATCH_RADIUS_PX`` of
#: where the global alignment puts it.
PATCH_CELLS: Final = 8
PATCH_MIN_PX: Final = 24
PATCH_MAX_PX: Final = 64
PATCH_RADIUS_PX: Final = 3
#: A patch whose mean squared field magnitude is below this has too little structure to be placed.
PATCH_MIN_TEXTURE: Final = 0.05
#: Patches are tried only when the whole frame's fine peak is at least this: frames that close to the map
#: (same-source imagery peaks at 0.6-0.9) give patches that find their own places; across dates (peaks
#: 0.13-0.2 on NAIP) nearly none agree, and trying them would cost a fifth of the attempt for nothing.
PATCH_MIN_PEAK: Final = 0.3
_EPS: Final = 1e-9


class FieldWindowSource(Protocol):
    """Map orientation fields by level (1: the mosaic's pixels, each level down half the resolution)."""

    def window(self, level: int, x0: int, y0: int, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """``(z, valid)`` of the level's pixels [y0, y0 + height) x [x0, x0 + width): (h, w) complex64
        and (h, w) bool; outside the map ``valid`` is false and ``z`` 0."""
        ...


@dataclass(frozen=True)
class LevelView:
    """``source`` seen from its level ``base``: this view's level 1 is ``base``, its level 2 ``base + 1``."""

    source: FieldWindowSource
    base: int

    def window(self, level: int, x0: int, y0: int, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        return self.source.window(self.base + level - 1, x0, y0, width, height)


def to_level(px: float, from_level: int, to_level: int) -> float:
    """A pixel coordinate at ``from_level`` in the pixels of ``to_level`` (centres, see the docstring)."""
    scale = 2.0 ** (to_level - from_level)
    return (px + 0.5) / scale - 0.5


@dataclass(frozen=True)
class Hypothesis:
    """A rotation (degrees, OpenCV's sense: counter-clockwise on the image) and a scale, both about the
    frame's nadir point, that bring the rectified frame onto the map."""

    rotation_deg: float
    scale: float


@dataclass(frozen=True)
class Template:
    """A rectified frame: ``grey`` (H, W) float32 at the map's GSD, north up; ``valid`` (H, W) bool, its
    footprint; ``nadir_px`` (x, y), where the ground under the camera lies in it."""

    grey: np.ndarray
    valid: np.ndarray
    nadir_px: tuple[float, float]


@dataclass(frozen=True)
class AreaSearch:
    """What :func:`search` found (see the module docstring for the evidence)."""

    #: Where the frame's nadir lies on the map, level-1 (mosaic) px, sub-pixel.
    nadir_map_px: tuple[float, float]
    hypothesis: Hypothesis
    peak: float
    psr: float
    secondary_ratio: float
    #: Share of the footprint on map data at the peak.
    coverage: float
    #: Mean squared field magnitude over the frame's footprint (0..1): how much structure it holds.
    texture: float
    #: The disc searched, level-1 px, and how many shifts in it were candidates.
    radius_px: float
    candidates: int
    #: How many hypotheses were correlated over the disc.
    hypotheses_tried: int = 0
    #: Local correspondences (P, 4) float64: (x, y) in the rectified frame (``Template`` px) and (x, y)
    #: on the map (level-1 px), one per patch placed by its own peak (:func:`_patches`); and how many
    #: patches had the structure to be tried.
    patches: np.ndarray = field(default_factory=lambda: np.empty((0, 4)))
    patches_tried: int = 0
    timings_ms: dict[str, float] = field(default_factory=dict)


def _canvas(grey: np.ndarray, valid: np.ndarray, margin: int) -> tuple[np.ndarray, np.ndarray]:
    g = cv2.copyMakeBorder(grey, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=0.0)
    v = cv2.copyMakeBorder(
        valid.astype(np.uint8), margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=0
    )
    return g, v > 0


def _warp_field(
    z: np.ndarray, mask: np.ndarray | None, centre: tuple[float, float], hyp: Hypothesis
) -> tuple[np.ndarray, np.ndarray | None]:
    """A field (and its mask) rotated and scaled about ``centre`` by ``hyp``, on the same canvas.

    Rotating an image by ``a`` (OpenCV's sense) turns every gradient direction by ``-a`` in pixel
    coordinates, so the double-angle field turns by ``-2a``: warping the field and turning its phase is
    the field of the warped image, up to the interpolation's smoothing (and it is the same for every
    hypothesis). A pixel of the mask stays valid only where its whole bilinear neighbourhood was."""
    if hyp.rotation_deg == 0.0 and hyp.scale == 1.0:
        return z, mask
    m = cv2.getRotationMatrix2D(centre, hyp.rotation_deg, hyp.scale)
    size = (z.shape[1], z.shape[0])
    pair = cv2.warpAffine(
        z.view(np.float32).reshape(z.shape[0], z.shape[1], 2),
        m,
        size,
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=(0.0, 0.0),
    )
    out = np.ascontiguousarray(pair).view(np.complex64).reshape(z.shape)
    out *= np.complex64(np.exp(-2j * math.radians(hyp.rotation_deg)))
    if mask is None:
        return out, None
    warped = cv2.warpAffine(
        mask.astype(np.float32),
        m,
        size,
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0.0,
    )
    return out, warped > 0.999


class _Correlator:
    """FFT correlation of templates of one canvas size against one map window."""

    def __init__(self, window: np.ndarray, window_valid: np.ndarray, canvas_shape: tuple[int, int]) -> None:
        self.out_shape = (window.shape[0] - canvas_shape[0] + 1, window.shape[1] - canvas_shape[1] + 1)
        self.fft_shape = (sfft.next_fast_len(window.shape[0]), sfft.next_fast_len(window.shape[1]))
        self._fw = sfft.fft2(window, self.fft_shape)
        self._fw2 = sfft.rfft2(np.abs(window) ** 2, self.fft_shape)
        self._fv = sfft.rfft2(window_valid.astype(np.float32), self.fft_shape)

    def _crop(self, a: np.ndarray) -> np.ndarray:
        return a[: self.out_shape[0], : self.out_shape[1]]

    def energy_and_coverage(self, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map energy under ``mask`` at every shift, and the share of ``mask`` on map data."""
        fm = np.conj(sfft.rfft2(mask.astype(np.float32), self.fft_shape))
        energy = self._crop(sfft.irfft2(fm * self._fw2, self.fft_shape))
        cover = self._crop(sfft.irfft2(fm * self._fv, self.fft_shape)) / max(float(mask.sum()), 1.0)
        return energy, cover

    def correlate(self, template: np.ndarray) -> np.ndarray:
        """``Re sum conj(t(x)) w(x + s)`` at every shift ``s`` (the template's top-left corner)."""
        ft = np.conj(sfft.fft2(template, self.fft_shape))
        return self._crop(sfft.ifft2(ft * self._fw).real)


def _fine_surfaces(
    window: np.ndarray, window_valid: np.ndarray, z: np.ndarray, mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(map energy under ``mask``, share of ``mask`` on map data, ``Re sum conj(z) w``) at every shift of
    the template ``z`` over ``window``: the few shifts of the fine stage, by OpenCV's template matching
    (its DFT blocks beat a full-size FFT here by about 2x; the coarse stage, many hypotheses over one
    window, reuses the window's FFT instead)."""
    pair_w = np.ascontiguousarray(window.view(np.float32).reshape(window.shape[0], window.shape[1], 2))
    pair_t = np.ascontiguousarray(z.view(np.float32).reshape(z.shape[0], z.shape[1], 2))
    mask_f = mask.astype(np.float32)
    corr = cv2.matchTemplate(pair_w, pair_t, cv2.TM_CCORR)
    energy = cv2.matchTemplate(
        np.ascontiguousarray(np.abs(window) ** 2, dtype=np.float32), mask_f, cv2.TM_CCORR
    )
    cover = cv2.matchTemplate(window_valid.astype(np.float32), mask_f, cv2.TM_CCORR) / max(
        float(mask.sum()), 1.0
    )
    return energy, cover, corr


def _subpixel(score: np.ndarray, r: int, c: int) -> tuple[float, float]:
    """(dx, dy) of a parabola's vertex through the peak and its neighbours on each axis (0 at an edge or
    where the surface is not curved down)."""

    def vertex(a: float, b: float, d: float) -> float:
        den = a - 2.0 * b + d
        if not (math.isfinite(a) and math.isfinite(d) and den < 0.0):
            return 0.0
        return float(np.clip(0.5 * (a - d) / den, -0.5, 0.5))

    dx = vertex(score[r, c - 1], score[r, c], score[r, c + 1]) if 0 < c < score.shape[1] - 1 else 0.0
    dy = vertex(score[r - 1, c], score[r, c], score[r + 1, c]) if 0 < r < score.shape[0] - 1 else 0.0
    return dx, dy


def search(
    template: Template,
    source: FieldWindowSource,
    predicted_nadir_px: tuple[float, float],
    radius_px: float,
    rotations_deg: Sequence[float] = (0.0,),
    scales: Sequence[float] = (1.0,),
    start: Hypothesis | None = None,
) -> AreaSearch | None:
    """Search the frame ``template`` within ``radius_px`` (level-1 px) of ``predicted_nadir_px`` (level-1
    map px), over the hypotheses ``rotations_deg`` x ``scales`` (each sorted, 0 and 1 among them).

    Without ``start`` the hypotheses are searched one axis at a time from (0, 1): every rotation at the
    best scale, every scale at the best rotation, then the rotations next to the best once more. Heading
    and height errors lower the same peak largely independently, so this finds the grid's best in about a
    third of the correlations of the full grid. With ``start`` (the last frame's answer: the autopilot's
    heading and height errors change slowly) the search climbs from it, one grid step at a time along each
    axis, while the peak grows: about five correlations instead of fifteen. None when no shift in the disc
    has the footprint on the map, or the disc is too small for a peak-to-sidelobe ratio."""
    rots = sorted({float(r) for r in rotations_deg} | {0.0})
    scs = sorted({float(s) for s in scales} | {1.0})
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    extent = max(template.grey.shape)
    # Room for the largest hypothesis to grow the footprint (a few clipped corner pixels do not matter).
    grow = max(max(scs) - 1.0, 0.0) + math.sin(math.radians(max(abs(r) for r in rots)))
    margin1 = 2 * (math.ceil(0.25 * extent * grow) + 2)
    canvas1, valid1 = _canvas(template.grey, template.valid, margin1)
    nadir1 = (template.nadir_px[0] + margin1, template.nadir_px[1] + margin1)
    grey2, valid2 = downsample2(canvas1, valid1)
    nadir2 = ((nadir1[0] + 0.5) / 2.0 - 0.5, (nadir1[1] + 0.5) / 2.0 - 0.5)

    # Coarse: one window for every hypothesis.
    r2 = radius_px / 2.0
    ri = math.ceil(r2)
    pred2 = ((predicted_nadir_px[0] + 0.5) / 2.0 - 0.5, (predicted_nadir_px[1] + 0.5) / 2.0 - 0.5)
    ox = round(pred2[0] - nadir2[0]) - ri
    oy = round(pred2[1] - nadir2[1]) - ri
    h2, w2 = grey2.shape
    window, window_valid = source.window(2, ox, oy, w2 + 2 * ri, h2 + 2 * ri)
    corr = _Correlator(window, window_valid, (h2, w2))
    z_id, m_id = orientation_field(grey2, valid2)
    energy, cover = corr.energy_and_coverage(m_id)
    rows, cols = np.mgrid[: corr.out_shape[0], : corr.out_shape[1]]
    # Shift of the nadir from the prediction at each output index, level-2 px.
    sx = ox + cols + nadir2[0] - pred2[0]
    sy = oy + rows + nadir2[1] - pred2[1]
    inside = (sx * sx + sy * sy <= r2 * r2) & (cover >= MIN_COVERAGE) & (energy > _EPS)
    n_candidates = int(inside.sum())
    timings["coarse_setup"] = (time.perf_counter() - t0) * 1e3
    if n_candidates == 0:
        return None
    denom = np.sqrt(np.where(inside, energy, 1.0))
    texture = float(np.mean(np.abs(z_id[m_id]) ** 2)) if m_id.any() else 0.0

    tried: dict[tuple[float, float], tuple[float, np.ndarray | None]] = {}

    def evaluate(rot: float, scale: float) -> None:
        if (rot, scale) in tried:
            return
        z, _ = _warp_field(z_id, None, nadir2, Hypothesis(rot, scale))
        et = float(np.vdot(z, z).real)
        if et <= _EPS:
            tried[(rot, scale)] = (-math.inf, None)
            return
        score = np.where(inside, corr.correlate(z) / (denom * math.sqrt(et)), -np.inf)
        tried[(rot, scale)] = (float(score.max()), score)

    def best_key() -> tuple[float, float]:
        return max(tried, key=lambda k: tried[k][0])

    if start is not None and start.rotation_deg in rots and start.scale in scs:
        evaluate(start.rotation_deg, start.scale)
        while True:  # climb: the neighbours of the best along each axis, until none is better
            key = best_key()
            i, j = rots.index(key[0]), scs.index(key[1])
            for r in rots[max(i - 1, 0) : i + 2]:
                evaluate(r, key[1])
            for sc in scs[max(j - 1, 0) : j + 2]:
                evaluate(key[0], sc)
            if best_key() == key:
                break
    else:
        evaluate(0.0, 1.0)
        for r in rots:
            evaluate(r, best_key()[1])
        for sc in scs:
            evaluate(best_key()[0], sc)
        i = rots.index(best_key()[0])
        for r in rots[max(i - 1, 0) : i + 2]:
            evaluate(r, best_key()[1])
    timings["coarse"] = (time.perf_counter() - t0) * 1e3
    key = best_key()
    peak2, score2 = tried[key]
    if score2 is None:
        return None
    hyp = Hypothesis(*key)
    k = int(np.argmax(score2))
    pr, pc = divmod(k, score2.shape[1])
    side = inside & ((rows - pr) ** 2 + (cols - pc) ** 2 > EXCLUSION_PX**2)
    if int(side.sum()) < MIN_SIDELOBE_PX:
        return None
    lobes = score2[side]
    psr = float((peak2 - lobes.mean()) / max(float(lobes.std()), _EPS))
    secondary = float(lobes.max() / peak2) if peak2 > 0 else 1.0
    coarse_nadir2 = (ox + pc + nadir2[0], oy + pr + nadir2[1])

    # Fine: the best hypothesis at level 1 around the coarse peak.
    z1, m1 = orientation_field(canvas1, valid1)
    z1, m1w = _warp_field(z1, m1, nadir1, hyp)
    m1 = m1 if m1w is None else m1w
    c1 = ((coarse_nadir2[0] + 0.5) * 2.0 - 0.5, (coarse_nadir2[1] + 0.5) * 2.0 - 0.5)
    rf = FINE_RADIUS_PX
    fx = round(c1[0] - nadir1[0]) - rf
    fy = round(c1[1] - nadir1[1]) - rf
    pad = rf + PATCH_RADIUS_PX
    big, big_valid = source.window(
        1, fx - PATCH_RADIUS_PX, fy - PATCH_RADIUS_PX, canvas1.shape[1] + 2 * pad, canvas1.shape[0] + 2 * pad
    )
    inner = (slice(PATCH_RADIUS_PX, -PATCH_RADIUS_PX), slice(PATCH_RADIUS_PX, -PATCH_RADIUS_PX))
    e1, cov1, c1_surface = _fine_surfaces(big[inner], big_valid[inner], z1, m1)
    et1 = float(np.vdot(z1, z1).real)
    ok1 = (cov1 >= MIN_COVERAGE) & (e1 > _EPS)
    if et1 <= _EPS or not ok1.any():
        return None
    s1 = np.where(ok1, c1_surface / np.sqrt(np.where(ok1, e1, 1.0) * et1), -np.inf)
    k1 = int(np.argmax(s1))
    fr, fc = divmod(k1, s1.shape[1])
    dx, dy = _subpixel(s1, fr, fc)
    nadir_map = (fx + fc + dx + nadir1[0], fy + fr + dy + nadir1[1])
    timings["fine"] = (time.perf_counter() - t0) * 1e3
    # Local: each patch placed by its own peak near where the global alignment puts it.
    placed, patches_tried = np.empty((0, 4)), 0
    if float(s1[fr, fc]) >= PATCH_MIN_PEAK:
        placed, patches_tried = _patches(z1, m1, big, big_valid, (fc, fr))
    if placed.shape[0]:
        # Back through the hypothesis warp to the rectified frame's px, and to the map's.
        inverse = cv2.invertAffineTransform(cv2.getRotationMatrix2D(nadir1, hyp.rotation_deg, hyp.scale))
        canvas_px = placed[:, :2] @ inverse[:, :2].T + inverse[:, 2]
        placed = np.column_stack(
            [canvas_px - margin1, placed[:, 2] + fx - PATCH_RADIUS_PX, placed[:, 3] + fy - PATCH_RADIUS_PX]
        )
    timings["total"] = (time.perf_counter() - t0) * 1e3
    return AreaSearch(
        nadir_map_px=(float(nadir_map[0]), float(nadir_map[1])),
        hypothesis=hyp,
        peak=float(s1[fr, fc]),
        psr=psr,
        secondary_ratio=secondary,
        coverage=float(cov1[fr, fc]),
        texture=texture,
        radius_px=float(radius_px),
        candidates=n_candidates,
        hypotheses_tried=len(tried),
        patches=placed,
        patches_tried=patches_tried,
        timings_ms=timings,
    )


def _patches(
    z: np.ndarray, mask: np.ndarray, window: np.ndarray, window_valid: np.ndarray, at: tuple[int, int]
) -> tuple[np.ndarray, int]:
    """Place the patches of the aligned template field ``z`` (``mask``) each by its own peak.

    ``window`` (``window_valid``) is the map's level-1 field with ``PATCH_RADIUS_PX`` of room around the
    template placed at integer offset ``at`` (x, y). A cell is a patch when it lies wholly in the footprint
    and holds structure (``PATCH_MIN_TEXTURE``); it is placed when its normalised correlation (the same
    ``Re conj(a) b`` as the global search, two channels) peaks inside its search square, on map data: a
    patch whose best is on the square's rim has not found its place. Returns ((P, 4) float64: patch
    centre in template px, its place in window px; patches tried)."""
    ys, xs = np.nonzero(mask)
    if ys.size == 0:
        return np.empty((0, 4)), 0
    x_lo, x_hi, y_lo, y_hi = int(xs.min()), int(xs.max()) + 1, int(ys.min()), int(ys.max()) + 1
    cell = int(np.clip(max(x_hi - x_lo, y_hi - y_lo) // PATCH_CELLS, PATCH_MIN_PX, PATCH_MAX_PX))
    r = PATCH_RADIUS_PX
    pair_t = z.view(np.float32).reshape(z.shape[0], z.shape[1], 2)
    pair_w = window.view(np.float32).reshape(window.shape[0], window.shape[1], 2)
    centre = (cell - 1) / 2.0
    out: list[tuple[float, float, float, float]] = []
    tried = 0
    for y0 in range(y_lo, y_hi - cell + 1, cell):
        for x0 in range(x_lo, x_hi - cell + 1, cell):
            if not mask[y0 : y0 + cell, x0 : x0 + cell].all():
                continue
            if float(np.mean(np.abs(z[y0 : y0 + cell, x0 : x0 + cell]) ** 2)) < PATCH_MIN_TEXTURE:
                continue
            tried += 1
            wx, wy = x0 + at[0], y0 + at[1]
            if not window_valid[wy : wy + cell + 2 * r, wx : wx + cell + 2 * r].all():
                continue
            surface = cv2.matchTemplate(
                np.ascontiguousarray(pair_w[wy : wy + cell + 2 * r, wx : wx + cell + 2 * r]),
                np.ascontiguousarray(pair_t[y0 : y0 + cell, x0 : x0 + cell]),
                cv2.TM_CCORR_NORMED,
            )
            i, j = (int(v) for v in np.unravel_index(int(np.argmax(surface)), surface.shape))
            if not (0 < i < surface.shape[0] - 1 and 0 < j < surface.shape[1] - 1):
                continue
            dx, dy = _subpixel(surface, i, j)
            out.append((x0 + centre, y0 + centre, wx + j + dx + centre, wy + i + dy + centre))
    return np.array(out, dtype=np.float64).reshape(-1, 4), tried
