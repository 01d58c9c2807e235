"""Scoring a SITL flight: what the autopilot side received, against the scenario's truth.

The daemon sends a steady estimate stream (``mavlink.estimate_rate_hz``), each GPS_INPUT stamped with
the time its state was propagated to. Definitions (also in docs/sitl.md, "Report"):

- ``horizontal_error_m``: great-circle distance between each GPS_INPUT with fix_type >= 3 and the
  truth at that GPS_INPUT's ``time_usec``.
- ``consistency``: over the same messages, the share whose error is within 1, 2 and 3 times the stated
  ``horiz_accuracy``, and the count beyond 3 (a "confident lie": the autopilot follows it).
- ``per_frame``: each nav frame against the first GPS_INPUT received after the daemon recorded the frame
  as tracked (its FDR ``pipeline.frame`` record), i.e. the first estimate that includes the frame.
  ``latency_ms`` is that GPS_INPUT's receive time minus the frame's exposure time.
- ``availability``: over frames exposed after the first fix was received, the fraction for which
  the autopilot side received a GPS_INPUT with fix_type >= 3 within 1 s after the exposure.
- ``provenance_counts``: the provenance of the per-frame estimates, from the daemon's FDR
  ``mavlink.estimate`` record of the same ``time_usec``.
- ``stream``: the GPS_INPUT stream replayed through the ArduPilot rules test double
  (``sitl.ardupilot_rules``): intervals, the 215/245 ms health rule, NO_FIX and EKF failsafe.
- ``fix_age_ms``: for accepted absolute fixes, when the daemon fused them minus their exposure time.

With PX4 (``autopilot="px4"``) the estimate stream is GLOBAL_POSITION_SENSOR: each is read as a 3D fix
stating ``eph`` as its horizontal accuracy (``position_messages``: the daemon sends it only for a
position it backs, and PX4 has no "do not use"), and ``stream`` is what the PX4 double
(``sitl.px4_rules``) predicts of the same messages: intervals, and when the position timed out
(``POSITION_TIMEOUT_S`` without a message while the vehicle relied on it: PX4's failsafe).
"""

from __future__ import annotations

import bisect
import itertools
import math
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np

from gps_denied_onboard.constants import FdrKind
from gps_denied_onboard.geo import LocalTangentPlane, haversine_m
from gps_denied_onboard.sitl.ardupilot_rules import (
    SpeedAccuracyGlitch,
    evaluate_gps_stream,
    gps_input_accepted,
)
from gps_denied_onboard.sitl.autopilot import ReceivedMessage
from gps_denied_onboard.sitl.px4_rules import POSITION_TIMEOUT_S

AVAILABILITY_WINDOW_S = 1.0
#: GPSn_TYPE parameters of the autopilot the stream is judged against (GPS1_TYPE=14, MAVLink).
STREAM_GPS_TYPES: dict[int, int] = {0: 14}


@dataclass(frozen=True)
class SentFrame:
    seq: int
    exposure_time_unix_usec: int
    t_s: float
    lat_deg: float
    lon_deg: float
    alt_agl_m: float


def _pct(values: Sequence[float], q: float) -> float | None:
    return float(np.percentile(np.asarray(values, dtype=float), q)) if values else None


def _of_kind(records: Sequence[Mapping[str, Any]], kind: str) -> list[Mapping[str, Any]]:
    return [r for r in records if r.get("kind") == kind]


def position_messages(received: Sequence[ReceivedMessage]) -> list[ReceivedMessage]:
    """The estimate stream as the report reads it, by receive time: GPS_INPUT as received; where there is
    none, each GLOBAL_POSITION_SENSOR as a 3D fix whose horizontal accuracy is its ``eph``."""
    gps = [m for m in received if m.type == "GPS_INPUT"]
    if not gps:
        gps = [
            ReceivedMessage(
                m.recv_time_unix_s,
                "GPS_INPUT",
                {
                    "time_usec": m.fields["time_usec"],
                    "lat": m.fields["lat"],
                    "lon": m.fields["lon"],
                    "fix_type": 3,
                    "horiz_accuracy": m.fields["eph"],
                },
            )
            for m in received
            if m.type == "GLOBAL_POSITION_SENSOR"
        ]
    return sorted(gps, key=lambda m: m.recv_time_unix_s)


