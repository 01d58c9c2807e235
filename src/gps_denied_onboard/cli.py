"""``gdnav``: the daemon, the simulator, and the pre-flight tools.

Exit codes: 0 success; 1 runtime failure (also any exception no refusal maps: a bug, one line naming it,
its traceback in the debug log, ``logging_setup.log_unexpected``); 2 bad configuration or arguments; 3 a
resource the daemon needs is missing or refused (cache, model, calibration, signing key file, a UDP port
another process holds); 130 interrupted. Never a traceback on stderr; ``main`` maps the error types.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import structlog

from gps_denied_onboard import __version__
from gps_denied_onboard.config import ConfigError, config_to_dict, load_config
from gps_denied_onboard.constants import EXIT_CONFIG, EXIT_FAILURE, EXIT_OK, EXIT_RESOURCE, FdrKind, LogEvent
from gps_denied_onboard.logging_setup import configure_logging, log_unexpected

#: Ctrl-C (or a SIGTERM a command turns into one): the shell's convention, 128 + SIGINT.
EXIT_INTERRUPTED = 130


#: Where a vision worker's one refusal line goes instead of stderr: to its navigator core, which prints it
#: as its own last line when it stops with the worker's exit code (``daemon/core.py``).
_err_to_core: Callable[[str], object] | None = None


def _err(message: str) -> None:
    if _err_to_core is not None:
        _err_to_core(message)
        return
    print(f"gdnav: {message}", file=sys.stderr)


def _resource_refusals() -> tuple[type[Exception], ...]:
    """Errors meaning that a file or resource the daemon needs is refused (exit 3). Imported only while an
    error is being handled: these modules take a second to import and most commands never need them."""
    from gps_denied_onboard.components.c8_mavlink import MavlinkConfigError
    from gps_denied_onboard.runtime_root import StartupError

    return (StartupError, MavlinkConfigError)


#: The environment variables that set numpy's BLAS threads when it loads.
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def limit_blas_threads(n: int) -> bool:
    """Set numpy's BLAS to ``n`` threads (``daemon.blas_threads``); only before numpy is imported, as
    OpenBLAS reads the variables once when it loads. Returns whether it could."""
    if "numpy" in sys.modules:
        return False
    for name in BLAS_THREAD_VARIABLES:
        os.environ[name] = str(n)
    return True


def _apply_process_nice(target: int | None, log: Any) -> None:
    """``daemon.process_nice`` (see the config): lower this process's nice value to ``target`` before any
    thread starts (threads inherit it), where the process may; log what it runs at, and why."""
    if target is None:
        return
    before = os.getpriority(os.PRIO_PROCESS, 0)
    if before <= target:
        log.info(LogEvent.DAEMON_PRIORITY, nice=before, wanted=target, action="kept (already as high)")
        return
    try:
        os.setpriority(os.PRIO_PROCESS, 0, target)
    except OSError as exc:  # not root and no CAP_SYS_NICE: run as started, and say so
        log.warning(
            LogEvent.DAEMON_PRIORITY,
            nice=before,
            wanted=target,
            action="kept: not permitted (set Nice= in the unit, or CAP_SYS_NICE)",
            error=str(exc),
        )
        return
    log.info(LogEvent.DAEMON_PRIORITY, nice=os.getpriority(os.PRIO_PROCESS, 0), wanted=target, action="set")


def _cmd_run(args: argparse.Namespace) -> int:
    from gps_denied_onboard.daemon import signals

    signals.ignore()  # SIGHUP/SIGUSR1/SIGUSR2 must not end the daemon, not even while it starts
    config = load_config(args.config, args.set or ())
    blas_set = limit_blas_threads(config.daemon.blas_threads)
    configure_logging(config.logging.level, json=config.logging.json)
    log = structlog.get_logger("gdnav")
    log.info(
        LogEvent.DAEMON_CONFIG,
        source=str(args.config),
        version=__version__,
        config=config_to_dict(config),
        blas_threads=config.daemon.blas_threads if blas_set else "not set: numpy was already loaded",
    )
    worker = args.worker_fd is not None
    if not worker:  # a vision worker runs at the nice value its core gave it
        _apply_process_nice(config.daemon.process_nice, log)

    from gps_denied_onboard.clock import DaemonClock
    from gps_denied_onboard.components.c8_mavlink import MavlinkConfigError
    from gps_denied_onboard.daemon.beacon import StartupBeacon
    from gps_denied_onboard.runtime_root.link_first import StartupError, open_link_first

    if config.daemon.vision_worker and not worker:
        return _run_core(args, config, log)
    # The link first, and the beacon on it while the rest loads (imports included): the autopilot hears
    # the daemon (HEARTBEAT, GPS_INPUT without a fix) a second sooner after a restart (issue 27).
    clock = DaemonClock()
    channel = None
    if worker:
        from gps_denied_onboard.daemon.core import LAUNCH_ID_ENV, WORKER_SIGNING_LINK_ID
        from gps_denied_onboard.daemon.core_channel import CoreChannel, rendezvous_address

        hello = {
            "pid": os.getpid(),
            "mavlink_url": config.mavlink.url,
            "launch_id": os.environ.get(LAUNCH_ID_ENV),
        }
        channel = CoreChannel(  # listening for the core's next start, so a core crash never ends the vision
            args.worker_fd,
            rendezvous=rendezvous_address(config.fdr.dir),
            hello=hello,
            clock_anchor_ns=clock.anchor_unix_ns,
        )
        global _err_to_core
        _err_to_core = channel.send_refusal
        if not channel.poll():  # the core's handover, if it has an estimate, is already waiting
            log.error("daemon.startup_refused", what="--worker-fd", error="the navigator core has gone")
            return EXIT_FAILURE
    try:
        link = open_link_first(config, clock, signing_link_id=WORKER_SIGNING_LINK_ID if worker else 0)
    except (StartupError, MavlinkConfigError) as exc:
        log.error("daemon.startup_refused", what=getattr(exc, "what", "mavlink.url"), error=str(exc))
        raise  # main() prints the one line and exits 3
    beacon = StartupBeacon(
        link, config.mavlink, clock.now_unix_s, ask_estimate=config.init.autopilot_wait_s > 0
    )
    beacon.start()
    try:
        from gps_denied_onboard.daemon.service import NavDaemon
        from gps_denied_onboard.runtime_root import compose_root

        root = compose_root(config, pre_constructed={"clock": clock, "link": link})
        from gps_denied_onboard.components.c13_fdr.provenance import run_inputs
        from gps_denied_onboard.runtime_root.compose import WEIGHTS_FREE_MATCHERS

        # The resolved matcher (``auto`` picked, model_dir applied) says which model files this run uses.
        m = root.config.matcher
        learned = m.strategy not in WEIGHTS_FREE_MATCHERS
        inputs = run_inputs(
            args.config,
            overrides=args.set or (),
            cache_dir=root.config.cache.dir,
            model_dir=m.model_dir if learned else None,
            model_files=(
                [m.disk_weights_path, m.aliked_weights_path, m.xfeat_weights_path, m.lightglue_weights_path]
                if learned
                else []
            ),
        )
        root.fdr.record(FdrKind.CONFIG, {"version": __version__, "config": config_to_dict(config), **inputs})
        # The daemon opens its MAVLink link before READY: a UDP port another process holds is refused there.
        daemon = NavDaemon(root, beacon=beacon, core=channel)
        # Not asyncio.run: its teardown waits without bound for tasks that ignored their cancellation
        # (seen under load: a SIGTERM'd daemon still alive 10 s later, then SIGKILLed).
        loop = asyncio.new_event_loop()
        code = loop.run_until_complete(daemon.run())
    except BaseException as exc:
        beacon.stop()
        link.close()
        if isinstance(exc, (StartupError, MavlinkConfigError)):
            what = getattr(exc, "what", "mavlink.url")
            log.error("daemon.startup_refused", what=what, error=str(exc))
        raise  # main() prints the one line and exits 3 for a refusal
    if daemon.abandoned_threads or daemon.stuck_tasks:
        # A worker is still inside a frame (e.g. in ONNX Runtime), or a task is stuck. Interpreter
        # teardown would unwind or destroy native code under it and abort the process (SIGABRT, seen once
        # after SIGTERM), or wait on the task; the FDR and the link are already closed, so end here with
        # the daemon's own exit code.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    loop.run_until_complete(loop.shutdown_asyncgens())
    loop.close()
    return code


def _run_core(args: argparse.Namespace, config: Any, log: Any) -> int:
    """``daemon.vision_worker``: this process is the navigator core (``daemon/core.py``); the vision
    worker is ``gdnav run`` again, started by it."""
    from gps_denied_onboard.clock import DaemonClock
    from gps_denied_onboard.components.c8_mavlink import MavlinkConfigError
    from gps_denied_onboard.daemon.core import CORE_SIGNING_LINK_ID, NavigatorCore
    from gps_denied_onboard.runtime_root.link_first import StartupError, open_link_first

    clock = DaemonClock()
    try:
        link = open_link_first(config, clock, signing_link_id=CORE_SIGNING_LINK_ID)
    except (StartupError, MavlinkConfigError) as exc:
        log.error("daemon.startup_refused", what=getattr(exc, "what", "mavlink.url"), error=str(exc))
        raise
    core = NavigatorCore(config, args.config, args.set or (), link=link, clock=clock)
    loop = asyncio.new_event_loop()
    try:
        code = loop.run_until_complete(core.run())
    finally:
        loop.close()
    if core.refused_exit is not None and core.worker_refusal is not None:
        _err(core.worker_refusal)  # the worker's one line, last, as one process would have said it
    return code


def _cmd_cache_build(args: argparse.Namespace) -> int:
    from gps_denied_onboard.components.c10_cache_build import CacheBuildError
    from gps_denied_onboard.components.c10_cache_build.shards import EngineSpec, open_engine

    configure_logging("info", json=False)
    bbox: tuple[float, float, float, float] | None = None
    if args.bbox:
        try:
            west, south, east, north = (float(v) for v in args.bbox.split(","))
        except ValueError:
            _err(f"--bbox {args.bbox!r}: expected W,S,E,N in degrees")
            return EXIT_CONFIG
        bbox = (west, south, east, north)
    headers = {}
    for h in args.header:
        name, sep, value = h.partition(":")
        if not sep or not name.strip():
            _err(f"--header {h!r}: expected NAME:VALUE")
            return EXIT_CONFIG
        headers[name.strip()] = value.strip()
    try:
        engine = EngineSpec(workers=args.workers, address=args.address)
    except CacheBuildError as exc:
        _err(str(exc))
        return EXIT_CONFIG
    if args.dry_run:
        return _cache_dry_run(args, bbox, engine)
    if engine.distributed and not Path(args.source).is_file():
        _err("--workers and --address apply to a GeoTIFF source; XYZ tiles are built in this process")
        return EXIT_CONFIG
    # One engine for both stages (the mosaic's shards, the fields' bands): a cluster starts once.
    try:
        with open_engine(engine) as runner:
            return _cache_build_stages(args, bbox, headers, runner)
    except CacheBuildError as exc:
        _err(str(exc))
        return EXIT_CONFIG


def _cache_build_stages(
    args: argparse.Namespace,
    bbox: tuple[float, float, float, float] | None,
    headers: dict[str, str],
    engine: Any,
) -> int:
    from gps_denied_onboard.components.c10_cache_build import CacheBuildError, build_cache
    from gps_denied_onboard.components.c11_tile_download import TileDownloadError

    try:
        manifest = build_cache(
            args.source,
            Path(args.out),
            zoom=args.zoom,
            bbox_lonlat=bbox,
            tile_size_px=args.tile_size,
            tms=args.tms,
            progress=not args.quiet,
            allow_failed_tiles=args.allow_failed_tiles,
            downloader_options={
                "concurrency": args.concurrency,
                "rate_limit_per_s": args.rate_limit,
                "max_retries": args.max_retries,
                "timeout_s": args.timeout,
                "headers": headers,
            },
            engine=engine,
        )
    except (CacheBuildError, TileDownloadError) as exc:
        _err(str(exc))
        return EXIT_CONFIG
    print(f"cache: {args.out}: zoom {manifest.zoom}, {manifest.tile_count} tiles")
    code = (
        EXIT_OK
        if args.no_fields
        else _map_fields(Path(args.out), force=False, quiet=args.quiet, engine=engine)
    )
    if code != EXIT_OK:
        return code
    return _verify_built_cache(Path(args.out))


def _verify_built_cache(cache_dir: Path) -> int:
    """The full check at the end of ``gdnav cache build`` (the manifest's hash, every file's sha256), so
    that what the daemon's light check at start trusts was verified where the bytes were written."""
    from gps_denied_onboard.components.c10_cache_build.manifest import CacheManifestError, verify_cache

    t0 = time.monotonic()
    try:
        manifest = verify_cache(cache_dir)
    except CacheManifestError as exc:
        _err(f"the cache does not verify after its build: {exc}")
        return EXIT_RESOURCE
    print(
        f"cache: {cache_dir}: sha256 of every file verified in {time.monotonic() - t0:.1f} s "
        f"({len(manifest.artifacts)} artifacts, the fields and tile features included)"
    )
    return EXIT_OK


