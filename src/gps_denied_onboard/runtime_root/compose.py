"""Composition root (see the package docstring)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import structlog

from gps_denied_onboard.camera.sources import CameraSourceError, FrameSource, open_frame_source
from gps_denied_onboard.camera.types import CalibrationError, CameraCalibration, CameraMount
from gps_denied_onboard.clock import CameraStampOffset, DaemonClock
from gps_denied_onboard.components.c1_vio import HomographyVo
from gps_denied_onboard.components.c2_5_rerank.footprint import FootprintChips
from gps_denied_onboard.components.c2_5_rerank.inlier_rerank import InlierRerank
from gps_denied_onboard.components.c2_5_rerank.passthrough import PassthroughRerank
from gps_denied_onboard.components.c2_5_rerank.protocol import RerankStrategy
from gps_denied_onboard.components.c2_vpr.geo_prior import GeoPriorVpr
from gps_denied_onboard.components.c2_vpr.learned_local import XFeatDescriber, find_xfeat_extractor
from gps_denied_onboard.components.c2_vpr.protocol import VprStrategy
from gps_denied_onboard.components.c2_vpr.types import IndexUnavailableError
from gps_denied_onboard.components.c2_vpr.vlad import VladVpr
from gps_denied_onboard.components.c3_matcher import registry as matcher_registry
from gps_denied_onboard.components.c3_matcher.aliked_lightglue import ALIKED_MNN_MIN_SIMILARITY
from gps_denied_onboard.components.c3_matcher.errors import StrategyNotLinkedError
from gps_denied_onboard.components.c3_matcher.health import RollingHealthWindow
from gps_denied_onboard.components.c3_matcher.ladder import EffortLadder, LadderError
from gps_denied_onboard.components.c3_matcher.protocol import CrossDomainMatcher
from gps_denied_onboard.components.c3_matcher.tile_features import (
    ExtractorIdentity,
    PrecomputedTileFeatures,
    TileFeaturesRefused,
)
from gps_denied_onboard.components.c3_matcher.xfeat import XFEAT_DESCRIPTOR_DIM
from gps_denied_onboard.components.c4_pose import PoseSolver
from gps_denied_onboard.components.c4_pose.area_pose import AreaPoseSolver
from gps_denied_onboard.components.c4_pose.attitude_check import AttitudeCheck
from gps_denied_onboard.components.c4_pose.consistency import FixConsistency
from gps_denied_onboard.components.c4_pose.heading_height_check import HeadingHeightCheck
from gps_denied_onboard.components.c4_pose.integrity import FixIntegrity
from gps_denied_onboard.components.c5_estimator import NavEstimator, TimeAxis
from gps_denied_onboard.components.c5_estimator.journal import RecordingJournal
from gps_denied_onboard.components.c5_estimator.prior import (
    PreviousRun,
    in_the_air,
    read_previous_run,
    with_resume_state,
)
from gps_denied_onboard.components.c5_estimator.prior_doubt import PriorDoubt
from gps_denied_onboard.components.c5_estimator.resume_state import (
    ResumeStateFile,
    default_path,
    read_resume_state,
)
from gps_denied_onboard.components.c6_tiles.map_fields import MapFields, MapFieldsRefused
from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.components.c6_tiles.types import TileStoreError
from gps_denied_onboard.components.c7_inference import OnnxInferenceRuntime
from gps_denied_onboard.components.c7_inference.onnx_runtime import resolve_providers
from gps_denied_onboard.components.c7_inference.protocol import EngineLoadError
from gps_denied_onboard.components.c8_mavlink import (
    MavlinkConfigError,
    MavlinkLink,
    VehicleStateTracker,
)
from gps_denied_onboard.components.c10_cache_build.manifest import Verification
from gps_denied_onboard.components.c13_fdr import FdrClient, FlightDataRecorder, read_records_newest_first
from gps_denied_onboard.config import Config, LadderRung, MatcherConfig
from gps_denied_onboard.constants import FdrKind, LogEvent
from gps_denied_onboard.geo import LocalTangentPlane, haversine_m
from gps_denied_onboard.helpers.lightglue_runtime import LightGlueRuntime
from gps_denied_onboard.helpers.model_manifest import ModelDirError, ModelEntry, verify_model_dir
from gps_denied_onboard.helpers.ransac_filter import RansacFilter
from gps_denied_onboard.models.learned_export import FAMILY_STRATEGY, family_models
from gps_denied_onboard.models.verification import family_verified
from gps_denied_onboard.pipeline import NavigationPipeline
from gps_denied_onboard.runtime_root.link_first import StartupError, check_signing_key, make_tracker

log = structlog.get_logger(__name__)


@dataclass
class RuntimeRoot:
    config: Config
    calibration: CameraCalibration
    ltp: LocalTangentPlane
    tile_store: TileStore
    fdr: FlightDataRecorder
    tracker: VehicleStateTracker
    link: MavlinkLink
    camera: FrameSource
    matcher: CrossDomainMatcher
    pipeline: NavigationPipeline
    time_axis: TimeAxis
    previous_run: PreviousRun
    #: The daemon's one clock (monotonic, anchored to Unix time at start): every "now" comes from it.
    clock: DaemonClock = field(default_factory=DaemonClock)
    #: F8: where the daemon keeps its last 3D estimate apart from the FDR (``c5_estimator.resume_state``).
    resume_state: ResumeStateFile | None = None

    def close(self) -> None:
        self.link.close()
        self.fdr.close()


def _calibration(config: Config) -> CameraCalibration:
    cam = config.camera
    if cam.calibration_file is not None:
        try:
            return CameraCalibration.from_opencv_yaml(cam.calibration_file)
        except CalibrationError as exc:
            raise StartupError("camera.calibration_file", str(exc)) from exc
    i = cam.intrinsics
    if i.fx_px is None:
        base = CameraCalibration.from_hfov(i.width_px, i.height_px, i.hfov_deg)
        return CameraCalibration(
            base.width_px,
            base.height_px,
            base.fx_px,
            base.fy_px,
            base.cx_px,
            base.cy_px,
            tuple(i.dist_coeffs),
        )
    return CameraCalibration(
        i.width_px,
        i.height_px,
        i.fx_px,
        i.fy_px if i.fy_px is not None else i.fx_px,
        i.cx_px if i.cx_px is not None else (i.width_px - 1) / 2.0,
        i.cy_px if i.cy_px is not None else (i.height_px - 1) / 2.0,
        tuple(i.dist_coeffs),
    )


def _check_fdr_dir(config: Config) -> None:
    """Refuse an ``fdr.dir`` that exists and is not a directory, or that cannot be created because a path
    above it is a file: the recorder would record nothing and the next restart would be blind."""
    d = Path(config.fdr.dir)
    for p in (d, *d.absolute().parents):
        try:
            if not p.exists():
                continue
            if p.is_dir():
                return
        except OSError:  # not searchable by this user: the recorder's own errors will say so
            return
        why = "is not a directory" if p == d else f"cannot be created: {p} is not a directory"
        raise StartupError("fdr.dir", f"{d} {why}; expected a directory for the flight data recorder")


def _check_strategy_names(config: Config) -> None:
    """Refuse an unknown strategy name as ``compose_root`` refuses it when it builds the strategy."""
    _pick("vpr", VPR_STRATEGIES, config.vpr.strategy)
    _pick("rerank", RERANK_STRATEGIES, config.rerank.strategy)
    names = [("matcher.strategy", config.matcher.strategy)] + [
        (f"matcher.ladder[{i}].strategy", r.strategy)
        for i, r in enumerate(config.matcher.ladder)
        if r.strategy is not None
    ]
    for key, name in names:
        if name != "auto" and name not in matcher_registry.available_strategies():
            raise StartupError(
                key,
                f"C3 matcher strategy {name!r} is not linked; available: "
                f"{', '.join(matcher_registry.available_strategies())}",
            )


def preflight(config: Config) -> None:
    """The start-up checks that are cheap and need no cache, model or network: the calibration file, the
    signing key file, ``fdr.dir`` and the strategy names (``gdnav config check``). Raises ``StartupError``
    naming the key; ``compose_root`` runs the same checks."""
    _calibration(config)
    check_signing_key(config)
    _check_fdr_dir(config)
    _check_strategy_names(config)


#: C3 strategies that need no model file (and so no ONNX runtime objects).
WEIGHTS_FREE_MATCHERS = frozenset({"classical", "orientation_corr"})
#: The strategies that read the cache's orientation fields instead of chip pixels.
AREA_MATCHERS = frozenset({"orientation_corr"})

def _vlad_xfeat(tiles: TileStore, config: Config) -> VprStrategy:
    """``vlad_xfeat``: the XFeat extractor from ``vpr.xfeat_weights_path``, else from the verified
    ``matcher.model_dir``; the cache must have been built with that very model (sha256)."""
    path = config.vpr.xfeat_weights_path
    if path is None:
        if config.matcher.model_dir is None:
            raise StartupError(
                "vpr.xfeat_weights_path",
                "vpr.strategy vlad_xfeat needs an XFeat extractor: set vpr.xfeat_weights_path or "
                "matcher.model_dir (gdnav models export)",
            )
        try:
            path = str(find_xfeat_extractor(config.matcher.model_dir))
        except (ModelDirError, OSError, ValueError) as exc:
            raise StartupError("matcher.model_dir", str(exc)) from exc
    runtime = OnnxInferenceRuntime(intra_op_threads=config.daemon.onnx_intra_op_threads)
    try:
        describer = XFeatDescriber(runtime, path)
    except EngineLoadError as exc:
        raise StartupError("vpr.xfeat_weights_path", str(exc)) from exc
    return VladVpr.from_cache(tiles, top1_distance_warn=config.vpr.top1_distance_warn, describer=describer)


#: C2 strategies by config name.
VPR_STRATEGIES: Mapping[str, Callable[[TileStore, Config], VprStrategy]] = {
    "geo_prior": lambda tiles, cfg: GeoPriorVpr(tiles),
    "vlad": lambda tiles, cfg: VladVpr.from_cache(tiles, top1_distance_warn=cfg.vpr.top1_distance_warn),
    "vlad_xfeat": _vlad_xfeat,
}


def create_vpr(tiles: TileStore, config: Config) -> VprStrategy:
    """The C2 strategy of ``config``. Raises ``StartupError`` for an unknown strategy, a missing or
    unusable extractor model, or a cache whose VPR index was built otherwise (another strategy, another
    model, no index: rebuild it with ``gdnav cache vpr``)."""
    factory = _pick("vpr", VPR_STRATEGIES, config.vpr.strategy)
    try:
        vpr: VprStrategy = factory(tiles, config)
    except IndexUnavailableError as exc:
        log.error(LogEvent.VPR_ERROR, backbone=config.vpr.strategy, error=str(exc))
        raise StartupError("vpr.strategy", f"{config.vpr.strategy}: {exc}") from exc
    return vpr
#: C2.5 strategies by config name.
RERANK_STRATEGIES: Mapping[str, Callable[[TileStore, Config], RerankStrategy]] = {
    "passthrough": lambda tiles, cfg: PassthroughRerank(
        tiles, top_n=cfg.rerank.top_n, chip_size_px=cfg.matcher.chip_size_px
    ),
    "inliers": lambda tiles, cfg: InlierRerank(
        tiles,
        calibration=_calibration(cfg),
        ransac_filter=RansacFilter(
            confidence=cfg.matcher.ransac_confidence, max_iters=cfg.matcher.ransac_max_iters
        ),
        top_n=cfg.rerank.top_n,
        chip_size_px=cfg.matcher.chip_size_px,
    ),
}


def _pick(kind: str, table: Mapping[str, Any], name: str) -> Any:
    if name not in table:
        raise StartupError(
            f"{kind}.strategy", f"unknown strategy {name!r}; valid: {', '.join(sorted(table))}"
        )
    return table[name]


def _matcher_deps(
    config: Config,
    pre: Mapping[str, Any],
    ransac: RansacFilter,
    fdr: FdrClient,
    health: RollingHealthWindow,
    tile_features: PrecomputedTileFeatures | None = None,
    map_fields: MapFields | None = None,
) -> dict[str, Any]:
    """The superset of collaborators a C3 strategy may ask for; ONNX objects only for learned strategies
    (the weights-free default must start on a machine without any model file)."""
    deps: dict[str, Any] = {
        "config": config.matcher,
        "ransac_filter": ransac,
        "fdr_client": fdr,
        "health_window": health,
        "tile_features": tile_features,
        "map_fields": map_fields,
    }
    if config.matcher.strategy in WEIGHTS_FREE_MATCHERS:
        return deps
    runtime = pre.get("c7_inference") or OnnxInferenceRuntime(
        intra_op_threads=config.daemon.onnx_intra_op_threads
    )
    deps.update(inference_runtime=runtime)
    if config.matcher.strategy in matcher_registry.available_strategies() and not matcher_registry.takes(
        config.matcher.strategy, "lightglue_runtime"
    ):
        return deps  # it matches by its own rule (xfeat_mnn): no LightGlue model is loaded
    lightglue = pre.get("c3_lightglue_runtime")
    if lightglue is None:
        # Without a LightGlue model the helper matches by mutual nearest neighbour (logged by the helper).
        # Cross-date ALIKED descriptors have cosine similarities of ~0.5-0.8: the generic 0.75 threshold
        # kept 3/30 NAIP cross-date trials, 0.5 kept 30/30 (tests/test_c3_aliked.py).
        mnn = ALIKED_MNN_MIN_SIMILARITY if config.matcher.strategy == "aliked_lightglue" else 0.75
        dim = XFEAT_DESCRIPTOR_DIM if config.matcher.strategy == "xfeat" else None
        lightglue = LightGlueRuntime(
            runtime, config.matcher.lightglue_weights_path, mnn_min_similarity=mnn, descriptor_dim=dim
        )
    deps.update(lightglue_runtime=lightglue)
    return deps


#: Config field of each learned strategy's extractor model.
_EXTRACTOR_FIELD = {
    "disk_lightglue": "disk_weights_path",
    "aliked_lightglue": "aliked_weights_path",
    "xfeat": "xfeat_weights_path",
    "xfeat_mnn": "xfeat_weights_path",
}
#: Strategies that run another strategy's extractor without its LightGlue: they take that family's
#: extractor from the model directory and use that strategy's precomputed tile features.
_EXTRACTOR_OF = {"xfeat_mnn": "xfeat"}


def _family_paths(
    m: MatcherConfig, entries: tuple[ModelEntry, ...], strategy: str
) -> tuple[str, str | None] | None:
    """(extractor path, LightGlue path or None) for ``strategy`` from a verified model directory.

    A family export (extractor + its LightGlue) wins; for ``aliked_lightglue`` a lone ALIKED extractor
    (``gdnav models export --weights-dir``) is the fallback, matched by mutual nearest neighbour."""
    family = next(f for f, s in FAMILY_STRATEGY.items() if s == _EXTRACTOR_OF.get(strategy, strategy))
    found = family_models(entries, family)
    root = Path(str(m.model_dir))
    if found is not None:
        matcher_file = None if strategy in _EXTRACTOR_OF else str(root / found[1].file)
        return str(root / found[0].file), matcher_file
    if strategy == "aliked_lightglue":
        lone = [
            e for e in entries if e.source.name in ("aliked-t16", "aliked-n16") and "role" not in e.params
        ]
        if lone:
            return str(root / lone[0].file), None
    return None


#: ``auto``'s order where ONNX Runtime has a GPU provider (CUDA, TensorRT): the seed's default first.
AUTO_ORDER_GPU: tuple[str, ...] = ("disk_lightglue", "aliked_lightglue", "xfeat")
#: ``auto``'s order on a CPU alone: cheapest fix first (docs/benchmarks.md, per strategy on the 2-core
#: CPU: XFeat + LighterGlue ~2.4 s a frame, ALIKED ~9.6 s, DISK ~15.9 s).
AUTO_ORDER_CPU: tuple[str, ...] = ("xfeat", "aliked_lightglue", "disk_lightglue")


def auto_order(providers: Sequence[str]) -> tuple[tuple[str, ...], str]:
    """``auto``'s strategy order for the ONNX Runtime ``providers`` available here, and why."""
    gpu = [p for p in providers if p != "CPUExecutionProvider"]
    if gpu:
        return AUTO_ORDER_GPU, f"{gpu[0]} available"
    return AUTO_ORDER_CPU, "CPU only (no CUDA or TensorRT execution provider)"


