"""Fix integrity: an absolute fix leaves C4 only when the evidence behind it supports it.

Across dates RANSAC and PnP can explain a few dozen self-consistent matches on the wrong alignment to a
pixel, and the solver's covariance then states metres where the truth is tens of metres away. This
module is the one place that judges a solved fix on the evidence the pipeline has.

Input: a solved fix and its :class:`MatchEvidence` per matched candidate (``inlier_count``,
``inlier_ratio``, ``spread_share`` of the frame, ``mean_confidence`` when the matcher gives one: never
invented), the other candidates' poses and the VO-propagated prior. Output: an :class:`IntegrityVerdict`
that refuses the fix with a reason, or passes it with a covariance that reflects the evidence.

The rule (:meth:`FixIntegrity.assess`; the first failing test refuses; thresholds in ``integrity.*``):
1. ``too_few_inliers``, ``low_inlier_ratio``, ``narrow_spread``, ``low_match_confidence`` for a fix from
   point correspondences; for an area alignment (:class:`AreaEvidence`, C3 ``orientation_corr``)
   ``low_psr`` and ``low_peak`` (below the config's floor, or below a margin over what a wrong place
   scores on this map: the cache's calibration), ``ambiguous_peak`` (a second place in the disc
   scores ``max_secondary_ratio`` of the peak or more) and ``patches_disagree`` (a frame close enough to
   the map for its patches to be tried, fewer than ``min_patch_agreement`` of which fall into place);
2. ``ambiguous_candidates``: another candidate with at least ``ambiguity_inlier_share`` of the best's
   inliers gives a pose more than ``ambiguity_sigma`` combined (solver) sigmas away;
3. ``prior_disagreement``: a fix whose sigma the evidence scales by ``weak_evidence_scale`` or more must
   agree with an informative prior (NIS within ``prior_gate_chi2``); stronger fixes are C5's gate's.
A fix that passes has its covariance floored at ``min_sigma_map_px`` map pixels and scaled by ``k**2``
(``k`` grows as the inlier ratio and count, or an area alignment's PSR and peak, fall below
``full_evidence_*``, capped at ``max_sigma_scale``); ``PoseFix.shared_sigma_m`` is floored and scaled
alike. ``regional_sigma_map_px`` (off by default) adds shared regional error to fixes short of full
evidence (:func:`with_regional_error`).

Why each test exists: docs/design.md, "Fix integrity"; measured: docs/benchmarks.md, "How the integrity
thresholds were chosen".
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from gps_denied_onboard.components.c3_matcher.types import AreaAlignment, CandidateMatchSet
from gps_denied_onboard.components.c4_pose.types import PoseFix
from gps_denied_onboard.components.c5_estimator.types import EstimatorState
from gps_denied_onboard.config import IntegrityConfig
from gps_denied_onboard.constants import IntegrityReason


@dataclass(frozen=True)
class MatchEvidence:
    """What one matched candidate offers as evidence (see the module docstring)."""

    inlier_count: int
    putative_count: int
    #: Convex-hull area of the inliers (nav-frame px) over the frame's area, 0..1.
    spread_share: float
    #: Mean matcher confidence over the inliers (0..1), None when the matcher gives none.
    mean_confidence: float | None

    @property
    def inlier_ratio(self) -> float:
        return self.inlier_count / self.putative_count if self.putative_count > 0 else 0.0

    @classmethod
    def of_candidate(cls, candidate: CandidateMatchSet, frame_size_px: tuple[int, int]) -> MatchEvidence:
        """Evidence of ``candidate`` whose query points are pixels of a ``(width, height)`` nav frame."""
        corr = np.asarray(candidate.inlier_correspondences, dtype=np.float32)
        n = int(candidate.inlier_count)
        scores = candidate.inlier_scores
        mean_conf = None
        if scores is not None and np.asarray(scores).size:
            mean_conf = float(np.mean(np.asarray(scores, dtype=np.float64)))
        return cls(
            inlier_count=n,
            putative_count=n + int(candidate.ransac_outlier_count),
            spread_share=hull_share(corr[:, :2] if corr.ndim == 2 and corr.shape[0] else corr, frame_size_px),
            mean_confidence=mean_conf,
        )

    def fdr_fields(self) -> dict[str, Any]:
        return {
            "inliers": self.inlier_count,
            "putative": self.putative_count,
            "inlier_ratio": round(self.inlier_ratio, 4),
            "spread_share": round(self.spread_share, 4),
            "mean_confidence": None if self.mean_confidence is None else round(self.mean_confidence, 4),
        }


@dataclass(frozen=True)
class AreaEvidence:
    """What an area alignment offers as evidence (``CandidateMatchSet.area``; see ``AreaAlignment``)."""

    psr: float
    peak: float
    secondary_ratio: float
    coverage: float
    texture: float
    #: What a wrong place scores on this map for this footprint (the cache's calibration).
    null_psr: float
    null_peak: float
    #: The disc searched, m, and what the winning hypothesis measured of the autopilot's heading and height.
    radius_m: float
    heading_offset_deg: float
    height_scale: float
    #: The footprint's patches tried, and how many agree (0 and 0: not tried, the peak was too weak).
    patches_tried: int = 0
    patches_agreeing: int = 0

    @classmethod
    def of_alignment(cls, area: AreaAlignment) -> AreaEvidence:
        return cls(
            psr=area.psr,
            peak=area.peak,
            secondary_ratio=area.secondary_ratio,
            coverage=area.coverage,
            texture=area.texture,
            null_psr=area.null_psr,
            null_peak=area.null_peak,
            radius_m=area.radius_m,
            heading_offset_deg=math.degrees(area.heading_offset_rad),
            height_scale=area.height_scale,
            patches_tried=area.patches_tried,
            patches_agreeing=area.patches_agreeing,
        )

    def fdr_fields(self) -> dict[str, Any]:
        return {
            "psr": round(self.psr, 3),
            "peak": round(self.peak, 4),
            "secondary_ratio": round(self.secondary_ratio, 4),
            "coverage": round(self.coverage, 4),
            "texture": round(self.texture, 4),
            "null_psr": round(self.null_psr, 3),
            "null_peak": round(self.null_peak, 4),
            "radius_m": round(self.radius_m, 1),
            "heading_offset_deg": round(self.heading_offset_deg, 3),
            "height_scale": round(self.height_scale, 4),
            "patches_tried": self.patches_tried,
            "patches_agreeing": self.patches_agreeing,
        }


def evidence_of(candidate: CandidateMatchSet, frame_size_px: tuple[int, int]) -> MatchEvidence | AreaEvidence:
    """The evidence ``candidate`` offers: its alignment's when it is an area match, else its points'."""
    if candidate.area is not None:
        return AreaEvidence.of_alignment(candidate.area)
    return MatchEvidence.of_candidate(candidate, frame_size_px)


def hull_share(points_px: np.ndarray, frame_size_px: tuple[int, int]) -> float:
    """Area of the convex hull of ``points_px`` (N, 2) over ``width * height``, clipped to 0..1."""
    pts = np.ascontiguousarray(np.asarray(points_px, dtype=np.float32).reshape(-1, 2))
    width, height = frame_size_px
    if pts.shape[0] < 3 or width <= 0 or height <= 0:
        return 0.0
    area = float(cv2.contourArea(cv2.convexHull(pts)))
    return min(max(area / float(width * height), 0.0), 1.0)


@dataclass(frozen=True)
class CandidateFix:
    """A pose solved from one matched candidate, with that candidate's evidence."""

    fix: PoseFix
    evidence: MatchEvidence | AreaEvidence


