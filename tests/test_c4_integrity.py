"""The fix-integrity rule (``c4_pose/integrity.py``) on constructed evidence: each reason can refuse, each
can pass, and the stated covariance grows as the evidence weakens."""

from __future__ import annotations

import dataclasses
import uuid

import numpy as np
import pytest

from gps_denied_onboard.components.c3_matcher.base import (
    Features,
    _check_correspondences,
    match_with_lightglue,
)
from gps_denied_onboard.components.c3_matcher.types import CandidateMatchSet
from gps_denied_onboard.components.c4_pose.integrity import (
    CandidateFix,
    FixIntegrity,
    MatchEvidence,
    hull_share,
    with_regional_error,
)
from gps_denied_onboard.components.c4_pose.types import PoseFix
from gps_denied_onboard.components.c5_estimator.types import EstimatorState
from gps_denied_onboard.components.c6_tiles.types import TileId
from gps_denied_onboard.config import ConfigError, IntegrityConfig, config_from_mapping
from gps_denied_onboard.constants import IntegrityReason, Provenance
from gps_denied_onboard.helpers.ransac_filter import RansacFilter

CFG = IntegrityConfig(
    min_inliers=20,
    min_inlier_ratio=0.05,
    min_spread_share=0.05,
    min_mean_confidence=0.3,
    ambiguity_inlier_share=0.5,
    ambiguity_sigma=3.0,
    weak_evidence_scale=1.5,
    prior_gate_chi2=9.21,
    prior_max_sigma_m=150.0,
    full_evidence_inliers=100,
    full_evidence_ratio=0.3,
    max_sigma_scale=10.0,
    min_sigma_map_px=1.0,
)
#: Full evidence: nothing inflates the sigma.
STRONG = MatchEvidence(inlier_count=200, putative_count=400, spread_share=0.6, mean_confidence=None)
GSD = 0.3


def _fix(north_m: float = 0.0, east_m: float = 0.0, sigma_m: float = 1.0) -> PoseFix:
    return PoseFix(
        frame_id=uuid.uuid4(),
        exposure_time_unix_usec=1_000_000,
        pos_ned_m=np.array([north_m, east_m, -120.0]),
        cov_ned_m2=np.diag([sigma_m**2, sigma_m**2, 4.0 * sigma_m**2]),
        lat_deg=17.0,
        lon_deg=78.0,
        alt_amsl_m=620.0,
        yaw_rad=0.0,
        yaw_sigma_rad=0.01,
        attitude_disagreement_rad=0.01,
        image_tilt_off_cam_rad=(0.01, 0.0),
        inlier_count=200,
        residual_px=0.8,
        tile_id=TileId(18, 1, 2),
        shared_sigma_m=sigma_m,
    )


def _prior(
    north_m: float = 0.0, east_m: float = 0.0, sigma_m: float = 5.0, shared_sigma_m: float = 0.0
) -> EstimatorState:
    """``sigma_m``: the filter's own horizontal sigma; the stated covariance adds ``shared_sigma_m``."""
    return EstimatorState(
        time_unix_usec=1_000_000,
        provenance=Provenance.VISUAL_PROPAGATED,
        pos_ned_m=np.array([north_m, east_m, -120.0]),
        vel_ned_m_s=np.zeros(3),
        cov_pos_ned_m2=np.diag([sigma_m**2 + shared_sigma_m**2, sigma_m**2 + shared_sigma_m**2, 4.0]),
        cov_vel_ned_m2_s2=np.eye(3),
        lat_deg=17.0,
        lon_deg=78.0,
        alt_amsl_m=620.0,
        yaw_rad=None,
        last_fix_age_s=3.0,
        shared_sigma_m=shared_sigma_m,
    )


def _assess(ev: MatchEvidence = STRONG, **kw):  # type: ignore[no-untyped-def]
    fix = kw.pop("fix", _fix())
    return FixIntegrity(kw.pop("config", CFG)).assess(CandidateFix(fix, ev), map_gsd_m_px=GSD, **kw)


