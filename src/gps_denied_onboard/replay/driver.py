"""``gdnav replay``: the pipeline re-run deterministically, on one thread, from recorded inputs.

Two ways to drive it (``mode`` in the report):

``exact``
    an FDR whose run holds every tracked frame losslessly and the estimator's journal
    (``c5_estimator.journal``). The journal's units are performed in their recorded order:
    ``track`` -> :meth:`NavigationPipeline.track`, ``fix_prior`` -> :meth:`NavigationPipeline.attempt_fix`
    (the search region read then), ``fix`` -> :meth:`NavigationPipeline.fuse_attempt`; the time axis' clock
    and the IMU answers are the recorded ones. With the same config, every per-frame estimate equals the
    recorded one; the report compares them and says where the first difference is, if any.
``sequential``
    everything else (an FDR without the journal or with JPEG/sub-sampled frames, photos with a CSV, a
    telemetry log with a video or photos): each frame is admitted by the time axis with the clock at
    its exposure, tracked, then (with a map) localised, in time order. No IMU: the prediction is
    constant velocity.

Scoring against a truth reuses ``sitl.report.score`` and ``sitl.report.analyse``: the replay's estimate
for each frame stands for the GPS_INPUT the autopilot would have received when the frame was tracked.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import platform
import sys
import time
import uuid
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from tqdm import tqdm

from gps_denied_onboard import __version__
from gps_denied_onboard.camera.types import NavCameraFrame
from gps_denied_onboard.components.c5_estimator.journal import (
    UNIT_FIX,
    UNIT_FIX_PRIOR,
    UNIT_TRACK,
    ReplayDivergence,
    ReplayJournal,
)
from gps_denied_onboard.components.c8_mavlink.messages import fix_type_for
from gps_denied_onboard.config import Config, config_to_dict
from gps_denied_onboard.constants import FdrKind, Provenance
from gps_denied_onboard.geo import haversine_m
from gps_denied_onboard.pipeline import FixAttempt
from gps_denied_onboard.replay.inputs import ReplayFrame, ReplayInput

_T = TypeVar("_T")


class ListRecorder:
    """The replay's own FDR: records kept in memory, stamped with the replay's clock."""

    def __init__(self, clock_unix_usec: Any) -> None:
        self.records: list[dict[str, Any]] = []
        self._clock = clock_unix_usec
        self._seq = 0

    def record(self, kind: str, fields: Mapping[str, object]) -> None:
        self._seq += 1
        self.records.append({"t_unix_s": self._clock() / 1e6, "kind": str(kind), "seq": self._seq, **fields})

    def of_kind(self, kind: str) -> list[dict[str, Any]]:
        return [r for r in self.records if r["kind"] == kind]


class _Clock:
    def __init__(self) -> None:
        self.now_usec = 0

    def __call__(self) -> int:
        return self.now_usec


def _nav_frame(f: ReplayFrame) -> NavCameraFrame:
    return NavCameraFrame(
        uuid.uuid5(uuid.NAMESPACE_OID, f"{f.seq}:{f.exposure_time_unix_usec}"),
        f.seq,
        f.exposure_time_unix_usec,
        f.load(),
        f.attitude,
        f.alt_agl_m,
        0,
        f.timing,
    )


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return bool(a == b)


#: Per-frame fields an exact replay must reproduce bit for bit.
COMPARED_FIELDS = ("provenance", "lat_deg", "lon_deg", "horiz_sigma_m", "vo_ok", "vo_reason")


def _progress(items: Sequence[_T], unit: str) -> Iterable[_T]:
    """``items`` with a progress bar on stderr when it is a terminal (a learned matcher on a CPU replays a
    frame in seconds); nothing is printed otherwise, so logs and captured output stay clean."""
    return tqdm(items, desc="replay", unit=unit, disable=None, file=sys.stderr, leave=False)


def run_replay(
    inp: ReplayInput,
    config: Config,
    *,
    with_map: bool,
    vo_max_gap_s: float | None = None,
    force_sequential: bool = False,
    records_out: Path | None = None,
) -> dict[str, Any]:
    """Replay ``inp`` through the pipeline built from ``config``; returns the report (plain JSON types).
    ``records_out``: also write the replay's own FDR records there, one JSON object a line as in a
    flight's FDR segment, so that the ``gdnav fdr`` tools read a replay as they read a flight.
    Raises ``StartupError`` (cache, model, calibration refused) from the composition root."""
    from gps_denied_onboard.runtime_root.compose import compose_replay

    t_wall = time.monotonic()
    exact = bool(inp.journal) and not inp.not_exact and not force_sequential
    journal = ReplayJournal(inp.journal) if exact else None
    clock = _Clock()
    clock_fn = journal.clock_unix_usec if journal is not None else clock
    fdr = ListRecorder(clock_fn)
    if inp.ground_alt_amsl_m is not None:
        config = dataclasses.replace(
            config, terrain=dataclasses.replace(config.terrain, ground_alt_amsl_m=inp.ground_alt_amsl_m)
        )
    origin = (inp.prior.lat_deg, inp.prior.lon_deg) if inp.prior is not None else None
    if not with_map and origin is None:
        origin = inp.truth[0].lat_deg, inp.truth[0].lon_deg  # only reached with truth and no prior
    root = compose_replay(
        config,
        fdr=fdr,
        clock_unix_usec=clock_fn,
        journal=journal,
        with_map=with_map,
        calibration=inp.calibration,
        ltp_origin_lat_lon=origin,
        vo_max_gap_s=vo_max_gap_s,
    )
    calib = root.calibration
    pipeline, axis = root.pipeline, root.time_axis
    cache_note = _cache_matches_recording(inp, root.config) if with_map else None
    if cache_note is not None:
        inp.notes.append(cache_note)
    divergence: str | None = None
    stopped: str | None = None
    refused: Counter[str] = Counter()
    bad_frames: list[dict[str, Any]] = []

    def usable(f: ReplayFrame) -> NavCameraFrame | None:
        frame = _nav_frame(f)
        if frame.width_px != calib.width_px or frame.height_px != calib.height_px:
            bad_frames.append(
                {
                    "seq": f.seq,
                    "name": f.name,
                    "error": f"frame is {frame.width_px}x{frame.height_px}, "
                    f"calibration is for {calib.width_px}x{calib.height_px}",
                }
            )
            return None
        return frame

    if journal is not None:
        by_time = {f.exposure_time_unix_usec: f for f in inp.frames}
        last_use: dict[int, int] = {}
        for i, u in enumerate(inp.journal):
            last_use[int(u["time_unix_usec"])] = i
        loaded: dict[int, NavCameraFrame] = {}
        pending: dict[int, FixAttempt] = {}
        try:
            for i, unit in enumerate(_progress(inp.journal, "unit")):
                kind, t = str(unit.get("unit")), int(unit["time_unix_usec"])
                if t not in loaded:
                    f = by_time.get(t)
                    if f is None:
                        stopped = (
                            f"unit {unit.get('n')} of {len(inp.journal)}: the frame exposed at {t} has no "
                            "image in the FDR; replayed exactly up to there"
                        )
                        break
                    nav = usable(f)
                    if nav is None:
                        raise ReplayDivergence(
                            f"unit {unit.get('n')}: {bad_frames[-1]['error']}", unit=unit.get("n")
                        )
                    loaded[t] = nav
                frame = loaded[t]
                if kind == UNIT_TRACK:
                    pipeline.track(frame, inp.prior if unit.get("initialised") else None)
                elif kind == UNIT_FIX_PRIOR:
                    pending[t] = pipeline.attempt_fix(frame)
                elif kind == UNIT_FIX:
                    attempt = pending.pop(t, None)
                    if attempt is None:  # the attempt ended before the estimator (no attitude)
                        attempt = pipeline.attempt_fix(frame)
                    pipeline.fuse_attempt(frame, attempt)
                else:
                    raise ReplayDivergence(f"unit {unit.get('n')}: unknown unit {kind!r}", unit=unit.get("n"))
                if last_use.get(t) == i:
                    loaded.pop(t, None)
        except ReplayDivergence as exc:
            divergence = str(exc)
    else:
        for f in _progress(inp.frames, "frame"):
            clock.now_usec = f.exposure_time_unix_usec
            admission = axis.admit_frame(f.exposure_time_unix_usec)
            if not admission.admitted:
                refused[admission.reason.value if admission.reason is not None else "unknown"] += 1
                continue
            nav = usable(f)
            if nav is None:
                continue
            frame = nav
            pipeline.track(frame, inp.prior if not axis.is_initialised else None)
            if axis.is_initialised:
                pipeline.localise(frame)

    if records_out is not None:
        # Led by the config the replay ran with, as a daemon's run is: the FDR tools read it from there.
        head = {
            "t_unix_s": fdr.records[0]["t_unix_s"] if fdr.records else 0.0,
            "kind": FdrKind.CONFIG,
            "seq": 0,
            "version": __version__,
            "config": config_to_dict(root.config),
            "source": "gdnav replay",
        }
        records_out.parent.mkdir(parents=True, exist_ok=True)
        with records_out.open("w", encoding="utf-8") as out:
            for record in [head, *fdr.records]:
                out.write(json.dumps(record, allow_nan=True) + "\n")
    report = _report(inp, root.config, fdr, with_map=with_map, exact=exact, calib=calib)
    report.update(
        {
            "divergence": divergence,
            "stopped": stopped,
            "frames_refused": dict(sorted(refused.items())),
            "bad_frames": bad_frames,
            "vo_max_gap_s": vo_max_gap_s,
            "wall_s": round(time.monotonic() - t_wall, 2),
            "machine": {
                "platform": platform.platform(),
                "cpus": os.cpu_count(),
                "python": platform.python_version(),
            },
        }
    )
    if journal is not None:
        report["journal"] = {"units_total": journal.units_total, "units_replayed": journal.units_replayed}
    return report


def _cache_matches_recording(inp: ReplayInput, config: Config) -> str | None:
    """A note when the map cache is not the one the recorded run used (its manifest pins every artifact):
    an exact replay then has no reason to match."""
    if inp.recorded_cache_manifest_sha256 is None:
        return None
    import hashlib

    from gps_denied_onboard.components.c10_cache_build.manifest import MANIFEST_NAME

    try:
        now = hashlib.sha256((Path(config.cache.dir) / MANIFEST_NAME).read_bytes()).hexdigest()
    except OSError:
        return None  # compose_replay has already refused a missing cache
    if now != inp.recorded_cache_manifest_sha256:
        return (
            f"the map cache {config.cache.dir} is not the one the run used (manifest sha256 {now[:12]}, "
            f"recorded {inp.recorded_cache_manifest_sha256[:12]})"
        )
    return None


def _report(
    inp: ReplayInput, config: Config, fdr: ListRecorder, *, with_map: bool, exact: bool, calib: Any
) -> dict[str, Any]:
    frames = sorted(fdr.of_kind(FdrKind.FRAME), key=lambda r: r["frame_seq"])
    fixes = fdr.of_kind(FdrKind.FIX)
    names = {f.seq: f.name for f in inp.frames}
    prov = Counter(str(r["provenance"]) for r in frames)
    vo_reasons = Counter(
        str(r.get("vo_reason")).split(":")[0] + ":" + str(r.get("vo_reason")).split(":")[-1]
        for r in frames
        if not r.get("vo_ok")
    )
    no_fix = Counter(str(r.get("no_fix_reason")).split(":")[0] for r in fixes if not r.get("fix_accepted"))
    accepted = sum(bool(r.get("fix_accepted")) for r in fixes)
    per_frame: list[dict[str, Any]] = []
    for r in frames:
        sigma = r.get("horiz_sigma_m")
        p = Provenance(str(r["provenance"]))
        per_frame.append(
            {
                "seq": r["frame_seq"],
                "name": names.get(r["frame_seq"], ""),
                "exposure_time_unix_usec": r["exposure_time_unix_usec"],
                "provenance": p.value,
                "fix_type": fix_type_for(p, sigma if sigma is not None else math.inf),
                "lat_deg": r.get("lat_deg"),
                "lon_deg": r.get("lon_deg"),
                "horiz_sigma_m": sigma,
                "vo_ok": r.get("vo_ok"),
                "vo_reason": r.get("vo_reason"),
                "vo_inliers": r.get("vo_inliers"),
            }
        )
    out: dict[str, Any] = {
        "source": inp.source,
        "mode": "exact" if exact else "sequential",
        "not_exact_because": list(inp.not_exact),
        "map": config.cache.dir if with_map else None,
        "matcher": config.matcher.strategy if with_map else None,
        "calibration": {
            "width_px": calib.width_px,
            "height_px": calib.height_px,
            "fx_px": round(calib.fx_px, 2),
            "fy_px": round(calib.fy_px, 2),
        },
        "prior": dataclasses.asdict(inp.prior) if inp.prior is not None else None,
        "frames_in": len(inp.frames),
        "frames_tracked": len(frames),
        "vo": {
            "intervals_measured": sum(bool(r.get("vo_ok")) for r in frames),
            "not_measured": dict(sorted(vo_reasons.items())),
        },
        "fix": {
            "attempts": len(fixes),
            "accepted": accepted,
            "no_fix_reasons": dict(sorted(no_fix.items())),
            "path": "run" if with_map else "not run: no map cache (VO only)",
        },
        "provenance_counts": dict(sorted(prov.items())),
        "anchored_frames": prov.get(Provenance.SATELLITE_ANCHORED.value, 0),
        "notes": list(inp.notes),
        "per_frame": per_frame,
    }
    if inp.recorded_frames:
        out["reproduction"] = _compare(frames, inp.recorded_frames)
    if inp.truth:
        out["metrics"] = _metrics(inp, fdr, frames, per_frame)
        out["vo_intervals"] = _vo_vs_truth(inp, frames)
    return out


def _compare(replayed: list[dict[str, Any]], recorded: Mapping[int, Mapping[str, Any]]) -> dict[str, Any]:
    """Each replayed frame against the daemon's record of the same frame."""
    equal = 0
    first_diff: dict[str, Any] | None = None
    max_pos_m = 0.0
    max_sigma_m = 0.0
    for r in replayed:
        rec = recorded.get(int(r["frame_seq"]))
        if rec is None:
            continue
        diffs = {k: (rec.get(k), r.get(k)) for k in COMPARED_FIELDS if not _same(rec.get(k), r.get(k))}
        if not diffs:
            equal += 1
        elif first_diff is None:
            first_diff = {"seq": r["frame_seq"], "recorded_vs_replayed": diffs}
        if None not in (rec.get("lat_deg"), r.get("lat_deg")):
            max_pos_m = max(
                max_pos_m, float(haversine_m(rec["lat_deg"], rec["lon_deg"], r["lat_deg"], r["lon_deg"]))
            )
        if None not in (rec.get("horiz_sigma_m"), r.get("horiz_sigma_m")):
            max_sigma_m = max(max_sigma_m, abs(float(rec["horiz_sigma_m"]) - float(r["horiz_sigma_m"])))
    return {
        "frames_recorded": len(recorded),
        "frames_replayed": len(replayed),
        "frames_equal": equal,
        #: Every replayed frame equals its record (a replay stopped early compares the frames it reached).
        "all_equal": equal == len(replayed) and len(replayed) > 0,
        "complete": len(replayed) == len(recorded),
        "max_position_difference_m": max_pos_m,
        "max_sigma_difference_m": max_sigma_m,
        "first_difference": first_diff,
        "fields": list(COMPARED_FIELDS),
    }


