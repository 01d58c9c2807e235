"""A wrong start prior is found out (issue 37): failed fix attempts on frames that should match count
against a prior no map fix has confirmed, grow its sigma, and the fix path sweeps outward until the map
answers; nothing of it goes out as a 3D fix meanwhile.

The rule (``c5_estimator/prior_doubt.py``) alone, the texture measure it asks of frames and map
(``helpers/texture.py``), and the pipeline wired with it: fakes for C2/C2.5/C3/C4 at their component
boundaries, the real estimator and time axis.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass, field

import numpy as np
import pytest

from gps_denied_onboard.camera.types import Attitude, CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c1_vio.types import VoMotion
from gps_denied_onboard.components.c2_5_rerank.types import RerankResult
from gps_denied_onboard.components.c2_vpr.types import VprCandidate, VprQuery, VprResult
from gps_denied_onboard.components.c3_matcher.errors import InsufficientInliersError
from gps_denied_onboard.components.c3_matcher.ladder import EffortLadder
from gps_denied_onboard.components.c3_matcher.types import CandidateMatchSet, MatchResult
from gps_denied_onboard.components.c4_pose.attitude_check import AttitudeCheck
from gps_denied_onboard.components.c4_pose.consistency import FixConsistency
from gps_denied_onboard.components.c4_pose.integrity import FixIntegrity
from gps_denied_onboard.components.c4_pose.types import PoseFix
from gps_denied_onboard.components.c5_estimator import NavEstimator, TimeAxis
from gps_denied_onboard.components.c5_estimator.prior_doubt import PriorDoubt, is_match_failure
from gps_denied_onboard.components.c6_tiles.types import TileId
from gps_denied_onboard.components.c8_mavlink.messages import FIX_TYPE_NO_FIX, gps_input_fix_type
from gps_denied_onboard.config import EstimatorConfig, InitConfig, IntegrityConfig, PoseConfig, VprConfig
from gps_denied_onboard.constants import (
    STATUSTEXT_PRIOR_DISPUTED,
    STATUSTEXT_PRIOR_DOUBTED,
    STATUSTEXT_PRIOR_REANCHORED,
    STATUSTEXT_PRIOR_UNCONFIRMED,
    FdrKind,
)
from gps_denied_onboard.geo import LocalTangentPlane, haversine_m
from gps_denied_onboard.helpers.texture import edge_share
from gps_denied_onboard.pipeline import InitialPrior, NavigationPipeline

LTP = LocalTangentPlane(47.0, 8.0, 400.0)
T0 = 1_700_000_000_000_000
RNG = np.random.default_rng(3)
#: A frame and a map chip with fields and edges: 16 px blocks of random grey.
TEXTURED = np.kron(RNG.integers(0, 256, (30, 40)), np.ones((16, 16))).astype(np.uint8)
TEXTURED_BGR = np.repeat(TEXTURED[:, :, None], 3, axis=2)
#: Fog, snow, water: a smooth field with sensor noise.
FEATURELESS = np.clip(np.linspace(90, 140, 640)[None, :] + RNG.normal(0, 3, (480, 640)), 0, 255).astype(
    np.uint8
)


def _doubt(**init: object) -> PriorDoubt:
    d = PriorDoubt(InitConfig(**init))  # type: ignore[arg-type]
    d.start()
    return d


def _fail(d: PriorDoubt, searched_sigma_m: float, **kw: object):  # type: ignore[no-untyped-def]
    args: dict[str, object] = {
        "accepted": False,
        "reason": "insufficient_inliers",
        "frame_texture": 0.5,
        "map_texture": 0.5,
        "searched_sigma_m": searched_sigma_m,
        "cover_sigma_m": 5000.0,
    }
    return d.note(**{**args, **kw})  # type: ignore[arg-type]


def test_edge_share_tells_texture_from_fog_and_a_covered_lens() -> None:
    """Fields and edges: most of the image; a smooth field with 3 DN of noise, or a near-black frame:
    nothing (the orientation field, normalised by its neighbourhood, scores noise like texture)."""
    assert edge_share(TEXTURED_BGR) > 0.2
    assert edge_share(FEATURELESS) < 0.01
    assert edge_share((TEXTURED_BGR * 0.025).astype(np.uint8)) < 0.01
    assert edge_share(np.zeros((4, 4), np.uint8)) == 0.0


@pytest.mark.parametrize(
    ("reason", "counts"),
    [
        ("insufficient_inliers", True),
        ("integrity:low_psr", True),
        ("integrity:prior_disagreement", True),
        ("pose_rejected:degenerate", True),
        ("gated:gated", True),
        ("gated:too_late", False),
        ("consistency:unverified", False),
        ("attitude_off", False),
        ("vo_attitude_off", False),
        ("no_attitude_or_altitude", False),
        ("no_tiles_in_region", False),
        ("vpr_error", False),
        ("matcher_error", False),
        (None, False),
    ],
)
def test_only_the_map_not_answering_counts_against_the_prior(reason: str | None, counts: bool) -> None:
    """A matcher that ran and found nothing, a pose or a fix refused; not a fault of the attitude, of
    a component, of timing, nor a fix held back to be confirmed."""
    assert is_match_failure(reason) is counts


def test_counted_failures_grow_the_prior_until_it_covers_the_map_and_a_fix_ends_the_doubt() -> None:
    """From the 2nd counted failure on, each raises the sigma to twice what that attempt searched, up to
    the sigma that covers the map; the first accepted fix confirms the prior and says how far it was."""
    d = _doubt(doubt_after_failures=2, doubt_growth=2.0)
    first = _fail(d, 30.0)
    assert (first.counted, first.failures, first.raise_to_sigma_m) == (True, 1, None)
    assert not d.doubted
    assert _fail(d, 30.0).raise_to_sigma_m == 60.0
    assert d.doubted and d.widenings == 1
    assert _fail(d, 60.0).raise_to_sigma_m == 120.0
    assert _fail(d, 3000.0).raise_to_sigma_m == 5000.0  # the map covered from the state
    assert _fail(d, 5000.0).raise_to_sigma_m is None  # nothing more to widen: the sweep goes on
    done = d.note(
        accepted=True,
        reason=None,
        frame_texture=0.5,
        map_texture=0.5,
        searched_sigma_m=5000.0,
        cover_sigma_m=5000.0,
        moved_m=312.0,
    )
    assert (done.counted, done.reanchored_m) == (False, 312.0)
    assert not d.active and not d.doubted
    assert _fail(d, 10.0).why == "confirmed"  # a confirmed state is no prior: the rule is over


def test_a_prior_confirmed_at_once_was_never_doubted() -> None:
    d = _doubt()
    fix = d.note(
        accepted=True,
        reason=None,
        frame_texture=None,
        map_texture=None,
        searched_sigma_m=30.0,
        cover_sigma_m=5000.0,
        moved_m=4.0,
    )
    assert fix.reanchored_m is None and d.widenings == 0


@pytest.mark.parametrize(
    ("kw", "why"),
    [
        ({"frame_texture": 0.01}, "frame texture 0.010 < 0.05"),
        ({"frame_texture": None}, "frame texture n/a < 0.05"),
        ({"map_texture": 0.0}, "map texture 0.000 < 0.05"),
        ({"map_texture": None}, "no map where the search started"),
        ({"reason": "attitude_off"}, "not a match failure: attitude_off"),
    ],
)
def test_a_frame_that_could_not_have_matched_does_not_count(kw: dict[str, object], why: str) -> None:
    """Fog or a covered lens, a featureless map where the prior puts the camera, no map there, a fault
    that is not the map's: no evidence against the prior, and the run of failures is left as it was."""
    d = _doubt(doubt_after_failures=2)
    assert _fail(d, 30.0).failures == 1
    skipped = _fail(d, 30.0, **kw)
    assert (skipped.counted, skipped.why, skipped.failures, skipped.raise_to_sigma_m) == (False, why, 1, None)
    assert _fail(d, 30.0).raise_to_sigma_m == 60.0


