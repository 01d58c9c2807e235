"""``gdnav replay``: re-run the pipeline on recorded inputs and report what it made of them.

Inputs (exactly one):
- ``--fdr DIR``: the daemon's flight data recorder (one run; exact when it holds every frame as PNG and the
  estimator's journal);
- ``--images DIR --csv FILE``: photos plus a CSV of positions and attitudes (the positions are the truth);
- ``--tlog FILE`` (``.tlog`` or ``.bin``) with ``--video FILE`` or ``--images DIR``.
Writes the report JSON (``--report``) and prints a one-screen summary. Exit 0; 2 for bad arguments or
config; 3 for an input, cache, model or calibration file it cannot use (one line on stderr).
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import sys
from pathlib import Path
from typing import Any

import structlog

from gps_denied_onboard.helpers import bounded_json

EXIT_OK, EXIT_CONFIG, EXIT_RESOURCE = 0, 2, 3


def _err(message: str) -> None:
    print(f"gdnav: {message}", file=sys.stderr)


def load_truth(path: Path) -> list[Any]:
    """Truth samples from a CSV (time_unix_s, lat, lon columns) or a SITL report JSON (its per-frame
    true positions)."""
    from gps_denied_onboard.replay.inputs import ReplayInputError, TruthSample, _column, _parse_time

    if not path.is_file():
        raise ReplayInputError(f"{path}: truth file not found")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise ReplayInputError(f"{path}: cannot be read as UTF-8 text: {exc}") from exc
    out: list[TruthSample] = []
    if path.suffix.lower() == ".json":
        try:
            # A SITL report holds a row per frame: tens of MB for a long flight at most.
            rows = bounded_json.loads(text, max_bytes=1 << 28, what="truth JSON")["per_frame"]
            for r in rows:
                out.append(
                    TruthSample(
                        int(r["exposure_time_unix_usec"]) / 1e6,
                        float(r["true_lat_deg"]),
                        float(r["true_lon_deg"]),
                    )
                )
        except (ValueError, KeyError, TypeError, OverflowError) as exc:
            raise ReplayInputError(
                f"{path}: not a SITL report (per_frame rows with true_lat_deg): {exc}"
            ) from exc
    else:
        try:
            reader = csv.DictReader(text.splitlines())
            header = reader.fieldnames or []
            records = list(reader)
        except csv.Error as exc:  # e.g. a field over the csv module's limit
            raise ReplayInputError(f"{path}: not readable as CSV: {exc}") from exc
        cols = {k: _column(header, k) for k in ("time", "lat", "lon")}
        if None in cols.values():
            raise ReplayInputError(
                f"{path}: needs time_unix_s, lat and lon columns; header is {', '.join(header)}"
            )
        for i, r in enumerate(records, start=2):
            try:
                out.append(
                    TruthSample(
                        _parse_time(str(r[cols["time"] or ""]), f"{path}:{i}"),
                        float(r[cols["lat"] or ""]),
                        float(r[cols["lon"] or ""]),
                    )
                )
            except ReplayInputError:
                raise  # names the row already
            except (ValueError, TypeError) as exc:  # TypeError: a short row's missing cell is None
                raise ReplayInputError(f"{path}:{i}: {exc}") from exc
    if not out:
        raise ReplayInputError(f"{path}: no truth samples")
    return sorted(out, key=lambda s: s.time_unix_s)


def _calibration(arg: str | None, scale: float, first_image: Path | None) -> Any:
    from gps_denied_onboard.camera.types import CalibrationError, CameraCalibration
    from gps_denied_onboard.replay.inputs import ReplayInputError, calibration_from_exif

    if arg is None:
        return None
    if arg == "exif":
        if first_image is None:
            raise ReplayInputError("--calibration exif needs images (--images DIR)", resource=False)
        return calibration_from_exif(first_image, scale=scale)
    try:
        c = CameraCalibration.from_opencv_yaml(arg)
    except CalibrationError as exc:
        raise ReplayInputError(str(exc)) from exc
    if scale == 1.0:
        return c
    w, h = round(c.width_px * scale), round(c.height_px * scale)
    return CameraCalibration(
        w,
        h,
        c.fx_px * scale,
        c.fy_px * scale,
        (c.cx_px + 0.5) * scale - 0.5,
        (c.cy_px + 0.5) * scale - 0.5,
        c.dist_coeffs,
    )


def _cmd_replay(args: argparse.Namespace) -> int:
    from gps_denied_onboard.config import ConfigError, config_with_overrides, load_config
    from gps_denied_onboard.logging_setup import configure_logging
    from gps_denied_onboard.replay.driver import run_replay, summary_lines
    from gps_denied_onboard.replay.inputs import ReplayInputError, from_csv, from_fdr, from_tlog

    chosen = [
        n for n, v in (("--fdr", args.fdr), ("--csv", args.csv), ("--tlog", args.tlog)) if v is not None
    ]
    if len(chosen) != 1:
        _err(f"give exactly one of --fdr DIR, --images DIR --csv FILE, --tlog FILE; got {chosen or 'none'}")
        return EXIT_CONFIG
    if not (0.0 < args.image_scale <= 1.0):
        _err(f"--image-scale must be in (0, 1], got {args.image_scale}")
        return EXIT_CONFIG
    if args.vo_max_gap_s is not None and not args.vo_max_gap_s > 0:
        _err(f"--vo-max-gap-s must be > 0, got {args.vo_max_gap_s}")
        return EXIT_CONFIG
    if args.log_level is None:
        # The report says everything the logs would; a refusal stays one line on stderr.
        configure_logging("error", json=False)
        structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.CRITICAL))
    else:
        configure_logging(args.log_level, json=False)
    overrides = list(args.set or ())
    if args.cache is not None:
        overrides.append(f"cache.dir={args.cache}")
    try:
        if args.fdr is not None:
            inp = from_fdr(args.fdr, run=args.run)
            if args.config is not None or inp.recorded_config is None:
                config = load_config(args.config, overrides)
                if args.config is None:
                    inp.notes.append("no recorded config: the defaults were used")
            else:
                config = config_with_overrides(
                    inp.recorded_config, overrides, source=f"{args.fdr} (daemon.config)"
                )
            with_map = not args.no_map
            if args.truth is not None:
                inp.truth = load_truth(args.truth)
        else:
            config = load_config(args.config, overrides)
            with_map = args.cache is not None and not args.no_map
            images = args.images
            first = None
            if images is not None and images.is_dir():
                from gps_denied_onboard.replay.inputs import IMAGE_SUFFIXES

                first = next(
                    (p for p in sorted(images.iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES), None
                )
            if args.csv is not None:
                if images is None:
                    _err("--csv needs --images DIR (the photos it describes)")
                    return EXIT_CONFIG
                inp = from_csv(
                    images,
                    args.csv,
                    ground_alt_amsl_m=args.ground_alt_amsl,
                    image_scale=args.image_scale,
                    prior_sigma_m=config.init.sigma_m,
                )
            else:
                inp = from_tlog(
                    args.tlog,
                    images_dir=images,
                    video=args.video,
                    frame_times_csv=args.frame_times,
                    video_start_unix_s=args.video_start_unix_s,
                    image_scale=args.image_scale,
                    prior_sigma_m=config.init.sigma_m,
                )
                if args.ground_alt_amsl is not None:
                    inp.ground_alt_amsl_m = args.ground_alt_amsl
            inp.calibration = _calibration(args.calibration, args.image_scale, first)
            if args.calibration == "exif":
                inp.notes.append(
                    "calibration from EXIF (FocalLength x FocalPlaneXResolution, centred principal point, "
                    "no distortion): nominal, not calibrated"
                )
    except ReplayInputError as exc:
        _err(str(exc))
        return EXIT_RESOURCE if exc.resource else EXIT_CONFIG
    except ConfigError as exc:
        _err(str(exc))
        return EXIT_CONFIG
    try:
        # Frames are read as the replay reaches them: an unreadable one is refused here.
        report = run_replay(
            inp,
            config,
            with_map=with_map,
            vo_max_gap_s=args.vo_max_gap_s,
            force_sequential=args.sequential,
            records_out=args.records,
        )
    except ReplayInputError as exc:
        _err(str(exc))
        return EXIT_RESOURCE if exc.resource else EXIT_CONFIG
    args.report.parent.mkdir(parents=True, exist_ok=True)
    args.report.write_text(json.dumps(report, indent=2, allow_nan=True))
    for line in summary_lines(report):
        print(line)
    print(f"report: {args.report}")
    return EXIT_OK


def register(sub: Any) -> None:
    p = sub.add_parser(
        "replay",
        help="re-run the pipeline on a recorded flight and report what it made of it",
        description="Re-run the pipeline deterministically, on one thread, from an FDR (exact when it holds "
        "every frame as PNG and the estimator's journal), from photos plus a CSV of positions and attitudes, "
        "or from a MAVLink telemetry log plus a video or photos; scores the result against the truth when "
        "there is one (the CSV's or the log's positions, or --truth).",
    )
    src = p.add_argument_group("input (one of)")
    src.add_argument("--fdr", type=Path, default=None, help="FDR directory (or one segment file)")
    src.add_argument(
        "--csv", type=Path, default=None, help="CSV: file, lat, lon, alt, roll, pitch, heading[, time]"
    )
    src.add_argument("--tlog", type=Path, default=None, help="MAVLink telemetry log (.tlog or .bin)")
    src.add_argument("--images", type=Path, default=None, help="image directory (with --csv or --tlog)")
    src.add_argument("--video", type=Path, default=None, help="video file (with --tlog)")
    p.add_argument("--run", type=int, default=None, help="FDR: run index (default: the last run with frames)")
    p.add_argument(
        "--truth", type=Path, default=None, help="FDR: truth CSV (time_unix_s, lat, lon) or SITL report JSON"
    )
    p.add_argument(
        "--sequential", action="store_true", help="FDR: ignore the journal (replay frame by frame)"
    )
    p.add_argument("--frame-times", type=Path, default=None, help="tlog + images: CSV of file, time_unix_s")
    p.add_argument(
        "--video-start-unix-s", type=float, default=None, help="tlog + video: Unix time of the first frame"
    )
    p.add_argument(
        "--calibration",
        default=None,
        help="OpenCV calibration YAML for the images at full size, or 'exif' (derived from the first image's "
        "EXIF); default: the config's camera",
    )
    p.add_argument(
        "--image-scale", type=float, default=1.0, help="downscale images (and calibration) by this"
    )
    p.add_argument(
        "--ground-alt-amsl", type=float, default=None, help="ground height AMSL, m (heights from AMSL)"
    )
    p.add_argument("--cache", default=None, help="map cache directory (CSV/tlog: without it, VO only)")
    p.add_argument("--no-map", action="store_true", help="run without the map (VO only)")
    p.add_argument("--vo-max-gap-s", type=float, default=None, help="C1's longest measured interval, s")
    p.add_argument("--config", type=Path, default=None, help="profile (FDR: default the recorded config)")
    p.add_argument("--set", action="append", metavar="KEY.PATH=VALUE", help="config override (repeatable)")
    p.add_argument(
        "--log-level",
        choices=("debug", "info", "warning", "error"),
        default=None,
        help="pipeline logs on stderr (default: none; the report holds the outcome)",
    )
    p.add_argument("--report", type=Path, default=Path("out/replay/report.json"), help="report JSON path")
    p.add_argument(
        "--records",
        type=Path,
        default=None,
        metavar="OUT.jsonl",
        help="also write the replay's own FDR records (one JSON object a line, as a flight's FDR segment; "
        "`gdnav fdr` tools read it)",
    )
    p.set_defaults(func=_cmd_replay)
