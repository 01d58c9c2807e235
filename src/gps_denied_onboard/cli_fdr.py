"""``gdnav fdr summary FILE|DIR``: what a flight data recorder says about the daemon's runs;
``gdnav fdr boresight FILE|DIR``: the camera mount its VO ground tilts ask for (``c4_pose/boresight.py``).

Prints the records by kind, the runs (start, end, clean stop or crash) with their frame, fix-attempt and
estimate rates, the errors (frame errors by stage, refused frames by reason, no-fix reasons) and the
provenance timeline; ``--json`` prints the same as one JSON object, ``--png`` draws the track coloured by
provenance, the fix inliers and the stated horizontal sigma over time. The record schema is docs/fdr.md.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import sys
from collections import Counter
from pathlib import Path
from typing import Any, Final

import numpy as np

from gps_denied_onboard.components.c13_fdr.reader import (
    EstimateRecord,
    FdrReader,
    FdrReadError,
    FixRecord,
    split_runs,
)
from gps_denied_onboard.constants import FdrKind, Provenance

# Same values as ``cli``'s (not imported: ``cli`` imports this module).
EXIT_OK, EXIT_CONFIG, EXIT_RESOURCE = 0, 2, 3

#: Per-run rates reported, by name.
RATE_KINDS: Final[dict[str, str]] = {
    "frames_per_s": FdrKind.FRAME,
    "fix_attempts_per_s": FdrKind.FIX,
    "estimates_per_s": FdrKind.ESTIMATE_SENT,
}
#: The sigma plot's line breaks where estimates are further apart than this, s.
SIGMA_GAP_S: Final[float] = 5.0
PROVENANCE_COLORS: Final[dict[str, str]] = {
    Provenance.SATELLITE_ANCHORED.value: "tab:green",
    Provenance.VISUAL_PROPAGATED.value: "tab:orange",
    Provenance.DEAD_RECKONING.value: "tab:red",
    Provenance.NO_ESTIMATE.value: "tab:gray",
}


def _utc(t_unix_s: float) -> str:
    if not math.isfinite(t_unix_s):
        return "?"
    try:
        return _dt.datetime.fromtimestamp(t_unix_s, tz=_dt.timezone.utc).isoformat(timespec="milliseconds")
    except (ValueError, OverflowError, OSError):  # a time past what datetime holds (a damaged record)
        return "?"


def summarise(reader: FdrReader) -> dict[str, Any]:
    """The summary as plain JSON types. Raises ``FdrReadError`` for a missing or empty recorder."""
    runs = reader.runs()
    if not runs:
        raise FdrReadError(f"{reader.path}: no FDR records", path=reader.path)
    counts: Counter[str] = Counter()
    for run in runs:
        counts.update(run.counts)
    no_fix = Counter(f.no_fix_reason for f in reader.fixes() if f.no_fix_reason is not None)
    return {
        "path": str(reader.path),
        "segments": len(reader.segments()),
        "refused_files": reader.refused(),
        "records": sum(counts.values()),
        "counts": dict(sorted(counts.items())),
        "runs": [
            {
                "index": run.index,
                "pid": run.pid,
                "start_unix_s": run.start_unix_s,
                "start_utc": _utc(run.start_unix_s),
                "end_unix_s": run.end_unix_s,
                "end_utc": _utc(run.end_unix_s),
                "duration_s": round(run.duration_s, 3),
                "stop": run.stop.value,
                "records": sum(run.counts.values()),
                "bad_lines": run.bad_lines,
                "torn_lines_at_end": run.torn_lines_at_end,
                **{name: _round(run.rate_hz(kind)) for name, kind in RATE_KINDS.items()},
            }
            for run in runs
        ],
        "errors": {
            "frame_error_by_stage": dict(Counter(e.stage for e in reader.frame_errors()).most_common()),
            "frame_refused_by_reason": dict(Counter(r.reason for r in reader.frame_refusals()).most_common()),
            "no_fix_reason": dict(no_fix.most_common()),
        },
        "provenance_timeline": [
            {"t_unix_s": c.t_unix_s, "utc": _utc(c.t_unix_s), "from": c.old, "to": c.new, "reason": c.reason}
            for c in reader.provenance_changes()
        ],
    }


def _round(v: float | None) -> float | None:
    return None if v is None else round(v, 3)


def format_summary(s: dict[str, Any]) -> str:
    """The summary as text for a terminal."""
    out = [f"FDR {s['path']}: {s['records']} records in {s['segments']} segment(s), {len(s['runs'])} run(s)"]
    if s["refused_files"]:
        out.append("refused unread (not regular files): " + ", ".join(s["refused_files"]))
    out.append("records by kind:")
    out += [f"  {kind:<32} {n:>8}" for kind, n in s["counts"].items()]
    out.append("runs:")
    for r in s["runs"]:
        rates = ", ".join(
            f"{name.removesuffix('_per_s').replace('_', ' ')} {r[name]:.2f}/s"
            for name in RATE_KINDS
            if r[name] is not None
        )
        torn = r["bad_lines"]  # torn_lines_at_end counts some of the same lines again
        out.append(
            f"  #{r['index']} pid {r['pid'] if r['pid'] is not None else '?'}: {r['start_utc']} .. "
            f"{r['end_utc']} ({r['duration_s']:.1f} s) {r['stop'].upper()}"
            + (f", {torn} torn line(s)" if torn else "")
            + (f"; {rates}" if rates else "")
        )
    for title, key in (
        ("frame errors by stage", "frame_error_by_stage"),
        ("refused frames by reason", "frame_refused_by_reason"),
        ("no-fix reasons", "no_fix_reason"),
    ):
        items = s["errors"][key]
        out.append(f"{title}:" + ("" if items else " none"))
        out += [f"  {name:<40} {n:>8}" for name, n in items.items()]
    out.append("provenance timeline:" + ("" if s["provenance_timeline"] else " no changes"))
    out += [
        f"  {c['utc']}  {c['from']} -> {c['to']}" + (f"  ({c['reason']})" if c["reason"] else "")
        for c in s["provenance_timeline"]
    ]
    return "\n".join(out)


def plot_summary(
    estimates: list[EstimateRecord], fixes: list[FixRecord], t0_unix_s: float, path: Path, *, title: str
) -> None:
    """PNG: the estimate track (local metres) coloured by provenance, the fix inliers and the stated
    horizontal sigma over time (seconds since the first record)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax0, ax1, ax2) = plt.subplots(1, 3, figsize=(17, 5.5), gridspec_kw={"width_ratios": [1.2, 1, 1]})
    located = [e for e in estimates if e.lat_deg is not None and e.lon_deg is not None]
    if located:
        lat0, lon0 = located[0].lat_deg or 0.0, located[0].lon_deg or 0.0
        k_e = 111_320.0 * math.cos(math.radians(lat0))
        for prov, color in PROVENANCE_COLORS.items():
            pts = [e for e in located if e.provenance == prov]
            if pts:
                ax0.scatter(
                    [((e.lon_deg or 0.0) - lon0) * k_e for e in pts],
                    [((e.lat_deg or 0.0) - lat0) * 111_320.0 for e in pts],
                    s=6,
                    color=color,
                    label=prov,
                )
        ax0.set_aspect("equal", adjustable="datalim")
        ax0.legend(loc="best", fontsize=8)
    else:
        ax0.text(0.5, 0.5, "no located estimates", ha="center", va="center", transform=ax0.transAxes)
    ax0.set_xlabel("east [m]")
    ax0.set_ylabel("north [m]")
    ax0.set_title(title)
    for accepted, color, label in ((True, "tab:green", "accepted"), (False, "tab:red", "not accepted")):
        attempts = [f for f in fixes if f.fix_accepted is accepted]
        ax1.plot(
            [f.t_unix_s - t0_unix_s for f in attempts],
            [f.inliers for f in attempts],
            ".",
            ms=4,
            color=color,
            label=label,
        )
    ax1.set_xlabel("time since first record [s]")
    ax1.set_ylabel("inliers")
    ax1.set_title(f"pipeline.fix: {len(fixes)} attempts")
    ax1.legend(fontsize=8)
    ax1.grid(alpha=0.3)
    sig = [e for e in estimates if e.horiz_sigma_m is not None]
    ts: list[float] = []
    sigmas: list[float] = []
    for e in sig:
        if ts and e.t_unix_s - t0_unix_s - ts[-1] > SIGMA_GAP_S:
            ts.append(math.nan)  # a gap (a restart, a stopped stream): no line across it
            sigmas.append(math.nan)
        ts.append(e.t_unix_s - t0_unix_s)
        sigmas.append(e.horiz_sigma_m or math.nan)
    ax2.plot(ts, sigmas, "-", lw=0.8)
    ax2.set_yscale("log" if sig and max(e.horiz_sigma_m or 0.0 for e in sig) > 100.0 else "linear")
    ax2.set_xlabel("time since first record [s]")
    ax2.set_ylabel("stated horizontal sigma (1σ) [m]")
    ax2.set_title("mavlink.estimate")
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _cmd_summary(args: argparse.Namespace) -> int:
    reader = FdrReader(args.path)
    try:
        summary = summarise(reader)
    except FdrReadError as exc:
        print(f"gdnav: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    if args.png is not None:
        try:
            args.png.parent.mkdir(parents=True, exist_ok=True)
            plot_summary(
                list(reader.estimates()),
                list(reader.fixes()),
                summary["runs"][0]["start_unix_s"],
                args.png,
                title=f"FDR {reader.path.name}",
            )
        except OSError as exc:
            print(f"gdnav: --png {args.png}: {exc}", file=sys.stderr)
            return EXIT_CONFIG
        summary["png"] = str(args.png)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(format_summary(summary))
        if args.png is not None:
            print(f"plot: {args.png}")
    return EXIT_OK


def _tilts(records: list[dict[str, Any]], kind: str, check: str) -> np.ndarray:
    """The ``tilt_off_deg`` of ``check`` in every ``kind`` record that has one, (N, 2) deg."""
    rows = [
        r[check]["tilt_off_deg"]
        for r in records
        if r.get("kind") == kind and isinstance(r.get(check), dict) and r[check].get("tilt_off_deg")
    ]
    # A pair of finite numbers is what the daemon writes; anything else is skipped.
    pairs = [pair for row in rows if (pair := _finite_pair(row)) is not None]
    return np.asarray(pairs, dtype=np.float64).reshape(-1, 2)


def _finite_pair(row: Any) -> tuple[float, float] | None:
    if not isinstance(row, list) or len(row) != 2:
        return None
    try:
        a, b = (float(v) for v in row if not isinstance(v, (bool, str)))
    except (TypeError, ValueError, OverflowError):
        return None
    return (a, b) if math.isfinite(a) and math.isfinite(b) else None


def boresight(path: Path, run: int | None, max_half_width_deg: float) -> dict[str, Any]:
    """``gdnav fdr boresight`` as plain JSON types. Raises ``FdrReadError`` for a recorder that holds
    no such run or no recorded config."""
    from gps_denied_onboard.components.c4_pose.boresight import estimate_boresight

    reader = FdrReader(path)
    runs = split_runs(reader.records(FdrKind.FDR_OPENED, FdrKind.CONFIG, FdrKind.FRAME, FdrKind.FIX))
    with_frames = [i for i, r in enumerate(runs) if any(x.get("kind") == FdrKind.FRAME for x in r)]
    if run is None:
        if not with_frames:
            raise FdrReadError(f"{path}: no run tracked any frame (no pipeline.frame records)", path=path)
        run = with_frames[-1]
    if not 0 <= run < len(runs):
        raise FdrReadError(f"--run {run}: {path} has runs 0..{len(runs) - 1}", path=path)
    recs = runs[run]
    config = next((r.get("config") for r in recs if r.get("kind") == FdrKind.CONFIG), None)
    if not isinstance(config, dict):
        raise FdrReadError(f"{path}: run {run} has no daemon.config record (its mount)", path=path)
    camera = config.get("camera", {})
    try:
        used = (float(camera.get("mount_roll_deg", 0.0)), float(camera.get("mount_pitch_deg", 0.0)))
    except (AttributeError, TypeError, ValueError, OverflowError) as exc:
        raise FdrReadError(
            f"{path}: run {run}: the recorded camera mount is not two numbers", path=path
        ) from exc
    estimate = estimate_boresight(
        _tilts(recs, FdrKind.FRAME, "ground_tilt_check"),
        _tilts(recs, FdrKind.FIX, "attitude_check"),
        used,
        max_half_width_deg=max_half_width_deg,
    )
    return {"path": str(path), "run": run, "runs": len(runs), **estimate.as_dict()}


def format_boresight(b: dict[str, Any]) -> str:
    used = b["mount_used_deg"]
    lines = [
        f"boresight from run {b['run']} of {b['runs']} in {b['path']} "
        f"(flown with camera.mount_roll_deg {used[0]:+.3f}, camera.mount_pitch_deg {used[1]:+.3f})"
    ]
    for name, key in (("VO ground tilt", "vo_ground_tilt"), ("fixes", "fixes")):
        o = b[key]
        if o is None:
            lines.append(f"  {name:<15} none recorded")
            continue
        (mx, my), (sx, sy) = o["mean_deg"], o["scatter_deg"]
        if "half_width_99_deg" in o:
            hx, hy = o["half_width_99_deg"]
            left = (
                f"x {mx:+.3f} +/- {hx:.3f}, y {my:+.3f} +/- {hy:.3f} deg (99 %; scatter {sx:.2f}, {sy:.2f})"
            )
        else:
            shared = "a check: their errors are shared, so no interval"
            left = f"x {mx:+.3f}, y {my:+.3f} deg (scatter {sx:.2f}, {sy:.2f}; {shared})"
        lines.append(f"  {name:<15} {o['samples']:>5}  tilt left {left}")
    if b["mount_deg"] is not None:
        roll, pitch = b["mount_deg"]
        verdict = "set" if b["settable"] else f"not settable ({b['why_not']}); would be"
        lines.append(f"  {verdict}: camera.mount_roll_deg: {roll:.3f}, camera.mount_pitch_deg: {pitch:.3f}")
    else:
        lines.append(f"  not settable ({b['why_not']})")
    return "\n".join(lines)


def _cmd_boresight(args: argparse.Namespace) -> int:
    if not args.max_half_width_deg > 0:
        print(f"gdnav: --max-half-width-deg must be > 0, got {args.max_half_width_deg}", file=sys.stderr)
        return EXIT_CONFIG
    try:
        result = boresight(args.path, args.run, args.max_half_width_deg)
    except FdrReadError as exc:
        print(f"gdnav: {exc}", file=sys.stderr)
        return EXIT_RESOURCE
    print(json.dumps(result, indent=2) if args.json else format_boresight(result))
    return EXIT_OK


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``fdr`` with its ``summary`` and ``boresight`` subcommands; returns the ``fdr`` parser."""
    fdr = subparsers.add_parser(
        "fdr", help="flight data recorder tools", description="Flight data recorder tools (C13)."
    )
    fdr_sub = fdr.add_subparsers(dest="fdr_command", required=True, metavar="SUBCOMMAND")
    summary = fdr_sub.add_parser(
        "summary",
        help="counts, rates, errors, runs and provenance timeline of a recorder",
        description="Summarise a flight data recorder: records by kind, daemon runs (clean stop or "
        "crash) with their rates, errors, and the provenance timeline. Schema: docs/fdr.md.",
    )
    summary.add_argument(
        "path", type=Path, metavar="FILE|DIR", help="FDR directory or one fdr-*.jsonl segment"
    )
    summary.add_argument(
        "--png", type=Path, default=None, metavar="OUT.png", help="also draw track, inliers, sigma"
    )
    summary.add_argument("--json", action="store_true", help="print the summary as JSON")
    summary.set_defaults(func=_cmd_summary)
    bore = fdr_sub.add_parser(
        "boresight",
        help="the camera mount (camera.mount_roll_deg, _pitch_deg) a flight's VO ground tilts ask for",
        description="Measure the nav camera's boresight from a recorded flight: the mean of VO's ground "
        "tilt minus the autopilot's (each pair of frames), with its 99 %% interval, added to the mount "
        "the run flew with. Calibrate low over flat, textured ground. See c4_pose/boresight.py.",
    )
    bore.add_argument("path", type=Path, metavar="FILE|DIR", help="FDR directory or one fdr-*.jsonl segment")
    bore.add_argument("--run", type=int, default=None, help="run index (default: the last run with frames)")
    bore.add_argument(
        "--max-half-width-deg",
        type=float,
        default=0.1,
        metavar="DEG",
        help="settable only when both axes' 99 %% half-interval is within this (default 0.1)",
    )
    bore.add_argument("--json", action="store_true", help="print the result as JSON")
    bore.set_defaults(func=_cmd_boresight)
    return fdr