def px4_stream_verdict(
    recv_s: Sequence[float], *, end_s: float | None, relied_on_until_s: float | None
) -> dict[str, Any]:
    """What the PX4 double predicts of a GLOBAL_POSITION_SENSOR stream received at ``recv_s`` (the
    stream's seconds): the intervals, and each silence longer than ``POSITION_TIMEOUT_S`` before
    ``relied_on_until_s`` (PX4's failsafe: descend), with when it fired."""
    intervals = np.diff(np.asarray(recv_s, dtype=float)) * 1000.0
    edges = [*recv_s, end_s] if end_s is not None and recv_s else list(recv_s)
    failsafes = [
        round(a + POSITION_TIMEOUT_S, 3)
        for a, b in itertools.pairwise(edges)
        if b - a > POSITION_TIMEOUT_S
        and (relied_on_until_s is None or a + POSITION_TIMEOUT_S < relied_on_until_s)
    ]
    return {
        "autopilot": "px4",
        "interval_ms": {
            "n": len(intervals),
            "mean_ms": float(intervals.mean()),
            "p99_ms": float(np.percentile(intervals, 99)),
            "max_ms": float(intervals.max()),
        }
        if len(intervals)
        else None,
        "position_timeouts_s": failsafes,
        "health": {"tripped": bool(failsafes)},
        "ekf_failsafe_land_s": failsafes[0] if failsafes else None,
    }