def test_what_the_operator_reads_fits_a_statustext() -> None:
    """STATUSTEXT carries 50 characters: the texts about the prior fit with their longest values."""
    texts = [
        STATUSTEXT_PRIOR_DISPUTED.format(99_999.0),
        STATUSTEXT_PRIOR_UNCONFIRMED.format("home_position"),
        STATUSTEXT_PRIOR_DOUBTED.format(999, 99_999.0),
        STATUSTEXT_PRIOR_REANCHORED.format(99_999.0),
    ]
    assert all(len(t) <= 50 for t in texts), [(t, len(t)) for t in texts]


def test_doubt_after_failures_zero_never_doubts() -> None:
    d = _doubt(doubt_after_failures=0)
    assert not d.active
    assert all(_fail(d, 30.0).raise_to_sigma_m is None for _ in range(5))


# --- the pipeline with the rule --------------------------------------------------------------------


def _north_of(tile: TileId) -> float:
    """The fakes' map: tile i ((18, 1, i) as its id) is centred 100 m x i north of the flight's origin."""
    return 100.0 * tile.lon_deg


TILES = [TileId(18, 1, i) for i in range(20)]
TRUE_TILE = TILES[7]  # the vehicle hovers 700 m north of where every start point says


@dataclass
class _GeoVpr:
    """C2 double like ``geo_prior``: the tiles whose centre is within the region, nearest first."""

    regions: list[object] = field(default_factory=list)

    def descriptor_dim(self) -> int:
        return 0

    def embed_query(self, frame, calibration):  # type: ignore[no-untyped-def]
        return VprQuery(frame.frame_id, np.zeros(0, np.float32), 0)

    def retrieve_topk(self, query, k, *, region=None):  # type: ignore[no-untyped-def]
        self.regions.append(region)
        north = float(LTP.to_ned(region.center_lat_deg, region.center_lon_deg, 400.0)[0])
        near = sorted((abs(_north_of(t) - north), t) for t in TILES)
        inside = [VprCandidate(t, d, 0) for d, t in near if d <= region.radius_m]
        return VprResult(query.frame_id, inside[:k], 0, "fake")