@dataclass(frozen=True)
class IntegrityVerdict:
    """The rule's decision on one fix.

    ``fix``: the fix to hand to the estimator when accepted (covariance floored and scaled), else the
    solver's fix unchanged (for the record). ``reason``: an :class:`IntegrityReason` value when refused
    (with ``integrity.enabled: false``, the reason it would have been refused for, and ``accepted``).
    """

    accepted: bool
    reason: str | None
    fix: PoseFix
    evidence: MatchEvidence | AreaEvidence
    #: The factor applied to the sigma (1 = full evidence).
    sigma_scale: float
    #: The stated horizontal sigma before the rule (the solver's) and after it, metres.
    solver_sigma_m: float
    #: Distance to, and inlier count of, the strongest disagreeing (or nearest) rival candidate's pose.
    rival_distance_m: float | None = None
    rival_inliers: int | None = None
    #: Horizontal NIS of the fix against the prior (None when no prior was given).
    prior_nis: float | None = None
    #: Regional error (per axis, metres) to add to the fix after the comparisons between map fixes
    #: (:func:`with_regional_error`); 0 for a fix with full evidence.
    regional_sigma_m: float = 0.0

    def fdr_fields(self) -> dict[str, Any]:
        return {
            **self.evidence.fdr_fields(),
            "accepted": self.accepted,
            "reason": self.reason,
            "sigma_scale": round(self.sigma_scale, 3),
            "solver_sigma_m": round(self.solver_sigma_m, 3),
            "rival_distance_m": None if self.rival_distance_m is None else round(self.rival_distance_m, 2),
            "rival_inliers": self.rival_inliers,
            "prior_nis": None if self.prior_nis is None else round(self.prior_nis, 3),
            "regional_sigma_m": round(self.regional_sigma_m, 3),
        }