def score(
    frames: Sequence[SentFrame],
    received: Sequence[ReceivedMessage],
    truth_at_unix: Callable[[float], tuple[float, float]],
    fdr_records: Sequence[Mapping[str, Any]] = (),
    *,
    end_unix_s: float | None = None,
    gps_types: Mapping[int, int] | None = None,
    relied_on_until_unix_s: float | None = None,
    autopilot: str = "ardupilot",
) -> dict[str, Any]:
    """Build the report dict. ``truth_at_unix(t)`` -> (lat_deg, lon_deg) of the truth at Unix time t;
    ``fdr_records``: the daemon's flight data recorder (provenance and per-frame timing);
    ``end_unix_s``: end of the flight, for judging silence after the last message; ``gps_types``: the
    autopilot's GPSn_TYPE by instance the stream is judged with (default STREAM_GPS_TYPES);
    ``relied_on_until_unix_s``: when the autopilot's own GNSS took over again (its silences after that
    trip nothing); ``autopilot``: ``ardupilot`` or ``px4`` (module docstring)."""
    gps = position_messages(received)
    prov_by_time = {
        int(r["time_unix_usec"]): str(r.get("provenance"))
        for r in _of_kind(fdr_records, FdrKind.ESTIMATE_SENT)
    }
    tracked_at = {int(r["frame_seq"]): float(r["t_unix_s"]) for r in _of_kind(fdr_records, FdrKind.FRAME)}

    def err_m(m: ReceivedMessage) -> float:
        lat_t, lon_t = truth_at_unix(int(m.fields["time_usec"]) / 1e6)
        return float(haversine_m(lat_t, lon_t, m.fields["lat"] / 1e7, m.fields["lon"] / 1e7))

    fixes = [m for m in gps if int(m.fields["fix_type"]) >= 3]
    errors = [err_m(m) for m in fixes]
    ratios = [e / max(float(m.fields["horiz_accuracy"]), 1e-3) for e, m in zip(errors, fixes, strict=True)]

    first_fix_unix = min((m.recv_time_unix_s for m in fixes), default=None)
    fix_recv = np.array([m.recv_time_unix_s for m in fixes])
    gps_recv = [m.recv_time_unix_s for m in gps]
    per_frame: list[dict[str, Any]] = []
    latencies: list[float] = []
    prov_counts: Counter[str] = Counter()
    avail_num = avail_den = 0
    for f in frames:
        t_exp = f.exposure_time_unix_usec / 1e6
        row: dict[str, Any] = {
            "seq": f.seq,
            "t_s": round(f.t_s, 3),
            "exposure_time_unix_usec": f.exposure_time_unix_usec,
            "true_lat_deg": f.lat_deg,
            "true_lon_deg": f.lon_deg,
            "alt_agl_m": round(f.alt_agl_m, 2),
            "est_lat_deg": None,
            "fix_type": None,
            "provenance": None,
            "horizontal_error_m": None,
        }
        done = tracked_at.get(f.seq)
        i = bisect.bisect_left(gps_recv, done) if done is not None else len(gps)
        if i < len(gps) and gps_recv[i] - t_exp <= AVAILABILITY_WINDOW_S:
            m = gps[i]
            fx = m.fields
            latency = (m.recv_time_unix_s - t_exp) * 1000.0
            latencies.append(latency)
            prov = prov_by_time.get(int(fx["time_usec"]), "unknown")
            prov_counts[prov] += 1
            row.update(
                {
                    "est_lat_deg": fx["lat"] / 1e7,
                    "est_lon_deg": fx["lon"] / 1e7,
                    "est_time_usec": int(fx["time_usec"]),
                    "fix_type": int(fx["fix_type"]),
                    "horiz_accuracy_m": float(fx["horiz_accuracy"]),
                    "provenance": prov,
                    "latency_ms": round(latency, 1),
                    "horizontal_error_m": round(err_m(m), 3),
                }
            )
        if first_fix_unix is not None and t_exp >= first_fix_unix - AVAILABILITY_WINDOW_S:
            avail_den += 1
            lo, hi = np.searchsorted(fix_recv, [t_exp, t_exp + AVAILABILITY_WINDOW_S], side="left")
            avail_num += int(hi > lo)
        per_frame.append(row)

    statustexts = [
        {
            "t_unix_s": round(m.recv_time_unix_s, 3),
            "severity": m.fields.get("severity"),
            "text": m.fields.get("text"),
        }
        for m in received
        if m.type == "STATUSTEXT"
    ]
    t_ref = gps_recv[0] if gps_recv else 0.0
    end_s = None if end_unix_s is None or not gps else max(end_unix_s - t_ref, gps_recv[-1] - t_ref)
    relied_s = None if relied_on_until_unix_s is None else relied_on_until_unix_s - t_ref
    if autopilot == "px4":
        stream_dict = px4_stream_verdict(
            [t - t_ref for t in gps_recv], end_s=end_s, relied_on_until_s=relied_s
        )
    else:
        stream_dict = evaluate_gps_stream(
            [t - t_ref for t in gps_recv],
            [gps_input_accepted(m.fields, STREAM_GPS_TYPES if gps_types is None else gps_types) for m in gps],
            end_s=end_s,
            relied_on_until_s=relied_s,
        ).to_dict()
    # EKF3's speed-accuracy test over the 3D messages, as the autopilot would run it
    # (a replay's messages may carry no speed accuracy: then there is nothing to judge)
    with_sacc = [m for m in fixes if m.fields.get("speed_accuracy") is not None]
    sacc = [float(m.fields["speed_accuracy"]) for m in with_sacc]
    glitch = SpeedAccuracyGlitch()
    glitch_spans: list[list[float]] = []
    for m, sa in zip(with_sacc, sacc, strict=True):
        t = m.recv_time_unix_s - t_ref
        was = glitch.glitching
        if glitch.update(t, sa) and not was:
            glitch_spans.append([round(t, 3), round(t, 3)])
        elif was and glitch_spans:
            glitch_spans[-1][1] = round(t, 3)
    fix_ages = [
        (float(r["t_unix_s"]) - int(r["exposure_time_unix_usec"]) / 1e6) * 1000.0
        for r in _of_kind(fdr_records, FdrKind.FIX)
        if r.get("fix_accepted")
    ]
    n = len(ratios)
    return {
        "frames": len(frames),
        "frames_answered": len(latencies),
        "availability": (avail_num / avail_den) if avail_den else 0.0,
        "horizontal_error_m": {
            "p50": _pct(errors, 50),
            "p95": _pct(errors, 95),
            "max": max(errors) if errors else None,
            "n": len(errors),
        },
        "consistency": {
            "within_1sigma": sum(r <= 1.0 for r in ratios) / n if n else None,
            "within_2sigma": sum(r <= 2.0 for r in ratios) / n if n else None,
            "within_3sigma": sum(r <= 3.0 for r in ratios) / n if n else None,
            "beyond_3sigma": sum(r > 3.0 for r in ratios),
            "max_error_sigma": max(ratios) if ratios else None,
        },
        "latency_ms": {"p50": _pct(latencies, 50), "p95": _pct(latencies, 95)},
        "fix_age_ms": {"p50": _pct(fix_ages, 50), "p95": _pct(fix_ages, 95), "n": len(fix_ages)},
        "provenance_counts": dict(sorted(prov_counts.items())),
        "gps_input_received": len(gps),
        "speed_accuracy_m_s": {"p50": _pct(sacc, 50), "p95": _pct(sacc, 95), "max": max(sacc, default=None)},
        #: When EKF3's speed-accuracy test would call the GPS glitching, s on the stream's clock.
        "glitch_spans_s": glitch_spans,
        "stream": stream_dict,
        #: Unix time of the stream's 0 s (its first GPS_INPUT), to place its spans on the flight clock.
        "stream_t0_unix_s": t_ref,
        "statustext": statustexts,
        "per_frame": per_frame,
    }