@dataclass
class _Chip:
    pixels_bgr: np.ndarray
    gsd_m_px: float = 0.4

    def pixels(self) -> np.ndarray:
        return self.pixels_bgr


@dataclass
class _Cand:
    tile_id: TileId
    tile_pixels_handle: _Chip


class _OnlyTheTruth:
    """Rerank (the first 3, as passthrough) and matcher double: only ``TRUE_TILE`` matches; the map's
    chips are ``chip``; the tiles each attempt was given are kept."""

    def __init__(self, chip: np.ndarray) -> None:
        self.chip = chip
        self.given: list[list[TileId]] = []

    def rerank(self, frame, vpr_result):  # type: ignore[no-untyped-def]
        cands = [_Cand(c.tile_id, _Chip(self.chip)) for c in vpr_result.candidates[:3]]
        return RerankResult(frame.frame_id, cands, 0)  # type: ignore[arg-type]

    def match(self, frame, rerank_result, calibration):  # type: ignore[no-untyped-def]
        tiles = [c.tile_id for c in rerank_result.candidates]
        self.given.append(tiles)
        if TRUE_TILE not in tiles:
            raise InsufficientInliersError(
                "none", frame_id=frame.frame_id, best_inlier_count=6, threshold=25,
                candidates_input=len(tiles), candidates_dropped=0,
            )  # fmt: skip
        q = np.random.default_rng(0).uniform((0, 0), (640, 480), size=(200, 2))
        pts = np.hstack([q, q]).astype(np.float32)
        return MatchResult(
            frame.frame_id, [CandidateMatchSet(TRUE_TILE, 200, pts, 50, 0.8)], 0, 0.8, 0, "fake"
        )


class _PoseAtTheTile:
    """C4 double: a fix at the matched tile's centre, 1 m sigma, the image's tilt the autopilot's."""

    def solve(self, frame, candidate, handle, calibration, *, attitude_doubt_rad=0.0):  # type: ignore[no-untyped-def]
        ned = np.array([_north_of(candidate.tile_id), 0.0, -120.0])
        lat, lon, _ = LTP.to_geodetic(ned)
        return PoseFix(
            frame.frame_id, frame.exposure_time_unix_usec, ned, np.eye(3), float(lat), float(lon), 520.0,
            0.0, 0.01, 0.0, (0.0, 0.0), candidate.inlier_count, 0.8, candidate.tile_id, 1.0,
        )  # fmt: skip


class _HoverVo:
    def process(self, frame: NavCameraFrame) -> VoMotion:
        return VoMotion(frame.frame_id, uuid.uuid4(), 1 / 3, np.zeros(2), np.eye(2) * 0.09, 200)


class _Fdr:
    def __init__(self) -> None:
        self.records: list[tuple[str, dict]] = []

    def record(self, kind, fields):  # type: ignore[no-untyped-def]
        self.records.append((kind, dict(fields)))


def _pipeline(fdr: _Fdr, chip: np.ndarray) -> tuple[NavigationPipeline, _OnlyTheTruth]:
    fakes = _OnlyTheTruth(chip)
    p = NavigationPipeline(
        calibration=CameraCalibration.from_hfov(640, 480, 70.0),
        ltp=LTP,
        ground_alt_amsl_m=400.0,
        vo=_HoverVo(),
        vpr=_GeoVpr(),
        vpr_config=VprConfig(),
        rerank=fakes,  # type: ignore[arg-type]
        matcher=None,
        ladder=EffortLadder.single("fake", fakes, 3),  # type: ignore[arg-type]
        pose_solver=_PoseAtTheTile(),
        time_axis=TimeAxis(
            NavEstimator(EstimatorConfig(), LTP),
            max_delay_s=5.0,
            max_frame_age_s=1.0,
            clock_unix_usec=lambda: T0,
        ),
        fdr=fdr,
        integrity=FixIntegrity(IntegrityConfig()),
        consistency=FixConsistency(IntegrityConfig()),
        attitude_check=AttitudeCheck(PoseConfig()),
        prior_doubt=PriorDoubt(InitConfig()),
        map_extent=(*(float(v) for v in LTP.to_geodetic(np.array([1000.0, 0.0, 0.0]))[:2]), 1100.0),  # type: ignore[arg-type]
    )
    return p, fakes


