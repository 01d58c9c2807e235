"""The fix path's effort ladder: how much one fix attempt spends (which C3 matcher, how many candidates).

Rungs come from ``matcher.ladder`` (config), cheapest first. Each attempt takes the first rung that the
situation allows:

- a rung with ``max_prior_sigma_m`` applies only while the prior's horizontal sigma is at most that: a
  tight prior needs only the footprint chip (one candidate) and the fast matcher;
- a rung with ``give_up_after`` yields to the next rung after that many attempts in a row on it gave no
  accepted fix; an accepted fix on any rung sends the ladder back to the bottom.

When every rung the prior allows has given up, the ladder starts again from the lowest of them with fresh
counts (a rung gives up on the ground it was flying over, and the ground changes); a rung without
``give_up_after`` never gives up, so a ladder topped by one stays there. When the prior allows none, the
top rung takes the attempts. No rung in config is one rung, ``default``: the configured matcher with
``rerank.top_n`` candidates (the behaviour without a ladder).

The fix worker is the only caller (``choose`` before an attempt, ``note`` once it is judged), so a
replay of the FDR climbs the same rungs. The rung that gave each attempt is in its ``pipeline.fix``
record and in ``daemon.status``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from gps_denied_onboard.components.c3_matcher.protocol import CrossDomainMatcher
from gps_denied_onboard.config import LadderRung

#: The name of the one rung of a config without a ladder.
DEFAULT_RUNG = "default"


@dataclass(frozen=True)
class Rung:
    """A rung with its matcher: what ``EffortLadder.choose`` hands the fix path."""

    name: str
    #: The C3 strategy's name (as resolved) and the matcher built for it.
    strategy: str
    matcher: CrossDomainMatcher
    candidates: int
    max_prior_sigma_m: float | None = None
    give_up_after: int | None = None

    def allows(self, prior_sigma_m: float) -> bool:
        return self.max_prior_sigma_m is None or prior_sigma_m <= self.max_prior_sigma_m


class LadderError(ValueError):
    """A ladder that cannot work (names, strategies, candidate counts): ``what`` names the setting."""


class EffortLadder:
    """See the module docstring."""

    def __init__(self, rungs: Sequence[Rung]) -> None:
        if not rungs:
            raise LadderError("the effort ladder needs at least one rung")
        names = [r.name for r in rungs]
        if len(set(names)) != len(names):
            raise LadderError(f"rung names must be unique; got {names}")
        self._rungs = tuple(rungs)
        self._failures = dict.fromkeys(names, 0)

    @classmethod
    def single(cls, strategy: str, matcher: CrossDomainMatcher, candidates: int) -> EffortLadder:
        """The one-rung ladder of a config without ``matcher.ladder``."""
        return cls([Rung(DEFAULT_RUNG, strategy, matcher, candidates)])

    @classmethod
    def from_config(
        cls,
        rungs: Sequence[LadderRung],
        matchers: Mapping[str, CrossDomainMatcher],
        *,
        default_strategy: str,
        max_candidates: int,
    ) -> EffortLadder:
        """The ladder of ``matcher.ladder``: each rung's strategy (null: ``default_strategy``) must have
        a matcher in ``matchers``, and its candidates may not exceed ``max_candidates``
        (``rerank.top_n``). Raises ``LadderError`` naming the rung."""
        built = []
        for i, r in enumerate(rungs):
            strategy = r.strategy if r.strategy is not None else default_strategy
            if strategy not in matchers:
                raise LadderError(f"matcher.ladder[{i}] ({r.name}): no matcher for strategy {strategy!r}")
            if r.candidates > max_candidates:
                raise LadderError(
                    f"matcher.ladder[{i}] ({r.name}): candidates {r.candidates} > rerank.top_n "
                    f"{max_candidates} (the matcher can only get what C2.5 hands on)"
                )
            built.append(
                Rung(r.name, strategy, matchers[strategy], r.candidates, r.max_prior_sigma_m, r.give_up_after)
            )
        return cls(built)

    @property
    def rungs(self) -> tuple[Rung, ...]:
        return self._rungs

    def choose(self, prior_sigma_m: float) -> Rung:
        """The rung for an attempt whose prior has this horizontal sigma (m; inf when none)."""
        sigma = prior_sigma_m if math.isfinite(prior_sigma_m) else math.inf
        allowed = [r for r in self._rungs if r.allows(sigma)]
        if not allowed:
            return self._rungs[-1]
        for rung in allowed:
            if rung.give_up_after is None or self._failures[rung.name] < rung.give_up_after:
                return rung
        for rung in allowed:
            self._failures[rung.name] = 0
        return allowed[0]

    def note(self, rung_name: str, accepted: bool) -> None:
        """The outcome of an attempt made on ``rung_name``: an accepted fix resets every rung."""
        if rung_name not in self._failures:
            return
        if accepted:
            for name in self._failures:
                self._failures[name] = 0
        else:
            self._failures[rung_name] += 1

    def failures(self) -> dict[str, int]:
        """Attempts in a row without an accepted fix, per rung."""
        return dict(self._failures)