def test_strong_evidence_passes_with_the_solvers_covariance() -> None:
    v = _assess(prior=_prior())
    assert v.accepted and v.reason is None
    assert v.sigma_scale == pytest.approx(1.0)
    assert v.fix.horiz_sigma_m == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("weak", "reason"),
    [
        (dataclasses.replace(STRONG, inlier_count=19, putative_count=40), IntegrityReason.TOO_FEW_INLIERS),
        (dataclasses.replace(STRONG, inlier_count=30, putative_count=1000), IntegrityReason.LOW_INLIER_RATIO),
        (dataclasses.replace(STRONG, spread_share=0.02), IntegrityReason.NARROW_SPREAD),
        (dataclasses.replace(STRONG, mean_confidence=0.2), IntegrityReason.LOW_MATCH_CONFIDENCE),
    ],
)
def test_each_evidence_threshold_refuses_and_passes_just_above(weak: MatchEvidence, reason: str) -> None:
    v = _assess(weak)
    assert not v.accepted and v.reason == reason
    # The refused verdict carries the solver's fix unchanged, for the record.
    assert v.fix.horiz_sigma_m == pytest.approx(1.0)
    passing = {
        IntegrityReason.TOO_FEW_INLIERS: dataclasses.replace(weak, inlier_count=20),
        IntegrityReason.LOW_INLIER_RATIO: dataclasses.replace(weak, inlier_count=60),
        IntegrityReason.NARROW_SPREAD: dataclasses.replace(weak, spread_share=0.06),
        IntegrityReason.LOW_MATCH_CONFIDENCE: dataclasses.replace(weak, mean_confidence=0.35),
    }[reason]
    assert _assess(passing).accepted


def test_no_confidence_is_not_invented_for_matchers_that_give_none() -> None:
    assert _assess(dataclasses.replace(STRONG, mean_confidence=None)).accepted
    assert not _assess(dataclasses.replace(STRONG, mean_confidence=0.1)).accepted


def test_a_distant_well_supported_rival_makes_the_fix_ambiguous() -> None:
    rival = CandidateFix(_fix(north_m=40.0), dataclasses.replace(STRONG, inlier_count=150))
    v = _assess(rivals=[rival])
    assert not v.accepted and v.reason == IntegrityReason.AMBIGUOUS_CANDIDATES
    assert v.rival_distance_m == pytest.approx(40.0)
    assert v.rival_inliers == 150


def test_a_rival_that_agrees_or_is_weak_is_no_ambiguity() -> None:
    agreeing = CandidateFix(_fix(north_m=2.0), dataclasses.replace(STRONG, inlier_count=150))
    weak_far = CandidateFix(_fix(north_m=400.0), dataclasses.replace(STRONG, inlier_count=90))
    v = _assess(rivals=[agreeing, weak_far])
    assert v.accepted
    assert v.rival_distance_m == pytest.approx(2.0)


def test_rival_distance_is_judged_with_the_solvers_sigmas_not_the_inflated_ones() -> None:
    # 12 m apart: beyond 3 combined sigmas of two 1 m fixes, however weak (inflated) the evidence is;
    # within them once the solvers' own sigmas say 3 m.
    weak = MatchEvidence(inlier_count=25, putative_count=250, spread_share=0.1, mean_confidence=None)
    rival = CandidateFix(_fix(north_m=12.0), weak)
    assert FixIntegrity(CFG).sigma_scale(weak) > 3.0
    assert not _assess(weak, rivals=[rival]).accepted
    loose = CandidateFix(_fix(north_m=12.0, sigma_m=3.0), weak)
    assert _assess(weak, fix=_fix(sigma_m=3.0), rivals=[loose]).accepted


def test_weak_fix_far_from_a_confident_prior_is_refused() -> None:
    weak = MatchEvidence(inlier_count=30, putative_count=60, spread_share=0.3, mean_confidence=None)
    assert FixIntegrity(CFG).sigma_scale(weak) >= CFG.weak_evidence_scale
    v = _assess(weak, fix=_fix(north_m=40.0), prior=_prior(sigma_m=5.0))
    assert not v.accepted and v.reason == IntegrityReason.PRIOR_DISAGREEMENT
    assert v.prior_nis is not None and v.prior_nis > CFG.prior_gate_chi2
    # The same fix near the prior passes; so does it when the prior is too uncertain to judge it.
    assert _assess(weak, fix=_fix(north_m=3.0), prior=_prior(sigma_m=5.0)).accepted
    assert _assess(weak, fix=_fix(north_m=40.0), prior=_prior(sigma_m=200.0)).accepted