def resolve_matcher(config: Config) -> Config:
    """Apply ``matcher.model_dir`` and ``matcher.strategy: auto`` (see MatcherConfig).

    The model directory is verified (manifest hashes) at start-up, and only where it is used: by
    ``auto``, and by a learned strategy whose extractor path is null (it then takes its extractor and,
    when ``lightglue_weights_path`` is null too, its LightGlue matcher from the directory). ``auto`` picks
    by what this machine can run (``auto_order``): with a GPU execution provider the order is
    disk_lightglue, aliked_lightglue, xfeat; on a CPU alone the cheapest first. It takes the first whose
    export also passed ``gdnav models verify`` (``verification.json``); then a lone ALIKED extractor
    (mutual NN); then the weights-free strategy, and logs the choice and why. A learned strategy that needs
    the directory refuses to start without it. (A GPU build of ONNX Runtime on a machine without the GPU
    lists the provider; the session then falls back to the CPU, logged by C7.)
    """
    m = config.matcher
    field = _EXTRACTOR_FIELD.get(m.strategy)
    uses_dir = m.strategy == "auto" or (field is not None and getattr(m, field) is None)
    if not uses_dir:
        return config

    def fallback(reason: str) -> Config:
        log.warning(LogEvent.C3_AUTO_SELECTED, strategy="classical", reason=reason)
        return dataclasses.replace(config, matcher=dataclasses.replace(m, strategy="classical"))

    def use(strategy: str, paths: tuple[str, str | None]) -> Config:
        extractor: dict[str, Any] = {_EXTRACTOR_FIELD[strategy]: paths[0]}
        chosen = dataclasses.replace(m, strategy=strategy, **extractor)
        if m.lightglue_weights_path is None and paths[1] is not None:
            chosen = dataclasses.replace(chosen, lightglue_weights_path=paths[1])
        return dataclasses.replace(config, matcher=chosen)

    if m.model_dir is None:
        if m.strategy == "auto":
            return fallback("matcher.model_dir is not set")
        return config  # the strategy's own factory names the missing weights path
    try:
        entries = verify_model_dir(m.model_dir)
    except (ModelDirError, OSError, ValueError) as exc:
        if m.strategy == "auto":
            return fallback(f"model directory unusable: {exc}")
        raise StartupError("matcher.model_dir", str(exc)) from exc
    if m.strategy != "auto":
        paths = _family_paths(m, entries, m.strategy)
        if paths is None:
            raise StartupError(
                "matcher.model_dir",
                f"{m.model_dir}: no {m.strategy} model in the manifest (run gdnav models export)",
            )
        return use(m.strategy, paths)
    unverified = []
    order, why = auto_order(resolve_providers())
    family_of = {s: f for f, s in FAMILY_STRATEGY.items()}
    for strategy in order:
        family = family_of[_EXTRACTOR_OF.get(strategy, strategy)]
        found = family_models(entries, family)
        if found is None:
            continue
        if not family_verified(Path(m.model_dir), family, *found):
            unverified.append(strategy)
            continue
        log.info(
            LogEvent.C3_AUTO_SELECTED,
            strategy=strategy,
            model_dir=m.model_dir,
            reason=f"{why}: verified {family} export, first in {', '.join(order)}",
            skipped_unverified=unverified,
        )
        return use(strategy, (str(Path(m.model_dir) / found[0].file), str(Path(m.model_dir) / found[1].file)))
    lone = _family_paths(m, tuple(e for e in entries if "role" not in e.params), "aliked_lightglue")
    if lone is not None:
        log.info(
            LogEvent.C3_AUTO_SELECTED,
            strategy="aliked_lightglue",
            model_dir=m.model_dir,
            reason="ALIKED extractor export without LightGlue: mutual nearest neighbour",
            skipped_unverified=unverified,
        )
        return use("aliked_lightglue", lone)
    if unverified:
        return fallback(
            f"exports in {m.model_dir} not verified against PyTorch ({', '.join(unverified)}): "
            f"run gdnav models verify --dir {m.model_dir}"
        )
    return fallback(f"no learned model in {m.model_dir}")


