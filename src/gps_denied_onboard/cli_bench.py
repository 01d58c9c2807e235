"""``gdnav bench ...``: benchmarks that print measured figures (and optionally write them as JSON).

``register(subparsers)`` adds the ``bench`` command with one subcommand per entry of ``BENCH_COMMANDS``.
Adding a benchmark = one ``BenchCommand`` (name, help, an argument adder and a runner) appended to that
tuple; the benchmark modules themselves are imported only when their subcommand runs, so ``gdnav --help``
stays light.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from gps_denied_onboard.constants import EXIT_CONFIG, EXIT_FAILURE, EXIT_OK, EXIT_RESOURCE


@dataclass(frozen=True)
class BenchCommand:
    """One ``gdnav bench <name>`` subcommand.

    ``add_arguments`` fills the subcommand's parser; ``run`` executes it and returns the exit code.
    """

    name: str
    help: str
    description: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


def _err(message: str) -> None:
    print(f"gdnav: {message}", file=sys.stderr)


def write_json(path: Path, figures: dict[str, Any]) -> None:
    """Write ``figures`` to ``path`` (parents created), pretty-printed."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(figures, indent=2, sort_keys=False) + "\n", encoding="utf-8")


# --- bench matcher ---------------------------------------------------------------------------------------
#: ``--frames-from`` of ``bench matcher`` and ``bench vpr``: the cross-date pairs.
_FRAMES_FROM_HELP: Final[str] = (
    "render the query frames from this image of the same area (e.g. another date); the map stays --map"
)


def _add_matcher_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--strategies",
        default=None,
        metavar="A,B",
        help="strategies besides classical (always run, the baseline); default: every strategy "
        "whose model files are given",
    )
    p.add_argument("--frames", type=int, default=30, help="rendered frames (default 30)")
    p.add_argument("--candidates", type=int, default=3, help="chips per frame, true one first (default 3)")
    p.add_argument(
        "--map",
        type=Path,
        default=None,
        help="GeoTIFF orthophoto (default: the shared GeoVision India z18 ortho)",
    )
    p.add_argument(
        "--disk-model", type=Path, default=None, help="DISK extractor ONNX (LightGlue-ONNX layout)"
    )
    p.add_argument(
        "--aliked-model", type=Path, default=None, help="ALIKED extractor ONNX (gdnav models export)"
    )
    p.add_argument(
        "--xfeat-model", type=Path, default=None, help="XFeat extractor ONNX (LightGlue-ONNX layout)"
    )
    p.add_argument(
        "--lightglue-model",
        type=Path,
        default=None,
        help="LightGlue matcher ONNX for the learned strategies (default: mutual nearest neighbour)",
    )
    p.add_argument("--model-dir", type=Path, default=None, help="look here for models not given explicitly")
    p.add_argument("--threads", type=int, default=2, help="ONNX Runtime intra-op threads (default 2)")
    p.add_argument("--seed", type=int, default=0, help="poses and chips (default 0)")
    p.add_argument(
        "--cache",
        type=Path,
        default=None,
        help="map cache of the same map (gdnav cache build): candidates are its chips, and strategies "
        "with precomputed tile features in it (gdnav cache features) are also timed with them",
    )
    p.add_argument("--frames-from", type=Path, default=None, help=_FRAMES_FROM_HELP)
    p.add_argument(
        "--first-chip",
        default="nearest_tile",
        metavar="{nearest_tile,footprint}",
        help="with --cache: the true chip is the nearest tile's (default) or the one the daemon cuts "
        "around the footprint while its prior is tight (rerank.footprint_chip); checked by the benchmark",
    )
    p.add_argument("--chip-size", type=int, default=512, help="chip side, px (default 512)")
    p.add_argument("--alt", type=float, default=120.0, help="frames' height above ground, m (default 120)")
    p.add_argument("--json", type=Path, default=None, metavar="OUT", help="also write every figure to OUT")


