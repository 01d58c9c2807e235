"""``gdnav bench flights``: the bundled scenarios flown with each matcher strategy, one table.

Every row is one real ``gdnav sitl run`` flight (``sitl.runner.run_sitl``: the daemon as its own process,
frames over TCP, MAVLink over UDP on loopback), with ``matcher.strategy`` set to the row's strategy and
nothing else changed but the caller's ``--set`` overrides. The figures are the flight report's own:

- integrity: fix attempts, accepted fixes and how many of those were farther from the truth than 3 of
  their own stated sigmas (``analysis.accepted_fixes_beyond_3sigma``, the worst in sigmas), and the same
  for every GPS_INPUT the autopilot received with a 3D fix (``consistency``);
- accuracy: horizontal error p50 / p95 of those GPS_INPUTs;
- latency: frame exposure to GPS_INPUT p50 / p95, and the accepted fixes' age when fused p50 / p95;
- provenance: the share of answered frames labelled ``satellite_anchored``.

Rows run one after another (a flight needs the machine's cores to itself to keep its frame rate) and
each keeps its report, PNG, FDR and daemon log under ``OUT/<flight>/<strategy>/``. The map caches are
shared between the rows of one map (``OUT/caches``). ``--resume`` reuses a row whose report is already
there, so a matrix of hours can be flown in parts.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

#: Strategies flown when none are named: the weights-free one and the three learned ones.
DEFAULT_STRATEGIES: Final[tuple[str, ...]] = ("classical", "xfeat", "aliked_lightglue", "disk_lightglue")
#: Scenarios not in the default plan, and why.
LEFT_OUT: Final[dict[str, str]] = {
    "soak": "20 minutes per strategy: fly it on its own (docs/benchmarks.md, Soak)",
    "autopilot_square": "needs an autopilot (gdnav sitl run --autopilot)",
    "autopilot_restart": "needs an autopilot (gdnav sitl run --autopilot)",
    "autopilot_worker_crash": "needs an autopilot (gdnav sitl run --autopilot)",
    "px4_square": "needs PX4 (gdnav sitl run --autopilot)",
    "px4_restart": "needs PX4 (gdnav sitl run --autopilot)",
    "px4_worker_crash": "needs PX4 (gdnav sitl run --autopilot)",
}
_NAIP: Final = ("data", "naip_timeseries", "naip")
_GEOVISION: Final = ("data", "geovision_india", "geovision_india_z18.tif")
_NAIP_2009: Final = "m_4709963_se_14_1_20090818.tif"


class FlightPlanError(ValueError):
    """A flight of the plan cannot be flown (unknown name, missing imagery)."""


@dataclass(frozen=True)
class Flight:
    """One scenario over one map; ``appearance_path`` renders the frames from another image (date)."""

    name: str
    scenario: str
    map_path: Path | None  # None: the embedded procedural demo map
    appearance_path: Path | None = None


def default_flights(shared: Path) -> list[Flight]:
    """The bundled scenarios over the maps the tests fly them on (``shared``: the ``../shared`` folder).

    The fault scenarios fly over the procedural demo map, the real-imagery ones (the autopilot's attitude
    going wrong among them) over GeoVision India,
    and the cross-date ones over NAIP 2009 with frames from 2020 and from 2014 (the attitude going wrong
    at 1200 m AGL with frames from 2020).
    """
    geovision = shared.joinpath(*_GEOVISION)
    naip = shared.joinpath(*_NAIP)
    return [
        Flight("smoke", "smoke", None),
        Flight("demo", "demo", None),
        Flight("restart", "restart", None),
        Flight("clock_faults", "clock_faults", None),
        Flight("faults", "faults", None),
        Flight("spoofed_start", "spoofed_start", None),
        Flight("spoofed_home", "spoofed_home", None),
        Flight("nominal_real", "nominal_real", geovision),
        Flight("map_gap", "map_gap", geovision),
        Flight("wrong_tile_trap", "wrong_tile_trap", geovision),
        Flight("link_drop", "link_drop", geovision),
        Flight("attitude_offset", "attitude_offset", geovision),
        Flight(
            "naip_cross_date_2020",
            "naip_cross_date",
            naip / _NAIP_2009,
            naip / "m_4709963_se_14_1_20200831.tif",
        ),
        Flight(
            "naip_cross_date_2014",
            "naip_cross_date",
            naip / _NAIP_2009,
            naip / "m_4709963_se_14_1_20140720.tif",
        ),
        Flight(
            "naip_cross_date_attitude",
            "naip_cross_date_attitude",
            naip / _NAIP_2009,
            naip / "m_4709963_se_14_1_20200831.tif",
        ),
    ]


def select_flights(plan: Sequence[Flight], names: Sequence[str] | None) -> list[Flight]:
    """The flights of ``plan`` named in ``names`` (all when None), their imagery checked to exist."""
    by_name = {f.name: f for f in plan}
    chosen = list(plan) if not names else []
    for name in names or ():
        if name not in by_name:
            why = f" ({LEFT_OUT[name]})" if name in LEFT_OUT else ""
            raise FlightPlanError(f"unknown flight {name!r}{why}; expected some of {', '.join(by_name)}")
        chosen.append(by_name[name])
    for f in chosen:
        for path in (f.map_path, f.appearance_path):
            if path is not None and not path.is_file():
                raise FlightPlanError(f"flight {f.name}: imagery {path} not found (pass --shared DIR)")
    return chosen


def row_from_report(flight: str, strategy: str, report: dict[str, Any]) -> dict[str, Any]:
    """The table's figures for one flight report (``sitl.runner.run_sitl``'s)."""
    analysis, cons = report["analysis"], report["consistency"]
    prov = report["provenance_counts"]
    answered = sum(v for k, v in prov.items() if k != "unknown")
    return {
        "flight": flight,
        "strategy": strategy,
        "matcher_in_use": report.get("matcher"),
        "daemon_exit_code": report["daemon_exit_code"],
        "frames": report["frames"],
        "fix_attempts": analysis["fdr_fix_attempts"],
        "accepted_fixes": analysis["accepted_fixes"],
        "accepted_fixes_beyond_3sigma": analysis["accepted_fixes_beyond_3sigma"],
        "max_accepted_fix_error_sigma": analysis["max_accepted_fix_error_sigma"],
        "integrity_refused": analysis["integrity_refused"],
        "no_fix_reasons": analysis["no_fix_reasons"],
        "gps_input_3d": report["horizontal_error_m"]["n"],
        "gps_input_beyond_3sigma": cons["beyond_3sigma"],
        "gps_input_max_error_sigma": cons["max_error_sigma"],
        "gps_input_within_1sigma": cons["within_1sigma"],
        "horizontal_error_p50_m": report["horizontal_error_m"]["p50"],
        "horizontal_error_p95_m": report["horizontal_error_m"]["p95"],
        "latency_p50_ms": report["latency_ms"]["p50"],
        "latency_p95_ms": report["latency_ms"]["p95"],
        "fix_age_p50_ms": report["fix_age_ms"]["p50"],
        "fix_age_p95_ms": report["fix_age_ms"]["p95"],
        "anchored_share": prov.get("satellite_anchored", 0) / answered if answered else None,
        "availability": report["availability"],
    }


def _fmt(v: Any, spec: str = ".0f") -> str:
    return "-" if v is None else format(v, spec)


COLUMNS: Final[str] = (
    f"{'flight':<22} {'strategy':<17} {'exit':>4} {'att':>4} {'acc':>4} {'>3σ':>4} {'worst':>6} "
    f"{'3D out':>6} {'>3σ':>4} {'worst':>6} {'p50 m':>7} {'p95 m':>7} {'lat p50/p95 ms':>15} "
    f"{'fix age p50/p95 ms':>19} {'anch':>5}"
)


def format_row(r: dict[str, Any]) -> str:
    lat = f"{_fmt(r['latency_p50_ms'])}/{_fmt(r['latency_p95_ms'])}"
    age = f"{_fmt(r['fix_age_p50_ms'])}/{_fmt(r['fix_age_p95_ms'])}"
    strategy = r["strategy"] if r["matcher_in_use"] in (None, r["strategy"]) else f"{r['strategy']}!"
    return (
        f"{r['flight']:<22} {strategy:<17} {r['daemon_exit_code']:>4} {r['fix_attempts']:>4} "
        f"{r['accepted_fixes']:>4} {r['accepted_fixes_beyond_3sigma']:>4} "
        f"{_fmt(r['max_accepted_fix_error_sigma'], '.2f'):>6} {r['gps_input_3d']:>6} "
        f"{r['gps_input_beyond_3sigma']:>4} {_fmt(r['gps_input_max_error_sigma'], '.2f'):>6} "
        f"{_fmt(r['horizontal_error_p50_m'], '.2f'):>7} {_fmt(r['horizontal_error_p95_m'], '.2f'):>7} "
        f"{lat:>15} {age:>19} {_fmt(r['anchored_share'], '.2f'):>5}"
    )


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)


def run_flights_benchmark(
    flights: Sequence[Flight],
    strategies: Sequence[str],
    out: Path,
    *,
    overrides: Sequence[str] = (),
    config_path: Path | None = None,
    resume: bool = False,
    echo: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Fly every flight with every strategy and return the figures (rows in flight-major order).

    A flight the SITL cannot fly (``SitlError``: a model missing for the strategy, a host fault that
    needs root) is a row with its ``error`` and no figures, and the matrix goes on.
    """
    from gps_denied_onboard.sitl.runner import SitlError, SitlOptions, run_sitl

    started = dt.datetime.now(dt.timezone.utc)
    cpu = platform.processor() or platform.machine()
    load = [round(v, 2) for v in os.getloadavg()]
    when = started.isoformat(timespec="seconds")
    echo(f"bench flights - {when} - {cpu}, {os.cpu_count()} CPUs (load average {load} at start)")
    echo(COLUMNS)
    rows: list[dict[str, Any]] = []
    for flight in flights:
        for strategy in strategies:
            row_dir = out / _safe(flight.name) / _safe(strategy)
            report_path = row_dir / "report.json"
            t0 = time.monotonic()
            if resume and report_path.is_file():
                report = json.loads(report_path.read_text())
            else:
                try:
                    report = run_sitl(
                        SitlOptions(
                            map_path=flight.map_path,
                            scenario=flight.scenario,
                            report_path=report_path,
                            appearance_path=flight.appearance_path,
                            config_path=config_path,
                            overrides=(*overrides, f"matcher.strategy={strategy}"),
                            workdir=row_dir / "work",
                            cache_root=out / "caches",
                            quiet=True,
                        )
                    )
                except SitlError as exc:
                    rows.append({"flight": flight.name, "strategy": strategy, "error": str(exc)})
                    echo(f"{flight.name:<22} {strategy:<17} not flown: {exc}")
                    continue
            row = row_from_report(flight.name, strategy, report)
            row["wall_s"] = round(time.monotonic() - t0, 1)
            row["report"] = str(report_path)
            rows.append(row)
            echo(format_row(row))
    flown = [r for r in rows if "error" not in r]
    return {
        "started_utc": started.isoformat(timespec="seconds"),
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
        },
        "overrides": list(overrides),
        "strategies": list(strategies),
        "rows": rows,
        "accepted_fixes_beyond_3sigma": sum(r["accepted_fixes_beyond_3sigma"] for r in flown),
        "gps_input_beyond_3sigma": sum(r["gps_input_beyond_3sigma"] for r in flown),
        "not_flown": [f"{r['flight']}/{r['strategy']}" for r in rows if "error" in r],
    }
