"""C4 fix consistency: the fixes' stated covariance is scaled by what pairs of fixes, compared through
VO, measured (``components/c4_pose/consistency.py``)."""

from __future__ import annotations

import uuid

import numpy as np
import pytest
from scipy.stats import chi2

from gps_denied_onboard.components.c1_vio.types import VoMotion
from gps_denied_onboard.components.c4_pose.consistency import FixConsistency
from gps_denied_onboard.components.c4_pose.types import PoseFix
from gps_denied_onboard.components.c6_tiles.types import TileId
from gps_denied_onboard.config import IntegrityConfig

FRAME_DT_US = 333_333
SPEED_N_M_S = 40.0
VO_SIGMA_M = 0.3


class _Flight:
    """A vehicle flying north at 40 m/s, its frames tracked by VO with 0.3 m per-frame sigma (noise
    drawn), and fixes of it with a stated sigma and a real error drawn at another sigma."""

    def __init__(self, monitor: FixConsistency, seed: int = 0) -> None:
        self.monitor = monitor
        self.rng = np.random.default_rng(seed)
        self.t_us = 1_000_000_000
        self.frame_id = uuid.uuid4()
        self.true_n = 0.0
        monitor.note_track(self.frame_id, self.t_us, None)

    def fly(self, frames: int, *, vo: bool = True) -> None:
        for _ in range(frames):
            prev, self.frame_id = self.frame_id, uuid.uuid4()
            self.t_us += FRAME_DT_US
            step = SPEED_N_M_S * FRAME_DT_US / 1e6
            self.true_n += step
            motion = None
            if vo:
                delta = np.array([step, 0.0]) + self.rng.normal(0.0, VO_SIGMA_M, 2)
                cov = np.eye(2) * VO_SIGMA_M**2
                motion = VoMotion(self.frame_id, prev, FRAME_DT_US / 1e6, delta, cov, 300)
            self.monitor.note_track(self.frame_id, self.t_us, motion)

    def fix(self, stated_sigma_m: float, true_sigma_m: float) -> PoseFix:
        err = self.rng.normal(0.0, true_sigma_m, 2)
        return PoseFix(
            frame_id=self.frame_id,
            exposure_time_unix_usec=self.t_us,
            pos_ned_m=np.array([self.true_n + err[0], err[1], -1200.0]),
            cov_ned_m2=np.diag([stated_sigma_m**2, stated_sigma_m**2, 4 * stated_sigma_m**2]),
            lat_deg=47.0,
            lon_deg=-99.1,
            alt_amsl_m=1600.0,
            yaw_rad=0.0,
            yaw_sigma_rad=0.01,
            attitude_disagreement_rad=0.01,
            image_tilt_off_cam_rad=(0.01, 0.0),
            inlier_count=150,
            residual_px=1.5,
            tile_id=TileId(16, 1, 2),
            shared_sigma_m=stated_sigma_m,
        )


def _run(stated: float, true: float, fixes: int, seed: int = 0, **cfg: object) -> list[float]:
    flight = _Flight(FixConsistency(IntegrityConfig(**cfg)), seed)  # type: ignore[arg-type]
    scales = []
    for _ in range(fixes):
        flight.fly(10)
        scales.append(flight.monitor.assess(flight.fix(stated, true), full_evidence=True).sigma_scale)
    return scales


def test_first_fix_is_scaled_by_the_unverified_factor() -> None:
    flight = _Flight(FixConsistency(IntegrityConfig(unverified_sigma_scale=3.0)))
    flight.fly(5)
    fix = flight.fix(5.0, 5.0)
    verdict = flight.monitor.assess(fix, full_evidence=True)
    assert verdict.pairs == 0 and verdict.pair_nis is None
    assert verdict.sigma_scale == pytest.approx(3.0)
    np.testing.assert_allclose(verdict.fix.cov_ned_m2, fix.cov_ned_m2 * 9.0)


def test_honest_fixes_converge_towards_their_stated_sigma() -> None:
    """Fixes as good as they say: once the window (20 pairs) is full the scale stays under 1.6 (median
    under 1.4), and it is never below 1."""
    for seed in range(3):
        scales = _run(stated=5.0, true=5.0, fixes=40, seed=seed)
        assert scales[0] == pytest.approx(3.0)
        assert all(s >= 1.0 for s in scales)
        assert max(scales[21:]) < 1.6
        assert np.median(scales[21:]) < 1.4


def test_overconfident_fixes_get_the_sigma_they_really_have() -> None:
    """The NAIP cross-date case: 6 m stated, ~30 m real per axis. The scale measures ~5 and the scaled
    sigma covers the real error (within 3 sigma for ~99 % of the fixes, as 2-D Gaussians should)."""
    flight = _Flight(FixConsistency(IntegrityConfig()), seed=3)
    errors_sigma = []
    scales = []
    for _ in range(60):
        flight.fly(12)
        fix = flight.fix(6.0, 30.0)
        verdict = flight.monitor.assess(fix, full_evidence=True)
        scales.append(verdict.sigma_scale)
        err = float(np.hypot(fix.pos_ned_m[0] - flight.true_n, fix.pos_ned_m[1]))
        errors_sigma.append(err / verdict.fix.horiz_sigma_m)
    assert np.median(scales[10:]) > 4.0
    assert sum(e > 3.0 for e in errors_sigma) <= 2
    # Without the monitor 6 m would have been stated: most of them beyond 3 sigma.
    unscaled = np.array(errors_sigma) * np.array(scales)
    assert np.mean(unscaled > 3.0) > 0.5