def _uses_area_matcher(config: Config) -> bool:
    m = config.matcher
    return m.strategy in AREA_MATCHERS or any(r.strategy in AREA_MATCHERS for r in m.ladder)


def with_area_rung(unresolved: Config, config: Config, tiles: TileStore) -> Config:
    """``auto`` on a CPU alone, with no ladder configured, on a cache whose orientation fields are
    calibrated: the area correlation first, as the fast rung of a ladder whose heavy rung is the strategy
    ``resolve_matcher`` picked (docs/design.md, "Area correlation"). It gives up to the heavy rung after
    ``AUTO_AREA_GIVE_UP`` attempts in a row without an accepted fix, which gives back after
    ``AUTO_HEAVY_GIVE_UP``. Anything else: ``config`` unchanged. The choice is logged with why."""
    m = unresolved.matcher
    if m.strategy != "auto" or m.ladder:
        return config
    _order, why = auto_order(resolve_providers())
    if any(p != "CPUExecutionProvider" for p in resolve_providers()):
        return config
    info = tiles.manifest.map_fields
    if info is None or not info.calibrations:
        log.info(
            LogEvent.C3_AUTO_SELECTED,
            strategy=config.matcher.strategy,
            area_rung=False,
            reason=f"{why}: the cache has no calibrated orientation fields (gdnav cache fields)",
        )
        return config
    top_n = config.rerank.top_n
    ladder = (
        LadderRung("correlation", "orientation_corr", candidates=top_n, give_up_after=AUTO_AREA_GIVE_UP),
        LadderRung("keypoints", None, candidates=top_n, give_up_after=AUTO_HEAVY_GIVE_UP),
    )
    log.info(
        LogEvent.C3_AUTO_SELECTED,
        strategy="orientation_corr",
        heavy_rung=config.matcher.strategy,
        area_rung=True,
        reason=f"{why}: the cache's orientation fields are calibrated; {config.matcher.strategy} "
        f"after {AUTO_AREA_GIVE_UP} attempts without a fix",
    )
    return dataclasses.replace(config, matcher=dataclasses.replace(config.matcher, ladder=ladder))