def _cache_dry_run(
    args: argparse.Namespace, bbox: tuple[float, float, float, float] | None, engine: Any
) -> int:
    """``cache build --dry-run``: the tile count, each artifact's size and each stage's estimated time."""
    from gps_denied_onboard.components.c10_cache_build import CacheBuildError
    from gps_denied_onboard.components.c10_cache_build.dry_run import estimate_geotiff_build

    if not Path(args.source).is_file():
        _err(f"--dry-run estimates a GeoTIFF build; {args.source!r} is not a file")
        return EXIT_CONFIG
    try:
        estimate = estimate_geotiff_build(
            Path(args.source),
            zoom=args.zoom,
            bbox_lonlat=bbox,
            tile_size_px=args.tile_size if args.tile_size is not None else 256,
            engine=engine,
            fields=not args.no_fields,
        )
    except CacheBuildError as exc:
        _err(str(exc))
        return EXIT_CONFIG
    print(f"dry run: {args.source} -> {args.out} (nothing written)")
    for line in estimate.lines():
        print(line)
    return EXIT_OK


def _map_fields(cache_dir: Path, *, force: bool, quiet: bool, engine: Any = None) -> int:
    """Add the area correlation's orientation fields and their calibration (``c10_cache_build.map_fields``)
    and say what they are."""
    from gps_denied_onboard.components.c10_cache_build import CacheBuildError
    from gps_denied_onboard.components.c10_cache_build.map_fields import build_map_fields

    try:
        result = build_map_fields(cache_dir, force=force, progress=not quiet, engine=engine)
    except CacheBuildError as exc:
        _err(str(exc))
        return EXIT_RESOURCE
    info = result.manifest.map_fields
    assert info is not None
    size_mib = sum(f.bytes for f in info.files.values()) / 2**20
    what = "built" if result.built else "up to date"
    if not info.calibrations:
        print(
            f"cache: {cache_dir}: orientation fields {what} ({size_mib:.1f} MiB), not calibrated: the map "
            "has no room for a calibration template and its search disc; orientation_corr will not run on it"
        )
        return EXIT_OK
    print(f"cache: {cache_dir}: orientation fields {what} ({size_mib:.1f} MiB)")
    for level, cal in sorted(info.calibrations.items()):
        print(
            f"  level {level}: {cal.samples} templates of {cal.template_px[0]}x{cal.template_px[1]} px in a "
            f"{cal.radius_px:.0f} px disc: wrong places PSR <= {cal.null_psr_max:.1f}, peak <= "
            f"{cal.null_peak_max:.3f}; right places PSR p5 {cal.right_psr_p5:.1f}, peak p5 "
            f"{cal.right_peak_p5:.3f}"
        )
    return EXIT_OK