def _run_matcher(args: argparse.Namespace) -> int:
    from gps_denied_onboard.bench.matcher import BenchmarkError, run_matcher_benchmark
    from gps_denied_onboard.logging_setup import configure_logging

    configure_logging("warning", json=False)  # per-frame debug/info logs would bury the table
    strategies = None
    if args.strategies:
        strategies = [s.strip() for s in args.strategies.split(",") if s.strip()]
    models = {
        "disk": args.disk_model,
        "aliked": args.aliked_model,
        "xfeat": args.xfeat_model,
        "lightglue": args.lightglue_model,
    }
    try:
        figures = run_matcher_benchmark(
            strategies=strategies,
            **({} if args.map is None else {"map_path": args.map}),
            model_paths=models,
            model_dir=args.model_dir,
            n_frames=args.frames,
            n_candidates=args.candidates,
            intra_op_threads=args.threads,
            seed=args.seed,
            cache_dir=args.cache,
            frames_path=args.frames_from,
            first_chip=args.first_chip,
            chip_size_px=args.chip_size,
            alt_agl_m=args.alt,
        )
    except BenchmarkError as exc:
        _err(str(exc))
        return EXIT_CONFIG
    if args.json is not None:
        write_json(args.json, figures)
        print(f"figures written to {args.json}")
    # A strategy the user asked for (by name or by giving its model) that did not run is a failure to
    # benchmark it, not a detail to scroll past.
    if figures["skipped"]:
        _err("not benchmarked: " + "; ".join(f"{k} ({v})" for k, v in figures["skipped"].items()))
        return EXIT_RESOURCE
    return EXIT_OK


MATCHER_COMMAND: Final[BenchCommand] = BenchCommand(
    name="matcher",
    help="C3 matcher latency, memory and inliers vs classical",
    description="Per-candidate and per-frame latency (cold/warm tile-feature cache), memory and inlier "
    "counts of each C3 strategy on frames rendered from a real orthophoto, side by side with classical.",
    add_arguments=_add_matcher_arguments,
    run=_run_matcher,
)


# --- bench vpr -------------------------------------------------------------------------------------------
def _add_vpr_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--map", type=Path, required=True, help="GeoTIFF the cache and index are built from")
    p.add_argument("--frames-from", type=Path, default=None, help=_FRAMES_FROM_HELP)
    p.add_argument("--queries", type=int, default=60, help="rendered query frames (default 60)")
    p.add_argument("--zoom", type=int, default=None, help="cache zoom (default: matched to the map)")
    p.add_argument("--tile-size", type=int, default=256, help="cache tile size, px (default 256)")
    p.add_argument(
        "--alt",
        default="100,150",
        metavar="LO,HI",
        help="query altitude range above ground, m (default 100,150; ~1500,2000 for 5 m/px maps)",
    )
    p.add_argument(
        "--synthetic",
        type=int,
        default=100_000,
        help="descriptors in the synthetic HNSW latency test (default 100000; 0 = skip)",
    )
    p.add_argument("--no-rerank", action="store_true", help="skip the C2.5 rerank measurement")
    p.add_argument(
        "--strategy",
        default="vlad",
        metavar="NAMES",
        help="comma-separated VPR strategies measured on the same cache and frames: vlad, vlad_xfeat "
        "(default vlad)",
    )
    p.add_argument(
        "--model-dir",
        type=Path,
        default=Path("models"),
        help="vlad_xfeat: model directory made by `gdnav models export` (default: models)",
    )
    p.add_argument("--seed", type=int, default=0, help="query poses (default 0)")
    p.add_argument("--json", type=Path, default=None, metavar="OUT", help="also write every figure to OUT")
    p.add_argument(
        "--workdir",
        type=Path,
        default=None,
        help="keep the benchmark's cache here (default: a temporary directory)",
    )


def _run_vpr(args: argparse.Namespace) -> int:
    from gps_denied_onboard.bench.vpr import BENCH_STRATEGIES, run_vpr_benchmark
    from gps_denied_onboard.components.c7_inference.protocol import EngineLoadError
    from gps_denied_onboard.components.c10_cache_build import CacheBuildError
    from gps_denied_onboard.helpers.model_manifest import ModelDirError
    from gps_denied_onboard.logging_setup import configure_logging

    configure_logging("warning", json=False)
    try:
        lo, hi = (float(v) for v in args.alt.split(","))
    except ValueError:
        _err(f"--alt {args.alt!r}: expected LO,HI in metres")
        return EXIT_CONFIG
    strategies = [name.strip() for name in args.strategy.split(",") if name.strip()]
    if not strategies or any(name not in BENCH_STRATEGIES for name in strategies):
        _err(f"--strategy {args.strategy!r}: expected some of {', '.join(BENCH_STRATEGIES)}")
        return EXIT_CONFIG
    try:
        figures = run_vpr_benchmark(
            args.map,
            zoom=args.zoom,
            n_queries=args.queries,
            seed=args.seed,
            out=args.workdir,
            frames_path=args.frames_from,
            alt_range_m=(lo, hi),
            tile_size_px=args.tile_size,
            synthetic_n=args.synthetic,
            rerank=not args.no_rerank,
            strategies=strategies,
            model_dir=args.model_dir,
        )
    except (ModelDirError, EngineLoadError) as exc:
        _err(str(exc))
        return EXIT_RESOURCE
    except (CacheBuildError, OSError) as exc:
        _err(str(exc))
        return EXIT_CONFIG
    if args.json is not None:
        write_json(args.json, figures)
    return EXIT_OK