#: ``auto``'s area rung gives the attempts to the heavy rung after this many in a row without a fix,
#: and the heavy rung gives them back after its own run of failures.
AUTO_AREA_GIVE_UP = 3
AUTO_HEAVY_GIVE_UP = 2


def open_map_fields(config: Config, tiles: TileStore, fdr: FdrClient) -> MapFields | None:
    """The cache's orientation fields when a rung runs an area matcher (``orientation_corr``), checked at
    the level the cache was opened at (``cache_verification``) and calibrated; None when none does. What
    was decided is logged and recorded (``cache.map_fields``). Raises ``StartupError("cache", ...)`` when
    the fields are needed and absent, damaged or not calibrated."""
    if not _uses_area_matcher(config):
        return None
    try:
        fields = MapFields.open(tiles)
        if not fields.calibrated_levels:
            raise MapFieldsRefused(
                f"{tiles.cache_dir}: the orientation fields are not calibrated (gdnav cache fields --cache "
                f"{tiles.cache_dir})"
            )
    except MapFieldsRefused as exc:
        log.error(LogEvent.MAP_FIELDS_REFUSED, reason=str(exc))
        fdr.record(FdrKind.MAP_FIELDS, {"used": False, "reason": str(exc)})
        raise StartupError("cache", f"orientation_corr: {exc}") from exc
    fields.on_corrupt = lambda info: fdr.record(FdrKind.MAP_FIELDS_CORRUPT, info)
    fields_rec = {
        "used": True,
        "version": fields.info.version,
        "verified_hashes": tiles.verification is Verification.FULL,
        "calibrations": [c.to_json() for c in fields.info.calibrations.values()],
    }
    log.info(LogEvent.MAP_FIELDS_READY, **fields_rec)
    fdr.record(FdrKind.MAP_FIELDS, fields_rec)
    return fields