def with_regional_error(fix: PoseFix, sigma_m: float) -> PoseFix:
    """``fix`` stating a regional error of ``sigma_m`` per horizontal axis more: added to its covariance
    and to the error it shares with the fixes around it (in quadrature)."""
    if sigma_m <= 0.0:
        return fix
    cov = np.array(fix.cov_ned_m2, dtype=np.float64, copy=True)
    cov[:2, :2] += np.eye(2) * sigma_m**2
    return dataclasses.replace(fix, cov_ned_m2=cov, shared_sigma_m=math.hypot(fix.shared_sigma_m, sigma_m))


def with_timing_error(fix: PoseFix, vel_ne_m_s: np.ndarray, sigma_s: float) -> PoseFix:
    """``fix`` stating the position error its exposure time's doubt makes: ``sigma_s`` (1 sigma) along
    the velocity ``vel_ne_m_s``, in its covariance and in the error it shares with its neighbours (the
    camera's lateness is the same for them)."""
    v = np.asarray(vel_ne_m_s, dtype=np.float64)[:2]
    if sigma_s <= 0.0 or not np.all(np.isfinite(v)):
        return fix
    cov = np.array(fix.cov_ned_m2, dtype=np.float64, copy=True)
    cov[:2, :2] += np.outer(v, v) * sigma_s**2
    along_m = float(np.hypot(*v)) * sigma_s
    return dataclasses.replace(fix, cov_ned_m2=cov, shared_sigma_m=math.hypot(fix.shared_sigma_m, along_m))


def _horiz_sigma_m(cov: np.ndarray) -> float:
    return float(np.sqrt(max(np.max(np.linalg.eigvalsh(np.asarray(cov)[:2, :2])), 0.0)))


