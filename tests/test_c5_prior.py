"""C5 start-up prior (F8): resume from the FDR with an honest sigma, start points only where they are
true, and the whole map when nothing is trustworthy."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from gps_denied_onboard.components.c5_estimator.prior import (
    InitialPrior,
    PreviousRun,
    PriorSource,
    ResumeState,
    choose_prior,
    read_previous_run,
    with_resume_state,
)
from gps_denied_onboard.components.c5_estimator.resume_state import ResumeStateFile, read_resume_state
from gps_denied_onboard.components.c8_mavlink.messages import DIALECT
from gps_denied_onboard.components.c8_mavlink.vehicle_state import (
    AutopilotPosition,
    FlightPhase,
    GroundPosition,
)
from gps_denied_onboard.components.c13_fdr import FlightDataRecorder, read_records_newest_first
from gps_denied_onboard.config import InitConfig
from gps_denied_onboard.geo import haversine_m

NOW = 1_800_000_000_000_000
HOME = (47.0, 8.0, 400.0)
MAP = {"map_centre_lat_lon": (47.001, 8.001), "map_radius_m": 900.0}
NO_RUN = PreviousRun(None, None)


def _resume(age_s: float, sigma_m: float = 2.0) -> PreviousRun:
    t = NOW - round(age_s * 1e6)
    return PreviousRun(ResumeState(47.002, 8.003, sigma_m, t), t / 1e6)


def test_prior_resumes_last_3d_estimate_with_sigma_grown_by_top_speed() -> None:
    """Restarted 4 s after the last 3D estimate (sigma 2 m): sigma = hypot(2, 25 m/s x 4 s) ~ 100 m."""
    prior = choose_prior(
        now_unix_usec=NOW, init=InitConfig(), previous=_resume(4.0), home=HOME, alt_agl_m=120.0, **MAP
    )
    assert prior.source == PriorSource.RESUMED
    assert (prior.lat_deg, prior.lon_deg) == (47.002, 8.003)
    assert prior.sigma_m == pytest.approx(math.hypot(2.0, 100.0))


def test_prior_restarted_in_flight_never_claims_home_with_its_small_sigma() -> None:
    """The defect: killed 250 m from home with nothing to resume from, the daemon started at home with
    30 m sigma. In the air after a restart, home is ignored: the whole map, a sigma that covers it."""
    stale = _resume(600.0)  # the last 3D estimate is too old to resume, but the run was 2 s ago
    previous = PreviousRun(stale.last_3d, NOW / 1e6 - 2.0)
    prior = choose_prior(
        now_unix_usec=NOW, init=InitConfig(sigma_m=30.0), previous=previous, home=HOME, alt_agl_m=120.0, **MAP
    )
    assert prior.source == PriorSource.MAP_EXTENT
    assert prior.sigma_m == 900.0
    assert "in the air after a restart" in prior.why and "old" in prior.why


def test_prior_cold_start_and_ground_restart_use_home() -> None:
    """Cold start on the ground (<= 10 m above home): home with init.sigma_m. After a restart on the
    ground home is right again."""
    cold = choose_prior(
        now_unix_usec=NOW, init=InitConfig(), previous=NO_RUN, home=HOME, alt_agl_m=0.3, **MAP
    )
    assert cold.source == PriorSource.HOME and cold.sigma_m == 50.0 and cold.why == "on the ground"
    previous = PreviousRun(None, NOW / 1e6 - 5.0)
    ground = choose_prior(
        now_unix_usec=NOW, init=InitConfig(), previous=previous, home=HOME, alt_agl_m=0.5, **MAP
    )
    assert ground.source == PriorSource.HOME and ground.why == "on the ground"
    unknown = choose_prior(
        now_unix_usec=NOW, init=InitConfig(), previous=previous, home=HOME, alt_agl_m=None, **MAP
    )
    assert unknown.source == PriorSource.MAP_EXTENT  # height unknown: not known to be on the ground


def test_prior_configured_position_follows_the_same_rules_as_home() -> None:
    """A configured start position wins over home, but only on the ground: in the air, with or without
    a previous run, it is ignored. (Home 27 m away agrees with it: see the cross-checks below.)"""
    init = InitConfig(lat_deg=47.0002, lon_deg=8.0002, sigma_m=20.0)
    cold = choose_prior(now_unix_usec=NOW, init=init, previous=NO_RUN, home=HOME, alt_agl_m=1.0, **MAP)
    assert (cold.source, cold.lat_deg, cold.sigma_m) == (PriorSource.CONFIG, 47.0002, 20.0)
    assert "agree" in cold.why and not cold.confirmed
    for previous in (NO_RUN, PreviousRun(None, NOW / 1e6 - 1.0)):
        air = choose_prior(now_unix_usec=NOW, init=init, previous=previous, home=HOME, alt_agl_m=80.0, **MAP)
        assert air.source == PriorSource.MAP_EXTENT and "config ignored: in the air" in air.why


def _phase(
    armed: bool | None = None, landed: int | None = None, ground_ago_s: float | None = None
) -> FlightPhase:
    ground = None if ground_ago_s is None else NOW / 1e6 - ground_ago_s
    return FlightPhase(armed, landed, ground)


@pytest.mark.parametrize(
    ("alt_agl_m", "phase"),
    [
        (120.0, None),  # 120 m above home, nothing else known
        (None, _phase(True, DIALECT.MAV_LANDED_STATE_IN_AIR)),  # no height, but landed_state says flying
        (3.0, _phase(True, DIALECT.MAV_LANDED_STATE_IN_AIR)),  # low, but flying
        (120.0, _phase(False, DIALECT.MAV_LANDED_STATE_ON_GROUND)),  # a flying height wins over the rest
    ],
)
def test_prior_in_the_air_with_no_record_covers_the_map_never_home(
    alt_agl_m: float | None, phase: FlightPhase | None
) -> None:
    """Issue 27 defect: a start in the air with no record (full FDR disk, past the resume window) used
    home with init.sigma_m as a "cold start". In the air with nothing to resume: the whole map."""
    for previous in (NO_RUN, PreviousRun(_resume(600.0).last_3d, NOW / 1e6 - 600.0)):
        prior = choose_prior(
            now_unix_usec=NOW,
            init=InitConfig(sigma_m=30.0),
            previous=previous,
            home=HOME,
            alt_agl_m=alt_agl_m,
            phase=phase,
            **MAP,  # type: ignore[arg-type]
        )
        assert prior.source == PriorSource.MAP_EXTENT, prior
        assert prior.sigma_m == 900.0 and "home_position ignored: in the air" in prior.why


def test_prior_on_the_ground_by_landed_state_or_disarmed_uses_home() -> None:
    """Height unknown: landed_state ON_GROUND, or a disarmed vehicle, is on the ground: home as before."""
    for phase in (_phase(True, DIALECT.MAV_LANDED_STATE_ON_GROUND), _phase(False, None)):
        prior = choose_prior(
            now_unix_usec=NOW,
            init=InitConfig(),
            previous=NO_RUN,
            home=HOME,
            alt_agl_m=None,
            phase=phase,
            **MAP,
        )
        assert prior.source == PriorSource.HOME and prior.sigma_m == 50.0, prior
    armed_only = choose_prior(
        now_unix_usec=NOW,
        init=InitConfig(),
        previous=NO_RUN,
        home=HOME,
        alt_agl_m=None,
        phase=_phase(True),
        **MAP,
    )
    assert armed_only.source == PriorSource.MAP_EXTENT  # armed says nothing of flying: not known
    assert "not known to be on the ground" in armed_only.why


def test_prior_in_the_air_after_this_run_saw_the_ground_grows_home_sigma_at_top_speed() -> None:
    """Seen on the ground by this run 4 s before its first frame: home, sigma hypot(30, 25 m/s x 4 s)."""
    prior = choose_prior(
        now_unix_usec=NOW,
        init=InitConfig(sigma_m=30.0),
        previous=NO_RUN,
        home=HOME,
        alt_agl_m=120.0,
        phase=_phase(True, DIALECT.MAV_LANDED_STATE_IN_AIR, ground_ago_s=4.0),
        **MAP,  # type: ignore[arg-type]
    )
    assert prior.source == PriorSource.HOME
    assert prior.sigma_m == pytest.approx(math.hypot(30.0, 100.0))


def test_prior_resumes_from_the_state_file_when_the_fdr_has_nothing(tmp_path: Path) -> None:
    """The FDR recorded nothing (full disk): the resume state file's last 3D estimate is resumed from."""
    store = ResumeStateFile(tmp_path / "resume_state.json")
    t = NOW - 3_000_000
    assert store.write(
        ResumeState(47.002, 8.003, 4.0, t), provenance="satellite_anchored", written_unix_s=t / 1e6
    )
    state = read_resume_state(store.path, NOW / 1e6)
    previous = with_resume_state(read_previous_run(read_records_newest_first(tmp_path / "fdr")), state)
    assert previous == PreviousRun(ResumeState(47.002, 8.003, 4.0, t), t / 1e6)
    prior = choose_prior(
        now_unix_usec=NOW, init=InitConfig(), previous=previous, home=HOME, alt_agl_m=120.0, **MAP
    )
    assert prior.source == PriorSource.RESUMED
    assert prior.sigma_m == pytest.approx(math.hypot(4.0, 75.0))
    older = PreviousRun(ResumeState(1.0, 1.0, 1.0, t - 10), t / 1e6)
    assert with_resume_state(older, state).last_3d == state  # the newer of the two wins
    assert with_resume_state(previous, None) == previous