def cache_verification(config: Config, air: bool | None) -> tuple[Verification, str]:
    """The level the daemon checks its map cache at when it starts, and why (the levels:
    ``c10_cache_build.manifest``; the reasons: docs/design.md, "Opening the cache in constant time").

    ``air``: whether the autopilot says the vehicle is flying (``prior.in_the_air``; None: nothing known
    yet). Full only when ``cache.verify_hashes`` asks for it and the autopilot says the vehicle is on the
    ground; light otherwise, whatever the config says: a full check reads every byte of the map (seconds
    to minutes on a mission's map) and a restart in the air must be back before the autopilot gives up
    on it (ArduPilot lands after 8 s without a fix). ``gdnav cache build`` and ``gdnav preflight`` check
    in full before the flight; every read is checked against its cell's CRC in flight."""
    if not config.cache.verify_hashes:
        return Verification.LIGHT, (
            "cache.verify_hashes is false (gdnav cache build and gdnav preflight verify every byte)"
        )
    if air is None:
        return Verification.LIGHT, "cache.verify_hashes set aside: not known to be on the ground"
    if air:
        return Verification.LIGHT, "cache.verify_hashes set aside: in the air (never re-hashed in flight)"
    return Verification.FULL, "cache.verify_hashes, on the ground"


def open_tile_store(config: Config, verification: Verification, why: str = "") -> TileStore:
    """Open the map cache, checked at ``verification`` (full: seconds for a large cache; light: the same
    on any map). Raises ``StartupError("cache", ...)``."""
    try:
        tiles = TileStore.open(Path(config.cache.dir), verification)
    except TileStoreError as exc:
        log.error(LogEvent.CACHE_REFUSED, dir=config.cache.dir, error=str(exc))
        raise StartupError("cache", str(exc)) from exc
    log.info(
        LogEvent.CACHE_OPENED,
        dir=config.cache.dir,
        tiles=len(tiles),
        zoom=tiles.zoom,
        gsd_m_px=round(tiles.gsd_m_px, 3),
        verification=verification.value,
        why=why,
    )
    return tiles