class FixIntegrity:
    """The fix-integrity rule (module docstring) with its thresholds from the ``integrity`` section."""

    def __init__(self, config: IntegrityConfig) -> None:
        self._cfg = config

    @property
    def config(self) -> IntegrityConfig:
        return self._cfg

    def wants_rival(self, best: MatchEvidence | AreaEvidence, rival: MatchEvidence | AreaEvidence) -> bool:
        """Whether a candidate with evidence ``rival`` is supported well enough to be a rival of the best
        (then the pipeline solves its pose and passes it to :meth:`assess`): points, at least
        ``ambiguity_inlier_share`` of the best's inliers; an area alignment, evidence that would pass
        the area tests on its own."""
        if isinstance(rival, AreaEvidence):
            return self._area_refusal(rival) is None
        if isinstance(best, AreaEvidence):
            return False
        return rival.inlier_count >= self._cfg.ambiguity_inlier_share * best.inlier_count

    def _area_refusal(self, ev: AreaEvidence) -> str | None:
        """Why an area alignment's own evidence refuses it (None: it does not)."""
        cfg = self._cfg
        if not ev.psr >= max(cfg.min_psr, cfg.psr_null_margin * ev.null_psr):
            return IntegrityReason.LOW_PSR
        if not ev.peak >= max(cfg.min_peak, cfg.peak_null_margin * ev.null_peak):
            return IntegrityReason.LOW_PEAK
        if not ev.secondary_ratio < cfg.max_secondary_ratio:
            return IntegrityReason.AMBIGUOUS_PEAK
        if ev.patches_tried and ev.patches_agreeing < cfg.min_patch_agreement * ev.patches_tried:
            return IntegrityReason.PATCHES_DISAGREE
        return None

    def sigma_scale(self, ev: MatchEvidence | AreaEvidence) -> float:
        """The evidence's sigma factor: 1 at full evidence, larger as it weakens, capped."""
        cfg = self._cfg
        if isinstance(ev, AreaEvidence):
            k = max(cfg.full_evidence_psr / max(ev.psr, 1e-6), 1.0)
            k *= max(cfg.full_evidence_peak / max(ev.peak, 1e-6), 1.0)
            return min(k, cfg.max_sigma_scale)
        k = math.sqrt(cfg.full_evidence_inliers / max(ev.inlier_count, 1)) if ev.inlier_count else math.inf
        k = max(k, 1.0)
        k *= max(cfg.full_evidence_ratio / max(ev.inlier_ratio, 1e-6), 1.0)
        if ev.mean_confidence is not None:
            k *= max(cfg.full_evidence_confidence / max(ev.mean_confidence, 1e-6), 1.0)
        return min(k, cfg.max_sigma_scale)

    def floored_cov(self, fix: PoseFix, map_gsd_m_px: float) -> np.ndarray:
        """The solver's covariance with each axis floored at ``min_sigma_map_px`` map pixels."""
        cov = np.array(fix.cov_ned_m2, dtype=np.float64, copy=True)
        floor_var = (self._cfg.min_sigma_map_px * float(map_gsd_m_px)) ** 2
        return cov + np.diag(np.maximum(floor_var - np.diag(cov), 0.0))

    def stated_cov(
        self, fix: PoseFix, ev: MatchEvidence | AreaEvidence, map_gsd_m_px: float
    ) -> tuple[np.ndarray, float]:
        """(covariance the fix should state, its sigma scale): floored at the map pixel, then scaled.

        An area alignment's error is mostly the part every fix shares (the autopilot's tilt times the
        height, the map's registration: ``PoseFix.shared_sigma_m``, floored at the map pixel), which no
        peak can vouch for or against; only its own part, the alignment's, grows as the peak weakens."""
        k = self.sigma_scale(ev)
        if isinstance(ev, AreaEvidence):
            shared = self.area_shared_sigma_m(fix, map_gsd_m_px)
            cov = np.array(fix.cov_ned_m2, dtype=np.float64, copy=True)
            own_var = np.maximum(np.diag(cov)[:2] - fix.shared_sigma_m**2, 0.0)
            cov[:2, :2] = np.diag(shared**2 + own_var * k * k)
            return cov, k
        cov = self.floored_cov(fix, map_gsd_m_px)
        return cov * k * k, k

    def area_shared_sigma_m(self, fix: PoseFix, map_gsd_m_px: float) -> float:
        """The error an area fix shares with every fix (its tilt and registration), floored at the map's
        pixel: the map's own georeference is common to every fix too."""
        return max(fix.shared_sigma_m, self._cfg.min_sigma_map_px * float(map_gsd_m_px))

    def assess(
        self,
        best: CandidateFix,
        *,
        map_gsd_m_px: float,
        rivals: Sequence[CandidateFix] = (),
        prior: EstimatorState | None = None,
    ) -> IntegrityVerdict:
        """Judge ``best`` (the fix the pipeline would fuse) on its evidence, its ``rivals`` (poses solved
        from the other well-supported candidates, see :meth:`wants_rival`) and the ``prior`` (the
        estimate at the frame's exposure time, propagated on VO)."""
        cfg = self._cfg
        ev = best.evidence
        solver_sigma = best.fix.horiz_sigma_m
        cov, k = self.stated_cov(best.fix, ev, map_gsd_m_px)
        # The map pixel is the map's own georeference: common to every fix, like the solver's floor.
        if isinstance(ev, AreaEvidence):
            shared = self.area_shared_sigma_m(best.fix, map_gsd_m_px)
        else:
            shared = max(best.fix.shared_sigma_m, cfg.min_sigma_map_px * float(map_gsd_m_px)) * k
        stated = dataclasses.replace(best.fix, cov_ned_m2=cov, shared_sigma_m=shared)

        def verdict(reason: str | None, **extra: Any) -> IntegrityVerdict:
            if not cfg.enabled:  # measurements only: the verdict is recorded, the solver's fix passes
                return IntegrityVerdict(True, reason, best.fix, ev, k, solver_sigma, **extra)
            accepted = reason is None
            weak = k >= cfg.weak_evidence_scale
            return IntegrityVerdict(
                accepted=accepted,
                reason=reason,
                fix=stated if accepted else best.fix,
                evidence=ev,
                sigma_scale=k,
                solver_sigma_m=solver_sigma,
                regional_sigma_m=cfg.regional_sigma_map_px * float(map_gsd_m_px) if weak else 0.0,
                **extra,
            )

        rival_d: float | None = None
        rival_n: int | None = None
        ambiguous = False
        sigma_b = _horiz_sigma_m(self.floored_cov(best.fix, map_gsd_m_px))
        for rival in rivals:
            if not self.wants_rival(ev, rival.evidence):
                continue
            d = float(np.hypot(*(np.asarray(rival.fix.pos_ned_m)[:2] - np.asarray(best.fix.pos_ned_m)[:2])))
            sigma_r = _horiz_sigma_m(self.floored_cov(rival.fix, map_gsd_m_px))
            limit = cfg.ambiguity_sigma * math.hypot(sigma_b, sigma_r)
            far = d > limit
            # Report the disagreeing rival if any, else the nearest one.
            if (far and not ambiguous) or (not ambiguous and (rival_d is None or d < rival_d)):
                rival_d = d
                rival_n = rival.evidence.inlier_count if isinstance(rival.evidence, MatchEvidence) else None
            ambiguous = ambiguous or far

        nis: float | None = None
        if prior is not None:
            innov = np.asarray(stated.pos_ned_m)[:2] - np.asarray(prior.pos_ned_m)[:2]
            # Relative to the map: the prior and the fix carry the same map error, which cancels here.
            s_mat = prior.map_frame_cov_ne_m2 + cov[:2, :2]
            try:
                nis = float(innov @ np.linalg.solve(s_mat, innov))
            except np.linalg.LinAlgError:
                nis = None
        extra = {"rival_distance_m": rival_d, "rival_inliers": rival_n, "prior_nis": nis}

        if isinstance(ev, AreaEvidence):
            refusal = self._area_refusal(ev)
            if refusal is not None:
                return verdict(refusal, **extra)
        elif ev.inlier_count < cfg.min_inliers:
            return verdict(IntegrityReason.TOO_FEW_INLIERS, **extra)
        elif ev.inlier_ratio < cfg.min_inlier_ratio:
            return verdict(IntegrityReason.LOW_INLIER_RATIO, **extra)
        elif ev.spread_share < cfg.min_spread_share:
            return verdict(IntegrityReason.NARROW_SPREAD, **extra)
        elif ev.mean_confidence is not None and ev.mean_confidence < cfg.min_mean_confidence:
            return verdict(IntegrityReason.LOW_MATCH_CONFIDENCE, **extra)
        if ambiguous:
            return verdict(IntegrityReason.AMBIGUOUS_CANDIDATES, **extra)
        if (
            nis is not None
            and prior is not None
            and k >= cfg.weak_evidence_scale
            and _horiz_sigma_m(prior.map_frame_cov_ne_m2) <= cfg.prior_max_sigma_m
            and nis > cfg.prior_gate_chi2
        ):
            return verdict(IntegrityReason.PRIOR_DISAGREEMENT, **extra)
        return verdict(None, **extra)
