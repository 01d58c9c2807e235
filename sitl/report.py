"""Scoring a SITL flight: what the autopilot side received, against the scenario's truth.

Definitions (also in the README):
- ``horizontal_error_m``: great-circle distance between each GPS_INPUT with fix_type >= 3 and the
  truth at the GPS_INPUT's ``time_usec`` (the daemon stamps the exposure time of the frame it used).
- ``latency_ms``: per frame, GPS_INPUT receive time minus the frame's exposure time.
- ``availability``: over frames exposed after the first fix was received, the fraction for which
  the autopilot side received a GPS_INPUT with fix_type >= 3 within 1 s after the exposure.
- ``provenance_counts``: the daemon's provenance (NAMED_VALUE_INT GDN_PROV, sent right after each
  GPS_INPUT) per answered frame.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gps_denied_onboard.constants import NV_PROVENANCE, Provenance
from gps_denied_onboard.geo import haversine_m
from gps_denied_onboard.sitl.autopilot import ReceivedMessage

AVAILABILITY_WINDOW_S = 1.0
_PROV_BY_CODE = {p.code: p.value for p in Provenance}


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


def score(
    frames: Sequence[SentFrame],
    received: Sequence[ReceivedMessage],
    truth_at_unix: Callable[[float], tuple[float, float]],
) -> dict[str, Any]:
    """Build the report dict. ``truth_at_unix(t)`` -> (lat_deg, lon_deg) of the truth at Unix time t."""
    gps: list[tuple[ReceivedMessage, str | None]] = []
    pending: ReceivedMessage | None = None
    for m in received:
        if m.type == "GPS_INPUT":
            if pending is not None:
                gps.append((pending, None))
            pending = m
        elif m.type == "NAMED_VALUE_INT" and m.fields.get("name") == NV_PROVENANCE and pending is not None:
            gps.append((pending, _PROV_BY_CODE.get(int(m.fields["value"]), "unknown")))
            pending = None
    if pending is not None:
        gps.append((pending, None))

    by_time = {int(m.fields["time_usec"]): (m, prov) for m, prov in gps}
    fixes = [(m, prov) for m, prov in gps if int(m.fields["fix_type"]) >= 3]
    errors = []
    for m, _ in fixes:
        lat_t, lon_t = truth_at_unix(int(m.fields["time_usec"]) / 1e6)
        errors.append(float(haversine_m(lat_t, lon_t, m.fields["lat"] / 1e7, m.fields["lon"] / 1e7)))

    first_fix_unix = min((m.recv_time_unix_s for m, _ in fixes), default=None)
    fix_recv = np.array(sorted(m.recv_time_unix_s for m, _ in fixes))
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
        }
        hit = by_time.get(f.exposure_time_unix_usec)
        if hit is not None:
            m, prov = hit
            latency = (m.recv_time_unix_s - t_exp) * 1000.0
            latencies.append(latency)
            prov_counts[prov or "unknown"] += 1
            fx = m.fields
            row.update(
                {
                    "est_lat_deg": fx["lat"] / 1e7,
                    "est_lon_deg": fx["lon"] / 1e7,
                    "fix_type": int(fx["fix_type"]),
                    "horiz_accuracy_m": float(fx["horiz_accuracy"]),
                    "provenance": prov,
                    "latency_ms": round(latency, 1),
                    "horizontal_error_m": round(
                        float(haversine_m(f.lat_deg, f.lon_deg, fx["lat"] / 1e7, fx["lon"] / 1e7)), 3
                    ),
                }
            )
        else:
            row.update(
                {"est_lat_deg": None, "fix_type": None, "provenance": None, "horizontal_error_m": None}
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
        "latency_ms": {"p50": _pct(latencies, 50), "p95": _pct(latencies, 95)},
        "provenance_counts": dict(sorted(prov_counts.items())),
        "gps_input_received": len(gps),
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