def open_tile_features(
    config: Config, tiles: TileStore, fdr: FdrClient
) -> PrecomputedTileFeatures | None:
    """The cache's precomputed tile features for the resolved learned strategy, verified against its
    extractor (``matcher.tile_features``); None when they are off, absent or refused, and the matcher
    then extracts every chip live. What was decided is logged and recorded (``cache.tile_features``);
    ``require`` turns a refusal into ``StartupError``."""
    m = config.matcher
    field = _EXTRACTOR_FIELD.get(m.strategy)
    if m.tile_features == "off":
        return None
    if field is None:
        if m.tile_features == "require":
            raise StartupError(
                "matcher.tile_features",
                f"require: the {m.strategy} strategy has no precomputed tile features "
                "(learned strategies only)",
            )
        return None
    path = getattr(m, field)
    try:
        label = _EXTRACTOR_OF.get(m.strategy, m.strategy)
        identity = ExtractorIdentity.of(label, path, m) if path is not None else None
    except OSError:
        identity = None  # the strategy's factory refuses the missing model file, naming it
    if identity is None:
        return None
    try:
        feats = PrecomputedTileFeatures.open(tiles, identity)
    except TileFeaturesRefused as exc:
        fields = {"strategy": m.strategy, "used": False, "reason": str(exc), "mode": m.tile_features}
        if exc.absent:
            log.info(LogEvent.TILE_FEATURES_REFUSED, action="tiles extracted live", **fields)
        else:
            log.error(LogEvent.TILE_FEATURES_REFUSED, action="tiles extracted live", **fields)
        fdr.record(FdrKind.TILE_FEATURES, fields)
        if m.tile_features == "require":
            raise StartupError("matcher.tile_features", str(exc)) from exc
        return None
    feats.on_corrupt = lambda info: fdr.record(FdrKind.TILE_FEATURES_CORRUPT, info)
    fields = {
        "strategy": m.strategy,
        "used": True,
        "model_sha256": identity.model_sha256,
        "chip_size_px": identity.chip_size_px,
        "tiles": len(feats),
        "verified_hashes": tiles.verification is Verification.FULL,
    }
    log.info(LogEvent.TILE_FEATURES_READY, **fields)
    fdr.record(FdrKind.TILE_FEATURES, fields)
    return feats


def create_matcher(
    config: Config,
    pre: Mapping[str, Any],
    fdr: FdrClient,
    tile_features: PrecomputedTileFeatures | None = None,
    map_fields: MapFields | None = None,
) -> CrossDomainMatcher:
    """The C3 strategy of an already resolved ``config`` (``resolve_matcher``), with its ONNX Runtime
    sessions for a learned strategy, ``tile_features`` (``open_tile_features``) and the cache's
    ``map_fields`` for an area matcher (``open_map_fields``). Raises ``StartupError`` for an unknown
    strategy or a model that does not load."""
    ransac = pre.get("c282_ransac_filter") or RansacFilter(
        confidence=config.matcher.ransac_confidence, max_iters=config.matcher.ransac_max_iters
    )
    health = RollingHealthWindow(low_inlier_threshold=config.matcher.min_inliers_threshold)
    try:
        matcher: CrossDomainMatcher = matcher_registry.create_matcher(
            config.matcher.strategy,
            **_matcher_deps(config, pre, ransac, fdr, health, tile_features, map_fields),
        )
    except StrategyNotLinkedError as exc:
        raise StartupError("matcher.strategy", str(exc)) from exc
    except EngineLoadError as exc:
        raise StartupError("matcher model", str(exc)) from exc
    return matcher


def create_ladder(
    config: Config,
    unresolved: Config,
    pre: Mapping[str, Any],
    fdr: FdrClient,
    tiles: TileStore,
    primary: CrossDomainMatcher,
    map_fields: MapFields | None = None,
) -> EffortLadder:
    """The fix path's effort ladder (``c3_matcher/ladder.py``) of the resolved ``config``: ``primary``
    (its matcher.strategy) and one matcher for each other strategy a rung names, resolved from
    ``unresolved`` as matcher.strategy is (models from model_dir, its own tile features). Raises
    ``StartupError("matcher.ladder", ...)`` naming a rung that cannot work."""
    m = config.matcher
    if not m.ladder:
        return EffortLadder.single(m.strategy, primary, config.rerank.top_n)
    matchers: dict[str, CrossDomainMatcher] = {m.strategy: primary}
    for rung in m.ladder:
        if rung.strategy is None or rung.strategy in matchers:
            continue
        own = dataclasses.replace(unresolved.matcher, strategy=rung.strategy)
        rung_config = resolve_matcher(dataclasses.replace(unresolved, matcher=own))
        matchers[rung.strategy] = create_matcher(
            rung_config, pre, fdr, open_tile_features(rung_config, tiles, fdr), map_fields
        )
    try:
        return EffortLadder.from_config(
            m.ladder, matchers, default_strategy=m.strategy, max_candidates=config.rerank.top_n
        )
    except LadderError as exc:
        raise StartupError("matcher.ladder", str(exc)) from exc


def open_camera_source(config: Config) -> FrameSource:
    """The configured camera source (nothing is connected until its ``frames()`` is iterated). Raises
    ``StartupError("camera.source", ...)`` for a source string that cannot be used."""
    try:
        return open_frame_source(
            config.camera.source,
            connect_timeout_s=config.camera.connect_timeout_s,
            frame_timeout_s=config.camera.frame_timeout_s,
            backoff_max_s=config.camera.reconnect_backoff_max_s,
        )
    except CameraSourceError as exc:
        raise StartupError("camera.source", str(exc)) from exc