def _metrics(
    inp: ReplayInput, fdr: ListRecorder, frames: list[dict[str, Any]], per_frame: list[dict[str, Any]]
) -> dict[str, Any]:
    """The SITL scorer on the replay: each frame's estimate as the GPS_INPUT received when it was tracked."""
    from gps_denied_onboard.sitl.autopilot import ReceivedMessage
    from gps_denied_onboard.sitl.report import SentFrame, analyse, score

    sent: list[SentFrame] = []
    received: list[ReceivedMessage] = []
    records = list(fdr.records)
    t0 = inp.frames[0].exposure_time_unix_usec / 1e6 if inp.frames else 0.0
    by_seq = {f.seq: f for f in inp.frames}
    for r, row in zip(frames, per_frame, strict=True):
        f = by_seq[int(r["frame_seq"])]
        t_exp = f.exposure_time_unix_usec / 1e6
        lat_t, lon_t = inp.truth_at(t_exp)
        sent.append(SentFrame(f.seq, f.exposure_time_unix_usec, t_exp - t0, lat_t, lon_t, f.alt_agl_m or 0.0))
        if r.get("lat_deg") is None:
            continue
        received.append(
            ReceivedMessage(
                float(r["t_unix_s"]),
                "GPS_INPUT",
                {
                    "time_usec": f.exposure_time_unix_usec,
                    "lat": round(float(r["lat_deg"]) * 1e7),
                    "lon": round(float(r["lon_deg"]) * 1e7),
                    "fix_type": row["fix_type"],
                    "horiz_accuracy": float(r["horiz_sigma_m"]),
                    "time_week": 1,
                    "gps_id": 0,
                },
            )
        )
        records.append(
            {
                "kind": FdrKind.ESTIMATE_SENT,
                "time_unix_usec": f.exposure_time_unix_usec,
                "provenance": row["provenance"],
            }
        )
    report = score(sent, received, inp.truth_at, records)
    analysis = analyse(report, records, inp.truth_at)
    keep = ("frames", "frames_answered", "availability", "horizontal_error_m", "consistency", "fix_age_ms")
    out = {k: report[k] for k in keep}
    out["analysis"] = analysis
    # The error of every frame (fix_type or not), so a VO-only replay still says how far it drifted.
    errs = {row["seq"]: row.get("horizontal_error_m") for row in report["per_frame"]}
    for row in per_frame:
        row["horizontal_error_m"] = errs.get(row["seq"])
    all_err = []
    for r in frames:
        if r.get("lat_deg") is None:
            continue
        lat_t, lon_t = inp.truth_at(int(r["exposure_time_unix_usec"]) / 1e6)
        all_err.append(float(haversine_m(lat_t, lon_t, r["lat_deg"], r["lon_deg"])))
    out["error_any_fix_type_m"] = {
        "p50": float(np.percentile(all_err, 50)) if all_err else None,
        "max": max(all_err) if all_err else None,
        "n": len(all_err),
    }
    out["truth"] = "the input's own positions" if inp.truth else None
    return out