VPR_COMMAND: Final[BenchCommand] = BenchCommand(
    name="vpr",
    help="C2 place-recognition recall and HNSW latency",
    description="Recall@1/5/10 of the true tile (corpus-wide and prior-gated) and post-rerank Recall@1/3 "
    "on frames rendered from a real orthophoto, and HNSW top-10 latency over synthetic descriptors.",
    add_arguments=_add_vpr_arguments,
    run=_run_vpr,
)


# --- bench flights ---------------------------------------------------------------------------------------
def _add_flights_arguments(p: argparse.ArgumentParser) -> None:
    from gps_denied_onboard.bench.flights import DEFAULT_STRATEGIES

    p.add_argument(
        "--strategies",
        default=",".join(DEFAULT_STRATEGIES),
        metavar="A,B",
        help=f"matcher strategies, one flight each (default {','.join(DEFAULT_STRATEGIES)})",
    )
    p.add_argument(
        "--flights",
        default=None,
        metavar="A,B",
        help="flights of the plan to fly (default: all; soak and autopilot_square are not in it)",
    )
    p.add_argument(
        "--shared",
        type=Path,
        default=Path(os.environ.get("GDNAV_SHARED_DIR", "../shared")),
        help="the shared data folder with the real imagery (default $GDNAV_SHARED_DIR or ../shared)",
    )
    p.add_argument("--out", type=Path, default=Path("out/bench_flights"), help="reports and work dirs")
    p.add_argument("--config", type=Path, default=None, help="daemon profile (default: config/sitl.yaml)")
    p.add_argument("--set", action="append", metavar="KEY.PATH=VALUE", help="daemon override, every flight")
    p.add_argument("--resume", action="store_true", help="reuse the rows whose report is already in --out")
    p.add_argument("--json", type=Path, default=None, metavar="OUT", help="also write every figure to OUT")


def _run_flights(args: argparse.Namespace) -> int:
    from gps_denied_onboard.bench.flights import (
        FlightPlanError,
        default_flights,
        run_flights_benchmark,
        select_flights,
    )
    from gps_denied_onboard.logging_setup import configure_logging

    configure_logging("warning", json=False)
    strategies = [s.strip() for s in args.strategies.split(",") if s.strip()]
    names = [s.strip() for s in args.flights.split(",") if s.strip()] if args.flights else None
    try:
        flights = select_flights(default_flights(args.shared), names)
    except FlightPlanError as exc:
        _err(str(exc))
        return EXIT_CONFIG
    figures = run_flights_benchmark(
        flights,
        strategies,
        args.out,
        overrides=tuple(args.set or ()),
        config_path=args.config,
        resume=args.resume,
    )
    print(
        f"accepted fixes beyond 3 sigma: {figures['accepted_fixes_beyond_3sigma']}; 3D GPS_INPUT beyond "
        f"3 sigma: {figures['gps_input_beyond_3sigma']}; not flown: {figures['not_flown'] or 'none'}"
    )
    if args.json is not None:
        write_json(args.json, figures)
        print(f"figures written to {args.json}")
    if figures["not_flown"]:
        return EXIT_RESOURCE
    flown = [r for r in figures["rows"] if "error" not in r]
    if figures["accepted_fixes_beyond_3sigma"] or figures["gps_input_beyond_3sigma"]:
        return EXIT_FAILURE
    return EXIT_OK if all(r["daemon_exit_code"] == 0 for r in flown) else EXIT_FAILURE


FLIGHTS_COMMAND: Final[BenchCommand] = BenchCommand(
    name="flights",
    help="every scenario with every matcher strategy: integrity, accuracy, latency",
    description="Fly the bundled SITL scenarios with each matcher strategy (one real gdnav sitl run per "
    "row) and print accepted fixes and GPS_INPUTs beyond 3 sigma, error, latency and fix age side by side.",
    add_arguments=_add_flights_arguments,
    run=_run_flights,
)