def test_a_broken_vo_chain_pairs_nothing() -> None:
    """No pair across a frame without accepted VO: the motion in between would be the estimator's
    prediction, the thing being checked."""
    flight = _Flight(FixConsistency(IntegrityConfig()))
    flight.fly(10)
    flight.monitor.assess(flight.fix(5.0, 5.0), full_evidence=True)
    flight.fly(1, vo=False)
    flight.fly(9)
    verdict = flight.monitor.assess(flight.fix(5.0, 5.0), full_evidence=True)
    assert verdict.pair_nis is None and verdict.pairs == 0
    assert verdict.pair_gap_s == pytest.approx(10 * FRAME_DT_US / 1e6)
    # The chain restarted at the gap: the next fix pairs with this one.
    flight.fly(10)
    assert flight.monitor.assess(flight.fix(5.0, 5.0), full_evidence=True).pairs == 1


def test_pairs_too_far_apart_are_not_formed() -> None:
    flight = _Flight(FixConsistency(IntegrityConfig(consistency_max_gap_s=2.0)))
    flight.fly(3)
    flight.monitor.assess(flight.fix(5.0, 5.0), full_evidence=True)
    flight.fly(7)  # 2.33 s
    assert flight.monitor.assess(flight.fix(5.0, 5.0), full_evidence=True).pair_nis is None


def test_the_scale_is_the_confidence_bound_over_the_capped_pairs() -> None:
    """The formula of the module docstring, on NIS values the test computes itself."""
    cfg = IntegrityConfig(consistency_window_pairs=3, consistency_nis_cap=50.0, consistency_confidence=0.1)
    flight = _Flight(FixConsistency(cfg), seed=7)
    nis = []
    last = None
    for _ in range(5):
        flight.fly(10)
        last = flight.monitor.assess(flight.fix(2.0, 8.0), full_evidence=True)
        if last.pair_nis is not None:
            nis.append(last.pair_nis)
    assert last is not None and len(nis) == 4 and last.pairs == 3
    kept = [min(v, 50.0) for v in nis[-3:]]
    expected = max(1.0, sum(kept) / chi2.ppf(0.1, 6))
    assert last.sigma_scale == pytest.approx(np.sqrt(expected))
    # The error every fix shares grows with the same scale as the covariance.
    assert last.fix.shared_sigma_m == pytest.approx(2.0 * np.sqrt(expected))


def test_one_wrong_fix_is_capped() -> None:
    """A wrong-tile fix 300 m off (stated 2 m) among honest ones: its two pairs count at most the cap."""
    cfg = IntegrityConfig(consistency_nis_cap=100.0)
    flight = _Flight(FixConsistency(cfg), seed=11)
    for _ in range(12):
        flight.fly(10)
        flight.monitor.assess(flight.fix(2.0, 2.0), full_evidence=True)
    flight.fly(10)
    wrong = flight.fix(2.0, 2.0)
    wrong = PoseFix(**{**wrong.__dict__, "pos_ned_m": wrong.pos_ned_m + np.array([0.0, 300.0, 0.0])})
    assert flight.monitor.assess(wrong, full_evidence=True).pair_nis > 1000  # type: ignore[operator]
    flight.fly(10)
    after = flight.monitor.assess(flight.fix(2.0, 2.0), full_evidence=True)
    assert after.pair_nis is not None and after.pair_nis > 1000
    # Two capped pairs among 13: sum <= 2 * 100 + 11 honest pairs.
    assert after.pairs == 13
    assert after.sigma_scale < np.sqrt((200 + 11 * 8) / chi2.ppf(0.05, 26))


def test_off_keeps_the_covariance() -> None:
    scales = _run(stated=5.0, true=30.0, fixes=5, consistency_enabled=False)
    assert scales == [1.0] * 5


def test_an_unverified_fix_with_weak_evidence_is_not_fused_but_anchors_the_next_pair() -> None:
    """No pair yet and the integrity rule inflated its sigma: refused as ``unverified``; the next fix
    pairs with it and is fused with what that pair measured."""
    flight = _Flight(FixConsistency(IntegrityConfig()), seed=5)
    flight.fly(10)
    first = flight.monitor.assess(flight.fix(6.0, 30.0), full_evidence=False)
    assert not first.accepted and first.reason == "unverified" and first.pairs == 0
    assert first.fdr_fields()["reason"] == "unverified"
    flight.fly(10)
    second = flight.monitor.assess(flight.fix(6.0, 30.0), full_evidence=False)
    assert second.accepted and second.pairs == 1 and second.pair_nis is not None
    assert second.sigma_scale == pytest.approx(np.sqrt(max(1.0, second.pair_nis / chi2.ppf(0.05, 2))))
