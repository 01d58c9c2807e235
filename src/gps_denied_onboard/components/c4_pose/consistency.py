"""Fix consistency: how wrong the absolute fixes really are, measured from the fixes themselves.

One fix's evidence cannot show a failure that every fix shares (across dates, right and wrong fixes had
the same evidence); two fixes of the same flight, compared through the VO between them, can.

Input: every fix the integrity rule passed (whether or not the estimator's gate then took it), and on the
track path (:meth:`FixConsistency.note_track`) the VO motions the estimator accepted. Output: from
:meth:`FixConsistency.assess`, the scale for the next fix's covariance, or ``unverified`` (not fused).

Rule: for consecutive fixes ``i``, ``j`` joined by an unbroken VO chain at most ``consistency_max_gap_s``
apart, ``d = (p_j - p_i) - delta`` and ``NIS = d^T (R_i + R_j + Q)^-1 d`` (chi-square, 2 dof, when the
stated covariances are right). Over the last ``consistency_window_pairs`` pairs the covariance scale is
``s^2 = max(1, sum(min(NIS, cap)) / chi2_{2n}.ppf(alpha))`` (``alpha`` = ``consistency_confidence``: the
upper end of a one-sided interval). Before any pair a fix with full evidence is scaled by
``unverified_sigma_scale`` and a weaker one is not fused: it anchors the next pair. Both calls run inside
their time-axis units, so a replay of the journal repeats them in order. A larger covariance never makes
a wrong fix pull harder.

Why, and what it measured: docs/design.md, "`c4_pose/consistency.py`: fix consistency"; docs/benchmarks.md,
"Cross-date flights with the registry models, and the fix consistency monitor".
"""

from __future__ import annotations

import dataclasses
import math
import uuid
from collections import deque
from dataclasses import dataclass
from typing import Final

import numpy as np
from scipy.special import chdtri

from gps_denied_onboard.components.c1_vio.types import VoMotion
from gps_denied_onboard.components.c4_pose.types import PoseFix
from gps_denied_onboard.config import IntegrityConfig

#: VO chain entries older than this behind the newest are dropped, s (bounds memory; pairs farther
#: apart than ``consistency_max_gap_s`` are never formed anyway).
_CHAIN_KEEP_S: Final[float] = 600.0


@dataclass(frozen=True)
class ConsistencyVerdict:
    """What :meth:`FixConsistency.assess` did to one fix."""

    #: The fix with its covariance scaled by ``sigma_scale**2``.
    fix: PoseFix
    #: False: not to be fused (``reason`` says why); it still anchors the next pair.
    accepted: bool
    #: Factor applied to the fix's sigma (1 = its stated covariance was kept).
    sigma_scale: float
    #: Pairs of fixes the scale was measured on (0: nothing measured yet, ``unverified_sigma_scale``).
    pairs: int
    #: NIS of this fix against the previous one through VO (None: no VO chain to it).
    pair_nis: float | None
    #: Seconds between the previous fix and this one (None: no previous fix).
    pair_gap_s: float | None

    #: Why it was not accepted: ``unverified`` (no pair measured yet and less than full evidence).
    reason: str | None = None

    def fdr_fields(self) -> dict[str, object]:
        return {
            "accepted": self.accepted,
            "reason": self.reason,
            "sigma_scale": round(self.sigma_scale, 4),
            "pairs": self.pairs,
            "pair_nis": None if self.pair_nis is None else round(self.pair_nis, 3),
            "pair_gap_s": None if self.pair_gap_s is None else round(self.pair_gap_s, 3),
        }


@dataclass(frozen=True)
class _ChainPoint:
    frame_id: uuid.UUID
    time_unix_usec: int
    #: Chain segment: a frame without an accepted VO motion from the one before starts a new one.
    segment: int
    #: Sum of the VO displacements since the segment started, (2,) m, and of their covariances, m^2.
    odo_ne_m: np.ndarray
    odo_cov_m2: np.ndarray


@dataclass(frozen=True)
class _KeptFix:
    time_unix_usec: int
    pos_ne_m: np.ndarray
    cov_ne_m2: np.ndarray