def _time_axis(
    config: Config,
    ltp: LocalTangentPlane,
    journal: Any | None,
    *,
    clock: DaemonClock | None = None,
    clock_unix_usec: Callable[[], int] | None = None,
) -> TimeAxis:
    """The C5 estimator on its time axis, with the journal as its IMU (the daemon's records, a replay's
    playback): the one place its bounds are read from config."""
    return TimeAxis(
        NavEstimator(config.estimator, ltp, accel_source=journal),
        max_delay_s=config.estimator.max_fix_delay_s,
        max_frame_age_s=config.daemon.max_frame_age_s,
        max_future_s=config.estimator.max_future_s,
        clock=clock,
        clock_unix_usec=clock_unix_usec,
        journal=journal,
        camera_offset=CameraStampOffset(
            max_offset_s=config.camera.max_stamp_offset_s, prior_sigma_s=config.camera.stamp_sigma_s
        ),
    )


def _pipeline(
    config: Config,
    calibration: CameraCalibration,
    ltp: LocalTangentPlane,
    vo: HomographyVo,
    vpr: VprStrategy | None,
    rerank: RerankStrategy | None,
    ladder: EffortLadder | None,
    time_axis: TimeAxis,
    fdr: FdrClient,
    tiles: TileStore | None,
) -> NavigationPipeline:
    """The F3 pipeline, wired the same way for the daemon and for ``gdnav replay``."""
    footprint_chips = (
        FootprintChips(tiles, chip_size_px=config.matcher.chip_size_px)
        if tiles is not None and config.rerank.footprint_chip
        else None
    )
    return NavigationPipeline(
        calibration=calibration,
        ltp=ltp,
        ground_alt_amsl_m=config.terrain.ground_alt_amsl_m,
        vo=vo,
        vpr=vpr,
        vpr_config=config.vpr,
        rerank=rerank,
        matcher=None,
        ladder=ladder,
        pose_solver=PoseSolver(config.pose, ltp, config.terrain.ground_alt_amsl_m),
        area_pose_solver=AreaPoseSolver(config.pose, ltp, config.terrain.ground_alt_amsl_m),
        heading_height_check=HeadingHeightCheck(config.integrity.full_evidence_psr),
        time_axis=time_axis,
        fdr=fdr,
        integrity=FixIntegrity(config.integrity),
        consistency=FixConsistency(config.integrity),
        attitude_check=AttitudeCheck(config.pose),
        ground_tilt_check=(
            AttitudeCheck(
                config.pose,
                samples=config.pose.ground_tilt_check_samples,
                max_age_s=config.pose.ground_tilt_check_max_age_s,
                ground_correlated=False,
            )
            if config.pose.ground_tilt_check
            else None
        ),
        mount=CameraMount(
            math.radians(config.camera.mount_roll_deg), math.radians(config.camera.mount_pitch_deg)
        ),
        footprint_chips=footprint_chips,
        attitude_sigma_deg=config.pose.attitude_sigma_deg,
        prior_doubt=PriorDoubt(config.init),
        map_extent=_map_extent(tiles) if tiles is not None else None,
    )


def _map_extent(tiles: TileStore) -> tuple[float, float, float]:
    """The cache's centre (lat_deg, lon_deg) and the ground distance from it to its farthest corner, m."""
    west, south, east, north = tiles.bbox_lonlat
    lon, lat = tiles.center_lonlat
    radius_m = max(float(haversine_m(lat, lon, y, x)) for x in (west, east) for y in (south, north))
    return lat, lon, radius_m