def test_previous_run_is_read_newest_first_from_a_real_recorder(tmp_path: Path) -> None:
    """The newest mavlink.estimate with fix_type 3 and finite values is the resume state; a torn last
    line (a kill -9 mid-write) and later non-3D estimates do not hide it."""
    with FlightDataRecorder(tmp_path, max_bytes=1 << 20, segment_bytes=1 << 16) as fdr:
        for k in range(5):
            fdr.record(
                "mavlink.estimate",
                {
                    "time_unix_usec": NOW + k,
                    "fix_type": 3,
                    "lat_deg": 47.0 + k,
                    "lon_deg": 8.0,
                    "horiz_sigma_m": 1.5,
                },
            )
        fdr.record(
            "mavlink.estimate",
            {
                "time_unix_usec": NOW + 9,
                "fix_type": 3,
                "lat_deg": math.nan,
                "lon_deg": 8.0,
                "horiz_sigma_m": 1.0,
            },
        )
        fdr.record(
            "mavlink.estimate", {"time_unix_usec": NOW + 10, "fix_type": 1, "lat_deg": 1.0, "lon_deg": 1.0}
        )
        fdr.record("pipeline.frame", {"frame_seq": 99})
    seg = sorted(tmp_path.glob("fdr-*.jsonl"))[-1]
    with seg.open("ab") as f:
        f.write(b'{"kind": "mavlink.estimate", "fix_type": 3, "lat_de')  # torn
    previous = read_previous_run(read_records_newest_first(tmp_path))
    assert previous.last_3d is not None
    assert previous.last_3d.lat_deg == 51.0 and previous.last_3d.time_unix_usec == NOW + 4
    newest = json.loads(seg.read_bytes().splitlines()[-2])
    assert previous.last_record_unix_s == newest["t_unix_s"]
    assert read_previous_run(read_records_newest_first(tmp_path / "none")) == NO_RUN