def test_the_prior_is_judged_without_the_map_error_it_shares_with_the_fix() -> None:
    """A prior 5 m sure relative to the map, stated 30 m because of the map's common error (a
    cross-date flight): a weak fix 40 m off disagrees with it. Counting the common error, which the fix
    carries too, would let it pass (NIS 1.7 instead of 59)."""
    weak = MatchEvidence(inlier_count=30, putative_count=60, spread_share=0.3, mean_confidence=None)
    prior = _prior(sigma_m=5.0, shared_sigma_m=30.0)
    assert prior.horiz_sigma_m == pytest.approx(np.hypot(5.0, 30.0))
    v = _assess(weak, fix=_fix(north_m=40.0), prior=prior)
    assert not v.accepted and v.reason == IntegrityReason.PRIOR_DISAGREEMENT
    assert v.prior_nis is not None and v.prior_nis > 50.0


def test_full_or_nearly_full_evidence_is_left_to_the_estimators_gate() -> None:
    # C5's gate (with its recovery from a wrong prior) judges a well supported fix, not this rule.
    nearly = dataclasses.replace(STRONG, inlier_count=90)  # sigma scale 1.05 < 1.5
    for ev in (STRONG, nearly):
        v = _assess(ev, fix=_fix(north_m=40.0), prior=_prior(sigma_m=5.0))
        assert v.accepted
        assert v.prior_nis is not None and v.prior_nis > CFG.prior_gate_chi2


def test_a_fix_short_of_full_evidence_must_agree_with_the_prior_by_default() -> None:
    """The evidence of the cross-date XFeat + LighterGlue fix that was accepted 4.0 sigma off (NAIP map
    2009, frames 2014: 145 of 413 matches, confidence 0.31, prior NIS 15): with the default rule it must
    agree with the prior and is refused; with the old 1.5 it was left to the estimator's gate."""
    cfg = IntegrityConfig()
    ev = MatchEvidence(inlier_count=145, putative_count=413, spread_share=0.385, mean_confidence=0.313)
    old = dataclasses.replace(cfg, weak_evidence_scale=1.5, full_evidence_confidence=0.0)
    assert 1.1 <= FixIntegrity(old).sigma_scale(ev) < 1.5  # the confidence did not count
    assert FixIntegrity(cfg).sigma_scale(ev) == pytest.approx(0.5 / (145 / 413) * 0.6 / 0.313)
    fix, prior = _fix(north_m=60.0, sigma_m=5.0), _prior(sigma_m=5.0)
    v = _assess(ev, fix=fix, prior=prior, config=cfg)
    assert not v.accepted and v.reason == IntegrityReason.PRIOR_DISAGREEMENT, v
    assert _assess(ev, fix=fix, prior=prior, config=old).accepted
    # Full evidence (every same-date fix flown) is still the estimator's to judge.
    assert _assess(STRONG, fix=fix, prior=prior, config=cfg).accepted


def test_a_low_match_confidence_is_weaker_evidence() -> None:
    """Below ``full_evidence_confidence`` the mean LightGlue confidence scales the sigma linearly; a
    matcher that gives no confidence is not scaled for it."""
    cfg = IntegrityConfig()
    rule = FixIntegrity(cfg)
    full = MatchEvidence(inlier_count=200, putative_count=250, spread_share=0.5, mean_confidence=0.9)
    assert rule.sigma_scale(full) == 1.0
    assert rule.sigma_scale(dataclasses.replace(full, mean_confidence=None)) == 1.0
    assert rule.sigma_scale(dataclasses.replace(full, mean_confidence=0.48)) == pytest.approx(1.25)


def test_weak_evidence_states_a_regional_error_after_the_comparisons() -> None:
    """A fix short of full evidence carries ``regional_sigma_map_px`` map pixels of regional error, to be
    added (:func:`with_regional_error`) after the map fixes are compared: the prior check still judges it
    without that term. A fix with full evidence carries none."""
    cfg = IntegrityConfig(regional_sigma_map_px=8.0)
    assert IntegrityConfig().regional_sigma_map_px == 0.0  # off unless the map is known to wander
    weak = MatchEvidence(inlier_count=180, putative_count=400, spread_share=0.5, mean_confidence=0.48)
    near = _assess(weak, fix=_fix(north_m=3.0, sigma_m=5.0), prior=_prior(sigma_m=5.0), config=cfg)
    assert near.accepted and near.regional_sigma_m == pytest.approx(cfg.regional_sigma_map_px * GSD)
    far = _assess(weak, fix=_fix(north_m=40.0, sigma_m=5.0), prior=_prior(sigma_m=5.0), config=cfg)
    assert far.reason == IntegrityReason.PRIOR_DISAGREEMENT  # 8 px of regional error would hide it
    assert _assess(STRONG, prior=_prior(), config=cfg).regional_sigma_m == 0.0
    assert near.fdr_fields()["regional_sigma_m"] == pytest.approx(round(8 * GSD, 3))

    fix = near.fix
    more = with_regional_error(fix, 20.0)
    assert more.horiz_sigma_m == pytest.approx(np.hypot(fix.horiz_sigma_m, 20.0))
    assert more.shared_sigma_m == pytest.approx(np.hypot(fix.shared_sigma_m, 20.0))
    assert more.cov_ned_m2[2, 2] == fix.cov_ned_m2[2, 2]
    assert with_regional_error(fix, 0.0) is fix