def _cmd_cache_fields(args: argparse.Namespace) -> int:
    configure_logging("info", json=False)
    return _map_fields(Path(args.cache), force=args.force, quiet=args.quiet)


def _cmd_cache_vpr(args: argparse.Namespace) -> int:
    from gps_denied_onboard.components.c10_cache_build import CacheBuildError
    from gps_denied_onboard.components.c10_cache_build.shards import EngineSpec
    from gps_denied_onboard.components.c10_cache_build.vpr_index import build_vlad_index

    configure_logging("info", json=False)
    try:
        engine = EngineSpec(workers=args.workers, address=args.address)
    except CacheBuildError as exc:
        _err(str(exc))
        return EXIT_CONFIG
    describer = None
    params = None
    if args.descriptor == "xfeat":
        from gps_denied_onboard.components.c2_vpr.learned_local import (
            XFeatDescriber,
            default_xfeat_params,
            find_xfeat_extractor,
        )
        from gps_denied_onboard.components.c7_inference import OnnxInferenceRuntime
        from gps_denied_onboard.components.c7_inference.protocol import EngineLoadError
        from gps_denied_onboard.helpers.model_manifest import ModelDirError

        try:
            path = Path(args.xfeat) if args.xfeat else find_xfeat_extractor(args.model_dir)
            describer = XFeatDescriber(OnnxInferenceRuntime(intra_op_threads=args.threads), path)
        except (ModelDirError, EngineLoadError, OSError) as exc:
            _err(str(exc))
            return EXIT_RESOURCE
        params = default_xfeat_params()
    elif args.xfeat:
        _err("--xfeat is used only with --descriptor xfeat")
        return EXIT_CONFIG
    try:
        manifest = build_vlad_index(
            Path(args.cache),
            params,
            describer=describer,
            force=args.force,
            progress=not args.quiet,
            engine=engine,
        )
    except CacheBuildError as exc:
        _err(str(exc))
        return EXIT_CONFIG
    print(f"cache: {args.cache}: VPR index {manifest.vpr.backbone} over {manifest.tile_count} tiles")
    return EXIT_OK