def _autopilot(lat: float, lon: float, *, flags: int | None = None, age_s: float = 0.2) -> AutopilotPosition:
    good = DIALECT.EKF_ATTITUDE | DIALECT.EKF_VELOCITY_HORIZ | DIALECT.EKF_POS_HORIZ_ABS
    return AutopilotPosition(
        lat, lon, (20.0, 0.0), NOW - round(age_s * 1e6), good if flags is None else flags
    )


def _after_restart(
    previous: PreviousRun, autopilot: AutopilotPosition | None, alt_agl_m: float = 120.0
) -> InitialPrior:
    return choose_prior(
        now_unix_usec=NOW,
        init=InitConfig(),
        previous=previous,
        home=HOME,
        alt_agl_m=alt_agl_m,
        autopilot=autopilot,
        **MAP,  # type: ignore[arg-type]
    )


#: Killed 2 s ago, its last 3D estimate too old to resume from.
NOTHING_TO_RESUME = PreviousRun(_resume(600.0).last_3d, NOW / 1e6 - 2.0)


def test_prior_resumed_estimate_confirmed_by_the_autopilot_keeps_its_sigma() -> None:
    """The autopilot's estimate 60 m from the resumed one, inside its 3 sigma (~300 m): kept, and said."""
    alone = _after_restart(_resume(4.0), None)
    north_60m = 47.002 + 60.0 / 111_195.0
    prior = _after_restart(_resume(4.0), _autopilot(north_60m, 8.003))
    assert prior.source == PriorSource.RESUMED
    assert prior.sigma_m == alone.sigma_m
    assert "autopilot's estimate agrees (60 m away)" in prior.why