def _vo_vs_truth(inp: ReplayInput, frames: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each measured VO interval against the truth's displacement over the same interval."""
    import pymap3d

    by_t = {f.exposure_time_unix_usec: f for f in inp.frames}
    out = []
    for r in frames:
        delta, dt = r.get("vo_delta_ne_m"), r.get("vo_dt_s")
        if not r.get("vo_ok") or delta is None or dt is None:
            continue
        t1 = int(r["exposure_time_unix_usec"])
        t0 = t1 - round(float(dt) * 1e6)
        lat0, lon0 = inp.truth_at(t0 / 1e6)
        lat1, lon1 = inp.truth_at(t1 / 1e6)
        n, e, _ = pymap3d.geodetic2ned(lat1, lon1, 0.0, lat0, lon0, 0.0)
        truth_m = math.hypot(n, e)
        err = math.hypot(float(delta[0]) - n, float(delta[1]) - e)
        f = by_t.get(t1)
        out.append(
            {
                "to_seq": r["frame_seq"],
                "to_name": f.name if f is not None else "",
                "dt_s": round(float(dt), 3),
                "truth_m": round(truth_m, 2),
                "vo_m": round(math.hypot(float(delta[0]), float(delta[1])), 2),
                "error_m": round(err, 2),
                "error_pct_of_distance": round(100.0 * err / truth_m, 1) if truth_m > 0 else None,
            }
        )
    return out


def summary_lines(report: Mapping[str, Any]) -> list[str]:
    """One screen: what was replayed, what anchored and what did not, and the metrics."""
    lines = [
        f"replay: {report['source']} ({report['mode']}; map: {report['map'] or 'none'})",
        f"frames: {report['frames_in']} in, {report['frames_tracked']} tracked, "
        f"refused {report.get('frames_refused') or {}}, bad {len(report.get('bad_frames') or [])}",
        f"VO: {report['vo']['intervals_measured']} intervals measured; "
        f"not measured: {report['vo']['not_measured']}",
        f"fix path: {report['fix']['path']}; {report['fix']['attempts']} attempts, "
        f"{report['fix']['accepted']} accepted; no fix: {report['fix']['no_fix_reasons']}",
        f"anchored frames: {report['anchored_frames']}; provenance: {report['provenance_counts']}",
    ]
    if report.get("not_exact_because"):
        lines.append(f"not exact: {'; '.join(report['not_exact_because'])}")
    rep = report.get("reproduction")
    if rep is not None:
        lines.append(
            f"reproduction: {rep['frames_equal']}/{rep['frames_replayed']} replayed frames equal to the "
            f"recording ({rep['frames_recorded']} recorded), "
            f"max position difference {rep['max_position_difference_m']:.3g} m"
            + (
                f"; first difference at frame {rep['first_difference']['seq']}"
                if rep["first_difference"]
                else ""
            )
        )
    if report.get("stopped"):
        lines.append(f"stopped: {report['stopped']}")
    if report.get("divergence"):
        lines.append(f"diverged: {report['divergence']}")
    m = report.get("metrics")
    if m is not None:
        h, c = m["horizontal_error_m"], m["consistency"]

        def fmt(v: Any) -> str:
            return "-" if v is None else f"{v:.2f}"

        lines.append(
            f"vs truth: availability {m['availability']:.3f}, horizontal p50 {fmt(h['p50'])} m / p95 "
            f"{fmt(h['p95'])} m (fix_type 3, n={h['n']}), beyond 3 sigma {c['beyond_3sigma']}, "
            f"accepted fixes beyond 3 sigma {m['analysis']['accepted_fixes_beyond_3sigma']}"
        )
        from gps_denied_onboard.sitl.report import refused_fixes_line

        refused = refused_fixes_line(m["analysis"])
        if refused is not None:
            lines.append(refused)
        lines.append(
            f"error at every frame (any fix type): p50 {fmt(m['error_any_fix_type_m']['p50'])} m, "
            f"max {fmt(m['error_any_fix_type_m']['max'])} m"
        )
    vo = report.get("vo_intervals") or []
    if vo:
        errs = [v["error_m"] for v in vo]
        pcts = [v["error_pct_of_distance"] for v in vo if v["error_pct_of_distance"] is not None]
        lines.append(
            f"VO vs truth over {len(vo)} intervals: error p50 {float(np.median(errs)):.2f} m, "
            f"max {max(errs):.2f} m"
            + (f"; p50 {float(np.median(pcts)):.1f} % of the distance flown" if pcts else "")
        )
        for v in vo[:: max(1, len(vo) // 5)][:6]:
            lines.append(
                f"  VO -> {v['to_name'] or v['to_seq']}: {v['vo_m']} m vs truth {v['truth_m']} m "
                f"over {v['dt_s']} s (error {v['error_m']} m)"
            )
    for n in report.get("notes") or []:
        lines.append(f"note: {n}")
    lines.append(f"wall time {report.get('wall_s')} s")
    return lines