def _cmd_cache_features(args: argparse.Namespace) -> int:
    import dataclasses

    from gps_denied_onboard.components.c3_matcher.base import NULL_FDR
    from gps_denied_onboard.components.c3_matcher.learned import LearnedPairMatcher
    from gps_denied_onboard.components.c10_cache_build import CacheBuildError
    from gps_denied_onboard.components.c10_cache_build.tile_features import build_tile_features
    from gps_denied_onboard.runtime_root.compose import create_matcher, resolve_matcher

    config = load_config(args.config, args.set or ())
    configure_logging("info", json=False)
    if args.strategy is not None:
        config = dataclasses.replace(
            config, matcher=dataclasses.replace(config.matcher, strategy=args.strategy)
        )
    config = resolve_matcher(config)
    cache_dir = Path(args.cache if args.cache is not None else config.cache.dir)
    # The matcher is built exactly as the daemon builds it (same model, same settings), so the features
    # are those its candidate loop would extract.
    matcher = create_matcher(config, {}, NULL_FDR)
    if not isinstance(matcher, LearnedPairMatcher):
        _err(
            f"matcher.strategy {config.matcher.strategy!r} has no precomputable tile features; "
            "expected a learned strategy (disk_lightglue, aliked_lightglue, xfeat, xfeat_mnn)"
        )
        return EXIT_CONFIG
    try:
        result = build_tile_features(cache_dir, matcher, force=args.force, progress=not args.quiet)
    except CacheBuildError as exc:
        _err(str(exc))
        return EXIT_RESOURCE
    ident = matcher.extractor_identity
    what = "built" if result.built else "up to date"
    print(
        f"cache: {cache_dir}: {ident.strategy} tile features {what}: {result.manifest.tile_count} tiles, "
        f"{result.stats.get('keypoints', 0)} keypoints, {result.bytes / 2**20:.1f} MiB, "
        f"{result.stats.get('total_s', 0.0):.1f} s to build (model sha256 {ident.model_sha256[:12]}..., "
        f"chip {ident.chip_size_px} px, max {ident.max_keypoints} keypoints)"
    )
    return EXIT_OK