def _fly(p: NavigationPipeline, image: np.ndarray, n_frames: int):  # type: ignore[no-untyped-def]
    """``n_frames`` frames 1 s apart, the prior at the origin stating 20 m; the fix outcomes and the
    states each frame's VO left (before its fix)."""
    bgr = image if image.ndim == 3 else np.repeat(image[:, :, None], 3, axis=2)
    outs, states = [], []
    for k in range(n_frames):
        t = T0 - n_frames * 1_000_000 + k * 1_000_000
        frame = NavCameraFrame(uuid.uuid4(), k, t, bgr, Attitude(0, 0, 0), 120.0, 0)
        states.append(p.track(frame, InitialPrior(47.0, 8.0, 20.0, "config")).state)
        outs.append(p.localise(frame))
    return outs, states


def test_a_prior_700_m_off_at_20_m_is_found_out_and_the_map_answers() -> None:
    """Every attempt around the prior fails on a textured frame over textured map: from the 2nd on,
    each doubles the prior's sigma, the sweep goes outward with the prior's own tile kept first, and
    the true tile 700 m off anchors the state. Until then no state is a 3D fix; the FDR says it all."""
    fdr = _Fdr()
    p, fakes = _pipeline(fdr, TEXTURED_BGR)
    outs, states = _fly(p, TEXTURED_BGR, 12)
    accepted = [o.fix_accepted for o in outs]
    assert True in accepted, [o.no_fix_reason for o in outs]
    k = accepted.index(True)
    assert k <= 9, k
    assert all(g[0] == TILES[0] for g in fakes.given[2:k])  # the prior's own place, kept in the sweep
    swept = {t for g in fakes.given[:k] for t in g}
    assert TILES[1] in swept and TILES[3] in swept  # outward, one ring after the other
    assert outs[k].prior_doubt is not None and outs[k].prior_doubt.reanchored_m == pytest.approx(
        700.0, abs=1.0
    )
    state = p.time_axis.state_at(outs[k].exposure_time_unix_usec)
    assert abs(float(state.pos_ned_m[0]) - 700.0) < 5.0 and state.map_confirmed
    before = [o for o in outs[:k]]
    sigmas = [o.prior_doubt.raise_to_sigma_m for o in before if o.prior_doubt is not None]
    assert sigmas[0] is None and sigmas[1] == pytest.approx(40.0, rel=0.05)  # 2 x the 20 m searched
    for s in states[: k + 1]:
        assert s is not None and not s.map_confirmed and gps_input_fix_type(s) <= FIX_TYPE_NO_FIX
    assert states[k + 1] is not None and states[k + 1].map_confirmed
    kinds = [f.get("event") for kind, f in fdr.records if kind == FdrKind.PRIOR_DOUBT]
    assert kinds.count("reanchored") == 1 and kinds.count("doubted") >= 3
    fix_records = [f for kind, f in fdr.records if kind == FdrKind.FIX]
    assert fix_records[0]["prior_doubt"]["counted"] and fix_records[0]["prior_doubt"]["frame_texture"] > 0.2
    centre = p._vpr.regions[-1]  # type: ignore[attr-defined]
    assert float(haversine_m(centre.center_lat_deg, centre.center_lon_deg, 47.0, 8.0)) > 600.0


@pytest.mark.parametrize("frame_or_map", ["frame", "map"])
def test_failures_where_nothing_could_match_never_doubt_the_prior(frame_or_map: str) -> None:
    """The same flight over fog (the frame) or a featureless map where the prior puts the camera: the
    failures are no evidence; the prior stays as stated and the search around it."""
    fdr = _Fdr()
    chip = FEATURELESS if frame_or_map == "map" else TEXTURED_BGR
    frame = FEATURELESS if frame_or_map == "frame" else TEXTURED_BGR
    p, fakes = _pipeline(fdr, np.repeat(chip[:, :, None], 3, axis=2) if chip.ndim == 2 else chip)
    outs, _states = _fly(p, frame, 6)
    assert not any(o.fix_accepted for o in outs)
    assert all(o.prior_doubt is not None and not o.prior_doubt.counted for o in outs)
    assert not [f for kind, f in fdr.records if kind == FdrKind.PRIOR_DOUBT]
    assert fakes.given[0] == TILES[:2] and all(g == fakes.given[0] for g in fakes.given)
