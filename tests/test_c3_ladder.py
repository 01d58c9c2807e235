"""The fix path's effort ladder (``c3_matcher/ladder.py``): which rung each attempt gets from the prior's
sigma and each rung's run of failures. The matchers are stand-ins (the ladder only hands them on)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gps_denied_onboard.components.c3_matcher.errors import InsufficientInliersError
from gps_denied_onboard.components.c3_matcher.ladder import DEFAULT_RUNG, EffortLadder, LadderError
from gps_denied_onboard.components.c3_matcher.types import CandidateMatchSet, MatchResult
from gps_denied_onboard.config import LadderRung, config_from_mapping

FAST, HEAVY = object(), object()
MATCHERS = {"xfeat_mnn": FAST, "disk_lightglue": HEAVY}


def _ladder() -> EffortLadder:
    rungs = config_from_mapping(
        {
            "matcher": {
                "strategy": "xfeat_mnn",
                "ladder": [
                    {"name": "chip", "candidates": 1, "max_prior_sigma_m": 30.0, "give_up_after": 2},
                    {"name": "wide", "candidates": 3, "give_up_after": 3},
                    {"name": "heavy", "strategy": "disk_lightglue", "candidates": 3},
                ],
            }
        }
    ).matcher.ladder
    return EffortLadder.from_config(rungs, MATCHERS, default_strategy="xfeat_mnn", max_candidates=3)  # type: ignore[arg-type]


def test_a_tight_prior_takes_the_chip_alone_and_a_loose_one_skips_it() -> None:
    ladder = _ladder()
    chip = ladder.choose(10.0)
    assert (chip.name, chip.candidates, chip.matcher) == ("chip", 1, FAST)
    assert ladder.choose(30.0).name == "chip"
    assert ladder.choose(30.1).name == "wide"
    assert ladder.choose(math.inf).name == "wide"


def test_failures_climb_the_ladder_and_an_accepted_fix_sends_it_back_down() -> None:
    ladder = _ladder()
    for _ in range(2):
        ladder.note(ladder.choose(10.0).name, accepted=False)
    assert ladder.choose(10.0).name == "wide"  # the chip gave up after 2
    for _ in range(3):
        ladder.note(ladder.choose(10.0).name, accepted=False)
    heavy = ladder.choose(10.0)
    assert (heavy.name, heavy.strategy, heavy.matcher) == ("heavy", "disk_lightglue", HEAVY)
    ladder.note("heavy", accepted=False)
    assert ladder.choose(10.0).name == "heavy"  # the top never gives up
    ladder.note("heavy", accepted=True)
    assert ladder.failures() == {"chip": 0, "wide": 0, "heavy": 0}
    assert ladder.choose(10.0).name == "chip"


def test_when_every_allowed_rung_gave_up_the_ladder_starts_again_from_the_lowest() -> None:
    rungs = (
        LadderRung("a", candidates=1, give_up_after=1),
        LadderRung("b", candidates=2, give_up_after=2),
        LadderRung("c", candidates=2, max_prior_sigma_m=5.0, give_up_after=1),
    )
    ladder = EffortLadder.from_config(rungs, MATCHERS, default_strategy="xfeat_mnn", max_candidates=3)  # type: ignore[arg-type]
    ladder.note(ladder.choose(50.0).name, accepted=False)
    assert ladder.choose(50.0).name == "b"
    for _ in range(2):
        ladder.note(ladder.choose(50.0).name, accepted=False)
    # a and b (c is not allowed at 50 m) both gave up: a again, with fresh counts for both
    assert ladder.choose(50.0).name == "a"
    assert ladder.failures() == {"a": 0, "b": 0, "c": 0}


def test_a_rung_without_give_up_keeps_the_attempts_once_the_rest_gave_up() -> None:
    rungs = (
        LadderRung("a", candidates=1, give_up_after=1),
        LadderRung("b", candidates=2, max_prior_sigma_m=5.0),
    )
    ladder = EffortLadder.from_config(rungs, MATCHERS, default_strategy="xfeat_mnn", max_candidates=3)  # type: ignore[arg-type]
    ladder.note("a", accepted=False)
    assert ladder.choose(1.0).name == "b"
    ladder.note("b", accepted=False)
    assert ladder.choose(1.0).name == "b"  # b never gives up


def test_no_ladder_is_one_rung_with_the_configured_matcher() -> None:
    ladder = EffortLadder.single("classical", FAST, 3)  # type: ignore[arg-type]
    rung = ladder.choose(math.inf)
    assert (rung.name, rung.strategy, rung.matcher, rung.candidates) == (DEFAULT_RUNG, "classical", FAST, 3)
    ladder.note(DEFAULT_RUNG, accepted=False)
    assert ladder.choose(1.0).name == DEFAULT_RUNG


@pytest.mark.parametrize(
    ("rungs", "words"),
    [
        ((LadderRung("a"), LadderRung("a")), "unique"),
        ((LadderRung("a", strategy="aliked_lightglue"),), "no matcher for strategy 'aliked_lightglue'"),
        ((LadderRung("a", candidates=4),), "candidates 4 > rerank.top_n 3"),
        ((), "at least one rung"),
    ],
)
def test_a_ladder_that_cannot_work_is_refused_naming_the_rung(rungs: tuple, words: str) -> None:
    with pytest.raises(LadderError, match=words):
        EffortLadder.from_config(rungs, MATCHERS, default_strategy="xfeat_mnn", max_candidates=3)  # type: ignore[arg-type]


class _Counting:
    """A C3 double that notes how many candidates each call got; it finds too few inliers (``fail``) or
    matches each candidate it got with 200 inliers."""

    def __init__(self, *, fail: bool) -> None:
        self.fail = fail
        self.calls: list[int] = []

    def match(self, frame, rerank_result, calibration):  # type: ignore[no-untyped-def]
        self.calls.append(len(rerank_result.candidates))
        if self.fail:
            n = len(rerank_result.candidates)
            raise InsufficientInliersError(
                "too few", frame_id=frame.frame_id, best_inlier_count=3, threshold=25,
                candidates_input=n, candidates_dropped=0,
            )
        q = np.random.default_rng(0).uniform((0, 0), (640, 480), size=(200, 2))
        pts = np.hstack([q, q]).astype(np.float32)
        sets = [CandidateMatchSet(c.tile_id, 200, pts, 50, 0.8) for c in rerank_result.candidates]
        return MatchResult(frame.frame_id, sets, 0, 0.8, 0, "fake")


def test_the_pipeline_climbs_the_ladder_and_records_each_attempts_rung() -> None:
    """Through ``NavigationPipeline``: the first attempt (prior sigma 30 m) is made on the chip rung with
    one candidate and finds too few inliers, so the next is made on the wide rung with both candidates;
    each outcome and ``pipeline.fix`` record names its rung."""
    from test_pipeline import T0, InitialPrior, _Fdr, _frame, _HoverVo, _PosePerTile, _two_tile_pipeline

    fdr = _Fdr()
    p = _two_tile_pipeline(fdr, _HoverVo(), _PosePerTile())
    chip, wide = _Counting(fail=True), _Counting(fail=False)
    rungs = (
        LadderRung("chip", strategy="a", candidates=1, max_prior_sigma_m=50.0, give_up_after=1),
        LadderRung("wide", strategy="b", candidates=2),
    )
    matchers = {"a": chip, "b": wide}
    p._ladder = EffortLadder.from_config(rungs, matchers, default_strategy="a", max_candidates=2)  # type: ignore[arg-type]
    frame = _frame(0, T0)
    p.track(frame, InitialPrior(47.0, 8.0, 30.0, "test"))
    first = p.localise(frame)
    second = p.localise(frame)
    fixes = [r for kind, r in fdr.records if kind == "pipeline.fix"]
    assert [first.rung, second.rung] == ["chip", "wide"]
    assert [r["rung"] for r in fixes] == ["chip", "wide"]
    assert (chip.calls, wide.calls) == ([1], [2])
    assert first.no_fix_reason == "insufficient_inliers"


def test_the_composition_root_builds_the_configured_ladder_and_refuses_a_broken_one() -> None:
    """``create_ladder``: rungs on the configured (weights-free) matcher share it; a rung with more
    candidates than C2.5 hands on, or an unknown strategy, stops start-up naming the setting (the latter
    already in ``gdnav config check``)."""
    from gps_denied_onboard.runtime_root.compose import StartupError, create_ladder, preflight

    def config(*rungs: dict) -> object:
        return config_from_mapping({"matcher": {"strategy": "classical", "ladder": list(rungs)}})

    chip = {"name": "chip", "candidates": 1, "max_prior_sigma_m": 30.0}
    ok = config(chip, {"name": "wide", "candidates": 3})
    primary = object()
    ladder = create_ladder(ok, ok, {}, None, None, primary)  # type: ignore[arg-type]
    assert [(r.name, r.strategy, r.candidates, r.matcher) for r in ladder.rungs] == [
        ("chip", "classical", 1, primary),
        ("wide", "classical", 3, primary),
    ]
    too_many = config({"name": "wide", "candidates": 5})
    with pytest.raises(StartupError, match=r"matcher.ladder: .*candidates 5 > rerank.top_n 3"):
        create_ladder(too_many, too_many, {}, None, None, primary)  # type: ignore[arg-type]
    with pytest.raises(StartupError, match=r"matcher.ladder\[0\].strategy: .*'nope' is not linked"):
        preflight(config({"name": "x", "strategy": "nope"}))  # type: ignore[arg-type]