def _raise_interrupt(_signum: int, _frame: object) -> None:
    raise KeyboardInterrupt


def _cmd_sitl_run(args: argparse.Namespace) -> int:
    from gps_denied_onboard.sitl.runner import SitlError, run_sitl_cli

    configure_logging("warning", json=False)
    # SIGTERM unwinds like Ctrl-C, so the flight's cleanup stops the daemon it started (which also gets
    # SIGTERM from the kernel should this process die outright: runner.spawn_daemon)
    signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        if getattr(args, "autopilot", None):
            from gps_denied_onboard.sitl.autopilot_flight import run_autopilot_cli

            if getattr(args, "spoofed_start", None):
                raise SitlError("--spoofed-start: the scripted autopilot only (not with --autopilot)")

            return run_autopilot_cli(args)
        return run_sitl_cli(args)
    except SitlError as exc:
        _err(str(exc))
        return EXIT_CONFIG


def _cmd_sitl_emulate(args: argparse.Namespace) -> int:
    if args.px4:
        from gps_denied_onboard.sitl import px4_emulator

        return px4_emulator.run_from_args(args)
    from gps_denied_onboard.sitl.ap_emulator import run_from_args

    return run_from_args(args)


def _cmd_config_check(args: argparse.Namespace) -> int:
    config = load_config(args.config, args.set or ())
    from gps_denied_onboard.runtime_root import preflight

    # Run as the service user (docs/companion.md), the calibration and the signing key file are refused here
    # (exit 3) exactly as `gdnav run` refuses them. The cache and models are not checked (hashing the cache
    # takes seconds); `gdnav run` verifies them.
    preflight(config)
    print(f"{args.config}: ok")
    return EXIT_OK


def _top_parser() -> tuple[argparse.ArgumentParser, Any]:
    parser = argparse.ArgumentParser(prog="gdnav", description=__doc__.split("\n")[0])
    parser.add_argument("--version", action="version", version=f"gdnav {__version__}")
    return parser, parser.add_subparsers(dest="command", required=True, metavar="COMMAND")


def _add_run(sub: Any) -> None:
    run = sub.add_parser(
        "run", help="run the navigation daemon", description="Run the navigation daemon until SIGTERM/SIGINT."
    )
    run.add_argument("--config", required=True, type=Path, help="YAML profile, e.g. config/airborne.yaml")
    run.add_argument(
        "--set",
        action="append",
        metavar="KEY.PATH=VALUE",
        help="override one setting (repeatable), validated like the file",
    )
    # The navigator core starts its vision worker with this (``daemon.vision_worker``); not for people.
    run.add_argument("--worker-fd", type=int, default=None, help=argparse.SUPPRESS)
    run.set_defaults(func=_cmd_run)