def test_weaker_evidence_states_a_larger_sigma_capped() -> None:
    rule = FixIntegrity(CFG)
    sigmas = []
    for n in (200, 100, 50, 25):
        ev = MatchEvidence(inlier_count=n, putative_count=2 * n, spread_share=0.6, mean_confidence=None)
        v = _assess(ev)
        sigmas.append(v.fix.horiz_sigma_m)
        # The error every fix shares (1 m here) is scaled with the rest.
        assert v.fix.shared_sigma_m == pytest.approx(v.sigma_scale * 1.0)
    assert sigmas[0] == pytest.approx(sigmas[1]) == pytest.approx(1.0)
    assert sigmas[1] < sigmas[2] < sigmas[3]
    assert sigmas[3] == pytest.approx(2.0)  # sqrt(100 / 25)
    low_ratio = MatchEvidence(inlier_count=100, putative_count=1000, spread_share=0.6, mean_confidence=None)
    assert rule.sigma_scale(low_ratio) == pytest.approx(3.0)  # 0.3 / 0.1 (CFG's full_evidence_ratio)
    hopeless = MatchEvidence(inlier_count=20, putative_count=400, spread_share=0.06, mean_confidence=None)
    assert rule.sigma_scale(hopeless) == pytest.approx(CFG.max_sigma_scale)  # sqrt(5) * 6 > 10
    # The spread is in the solver's covariance already: it has a threshold, not a factor.
    narrow = dataclasses.replace(STRONG, spread_share=0.06)
    assert rule.sigma_scale(narrow) == pytest.approx(1.0)


def test_the_map_pixel_floors_the_stated_sigma() -> None:
    fix = _fix(sigma_m=1.0)
    cov, k = FixIntegrity(CFG).stated_cov(fix, STRONG, map_gsd_m_px=5.0)
    assert k == pytest.approx(1.0)
    assert np.sqrt(np.diag(cov)[:2]) == pytest.approx([5.0, 5.0])
    assert np.sqrt(cov[2, 2]) == pytest.approx(5.0)  # vertical 2 m < 5 m floor
    # The map's pixel is its own georeference: the shared error is floored at it too.
    v = FixIntegrity(CFG).assess(CandidateFix(fix, STRONG), map_gsd_m_px=5.0)
    assert v.fix.shared_sigma_m == pytest.approx(5.0)


def test_disabled_rule_records_the_verdict_but_passes_the_solvers_fix() -> None:
    off = dataclasses.replace(CFG, enabled=False)
    v = _assess(dataclasses.replace(STRONG, inlier_count=5, putative_count=10), config=off)
    assert v.accepted and v.reason == IntegrityReason.TOO_FEW_INLIERS
    assert v.fix.horiz_sigma_m == pytest.approx(1.0)


def test_evidence_of_a_candidate_hull_ratio_and_scores() -> None:
    corners = np.array([[0, 0], [320, 0], [320, 240], [0, 240], [100, 100]], dtype=np.float32)
    corr = np.hstack([corners, corners]).astype(np.float32)
    cand = CandidateMatchSet(TileId(18, 1, 2), 5, corr, 15, 0.5, inlier_scores=np.full(5, 0.8, np.float32))
    ev = MatchEvidence.of_candidate(cand, (640, 480))
    assert ev.spread_share == pytest.approx(0.25)
    assert ev.inlier_ratio == pytest.approx(0.25)
    assert ev.mean_confidence == pytest.approx(0.8)
    no_scores = MatchEvidence.of_candidate(dataclasses.replace(cand, inlier_scores=None), (640, 480))
    assert no_scores.mean_confidence is None
    line = np.array([[0, 0], [100, 100], [200, 200], [300, 300]], dtype=np.float32)
    assert hull_share(line, (640, 480)) == pytest.approx(0.0)
    assert hull_share(line[:2], (640, 480)) == 0.0


