"""``gdnav bench flights``: real SITL flights per row, the figures taken from each flight's own report,
a row that cannot fly reported as such, and ``--resume`` reusing what was flown."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from daemon_harness import build_small_cache
from gps_denied_onboard.bench.flights import (
    COLUMNS,
    LEFT_OUT,
    Flight,
    FlightPlanError,
    default_flights,
    row_from_report,
    run_flights_benchmark,
    select_flights,
)
from gps_denied_onboard.cli import main


def test_the_plan_names_every_bundled_scenario_but_those_left_out(tmp_path: Path) -> None:
    bundled = {p.stem for p in (Path(__file__).parents[1] / "sitl" / "scenarios").glob("*.yaml")}
    planned = {f.scenario for f in default_flights(tmp_path)}
    assert planned == bundled - set(LEFT_OUT)
    assert set(LEFT_OUT) >= {"soak", "autopilot_square", "autopilot_restart", "px4_square", "px4_restart"}


def test_a_flight_whose_imagery_is_missing_is_refused_by_name(tmp_path: Path) -> None:
    with pytest.raises(FlightPlanError, match=r"naip_cross_date_2020: imagery .*20090818\.tif not found"):
        select_flights(default_flights(tmp_path), ["smoke", "naip_cross_date_2020"])
    with pytest.raises(FlightPlanError, match=r"'soak' .*20 minutes"):
        select_flights(default_flights(tmp_path), ["soak"])
    assert main(["bench", "flights", "--shared", str(tmp_path), "--flights", "map_gap"]) == 2


@pytest.mark.sitl
@pytest.mark.slow
def test_bench_flights_flies_each_row_and_resumes(tmp_path: Path) -> None:
    """Two rows: one flown (classical over the small procedural map), one whose daemon refuses to start
    (xfeat with an empty model directory) and is reported as not flown. Resuming flies nothing again."""
    map_path, _cache = build_small_cache(tmp_path / "map")
    empty_models = tmp_path / "no_models"
    empty_models.mkdir()
    flights = [Flight("smoke", "smoke", map_path)]
    lines: list[str] = []
    figures = run_flights_benchmark(
        flights,
        ["classical", "xfeat"],
        tmp_path / "out",
        overrides=(f"matcher.model_dir={empty_models}",),
        echo=lines.append,
    )
    flown, refused = figures["rows"]
    report = json.loads(Path(flown["report"]).read_text())
    assert {k: v for k, v in flown.items() if k not in ("wall_s", "report")} == row_from_report(
        "smoke", "classical", report
    )
    assert flown["daemon_exit_code"] == 0 and flown["matcher_in_use"] == "classical"
    assert flown["accepted_fixes"] > 10 and flown["accepted_fixes_beyond_3sigma"] == 0
    assert flown["gps_input_3d"] > 50 and flown["gps_input_beyond_3sigma"] == 0
    assert 0.5 < flown["anchored_share"] <= 1.0
    assert flown["latency_p50_ms"] is not None and flown["fix_age_p95_ms"] is not None
    assert refused["strategy"] == "xfeat" and "before it was ready" in refused["error"]
    assert figures["not_flown"] == ["smoke/xfeat"]
    assert figures["accepted_fixes_beyond_3sigma"] == 0 and figures["gps_input_beyond_3sigma"] == 0
    assert lines[1] == COLUMNS and lines[2].startswith("smoke                  classical")
    assert "not flown" in lines[3]

    mtime = Path(flown["report"]).stat().st_mtime_ns
    again = run_flights_benchmark(flights, ["classical"], tmp_path / "out", resume=True, echo=lambda _: None)
    assert Path(flown["report"]).stat().st_mtime_ns == mtime
    assert again["rows"][0]["accepted_fixes"] == flown["accepted_fixes"]