def run_parser() -> argparse.ArgumentParser:
    """The parser of ``gdnav run`` alone: the other commands' parsers import numpy, OpenCV and the
    emulator (~0.3 s), which the daemon's start-up must not wait for, and numpy must load only after
    ``daemon.blas_threads`` is applied."""
    parser, sub = _top_parser()
    _add_run(sub)
    return parser


def build_parser() -> argparse.ArgumentParser:
    parser, sub = _top_parser()
    _add_run(sub)

    cfg = sub.add_parser("config", help="configuration tools", description="Configuration tools.")
    cfg_sub = cfg.add_subparsers(dest="config_command", required=True, metavar="SUBCOMMAND")
    check = cfg_sub.add_parser("check", help="validate a profile", description="Validate a YAML profile.")
    check.add_argument("--config", required=True, type=Path)
    check.add_argument("--set", action="append", metavar="KEY.PATH=VALUE")
    check.set_defaults(func=_cmd_config_check)

    cache = sub.add_parser("cache", help="pre-flight map cache", description="Pre-flight map cache (F1).")
    cache_sub = cache.add_subparsers(dest="cache_command", required=True, metavar="SUBCOMMAND")
    build = cache_sub.add_parser(
        "build",
        help="build a cache from a GeoTIFF, an XYZ tile directory or a tile server",
        description="Build a Web-Mercator tile cache (F1). Idempotent: re-running with the same inputs "
        "changes nothing; an interrupted download resumes.",
    )
    build.add_argument(
        "--source",
        required=True,
        help="GeoTIFF file (any CRS), directory of {z}/{x}/{y} tiles, or http(s):// tile URL "
        "template with {z}/{x}/{y}",
    )
    build.add_argument("--out", required=True, help="cache directory to create or resume")
    build.add_argument(
        "--zoom",
        type=int,
        default=None,
        help="Web-Mercator zoom (default: matched to a GeoTIFF's GSD; required for a tile server)",
    )
    build.add_argument(
        "--bbox",
        default=None,
        help="W,S,E,N in degrees (default: the whole source; required for a tile server)",
    )
    build.add_argument(
        "--tile-size",
        type=int,
        default=None,
        help="tile size in px (default: 256 for a GeoTIFF, detected for XYZ tiles)",
    )
    build.add_argument("--tms", action="store_true", help="XYZ directory uses TMS rows (y from the south)")
    build.add_argument(
        "--concurrency", type=int, default=4, help="tile server: parallel downloads (default 4)"
    )
    build.add_argument(
        "--rate-limit", type=float, default=10.0, help="tile server: max requests per second (default 10)"
    )
    build.add_argument(
        "--max-retries",
        type=int,
        default=5,
        help="tile server: retries per tile on 429/5xx/timeouts (default 5)",
    )
    build.add_argument("--timeout", type=float, default=20.0, help="tile server: per-request timeout, s")
    build.add_argument(
        "--header",
        action="append",
        default=[],
        metavar="NAME:VALUE",
        help="tile server: extra HTTP header (repeatable), e.g. Referer",
    )
    build.add_argument(
        "--allow-failed-tiles",
        action="store_true",
        help="tile server: build with gaps where downloads still failed after retries",
    )
    build.add_argument("--quiet", action="store_true", help="no progress bar")
    build.add_argument(
        "--no-fields",
        action="store_true",
        help="skip the orientation fields of the area correlation (gdnav cache fields adds them later)",
    )
    build.add_argument(
        "--workers",
        type=int,
        default=1,
        help="GeoTIFF: shards run on a local Dask cluster of this many worker processes (default 1: in "
        "this process, no cluster); the cache is the same bytes whatever the number",
    )
    build.add_argument(
        "--address",
        default=None,
        metavar="tcp://HOST:PORT",
        help="GeoTIFF: run the shards on this running Dask scheduler; every worker must read --source "
        "at the same path",
    )
    build.add_argument(
        "--dry-run",
        action="store_true",
        help="GeoTIFF: print the tile count, each artifact's size and each stage's estimated time "
        "(from small samples timed here), and build nothing",
    )
    build.set_defaults(func=_cmd_cache_build)
    vpr = cache_sub.add_parser(
        "vpr",
        help="add the VLAD place-recognition index to a cache",
        description="Train a VLAD vocabulary on the cache's own tiles, describe every tile and build the "
        "FAISS HNSW index (needed by vpr.strategy: vlad, or vlad_xfeat with --descriptor xfeat; the "
        "manifest records the XFeat model's sha256 and the daemon refuses another model). Idempotent.",
    )
    vpr.add_argument("--cache", required=True, help="cache directory made by `gdnav cache build`")
    vpr.add_argument(
        "--descriptor",
        choices=("rootsift", "xfeat"),
        default="rootsift",
        help="local descriptors: rootsift (weights-free, vpr.strategy vlad; default) or xfeat (the "
        "exported XFeat extractor, vpr.strategy vlad_xfeat)",
    )
    vpr.add_argument(
        "--model-dir",
        default="models",
        metavar="DIR",
        help="--descriptor xfeat: model directory made by `gdnav models export` (default: models)",
    )
    vpr.add_argument(
        "--xfeat", default=None, metavar="ONNX", help="--descriptor xfeat: this extractor file instead"
    )
    vpr.add_argument(
        "--threads", type=int, default=2, metavar="N", help="ONNX Runtime intra-op threads (default 2)"
    )
    vpr.add_argument("--force", action="store_true", help="rebuild even when the index is up to date")
    vpr.add_argument("--quiet", action="store_true", help="no progress bar")
    vpr.add_argument(
        "--workers",
        type=int,
        default=1,
        help="describe the tiles in shards on a local Dask cluster of this many worker processes (default "
        "1: in this process); the same bytes whatever the number; --descriptor rootsift only",
    )
    vpr.add_argument(
        "--address",
        default=None,
        metavar="tcp://HOST:PORT",
        help="describe the tiles on this running Dask scheduler (every worker reads the cache at the "
        "same path)",
    )
    vpr.set_defaults(func=_cmd_cache_vpr)
    feats = cache_sub.add_parser(
        "features",
        help="precompute the learned matcher's tile features into a cache",
        description="Run the configured learned strategy's extractor once over every tile's chip and store "
        "the keypoints and descriptors memory-mapped in the cache, tied to the model's sha256, the chip size "
        "and the keypoint cap (used by the daemon when matcher.tile_features is auto or require). "
        "Idempotent; a set made by another model is replaced.",
    )
    feats.add_argument("--config", required=True, type=Path, help="daemon profile naming the matcher")
    feats.add_argument("--set", action="append", metavar="KEY.PATH=VALUE", help="override one setting")
    feats.add_argument("--cache", default=None, help="cache directory (default: the profile's cache.dir)")
    feats.add_argument(
        "--strategy",
        default=None,
        choices=("auto", "disk_lightglue", "aliked_lightglue", "xfeat", "xfeat_mnn"),
        help="learned strategy (default: the profile's matcher.strategy)",
    )
    feats.add_argument("--force", action="store_true", help="rebuild even when the set is up to date")
    feats.add_argument("--quiet", action="store_true", help="no progress bar")
    feats.set_defaults(func=_cmd_cache_features)
    fields = cache_sub.add_parser(
        "fields",
        help="add the area correlation's orientation fields and their calibration to a cache",
        description="Compute the map's gradient-orientation fields (two pyramid levels, CRC-32 per cell) "
        "and calibrate what a right and a wrong place score on this map, for matcher.strategy "
        "orientation_corr and the area rung of auto. `gdnav cache build` does this itself. Idempotent.",
    )
    fields.add_argument("--cache", required=True, help="cache directory made by `gdnav cache build`")
    fields.add_argument("--force", action="store_true", help="rebuild even when the fields are up to date")
    fields.add_argument("--quiet", action="store_true", help="no progress bar")
    fields.set_defaults(func=_cmd_cache_fields)

    sitl = sub.add_parser(
        "sitl",
        help="software-in-the-loop simulation",
        description="Simulated flight: renders the nav camera, plays the autopilot over "
        "MAVLink/UDP, runs the daemon as its own process, scores it.",
    )
    sitl_sub = sitl.add_subparsers(dest="sitl_command", required=True, metavar="SUBCOMMAND")
    srun = sitl_sub.add_parser(
        "run",
        help="fly a scenario and write a report",
        description="Fly a scenario against the daemon and write a JSON + PNG report.",
    )
    srun.add_argument(
        "--map",
        type=Path,
        default=None,
        help="GeoTIFF map (any CRS); default: the embedded procedural demo map",
    )
    srun.add_argument(
        "--scenario",
        default="demo",
        help="scenario YAML path or the name of a bundled one (demo, smoke, nominal_real)",
    )
    srun.add_argument("--report", type=Path, default=Path("out/sitl/report.json"), help="report JSON path")
    srun.add_argument(
        "--appearance",
        type=Path,
        default=None,
        help="another image of the same area (e.g. another date) to render the frames from",
    )
    srun.add_argument("--config", type=Path, default=None, help="daemon profile (default: config/sitl.yaml)")
    srun.add_argument("--set", action="append", metavar="KEY.PATH=VALUE", help="daemon config override")
    srun.add_argument(
        "--workdir",
        type=Path,
        default=None,
        help="where the cache, FDR and logs go (default: next to the report)",
    )
    srun.add_argument("--duration", type=float, default=None, help="cut the flight to this many seconds")
    srun.add_argument("--quiet", action="store_true", help="print only the summary")
    srun.add_argument(
        "--spoofed-start",
        default=None,
        metavar="YAML",
        help="drag the start points off the truth before the flight, as the scenario key spoofed_start "
        "(replacing the scenario's), e.g. '{offset_m: [3000, 0], sigma_m: 50, sources: [home, autopilot, "
        "config]}' (docs/sitl.md)",
    )
    srun.add_argument(
        "--autopilot",
        default=None,
        metavar="URL",
        help="fly on an external autopilot SITL (ArduPilot SITL or `gdnav sitl emulate`) at this pymavlink "
        "URL, e.g. tcp:127.0.0.1:5762 or udpout:127.0.0.1:14555: truth from its SIMSTATE, the mission "
        "driver flies the scenario's waypoints with the GNSS off after take-off",
    )
    srun.set_defaults(func=_cmd_sitl_run)
    from gps_denied_onboard.sitl.ap_emulator import DESCRIPTION as EMULATOR_DESCRIPTION
    from gps_denied_onboard.sitl.ap_emulator import add_arguments as emulator_arguments
    from gps_denied_onboard.sitl.px4_emulator import add_arguments as px4_emulator_arguments

    semu = sitl_sub.add_parser(
        "emulate",
        help="the ArduPilot copter emulator, or with --px4 the PX4 one (test doubles, not the autopilots) "
        "on loopback UDP",
        description=f"{EMULATOR_DESCRIPTION} With --px4: the PX4 multicopter emulator (SITL with SIH), "
        "whose --param takes PX4's names (EKF2_AGP0_ID=1); the --ekf-*, --system-time-offset-s and "
        "--arming-skipchk options are ArduPilot's.",
    )
    emulator_arguments(semu)
    semu.add_argument(
        "--px4", action="store_true", help="emulate PX4 (SITL with SIH) instead of ArduPilot (docs/px4.md)"
    )
    px4_emulator_arguments(semu)
    semu.set_defaults(func=_cmd_sitl_emulate)

    from gps_denied_onboard import cli_bench, cli_match, cli_models

    cli_models.register(sub)
    cli_match.register(sub)
    cli_bench.register(sub)
    from gps_denied_onboard import cli_fdr

    cli_fdr.register(sub)
    from gps_denied_onboard import cli_preflight

    cli_preflight.register(sub)
    from gps_denied_onboard import cli_replay

    cli_replay.register(sub)
    return parser