def test_prior_resumed_estimate_far_from_the_autopilot_covers_both() -> None:
    """2 km apart: one of the two is wrong and nothing says which, so the sigma grows to reach the
    autopilot's estimate (plus what 0.2 s of its age allows at top speed)."""
    base = math.hypot(2.0, 100.0)
    north_2km = 47.002 + 2000.0 / 111_195.0
    prior = _after_restart(_resume(4.0), _autopilot(north_2km, 8.003))
    assert prior.source == PriorSource.RESUMED
    assert (prior.lat_deg, prior.lon_deg) == (47.002, 8.003)
    assert prior.sigma_m == pytest.approx(base + 2000.0 + 25.0 * 0.2, abs=2.0)
    assert "2000 m away: sigma covers both" in prior.why


@pytest.mark.parametrize(
    "flags",
    [
        DIALECT.EKF_ATTITUDE | DIALECT.EKF_VELOCITY_VERT,  # no absolute horizontal position
        DIALECT.EKF_POS_HORIZ_ABS | DIALECT.EKF_CONST_POS_MODE,  # it has lost every position source
    ],
)
def test_prior_ignores_an_autopilot_estimate_its_ekf_does_not_vouch_for(flags: int) -> None:
    prior = _after_restart(NOTHING_TO_RESUME, _autopilot(47.0015, 8.0, flags=flags))
    assert prior.source == PriorSource.MAP_EXTENT
    assert (prior.lat_deg, prior.lon_deg) == MAP["map_centre_lat_lon"]


def test_prior_restart_with_nothing_of_its_own_searches_the_map_from_the_autopilot() -> None:
    """Nothing to resume from after a restart in flight: centred on the autopilot's estimate with a
    sigma that still covers the whole map from there (not a fix: far above the 3D limit)."""
    ap = _autopilot(47.0015, 8.0)
    prior = _after_restart(NOTHING_TO_RESUME, ap)
    assert prior.source == PriorSource.AUTOPILOT
    assert (prior.lat_deg, prior.lon_deg) == (ap.lat_deg, ap.lon_deg)
    d = float(haversine_m(47.001, 8.001, ap.lat_deg, ap.lon_deg))
    assert prior.sigma_m == pytest.approx(900.0 + d)
    assert "autopilot" in prior.why


def test_prior_cold_start_does_not_use_the_autopilot_estimate() -> None:
    """No previous run, on the ground: home, the autopilot's estimate unused."""
    prior = _after_restart(NO_RUN, _autopilot(47.3, 8.3), alt_agl_m=0.0)
    assert prior.source == PriorSource.HOME


# --- issue 37: the start points cross-checked ---------------------------------------------------------

#: The autopilot's own position on the ground, 300 m north of HOME.
FAR_NORTH = (47.0 + 300.0 / 111_195.0, 8.0)


def _ground(lat_lon: tuple[float, float], sigma_m: float | None = 2.0) -> GroundPosition:
    return GroundPosition(lat_lon[0], lat_lon[1], NOW / 1e6 - 5.0, sigma_m)


def test_start_points_that_agree_are_picked_as_before_and_say_so() -> None:
    """Config, HOME and the autopilot's own position on the ground within their sigmas of each other:
    the configured position, at its sigma; a claim all the same (not confirmed: no 3D before a fix)."""
    init = InitConfig(lat_deg=47.0001, lon_deg=8.0, sigma_m=20.0)
    prior = choose_prior(
        now_unix_usec=NOW, init=init, previous=NO_RUN, home=HOME, alt_agl_m=0.5,
        autopilot_ground=_ground((47.00005, 8.0)), **MAP,
    )  # fmt: skip
    assert (prior.source, prior.lat_deg, prior.sigma_m) == (PriorSource.CONFIG, 47.0001, 20.0)
    assert "agree (within 11 m)" in prior.why and not prior.confirmed and prior.spread_m is None