def test_config_section_is_validated() -> None:
    with pytest.raises(ConfigError, match=r"integrity\.min_inlier_ratio"):
        config_from_mapping({"integrity": {"min_inlier_ratio": 1.5}})
    with pytest.raises(ConfigError, match=r"integrity\.max_sigma_scale"):
        config_from_mapping({"integrity": {"max_sigma_scale": 0.5}})
    assert config_from_mapping({"integrity": {"min_inliers": 30}}).integrity.min_inliers == 30


class _LightGlue:
    """LightGlue helper double: i <-> i with the given scores, in the given mode."""

    def __init__(self, mode: str, scores: np.ndarray) -> None:
        self.mode = mode
        self.scores = scores

    def match_pair(self, kpts0, desc0, kpts1, desc1, *, image_size0, image_size1):  # type: ignore[no-untyped-def]
        idx = np.arange(len(self.scores), dtype=np.int64)
        return np.stack([idx, idx], axis=1), self.scores


def test_lightglue_confidences_reach_the_inliers_and_mutual_nn_gives_none() -> None:
    """The matcher's scores ride along the correspondences, and RANSAC's mask picks the inliers'."""
    rng = np.random.default_rng(3)
    n = 60
    kpts = rng.uniform(0, 500, size=(n, 2)).astype(np.float32)
    tile_kpts = kpts + np.float32(7.0)  # a pure shift: every match is an inlier ...
    tile_kpts[:10] = rng.uniform(0, 500, size=(10, 2)).astype(np.float32)  # ... except these ten
    scores = np.linspace(0.2, 0.9, n).astype(np.float32)
    query = Features(kpts, np.zeros((n, 8), np.float32), (640, 480))
    tile = Features(tile_kpts, np.zeros((n, 8), np.float32), (512, 512))

    corr = match_with_lightglue(_LightGlue("lightglue", scores), query, tile)
    assert corr.shape == (n, 5)
    pts, conf = _check_correspondences(corr)
    assert pts.shape == (n, 4) and conf is not None
    result = RansacFilter().filter(pts, threshold_px=3.0)
    assert result.inlier_mask is not None and result.inlier_count == n - 10
    assert conf[result.inlier_mask] == pytest.approx(scores[10:])

    mnn = match_with_lightglue(_LightGlue("mutual_nn", scores), query, tile)
    assert mnn.shape == (n, 4)
    assert _check_correspondences(mnn)[1] is None
    with pytest.raises(ValueError, match=r"expected \(M, 4\) or \(M, 5\)"):
        _check_correspondences(np.zeros((3, 6), np.float32))


def test_the_ground_sees_the_refusal_count() -> None:
    """GDN_IREF: the NAMED_VALUE_INT a ground station shows, decoded by pymavlink."""
    from pymavlink.dialects.v20 import common

    from gps_denied_onboard.components.c8_mavlink.messages import named_values
    from gps_denied_onboard.components.c13_fdr.recorder import FdrHealthState
    from gps_denied_onboard.constants import NV_INTEGRITY_REFUSED

    tx = common.MAVLink(None, srcSystem=1, srcComponent=197)
    rx = common.MAVLink(None)
    msgs = named_values(tx, time_boot_ms=5, provenance=Provenance.VISUAL_PROPAGATED, inliers=30,
                        residual_px=1.0, horiz_sigma_m=9.0, frame_drops=0, fdr_health=FdrHealthState.OK,
                        integrity_refused=7)
    decoded = [rx.decode(bytearray(m.pack(tx))) for m in msgs]
    iref = [m for m in decoded if m.get_type() == "NAMED_VALUE_INT" and m.name == NV_INTEGRITY_REFUSED]
    assert len(iref) == 1 and iref[0].value == 7


def test_sitl_analysis_counts_integrity_refusals_by_reason() -> None:
    from gps_denied_onboard.constants import FdrKind
    from gps_denied_onboard.sitl.report import analyse

    def fix(seq: int, reason: str | None) -> dict:
        return {"kind": FdrKind.FIX, "frame_seq": seq, "exposure_time_unix_usec": seq * 10**6,
                "fix_accepted": reason is None, "no_fix_reason": reason}

    records = [fix(1, "integrity:low_inlier_ratio"), fix(2, "integrity:low_inlier_ratio"),
               fix(3, "integrity:ambiguous_candidates"), fix(4, "gated:gated"), fix(5, None)]
    a = analyse({"per_frame": []}, records, lambda t: (0.0, 0.0))
    assert a["integrity_refused"] == {"ambiguous_candidates": 1, "low_inlier_ratio": 2}
    assert a["no_fix_reasons"] == {"gated": 1, "integrity": 3}