def _command_name(args: argparse.Namespace) -> str:
    """``run``, ``fdr summary``...: the command and subcommand the arguments chose."""
    words = [args.command]
    words += [str(v) for k, v in sorted(vars(args).items()) if k.endswith("_command") and v]
    return " ".join(words)


def main(argv: Sequence[str] | None = None) -> int:
    words = list(sys.argv[1:] if argv is None else argv)
    parser = run_parser() if words[:1] == ["run"] else build_parser()
    args = parser.parse_args(words)
    # The one place where typed refusals become exit codes. Any other exception is a bug: one line naming
    # it, exit 1 (a runtime failure: under systemd a daemon's bug is restarted, a refusal is not), and
    # its traceback in the debug log. (An except clause's types are evaluated only when one reaches it.)
    try:
        return int(args.func(args))
    except ConfigError as exc:
        _err(str(exc))
        return EXIT_CONFIG
    except _resource_refusals() as exc:
        _err(str(exc))
        return EXIT_RESOURCE
    except KeyboardInterrupt:
        _err("interrupted")
        return EXIT_INTERRUPTED
    except Exception as exc:  # the top level: every other exception is reported here
        command = _command_name(args)
        kept = log_unexpected(command, exc)
        what = " ".join(str(exc).split())[:300]
        _err(f"{command}: unexpected error: {type(exc).__name__}: {what} (a bug; {kept})")
        return EXIT_FAILURE


if __name__ == "__main__":
    sys.exit(main())