def test_a_configured_start_300_m_from_home_is_a_wide_prior_not_a_pick() -> None:
    """The issue's reproduction: a configured start 300 m from HOME at a stated 30 m. Disagreeing beyond
    3 combined sigmas (127 m), neither is picked: the prior is centred between them and its sigma puts
    both within one sigma; in the air it grows at top speed since the ground as before."""
    init = InitConfig(lat_deg=FAR_NORTH[0], lon_deg=FAR_NORTH[1], sigma_m=30.0)
    prior = choose_prior(now_unix_usec=NOW, init=init, previous=NO_RUN, home=HOME, alt_agl_m=0.5, **MAP)
    assert prior.source == PriorSource.DISPUTED and not prior.confirmed
    assert prior.spread_m == pytest.approx(300.0, abs=1.0)
    assert prior.sigma_m == pytest.approx(150.0 + 30.0, abs=1.0)
    for point in (HOME[:2], FAR_NORTH):
        assert float(haversine_m(prior.lat_deg, prior.lon_deg, *point)) <= prior.sigma_m
    assert "config 300 m from HOME_POSITION (unsigned) (3 sigma 127 m)" in prior.why
    air = choose_prior(
        now_unix_usec=NOW, init=init, previous=NO_RUN, home=HOME, alt_agl_m=120.0,
        phase=_phase(landed=DIALECT.MAV_LANDED_STATE_IN_AIR, ground_ago_s=2.0), **MAP,
    )  # fmt: skip
    assert air.source == PriorSource.DISPUTED
    assert air.sigma_m == pytest.approx(math.hypot(180.0, 50.0), abs=1.0)


def test_an_unsigned_home_that_the_autopilot_contradicts_is_not_taken_with_a_small_sigma() -> None:
    """HOME is a claim: 300 m from the autopilot's own position (GNSS, 2 m stated), it makes a wide
    prior that covers both; signed, it is named so, and is still only a claim."""
    unsigned = choose_prior(
        now_unix_usec=NOW, init=InitConfig(sigma_m=30.0), previous=NO_RUN, home=HOME, alt_agl_m=0.5,
        autopilot_ground=_ground(FAR_NORTH), **MAP,
    )  # fmt: skip
    assert unsigned.source == PriorSource.DISPUTED and unsigned.sigma_m >= 150.0 + 30.0 - 1.0
    assert "HOME_POSITION (unsigned) 300 m from the autopilot's position (3 sigma 90 m)" in unsigned.why
    signed = choose_prior(
        now_unix_usec=NOW, init=InitConfig(sigma_m=30.0), previous=NO_RUN, home=HOME, alt_agl_m=0.5,
        autopilot_ground=_ground(FAR_NORTH), home_signed=True, **MAP,
    )  # fmt: skip
    assert signed.source == PriorSource.DISPUTED and "HOME_POSITION 300 m" in signed.why


def test_the_autopilots_stated_accuracy_sets_how_far_it_may_disagree() -> None:
    """50 m from HOME: within 3 sigma of a 30 m HOME and an autopilot stating 2 m (90 m); an autopilot
    stating nothing is given init.sigma_m."""
    near = (47.0 + 50.0 / 111_195.0, 8.0)
    for sigma in (2.0, None):
        prior = choose_prior(
            now_unix_usec=NOW, init=InitConfig(sigma_m=30.0), previous=NO_RUN, home=HOME, alt_agl_m=0.5,
            autopilot_ground=_ground(near, sigma), **MAP,
        )  # fmt: skip
        assert prior.source == PriorSource.HOME and prior.sigma_m == 30.0


def test_a_resumed_estimate_is_the_one_prior_confirmed_before_a_fix() -> None:
    """The previous run's own 3D output may go out as 3D at once after a restart (within its grown sigma);
    nothing else may before a map fix."""
    resumed = choose_prior(
        now_unix_usec=NOW, init=InitConfig(), previous=_resume(1.0), home=HOME, alt_agl_m=120.0, **MAP
    )
    assert resumed.source == PriorSource.RESUMED and resumed.confirmed
    home = choose_prior(
        now_unix_usec=NOW, init=InitConfig(), previous=NO_RUN, home=HOME, alt_agl_m=0.3, **MAP
    )
    assert home.source == PriorSource.HOME and not home.confirmed