def compose_root(config: Config, *, pre_constructed: Mapping[str, Any] | None = None) -> RuntimeRoot:
    """Build every object the daemon needs from ``config``.

    ``pre_constructed`` lets a caller (tests, the SITL) hand in objects by slot name instead of having
    them built here: ``c7_inference``, ``c3_lightglue_runtime``, ``c282_ransac_filter``, ``fdr``,
    ``clock`` (a ``DaemonClock``: the one "now" of the run, given to everything that needs one),
    ``link`` (the link ``link_first.open_link_first`` opened on that clock: given its FDR and frame here).
    """
    pre = dict(pre_constructed or {})
    clock: DaemonClock = pre.get("clock") or DaemonClock()
    unresolved, config = config, resolve_matcher(config)
    calibration = _calibration(config)
    check_signing_key(config)
    _check_fdr_dir(config)
    _check_strategy_names(config)
    early_link: MavlinkLink | None = pre.get("link")
    tracker = early_link.tracker if early_link is not None else make_tracker(config, clock)
    # The start-up beacon has been reading the autopilot on the early link since it opened.
    now_s = clock.now_unix_s()
    air = in_the_air(config.init, tracker.alt_agl_at(int(now_s * 1e6)), tracker.flight_phase(now_s))
    tiles = open_tile_store(config, *cache_verification(config, air))
    center_lon, center_lat = tiles.center_lonlat
    ltp = LocalTangentPlane(center_lat, center_lon, config.terrain.ground_alt_amsl_m)

    # F8: what the previous run left, read before this run records anything: the FDR and the resume
    # state file, which keeps the last 3D estimate when the FDR could not (a full disk).
    fdr_dir = Path(config.fdr.dir)
    if fdr_dir.exists() and not fdr_dir.is_dir():
        raise StartupError("fdr.dir", f"{fdr_dir} is not a directory (expected the recorder's directory)")
    state_path = config.init.resume_state_path or default_path(fdr_dir)
    previous_run = with_resume_state(
        read_previous_run(read_records_newest_first(fdr_dir)),
        read_resume_state(state_path, clock.now_unix_s()),
    )
    fdr = pre.get("fdr") or FlightDataRecorder(
        Path(config.fdr.dir),
        max_bytes=config.fdr.max_bytes,
        segment_bytes=config.fdr.segment_bytes,
        images_max_bytes=config.fdr.frame_jpeg_max_bytes,
        min_free_bytes=config.fdr.min_free_bytes,
        clock=clock.now_unix_s,
    )
    # A map cell corrupted after verification is masked by the store; the FDR keeps which and when.
    tiles.on_corrupt = lambda info: fdr.record(FdrKind.TILE_CORRUPT, info)
    config = with_area_rung(unresolved, config, tiles)
    fields = open_map_fields(config, tiles, fdr)
    matcher = create_matcher(config, pre, fdr, open_tile_features(config, tiles, fdr), fields)
    ladder = create_ladder(config, unresolved, pre, fdr, tiles, matcher, fields)

    vpr = create_vpr(tiles, config)
    rerank = _pick("rerank", RERANK_STRATEGIES, config.rerank.strategy)(tiles, config)
    # Every unit of the time axis and the IMU answers inside it go to the FDR (``gdnav replay``).
    journal = RecordingJournal(tracker, lambda fields: fdr.record(FdrKind.ESTIMATOR_INPUT, fields))
    time_axis = _time_axis(config, ltp, journal, clock=clock)
    vo = HomographyVo(calibration)
    pipeline = _pipeline(config, calibration, ltp, vo, vpr, rerank, ladder, time_axis, fdr, tiles)
    if early_link is not None:
        link = early_link
        try:
            link.attach(fdr, ltp)
        except MavlinkConfigError as exc:
            raise StartupError("mavlink.outputs", str(exc)) from exc
    else:
        link = MavlinkLink(config.mavlink, tracker, fdr, clock.now_unix_s, ltp=ltp)
    camera = open_camera_source(config)
    return RuntimeRoot(
        config,
        calibration,
        ltp,
        tiles,
        fdr,
        tracker,
        link,
        camera,
        matcher,
        pipeline,
        time_axis,
        previous_run,
        clock,
        ResumeStateFile(state_path),
    )


@dataclass
class ReplayRoot:
    """What ``gdnav replay`` runs: the same pipeline and time axis as the daemon, on one thread, with the
    clock and the IMU the replay gives them."""

    config: Config
    calibration: CameraCalibration
    ltp: LocalTangentPlane
    pipeline: NavigationPipeline
    time_axis: TimeAxis
    #: None when the replay runs without a map cache (VO only).
    tile_store: TileStore | None


def compose_replay(
    config: Config,
    *,
    fdr: FdrClient,
    clock_unix_usec: Callable[[], int],
    journal: Any | None = None,
    with_map: bool = True,
    calibration: CameraCalibration | None = None,
    ltp_origin_lat_lon: tuple[float, float] | None = None,
    vo_max_gap_s: float | None = None,
) -> ReplayRoot:
    """The pipeline for a replay, built the way ``compose_root`` builds the daemon's (same strategies and
    settings from ``config``), minus the link, the camera and the recorder.

    ``journal``: the ``ReplayJournal`` (exact replay of an FDR: it is then also the estimator's
    acceleration source) or None (no IMU: constant-velocity prediction). ``with_map``: open
    ``config.cache.dir`` and run the fix path; without it the pipeline has no VPR, rerank or matcher and
    every fix attempt says ``no_map``. ``calibration``: overrides the config's camera (a replay of photos
    brings its own). ``ltp_origin_lat_lon``: the NED origin without a map (the map's centre otherwise).
    ``vo_max_gap_s``: C1's longest measured interval (default: the daemon's).
    """
    unresolved, config = config, resolve_matcher(config)
    calib = calibration if calibration is not None else _calibration(config)
    tiles: TileStore | None = None
    vpr: VprStrategy | None = None
    rerank: RerankStrategy | None = None
    ladder: EffortLadder | None = None
    if with_map:
        # A replay runs on the ground: the configured full check is taken as asked.
        tiles = open_tile_store(config, *cache_verification(config, air=False))
        lon, lat = tiles.center_lonlat
        ltp = LocalTangentPlane(lat, lon, config.terrain.ground_alt_amsl_m)
        config = with_area_rung(unresolved, config, tiles)
        fields = open_map_fields(config, tiles, fdr)
        matcher = create_matcher(config, {}, fdr, open_tile_features(config, tiles, fdr), fields)
        ladder = create_ladder(config, unresolved, {}, fdr, tiles, matcher, fields)
        vpr = create_vpr(tiles, config)
        rerank = _pick("rerank", RERANK_STRATEGIES, config.rerank.strategy)(tiles, config)
    else:
        if ltp_origin_lat_lon is None:
            raise ValueError("a replay without a map needs ltp_origin_lat_lon")
        ltp = LocalTangentPlane(*ltp_origin_lat_lon, config.terrain.ground_alt_amsl_m)
    time_axis = _time_axis(config, ltp, journal, clock_unix_usec=clock_unix_usec)
    vo = HomographyVo(calib) if vo_max_gap_s is None else HomographyVo(calib, max_gap_s=vo_max_gap_s)
    pipeline = _pipeline(config, calib, ltp, vo, vpr, rerank, ladder, time_axis, fdr, tiles)
    return ReplayRoot(config, calib, ltp, pipeline, time_axis, tiles)