def plot_report(report: dict[str, Any], path: Path, *, title: str) -> None:
    """PNG: true vs estimated track (local metres) coloured by provenance, and error over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = report["per_frame"]
    if not rows:
        return
    lat0, lon0 = rows[0]["true_lat_deg"], rows[0]["true_lon_deg"]
    k_n = 111_320.0
    k_e = 111_320.0 * math.cos(math.radians(lat0))

    def ne(lat: float, lon: float) -> tuple[float, float]:
        return (lat - lat0) * k_n, (lon - lon0) * k_e

    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(13, 6), gridspec_kw={"width_ratios": [1.2, 1]})
    tn, te = zip(*(ne(r["true_lat_deg"], r["true_lon_deg"]) for r in rows), strict=False)
    ax0.plot(te, tn, "-", color="0.3", lw=1.5, label="truth")
    colors = {
        "satellite_anchored": "tab:green",
        "visual_propagated": "tab:orange",
        "dead_reckoning": "tab:red",
        "no_estimate": "tab:gray",
    }
    for prov, color in colors.items():
        pts = [ne(r["est_lat_deg"], r["est_lon_deg"]) for r in rows if r.get("provenance") == prov]
        if pts:
            en, ee = zip(*pts, strict=False)
            ax0.scatter(ee, en, s=10, color=color, label=f"estimate: {prov}", zorder=3)
    ax0.set_xlabel("east [m]")
    ax0.set_ylabel("north [m]")
    ax0.set_aspect("equal", adjustable="datalim")
    ax0.legend(loc="best", fontsize=8)
    ax0.set_title(title)
    t = [r["t_s"] for r in rows if r.get("horizontal_error_m") is not None]
    err = [r["horizontal_error_m"] for r in rows if r.get("horizontal_error_m") is not None]
    acc = [r["horiz_accuracy_m"] for r in rows if r.get("horizontal_error_m") is not None]
    ax1.plot(t, err, ".-", ms=3, lw=0.8, label="horizontal error")
    ax1.plot(t, acc, "--", lw=0.8, label="reported horiz_accuracy (1σ)")
    ax1.set_xlabel("flight time [s]")
    ax1.set_ylabel("[m]")
    h = report["horizontal_error_m"]
    ax1.set_title(
        f"p50 {h['p50'] or float('nan'):.2f} m, p95 {h['p95'] or float('nan'):.2f} m, "
        f"availability {report['availability']:.2f}"
    )
    ax1.legend(fontsize=8)
    ax1.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _run_segments(seqs: Sequence[int], labels: Sequence[str], label: str) -> list[tuple[int, int]]:
    """(first_index, last_index) of maximal runs of ``label`` in ``labels``."""
    runs, start = [], None
    for i, lab in enumerate(labels):
        if lab == label and start is None:
            start = i
        elif lab != label and start is not None:
            runs.append((start, i - 1))
            start = None
    if start is not None:
        runs.append((start, len(labels) - 1))
    return runs


def refused_fixes_line(analysis: Mapping[str, Any]) -> str | None:
    """``analysis["refused_fix_errors"]`` in one line for the summaries, or None when no solved fix was
    refused."""
    refused = analysis.get("refused_fix_errors") or {}
    if not refused:
        return None
    return "solved and refused, vs truth: " + "; ".join(
        f"{reason} {r['n']} ({r['beyond_3sigma']} beyond 3 sigma, p50 {r['p50_error_m']} m)"
        for reason, r in refused.items()
    )


def analyse(
    report: dict[str, Any],
    fdr_records: Sequence[dict[str, Any]],
    truth_at_unix: Callable[[float], tuple[float, float]],
) -> dict[str, Any]:
    """What the daemon did, from its own flight data recorder, checked against the truth:

    - ``accepted_fixes_beyond_3sigma``: accepted absolute fixes farther from the truth than 3 of their
      own stated sigmas (the wrong-tile trap must keep this at 0);
    - ``provenance_switch_lag_frames``: frames from the first insufficient-inliers frame to the first
      frame tracked as ``visual_propagated`` (the issue asks for <= 1; the fix path runs beside VO, so
      the frame whose fix failed was tracked before its fix finished);
    - ``frames_refused``: frames the time axis refused, by reason (future, stale, out of order);
    - ``integrity_refused``: solved fixes the fix-integrity rule refused, by reason;
    - ``accepted_fix_offset_m``: the accepted fixes' mean error, fix minus truth, north and east (m), with
      its length: what they share (a map's georeference against the frames', a camera tilt), which
      averaging more fixes does not remove; None without accepted fixes;
    - ``refused_fix_errors``: the fixes that were solved and then refused (attitude check, integrity,
      consistency, the estimator's gate), by reason, scored the same way against the sigma they would
      have carried: how many were beyond 3 of them, and so whether a refusal threw away a right fix or
      kept out a wrong one;
    - ``fix_attempts``: every attempt in frame order: accepted or the reason not, its inlier count, and for
      a solved fix its error (m), stated sigma (m) and error in sigmas;
    - ``vio_segments``: each VIO-only stretch with the distance flown, the error growth and the drift as
      a percentage of that distance, and how many fixes it took afterwards to get back under the
      nominal p95 error (measured on the anchored frames before the first stretch that follows one);
    - ``fix_attempts_per_s``: attempts over the span from the first to the last attempt's record;
      ``judged_fix_latency_ms``: p50 and p95 of each attempt's record time minus its frame's exposure
      (from exposure to a judged fix, accepted or not); ``rung_attempts``: attempts per ladder rung.
    """
    frames = sorted(_of_kind(fdr_records, FdrKind.FRAME), key=lambda r: r["frame_seq"])
    fixes = sorted(_of_kind(fdr_records, FdrKind.FIX), key=lambda r: r["frame_seq"])
    rows = {r["seq"]: r for r in report["per_frame"]}
    fix_errors_sigma = []
    fix_offsets_ne_m = []
    attempts = []
    refused_errors: dict[str, list[tuple[float, float]]] = {}
    for r in fixes:
        row: dict[str, Any] = {
            "seq": r["frame_seq"],
            "accepted": bool(r.get("fix_accepted")),
            "reason": r.get("no_fix_reason"),
            "inliers": r.get("inliers"),
        }
        attempts.append(row)
        if r.get("fix_lat_deg") is None or not r.get("fix_sigma_m"):
            continue  # no pose was solved: nothing to score
        lat_t, lon_t = truth_at_unix(r["exposure_time_unix_usec"] / 1e6)
        err = float(haversine_m(lat_t, lon_t, r["fix_lat_deg"], r["fix_lon_deg"]))
        sigma = float(r["fix_sigma_m"])
        row.update(error_m=round(err, 2), sigma_m=round(sigma, 2), error_sigma=round(err / sigma, 3))
        if row["accepted"]:
            fix_errors_sigma.append(err / sigma)
            fix_offsets_ne_m.append(
                LocalTangentPlane(lat_t, lon_t).to_ned(r["fix_lat_deg"], r["fix_lon_deg"], 0.0)
            )
        else:
            reason = str(r.get("no_fix_reason"))
            refused_errors.setdefault(reason, []).append((err, err / sigma))
    offset = None
    if fix_offsets_ne_m:
        north_m, east_m = (float(v) for v in np.mean(fix_offsets_ne_m, axis=0)[:2])
        offset = {
            "north": round(north_m, 2),
            "east": round(east_m, 2),
            "length": round(math.hypot(north_m, east_m), 2),
        }
    reasons = Counter(str(r.get("no_fix_reason")).split(":")[0] for r in fixes if not r.get("fix_accepted"))
    integrity = Counter(
        str(r.get("no_fix_reason")).split(":", 1)[1]
        for r in fixes
        if str(r.get("no_fix_reason")).startswith("integrity:")
    )
    refused = Counter(str(r.get("reason")) for r in _of_kind(fdr_records, FdrKind.FRAME_REFUSED))

    seqs = [r["frame_seq"] for r in frames]
    labels = [r.get("provenance", "unknown") for r in frames]
    transitions = [
        {"seq": seqs[i], "from": labels[i - 1], "to": labels[i]}
        for i in range(1, len(labels))
        if labels[i] != labels[i - 1]
    ]
    first_ii = next((r["frame_seq"] for r in fixes if r.get("no_fix_reason") == "insufficient_inliers"), None)
    switch_lag = None
    if first_ii is not None:
        vp = next(
            (s for s, lab in zip(seqs, labels, strict=True) if s >= first_ii and lab == "visual_propagated"),
            None,
        )
        switch_lag = None if vp is None else vp - first_ii

    def error_at(seq: int) -> float | None:
        row = rows.get(seq)
        return None if row is None else row.get("horizontal_error_m")

    segments = _run_segments(seqs, labels, "visual_propagated")
    # The nominal error: anchored frames before the first VIO stretch that follows an anchored frame
    # (frames tracked at start-up before the first fix landed are a VIO stretch too, with nothing before).
    first_anchored = next((i for i, lab in enumerate(labels) if lab == "satellite_anchored"), len(seqs))
    first_gap = next((a for a, _ in segments if a > first_anchored), len(seqs))
    before = [
        error_at(seqs[i])
        for i in range(first_gap)
        if labels[i] == "satellite_anchored" and error_at(seqs[i]) is not None
    ]
    nominal_p95 = _pct([e for e in before if e is not None], 95)
    vio = []
    for a, b in segments:
        path = [rows[s] for s in seqs[max(a - 1, 0) : b + 1] if s in rows]
        dist = sum(
            float(haversine_m(p["true_lat_deg"], p["true_lon_deg"], q["true_lat_deg"], q["true_lon_deg"]))
            for p, q in itertools.pairwise(path)
        )
        e0 = error_at(seqs[a - 1]) if a > 0 else None
        during = [e for e in (error_at(seqs[i]) for i in range(a, b + 1)) if e is not None]
        growth = (max(during) - (e0 or 0.0)) if during else None
        recover = None
        if nominal_p95 is not None:
            n_fixes = 0
            for i in range(b + 1, len(seqs)):
                if labels[i] == "satellite_anchored":
                    n_fixes += 1
                    e = error_at(seqs[i])
                    if e is not None and e <= nominal_p95:
                        recover = n_fixes
                        break
        vio.append(
            {
                "from_seq": seqs[a],
                "to_seq": seqs[b],
                "frames": b - a + 1,
                "distance_m": round(dist, 1),
                "error_before_m": e0,
                "max_error_m": max(during) if during else None,
                "drift_pct_of_distance": round(100.0 * growth / dist, 2)
                if growth is not None and dist > 0
                else None,
                "fixes_to_recover_nominal_p95": recover,
            }
        )
    # The time the fix was judged is its record's own time (the recorder stamps every record).
    timed = [r for r in fixes if isinstance(r.get("t_unix_s"), (int, float))]
    times = [float(r["t_unix_s"]) for r in timed]
    span_s = max(times) - min(times) if len(times) > 1 else 0.0
    judged_ms = [float(r["t_unix_s"]) * 1e3 - r["exposure_time_unix_usec"] / 1e3 for r in timed]
    return {
        "fdr_frames": len(frames),
        "fdr_fix_attempts": len(fixes),
        "fix_attempts_per_s": round((len(timed) - 1) / span_s, 3) if span_s > 0 else None,
        "judged_fix_latency_ms": {
            "p50": _round_or_none(_pct(judged_ms, 50), 1),
            "p95": _round_or_none(_pct(judged_ms, 95), 1),
        },
        "rung_attempts": dict(sorted(Counter(str(r.get("rung")) for r in fixes).items())),
        "frames_refused": dict(sorted(refused.items())),
        "accepted_fixes": len(fix_errors_sigma),
        "accepted_fixes_beyond_3sigma": sum(e > 3.0 for e in fix_errors_sigma),
        "max_accepted_fix_error_sigma": max(fix_errors_sigma) if fix_errors_sigma else None,
        "accepted_fix_offset_m": offset,
        "refused_fix_errors": {
            reason: {
                "n": len(errs),
                "beyond_3sigma": sum(e_sigma > 3.0 for _, e_sigma in errs),
                #: right fixes refused: within their own sigma of the truth
                "within_1sigma": sum(e_sigma <= 1.0 for _, e_sigma in errs),
                "max_error_sigma": round(max(e_sigma for _, e_sigma in errs), 3),
                "p50_error_m": round(float(np.median([e for e, _ in errs])), 2),
            }
            for reason, errs in sorted(refused_errors.items())
        },
        "fix_attempts": attempts,
        "no_fix_reasons": dict(sorted(reasons.items())),
        "integrity_refused": dict(sorted(integrity.items())),
        "transitions": transitions,
        "provenance_switch_lag_frames": switch_lag,
        "nominal_p95_m": nominal_p95,
        "vio_segments": vio,
    }


def _round_or_none(value: float | None, digits: int) -> float | None:
    return None if value is None else round(value, digits)


def _attempt_ms(record: Mapping[str, Any]) -> float:
    """One fix attempt's own time (VPR, rerank, matcher, pose, integrity), ms, from its FDR record."""
    timings = record.get("timings_ms") or {}
    return float(sum(v for k, v in timings.items() if k != "estimator_fix" and isinstance(v, (int, float))))


def _since(t_unix_s: float | None, origin_unix_s: float) -> float | None:
    return None if t_unix_s is None else round(t_unix_s - origin_unix_s, 3)


def restart_recovery(
    restarts: Sequence[Mapping[str, float]],
    received: Sequence[ReceivedMessage],
    fdr_records: Sequence[Mapping[str, Any]] = (),
) -> list[dict[str, Any]]:
    """For each kill and restart (``killed_unix_s``, ``restarted_unix_s``: when the new process was
    started), what the autopilot side heard and what the restarted daemon recorded, until the next kill:

    - ``last_before_kill_s``, ``first_after_s``, ``first_3d_after_s``: GPS_INPUT (any fix type, fix_type
      3; GLOBAL_POSITION_SENSOR with PX4, ``position_messages``) around the kill, s after the kill;
    - ``first_after_start_s``, ``first_3d_after_start_s``: the same, s after the new process started;
    - ``prior_source``, ``prior_sigma_m``: the start-up prior it chose (FDR ``estimator.prior``; None
      when a navigator core was killed and its next start adopted the running vision worker);
    - ``worker_adopted``: the restarted core took over the vision worker its previous process had left
      running (its FDR ``core.worker`` record);
    - ``first_anchored_after_start_s``: its first accepted absolute fix (FDR ``pipeline.fix``), s after
      it started: re-acquisition; ``fix_attempts_to_anchor``: the attempts up to and including that one;
      ``fix_attempts``: all of its attempts; ``fix_attempt_ms``: their own time (p50, max), up to the
      anchoring one (all of them when none anchored).

    The FDR fields are None when the FDR holds nothing of that run (a full disk)."""
    gps = [(m.recv_time_unix_s, int(m.fields["fix_type"])) for m in position_messages(received)]
    kills = [float(r["killed_unix_s"]) for r in restarts]
    out = []
    for i, r in enumerate(restarts):
        kill, start = float(r["killed_unix_s"]), float(r["restarted_unix_s"])
        until = kills[i + 1] if i + 1 < len(kills) else math.inf
        before = [t for t, _ in gps if t <= kill]
        after = [(t, ft) for t, ft in gps if kill < t <= until]

        first = after[0][0] if after else None
        first_3d = next((t for t, ft in after if ft >= 3), None)
        run = sorted(
            (x for x in fdr_records if start <= float(x.get("t_unix_s", -math.inf)) <= until),
            key=lambda x: float(x["t_unix_s"]),
        )
        prior = next((x for x in run if x.get("kind") == FdrKind.PRIOR), None)
        attempts = [x for x in run if x.get("kind") == FdrKind.FIX]
        n_anchor = next((k + 1 for k, x in enumerate(attempts) if x.get("fix_accepted")), None)
        upto = attempts[:n_anchor] if n_anchor is not None else attempts
        cost = [_attempt_ms(x) for x in upto]
        out.append(
            {
                **r,
                "last_before_kill_s": _since(before[-1], kill) if before else None,
                "first_after_s": _since(first, kill),
                "first_3d_after_s": _since(first_3d, kill),
                "first_after_start_s": _since(first, start),
                "first_3d_after_start_s": _since(first_3d, start),
                "prior_source": prior.get("source") if prior is not None else None,
                "prior_sigma_m": prior.get("sigma_m") if prior is not None else None,
                "worker_adopted": (
                    any(x.get("kind") == FdrKind.CORE_WORKER and x.get("event") == "adopted" for x in run)
                    if run
                    else None
                ),
                "first_anchored_after_start_s": (
                    _since(float(attempts[n_anchor - 1]["t_unix_s"]), start) if n_anchor is not None else None
                ),
                "fix_attempts_to_anchor": n_anchor,
                "fix_attempts": len(attempts) if run else None,
                "fix_attempt_ms": {"p50": _pct(cost, 50), "max": max(cost, default=None)},
            }
        )
    return out


#: How long after the vision worker is back a kill's stretch runs on (``worker_kill_recovery``), s.
WORKER_KILL_SETTLE_S: Final[float] = 10.0


def worker_kill_recovery(
    kills_unix_s: Sequence[float],
    received: Sequence[ReceivedMessage],
    fdr_records: Sequence[Mapping[str, Any]] = (),
) -> list[dict[str, Any]]:
    """For each kill of the vision worker (its navigator core lives on): when the core said the worker was
    back (FDR ``core.worker`` ``back``; ``back_after_s``), the restarted worker's start-up prior
    (``prior_source``: ``core_handover`` when it took the core's filter), and over the stretch the kill
    touched (from 1 s before it to ``WORKER_KILL_SETTLE_S`` after the worker was back, or to the next
    kill): the longest interval between the autopilot's position messages (``max_interval_ms``), the
    lowest fix_type sent after the kill (``min_fix_type``) and the most the stated accuracy of a 3D one
    grew to (``max_horiz_accuracy_m``)."""
    gps = [
        (m.recv_time_unix_s, int(m.fields["fix_type"]), float(m.fields.get("horiz_accuracy", math.nan)))
        for m in position_messages(received)
    ]
    out = []
    for i, kill in enumerate(kills_unix_s):
        until = kills_unix_s[i + 1] if i + 1 < len(kills_unix_s) else math.inf
        back = next(
            (
                r
                for r in fdr_records
                if r.get("kind") == FdrKind.CORE_WORKER
                and r.get("event") == "back"
                and kill < float(r.get("t_unix_s", -math.inf)) <= until
            ),
            None,
        )
        prior = next(
            (
                r
                for r in fdr_records
                if r.get("kind") == FdrKind.PRIOR and kill < float(r.get("t_unix_s", -math.inf)) <= until
            ),
            None,
        )
        if back is not None:
            until = min(until, float(back["t_unix_s"]) + WORKER_KILL_SETTLE_S)
        window = [g for g in gps if kill - 1.0 <= g[0] <= until]
        times = [t for t, _, _ in window]
        after = [g for g in window if g[0] > kill]
        out.append(
            {
                "killed_unix_s": kill,
                "max_interval_ms": round(1000.0 * max(np.diff(times)), 1) if len(times) > 1 else None,
                "min_fix_type": min((ft for _, ft, _ in after), default=None),
                "max_horiz_accuracy_m": max((acc for _, ft, acc in after if ft >= 3), default=None),
                "back_after_s": _since(float(back["t_unix_s"]), kill) if back is not None else None,
                "prior_source": prior.get("source") if prior is not None else None,
            }
        )
    return out