def test_sitl_analysis_reports_the_accepted_fixes_shared_offset() -> None:
    """Fixes 3 m east and 1 +/- 2 m north of the truth: the mean offset is (north 1, east 3), fix minus
    truth; refused fixes do not count."""
    from gps_denied_onboard.constants import FdrKind
    from gps_denied_onboard.geo import LocalTangentPlane
    from gps_denied_onboard.sitl.report import analyse

    def truth(t_s: float) -> tuple[float, float]:
        return 47.0 + 1e-4 * t_s, 8.0 + 2e-4 * t_s

    def fix(seq: int, north_m: float, east_m: float, accepted: bool = True) -> dict:
        lat, lon, _ = LocalTangentPlane(*truth(float(seq))).to_geodetic(np.array([north_m, east_m, 0.0]))
        return {"kind": FdrKind.FIX, "frame_seq": seq, "exposure_time_unix_usec": seq * 10**6,
                "fix_accepted": accepted, "no_fix_reason": None if accepted else "gated:gated",
                "fix_lat_deg": float(lat), "fix_lon_deg": float(lon), "fix_sigma_m": 5.0}

    records = [fix(1, 3.0, 3.0), fix(2, -1.0, 3.0), fix(3, 40.0, -40.0, accepted=False)]
    offset = analyse({"per_frame": []}, records, truth)["accepted_fix_offset_m"]
    assert offset == pytest.approx({"north": 1.0, "east": 3.0, "length": 10**0.5}, abs=0.01)
    assert analyse({"per_frame": []}, records[2:], truth)["accepted_fix_offset_m"] is None


def test_sitl_analysis_scores_refused_fixes_against_the_truth() -> None:
    """A refusal is scored like an acceptance: a fix refused 40 m off with sigma 5 was wrong (8 sigma), one
    refused 4 m off was right; an attempt with no solved pose is listed without an error."""
    from gps_denied_onboard.constants import FdrKind
    from gps_denied_onboard.geo import LocalTangentPlane
    from gps_denied_onboard.sitl.report import analyse

    def truth(t_s: float) -> tuple[float, float]:
        return 47.0, 8.0 + 1e-4 * t_s

    def fix(seq: int, north_m: float | None, reason: str | None, inliers: int) -> dict:
        rec = {"kind": FdrKind.FIX, "frame_seq": seq, "exposure_time_unix_usec": seq * 10**6,
               "fix_accepted": reason is None, "no_fix_reason": reason, "inliers": inliers}
        if north_m is not None:
            lat, lon, _ = LocalTangentPlane(*truth(float(seq))).to_geodetic(np.array([north_m, 0.0, 0.0]))
            rec.update(fix_lat_deg=float(lat), fix_lon_deg=float(lon), fix_sigma_m=5.0)
        return rec

    records = [fix(1, 2.0, None, 80), fix(2, 40.0, "integrity:low_inlier_ratio", 22),
               fix(3, 4.0, "integrity:low_inlier_ratio", 21), fix(4, None, "insufficient_inliers", 9)]
    a = analyse({"per_frame": []}, records, truth)
    refused = a["refused_fix_errors"]["integrity:low_inlier_ratio"]
    assert list(a["refused_fix_errors"]) == ["integrity:low_inlier_ratio"]
    assert (refused["n"], refused["beyond_3sigma"]) == (2, 1)
    assert refused["max_error_sigma"] == pytest.approx(8.0, abs=0.01)
    assert refused["p50_error_m"] == pytest.approx(22.0, abs=0.01)
    rows = a["fix_attempts"]
    assert [(r["seq"], r["accepted"], r["inliers"]) for r in rows] == [(1, True, 80), (2, False, 22),
                                                                      (3, False, 21), (4, False, 9)]
    assert rows[0]["error_m"] == pytest.approx(2.0, abs=0.01)
    assert rows[0]["error_sigma"] == pytest.approx(0.4, abs=0.01)
    assert rows[3]["reason"] == "insufficient_inliers" and "error_m" not in rows[3]
    assert a["accepted_fixes"] == 1 and a["accepted_fixes_beyond_3sigma"] == 0