class FixConsistency:
    """The fix-to-fix consistency monitor described in the module docstring. Not thread-safe: the
    pipeline calls it inside time-axis units, which the axis serialises."""

    def __init__(self, config: IntegrityConfig) -> None:
        self._cfg = config
        self._chain: deque[_ChainPoint] = deque()
        self._segment = 0
        self._nis: deque[float] = deque(maxlen=config.consistency_window_pairs)
        self._last_fix: _KeptFix | None = None

    @property
    def pairs(self) -> int:
        return len(self._nis)

    def note_track(self, frame_id: uuid.UUID, time_unix_usec: int, motion: VoMotion | None) -> None:
        """The track path's result for one frame: ``motion`` is its VO from the previous frame when the
        estimator accepted it, else None (the chain breaks here and restarts at this frame)."""
        last = self._chain[-1] if self._chain else None
        if motion is not None and last is not None and motion.prev_frame_id == last.frame_id:
            point = _ChainPoint(
                frame_id,
                time_unix_usec,
                last.segment,
                last.odo_ne_m + np.asarray(motion.delta_ne_m, dtype=np.float64),
                last.odo_cov_m2 + np.asarray(motion.cov_ne_m2, dtype=np.float64),
            )
        else:
            self._segment += 1
            point = _ChainPoint(frame_id, time_unix_usec, self._segment, np.zeros(2), np.zeros((2, 2)))
        self._chain.append(point)
        while self._chain and time_unix_usec - self._chain[0].time_unix_usec > _CHAIN_KEEP_S * 1e6:
            self._chain.popleft()

    def _point_at(self, time_unix_usec: int) -> _ChainPoint | None:
        for p in reversed(self._chain):
            if p.time_unix_usec == time_unix_usec:
                return p
            if p.time_unix_usec < time_unix_usec:
                return None
        return None

    def scale_squared(self) -> float:
        """The covariance factor the next fix gets from the pairs kept now."""
        n = len(self._nis)
        if n == 0:
            return float(self._cfg.unverified_sigma_scale) ** 2
        total = sum(min(v, self._cfg.consistency_nis_cap) for v in self._nis)
        bound = float(chdtri(2 * n, 1.0 - self._cfg.consistency_confidence))  # chi2 quantile
        return max(1.0, total / bound)

    def assess(self, fix: PoseFix, *, full_evidence: bool) -> ConsistencyVerdict:
        """Pair ``fix`` with the previous fix through VO, keep the pair's NIS, and return the fix with
        its covariance scaled by what the kept pairs measured. ``fix`` must have passed the integrity
        rule (``full_evidence``: it did not inflate the fix's sigma); its frame must already have been
        tracked (``note_track``)."""
        t = fix.exposure_time_unix_usec
        pos = np.asarray(fix.pos_ned_m[:2], dtype=np.float64)
        cov = np.asarray(fix.cov_ned_m2[:2, :2], dtype=np.float64)
        nis: float | None = None
        gap_s: float | None = None
        prev = self._last_fix
        if self._cfg.consistency_enabled and prev is not None and t > prev.time_unix_usec:
            gap_s = (t - prev.time_unix_usec) / 1e6
            a, b = self._point_at(prev.time_unix_usec), self._point_at(t)
            if (
                a is not None
                and b is not None
                and a.segment == b.segment
                and gap_s <= self._cfg.consistency_max_gap_s
            ):
                d = (pos - prev.pos_ne_m) - (b.odo_ne_m - a.odo_ne_m)
                s_mat = prev.cov_ne_m2 + cov + (b.odo_cov_m2 - a.odo_cov_m2)
                value = float(d @ np.linalg.solve(s_mat, d))
                if math.isfinite(value) and value >= 0.0:
                    nis = value
                    self._nis.append(value)
        if t > (prev.time_unix_usec if prev is not None else -1):
            self._last_fix = _KeptFix(t, pos, cov)
        if not self._cfg.consistency_enabled:
            return ConsistencyVerdict(fix, True, 1.0, 0, None, gap_s)
        n = len(self._nis)
        if n == 0 and not full_evidence:
            return ConsistencyVerdict(fix, False, 1.0, 0, None, gap_s, reason="unverified")
        k2 = self.scale_squared()
        scaled = dataclasses.replace(
            fix,
            cov_ned_m2=np.asarray(fix.cov_ned_m2, dtype=np.float64) * k2,
            shared_sigma_m=fix.shared_sigma_m * math.sqrt(k2),
        )
        return ConsistencyVerdict(scaled, True, math.sqrt(k2), n, nis, gap_s)