# --- bench area ------------------------------------------------------------------------------------------
def _add_area_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--maps",
        default=None,
        metavar="A.tif,B.tif",
        help="GeoTIFFs of one area on several dates: every ordered pair (map, frames) is measured",
    )
    p.add_argument("--frames", type=int, default=12, help="rendered frames per pair (default 12)")
    p.add_argument("--alt", type=float, default=1200.0, help="height above ground of the renders, m")
    p.add_argument("--photos", type=Path, default=None, help="a directory of overlapping drone photos")
    p.add_argument("--csv", type=Path, default=None, help="--photos: their positions and attitudes")
    p.add_argument(
        "--pairs",
        default=None,
        metavar="MAP:FRAME,...",
        help="--photos: the photo orthorectified as the map and its neighbour matched as the frame",
    )
    p.add_argument("--ground-alt-amsl", type=float, default=None, help="--photos: ground height AMSL, m")
    p.add_argument("--image-scale", type=float, default=0.25, help="--photos: downscale (default 0.25)")
    p.add_argument("--seed", type=int, default=0, help="poses and prior offsets (default 0)")
    p.add_argument("--workdir", type=Path, default=Path("out/bench_area"), help="caches and orthophotos")
    p.add_argument("--json", type=Path, default=None, metavar="OUT", help="also write every figure to OUT")


def _run_area(args: argparse.Namespace) -> int:
    from gps_denied_onboard.bench.area import run_dates, run_photos
    from gps_denied_onboard.logging_setup import configure_logging

    configure_logging("warning", json=False)
    args.workdir.mkdir(parents=True, exist_ok=True)
    if (args.maps is None) == (args.photos is None):
        _err("give --maps (dates of one area) or --photos with --csv and --pairs")
        return EXIT_CONFIG
    if args.maps is not None:
        tifs = [Path(t.strip()) for t in args.maps.split(",") if t.strip()]
        missing = [str(t) for t in tifs if not t.is_file()]
        if len(tifs) < 2 or missing:
            _err(f"--maps needs two or more GeoTIFFs; not found: {', '.join(missing) or 'none'}")
            return EXIT_CONFIG if len(tifs) < 2 else EXIT_RESOURCE
        figures = run_dates(tifs, args.workdir, frames=args.frames, alt_agl_m=args.alt, seed=args.seed)
    else:
        if args.csv is None or args.pairs is None or args.ground_alt_amsl is None:
            _err("--photos needs --csv, --pairs MAP:FRAME,... and --ground-alt-amsl")
            return EXIT_CONFIG
        pairs = [tuple(p.split(":", 1)) for p in args.pairs.split(",") if ":" in p]
        figures = run_photos(
            args.photos,
            args.csv,
            [(a, b) for a, b in pairs],
            args.workdir,
            ground_alt_amsl_m=args.ground_alt_amsl,
            image_scale=args.image_scale,
        )
    rows = figures["pairs"]
    wrong = sum(r["wrong_accepted"] for r in rows)
    print(
        f"right fixes accepted {sum(r['right_accepted'] for r in rows)} of {sum(r['frames'] for r in rows)}; "
        f"wrong places accepted {wrong} of {sum(r['wrong_searched'] for r in rows)}"
    )
    if args.json is not None:
        write_json(args.json, figures)
        print(f"figures written to {args.json}")
    return EXIT_FAILURE if wrong else EXIT_OK


AREA_COMMAND: Final[BenchCommand] = BenchCommand(
    name="area",
    help="the area correlation on real imagery: date pairs of one map, or overlapping drone photos",
    description="Build a cache with its orientation fields from each map (a date of a time series, or a "
    "drone photo orthorectified with its own pose), search frames from the other dates (or the neighbouring "
    "photo) with the truth in the disc and outside it, and print right fixes found and accepted, their "
    "error, and wrong places accepted (exit 1 on any).",
    add_arguments=_add_area_arguments,
    run=_run_area,
)

#: Subcommands of ``gdnav bench``; append a ``BenchCommand`` to add one.
BENCH_COMMANDS: tuple[BenchCommand, ...] = (MATCHER_COMMAND, VPR_COMMAND, FLIGHTS_COMMAND, AREA_COMMAND)


def register(
    subparsers: argparse._SubParsersAction, commands: Sequence[BenchCommand] | None = None
) -> argparse.ArgumentParser:
    """Add ``bench`` with one subcommand per entry of ``commands`` (default ``BENCH_COMMANDS``).

    Each subcommand's ``func`` is its ``run``, as ``cli.main`` expects. Returns the ``bench`` parser.
    """
    chosen = BENCH_COMMANDS if commands is None else tuple(commands)
    names = [c.name for c in chosen]
    if len(set(names)) != len(names):
        raise ValueError(f"duplicate bench subcommand names: {names}")
    bench = subparsers.add_parser(
        "bench",
        help="benchmarks (print measured figures)",
        description="Benchmarks that print measured figures.",
    )
    bench_sub = bench.add_subparsers(dest="bench_command", required=True, metavar="SUBCOMMAND")
    for command in chosen:
        p = bench_sub.add_parser(command.name, help=command.help, description=command.description)
        command.add_arguments(p)
        p.set_defaults(func=command.run)
    return bench
