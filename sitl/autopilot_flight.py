"""``gdnav sitl run --autopilot URL``: the vehicle is an external autopilot SITL, not the scripted path.

The autopilot (a real ArduPilot SITL, or the project's emulator ``sitl.ap_emulator``) flies; this
module reads its true pose (ArduPilot SITL's SIMSTATE, else SIM_STATE, else the autopilot's own
GLOBAL_POSITION_INT + ATTITUDE, which is then its estimate, not the truth, and the report says so),
renders the nav frames at that pose, relays the daemon's MAVLink to the same autopilot
(``sitl.mission.AutopilotRelay``), flies the scenario's waypoints with the mission driver
(``sitl.mission.MissionDriver``: GNSS off after take-off, back on before landing) and scores what the
daemon sent against the truth, with the same report as the scripted flights (``sitl.report.score``).

Flight time 0 (for the scenario's ``link_drops``) is the take-off command. The scenario's waypoints
are resolved over the map as usual; its speed and altitude become WPNAV_SPEED and the take-off height.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from gps_denied_onboard.camera.stream import encode_frame
from gps_denied_onboard.camera.types import Attitude
from gps_denied_onboard.components.c13_fdr import read_records
from gps_denied_onboard.config import ConfigError, load_config
from gps_denied_onboard.constants import CORE_FDR_SUBDIR, FdrKind
from gps_denied_onboard.geo import haversine_m
from gps_denied_onboard.sitl.frame_server import FrameServer
from gps_denied_onboard.sitl.host_faults import CpuHogs, child_pids
from gps_denied_onboard.sitl.mission import (
    TRUTH_TYPES,
    AutopilotRelay,
    MissionDriver,
    MissionError,
    MissionPlan,
)
from gps_denied_onboard.sitl.photometric import PhotometricModel
from gps_denied_onboard.sitl.px4_mission import Px4MissionDriver, is_px4
from gps_denied_onboard.sitl.render import MapRenderer, RenderError
from gps_denied_onboard.sitl.report import (
    SentFrame,
    analyse,
    plot_report,
    restart_recovery,
    score,
    worker_kill_recovery,
)
from gps_denied_onboard.sitl.runner import (
    DAEMON_READY_TIMEOUT_S,
    DAEMON_STOP_TIMEOUT_S,
    DEFAULT_CONFIG,
    SitlError,
    SitlOptions,
    _Flight,
    _free_udp_port,
    _sha_prefix,
    daemon_ready,
    spawn_daemon,
)
from gps_denied_onboard.sitl.scenario import FaultKind, ScenarioError, load_scenario

#: The camera's height above the ground when the vehicle stands on it, m (the renderer needs > 0).
CAMERA_GROUND_HEIGHT_M = 0.3
#: How long to wait for the autopilot's first true pose, s.
TRUTH_TIMEOUT_S = 30.0


#: The shipped unit's RestartSec= (systemd/gdnav.service; tests/test_systemd_unit.py keeps them equal): a
#: restart on a real autopilot is flown with the gap it would have in the air, s.
UNIT_RESTART_SEC_S = 0.2


def _home_refusal(lat: float, lon: float, bbox: tuple[float, float, float, float], map_path: Path) -> str:
    west, south, east, north = bbox
    return (
        f"the vehicle's home ({lat:.6f}, {lon:.6f}) is off the map {map_path.name} "
        f"(lat {south:.6f}..{north:.6f}, lon {west:.6f}..{east:.6f}); start the autopilot SITL with "
        f"--home inside it, e.g. --home {(south + north) / 2:.6f},{(west + east) / 2:.6f},<ground alt m>,0"
    )


def run_sitl_with_autopilot(opts: SitlOptions, autopilot_url: str) -> dict[str, Any]:
    """Fly the scenario on the external autopilot at ``autopilot_url``; returns the report (also written
    to ``opts.report_path``). Raises SitlError (bad map/scenario/config, home off the map, no autopilot)
    and MissionError (the autopilot did not do what the mission needs)."""
    from gps_denied_onboard.components.c10_cache_build import CacheBuildError, build_cache_from_geotiff

    workdir = opts.workdir or opts.report_path.parent / "work"
    workdir.mkdir(parents=True, exist_ok=True)
    opts.report_path.parent.mkdir(parents=True, exist_ok=True)
    config_path = opts.config_path or DEFAULT_CONFIG
    if opts.map_path is None:
        raise SitlError("--autopilot needs --map (the map the autopilot's home must lie on)")
    try:
        daemon_nice = load_config(config_path, opts.overrides).daemon.process_nice
        scenario = load_scenario(opts.scenario)
        renderer = MapRenderer(opts.map_path)
    except (ConfigError, ScenarioError, RenderError) as exc:
        raise SitlError(str(exc)) from exc
    bbox = renderer.bbox_lonlat

    say = (lambda _m: None) if opts.quiet else (lambda m: print(f"[sitl] {m}", flush=True))
    daemon_port = _free_udp_port()
    t0: list[float] = []  # flight time 0: the take-off command

    def link_down(t_unix_s: float) -> bool:
        return bool(t0) and scenario.link_down_at(t_unix_s - t0[0])

    relay = AutopilotRelay(autopilot_url, daemon_port, link_down=link_down)
    try:
        return _fly(
            opts,
            autopilot_url,
            scenario,
            renderer,
            bbox,
            config_path,
            workdir,
            relay,
            t0,
            say,
            build_cache_from_geotiff,
            CacheBuildError,
            daemon_nice=daemon_nice,
        )
    finally:
        relay.close()


#: How long to wait for the autopilot's first HEARTBEAT, to choose the mission driver, s.
HEARTBEAT_TIMEOUT_S = 60.0


def _autopilot_is_px4(relay: AutopilotRelay, url: str) -> bool:
    """Whether the autopilot at ``url`` is PX4, from its HEARTBEAT (else it is flown as ArduPilot)."""
    deadline = time.time() + HEARTBEAT_TIMEOUT_S
    while time.time() < deadline:
        hb = relay.last("HEARTBEAT")
        if hb is not None and hb.get_srcComponent() == 1:
            return is_px4(hb)
        time.sleep(0.1)
    raise SitlError(f"no HEARTBEAT from the autopilot at {url} in {HEARTBEAT_TIMEOUT_S:.0f} s")


def _fly(
    opts: SitlOptions,
    url: str,
    scenario: Any,
    renderer: MapRenderer,
    bbox: Any,
    config_path: Path,
    workdir: Path,
    relay: AutopilotRelay,
    t0: list[float],
    say: Any,
    build_cache: Any,
    cache_error: Any,
    *,
    daemon_nice: int | None = None,
) -> dict[str, Any]:
    trajectory = scenario.resolve(bbox, 0.0)
    plan = MissionPlan(
        tuple((float(a), float(b)) for a, b in trajectory.waypoints_lat_lon_deg),
        alt_rel_m=scenario.alt_agl_m,
        speed_m_s=scenario.speed_m_s,
    )
    px4 = _autopilot_is_px4(relay, url)
    if px4:
        sensor_id = load_config(config_path, opts.overrides).mavlink.global_position_sensor_id
        driver: MissionDriver = Px4MissionDriver(relay, plan, say=say, sensor_id=sensor_id)
    else:
        driver = MissionDriver(relay, plan, say=say)
    driver.prepare()
    deadline = time.time() + TRUTH_TIMEOUT_S
    while (not relay.truth or relay.last("GLOBAL_POSITION_INT") is None) and time.time() < deadline:
        time.sleep(0.2)
    pose = relay.truth[-1] if relay.truth else None
    gp = relay.last("GLOBAL_POSITION_INT")
    if pose is None or gp is None:
        raise SitlError(f"no position from the autopilot at {url} in {TRUTH_TIMEOUT_S:.0f} s")
    west, south, east, north = bbox
    if not (south <= pose.lat_deg <= north and west <= pose.lon_deg <= east):
        raise SitlError(_home_refusal(pose.lat_deg, pose.lon_deg, bbox, opts.map_path or Path("?")))
    ground_alt = driver.ground_alt_amsl_m()
    say(
        f"autopilot at {url}: home {pose.lat_deg:.6f}, {pose.lon_deg:.6f}, ground {ground_alt:.1f} m AMSL, "
        f"truth from {relay.truth_source}"
    )

    cache_dir = workdir / f"cache-{_sha_prefix(opts.map_path)}"  # type: ignore[arg-type]
    try:
        build_cache(opts.map_path, cache_dir, progress=not opts.quiet)
    except cache_error as exc:
        raise SitlError(f"cannot build the cache from {opts.map_path}: {exc}") from exc
    import shutil

    shutil.rmtree(workdir / "fdr", ignore_errors=True)
    outputs = (
        ('mavlink.outputs=["global_position_sensor"]',)  # PX4: EKF2_AGP0_ID, checked by the driver
        if px4
        else ("mavlink.gps_input_gps_id=1",)  # GPS 2 = GPS_INPUT (GPS2_TYPE=14), the in-flight switch
    )
    overrides = (f"terrain.ground_alt_amsl_m={ground_alt}", *outputs, *opts.overrides)
    fopts = dataclasses.replace(opts, overrides=overrides)
    flight = _Flight(
        fopts, scenario, trajectory, renderer, config_path, cache_dir, workdir, ground_alt, daemon_nice
    )
    cmd = flight._daemon_cmd(relay.daemon_port, 0)
    frames: list[SentFrame] = []
    mission: dict[str, Any] = {}
    restarts: list[dict[str, float]] = []
    injected: list[dict[str, Any]] = []
    result = asyncio.run(
        _run_flight(
            flight,
            cmd,
            relay,
            driver,
            scenario,
            renderer,
            ground_alt,
            frames,
            t0,
            say,
            mission,
            restarts,
            injected,
        )
    )
    end_unix_s, exit_code, stop_s = result

    def truth_at_unix(t: float) -> tuple[float, float]:
        p = relay.truth_at(t)
        assert p is not None
        return p.lat_deg, p.lon_deg

    records = [*read_records(workdir / "fdr"), *read_records(workdir / "fdr" / CORE_FDR_SUBDIR)]
    gps_types = {1: 14}  # GPS 2 = GPS_INPUT
    times = {e["kind"]: e["t_unix_s"] for e in mission.get("log", [])}
    # with the GNSS back on (GPS_AUTO_SWITCH = 1) GPS 1 is primary again: GPS 2's silences trip nothing
    report = score(
        frames,
        relay.received,
        truth_at_unix,
        records,
        end_unix_s=end_unix_s,
        gps_types=gps_types,
        relied_on_until_unix_s=times.get("gnss_on"),
        autopilot="px4" if px4 else "ardupilot",
    )
    # the stretch where the vehicle flew on the daemon alone: GNSS off .. GNSS back on
    if "gnss_off" in times:
        lo, hi = times["gnss_off"], times.get("gnss_on", end_unix_s)
        off = score(
            [f for f in frames if lo <= f.exposure_time_unix_usec / 1e6 <= hi],
            [m for m in relay.received if lo <= m.recv_time_unix_s <= hi],
            truth_at_unix,
            records,
            end_unix_s=hi,
            gps_types=gps_types,
            autopilot="px4" if px4 else "ardupilot",
        )
        report["gnss_off"] = {k: v for k, v in off.items() if k not in ("per_frame", "statustext")}
        report["gnss_off"]["window_unix_s"] = [lo, hi]
        # the autopilot's own position (its EKF fusing GPS_INPUT) against the truth, over the same stretch
        ap_errors = [
            float(haversine_m(*truth_at_unix(t), lat, lon))
            for t, lat, lon in relay.autopilot_track
            if lo <= t <= hi and relay.truth_at(t) is not None
        ]
        report["gnss_off"]["autopilot_position_error_m"] = {
            "p50": float(np.percentile(ap_errors, 50)) if ap_errors else None,
            "p95": float(np.percentile(ap_errors, 95)) if ap_errors else None,
            "max": max(ap_errors, default=None),
            "n": len(ap_errors),
        }
    report["analysis"] = analyse(report, records, truth_at_unix)
    report.update(
        {
            "scenario": scenario.name,
            "map": str(opts.map_path),
            "autopilot": {
                "url": url,
                "kind": "px4" if px4 else "ardupilot",
                "truth_source": relay.truth_source,
                "truth_stamp_lead_s": _percentiles(relay.truth_stamp_lead_s),
                "truth_note": None
                if relay.truth_source in TRUTH_TYPES
                else "no SIMSTATE/SIM_STATE/HIL_STATE_QUATERNION: scored against the autopilot's own "
                "estimate, not the truth",
                "statustext": [{"t_unix_s": round(t, 3), "text": s} for t, s in relay.statustext],
            },
            "mission": mission,
            "matcher": None,
            "daemon_config": str(config_path),
            "daemon_overrides": list(overrides),
            "daemon_exit_code": exit_code,
            "daemon_stop_s": stop_s,
            "daemon_restarts": restart_recovery(restarts, relay.received, records),
            "worker_kills": worker_kill_recovery(
                [f["killed_unix_s"] for f in injected if f["kind"] == "worker_kill"], relay.received, records
            ),
            "faults_injected": injected,
            "t0_unix_s": t0[0] if t0 else None,
            "daemon_log": str(workdir / "daemon.log"),
            "fdr_dir": str(workdir / "fdr"),
        }
    )
    opts.report_path.write_text(json.dumps(report, indent=2, default=str))
    with contextlib.suppress(Exception):
        plot_report(report, opts.report_path.with_suffix(".png"), title=f"{scenario.name} on {url}")
    return report


async def _run_flight(
    flight: _Flight,
    cmd: list[str],
    relay: AutopilotRelay,
    driver: MissionDriver,
    scenario: Any,
    renderer: MapRenderer,
    ground_alt: float,
    frames: list[SentFrame],
    t0: list[float],
    say: Any,
    mission: dict[str, Any],
    restarts: list[dict[str, float]],
    injected: list[dict[str, Any]],
) -> tuple[float, int | None, float | None]:
    server = FrameServer()
    cam_port = await server.start()
    cmd = [c.replace("tcp://127.0.0.1:0", f"tcp://127.0.0.1:{cam_port}") for c in cmd]
    log_path = flight.workdir / "daemon.log"
    calib = flight.calib
    photometric = PhotometricModel(scenario.photometric)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()

    def render(index: int) -> tuple[bytes, SentFrame] | None:
        # the newest true pose, exposed at its own time (not interpolated forward to "now")
        pose = relay.truth[-1] if relay.truth else None
        gp = relay.last("GLOBAL_POSITION_INT")
        if pose is None or gp is None:
            return None
        agl = (pose.alt_amsl_m - ground_alt) if pose.alt_amsl_m is not None else gp.relative_alt / 1000.0
        agl = max(agl, CAMERA_GROUND_HEIGHT_M)
        img = renderer.render(
            calib, pose.lat_deg, pose.lon_deg, agl, Attitude(pose.roll_rad, pose.pitch_rad, pose.yaw_rad)
        )
        img = photometric.apply(img, index)
        now = pose.t_unix_s  # the exposure, on this host's clock (the camera's)
        stamp_us = round((now + scenario.camera_stamp_offset_s) * 1e6)  # a camera that stamps late
        ref = t0[0] if t0 else now
        return (
            encode_frame(img, seq=index, exposure_time_unix_usec=stamp_us),
            SentFrame(index, round(now * 1e6), now - ref, pose.lat_deg, pose.lon_deg, agl),
        )

    async def camera() -> None:
        period = 1.0 / scenario.frame_rate_hz
        next_t = time.time()
        index = 0
        while not stop.is_set():
            await asyncio.sleep(max(0.0, next_t - time.time()))
            next_t += period
            out = await loop.run_in_executor(None, render, index)
            if out is None:
                continue
            await server.send(out[0])
            if t0:  # scored from the take-off on
                frames.append(out[1])
            index += 1

    def fly_mission() -> None:
        driver.wait_ready()
        orig_event = driver._event

        def event(kind: str, **data: Any) -> None:
            if kind == "takeoff" and not t0:
                t0.append(time.time())
            orig_event(kind, **data)

        driver._event = event  # type: ignore[method-assign]
        mission.update(driver.fly())

    env = {**os.environ, "PYTHONUNBUFFERED": "1"}

    async def restarter(procs: list[subprocess.Popen[bytes]], log_file: Any) -> None:
        """SIGKILL the daemon at each of the scenario's restart times (s after the take-off) and start
        the same command again ``UNIT_RESTART_SEC_S`` later, as the shipped unit's Restart= does."""
        for at_s in scenario.daemon_restarts_s:
            while not t0:
                await asyncio.sleep(0.1)
            await asyncio.sleep(max(0.0, t0[0] + at_s - time.time()))
            old = procs[-1]
            t_kill = time.time()
            old.kill()
            await loop.run_in_executor(None, old.wait)
            await asyncio.sleep(UNIT_RESTART_SEC_S)
            procs.append(spawn_daemon(cmd, log_file, env, nice=flight.daemon_nice))
            restarts.append({"killed_unix_s": t_kill, "restarted_unix_s": time.time()})
            say(f"daemon killed (SIGKILL) at {at_s:.1f} s and restarted: pid {procs[-1].pid}")

    async def worker_killer(procs: list[subprocess.Popen[bytes]]) -> None:
        """SIGKILL the navigator core's vision worker at each of the scenario's ``worker_kills`` (s after
        the take-off); the core restarts it."""
        for at_s in scenario.worker_kills_s:
            while not t0:
                await asyncio.sleep(0.1)
            await asyncio.sleep(max(0.0, t0[0] + at_s - time.time()))
            workers = child_pids(procs[-1].pid) or _adopted_worker(flight.workdir / "fdr" / CORE_FDR_SUBDIR)
            for pid in workers:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            injected.append(
                {"kind": "worker_kill", "t_s": at_s, "killed_unix_s": time.time(), "pids": workers}
            )
            say(f"vision worker killed (SIGKILL) at {at_s:.1f} s: pids {workers}")

    hogs = CpuHogs()

    async def host_load() -> None:
        """The scenario's ``cpu_hogs`` windows (s after the take-off): the one fault of the daemon's host
        a flight against an external autopilot injects (``sitl.host_faults``)."""
        events = sorted(
            [(f.from_s, True, f) for f in scenario.faults if f.kind is FaultKind.CPU_HOGS]
            + [(f.to_s, False, f) for f in scenario.faults if f.kind is FaultKind.CPU_HOGS],
            key=lambda e: (e[0], e[1]),
        )
        for at_s, start, fault in events:
            while not t0:
                await asyncio.sleep(0.1)
            await asyncio.sleep(max(0.0, t0[0] + at_s - time.time()))
            entry = hogs.start(fault.processes) if start else hogs.stop()
            injected.append(
                {"kind": fault.kind.value, "t_s": at_s, "phase": "start" if start else "end", **entry}
            )
            say(f"{fault.kind.value} {'on' if start else 'off'} at {at_s:.1f} s: {entry}")

    with log_path.open("wb") as log_file:
        procs = [spawn_daemon(cmd, log_file, env, nice=flight.daemon_nice)]
        proc = procs[0]
        cam_task = asyncio.create_task(camera())
        restart_task = asyncio.create_task(restarter(procs, log_file))
        load_task = asyncio.create_task(host_load())
        kill_task = asyncio.create_task(worker_killer(procs))
        exit_code: int | None = None
        stop_s: float | None = None
        try:
            deadline = time.time() + DAEMON_READY_TIMEOUT_S
            while not daemon_ready(relay.received):
                if proc.poll() is not None:
                    raise SitlError(
                        f"daemon exited with code {proc.returncode} before it was ready (a HEARTBEAT out "
                        f"of MAV_STATE_BOOT); see {log_path}"
                    )
                if time.time() > deadline:
                    raise SitlError(f"the daemon was not ready in {DAEMON_READY_TIMEOUT_S:.0f} s")
                await asyncio.sleep(0.1)
            say(f"daemon pid {proc.pid} up; flying the mission")
            await loop.run_in_executor(None, fly_mission)
            await asyncio.sleep(flight.opts.tail_s)
            end = time.time()
        finally:
            # At once, before any await: on SIGTERM/Ctrl-C (a KeyboardInterrupt) asyncio cancels every
            # task together, so awaiting the camera's raised CancelledError here and the daemon was never
            # stopped, while the mission thread flew on until the disarm (issue 36).
            driver.stop()
            stop.set()
            restart_task.cancel()  # no new daemon from here on
            cam_task.cancel()
            load_task.cancel()
            kill_task.cancel()
            hogs.stop()
            proc = procs[-1]
            t_term = time.monotonic()
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
            with contextlib.suppress(BaseException):
                await restart_task
            with contextlib.suppress(BaseException):
                await cam_task
            try:
                exit_code = await loop.run_in_executor(None, lambda: proc.wait(DAEMON_STOP_TIMEOUT_S))
                stop_s = time.monotonic() - t_term
            except subprocess.TimeoutExpired:
                proc.kill()
                exit_code = proc.wait()
            await server.close()
    return end, exit_code, stop_s


def run_autopilot_cli(args: Any) -> int:
    """``gdnav sitl run --autopilot URL``: fly, print the summary, exit 0 when the daemon exited 0 and
    the mission finished."""
    from gps_denied_onboard.sitl.runner import summary_lines

    opts = SitlOptions(
        map_path=args.map,
        scenario=args.scenario,
        report_path=args.report,
        config_path=args.config,
        overrides=tuple(args.set or ()),
        workdir=args.workdir,
        quiet=args.quiet,
    )
    try:
        report = run_sitl_with_autopilot(opts, args.autopilot)
    except MissionError as exc:
        print(f"error: mission: {exc}", file=sys.stderr)
        return 1
    report.setdefault("matcher", "?")
    for line in summary_lines({**report, "matcher": report.get("matcher") or "?"}):
        print(line)
    print(f"autopilot     {args.autopilot}, truth from {report['autopilot']['truth_source']}")
    print(f"report        {opts.report_path}")
    return 0 if report["daemon_exit_code"] == 0 else 1


def _adopted_worker(core_fdr: Path) -> list[int]:
    """The vision worker a restarted core adopted (not its child): the pid of its newest ``core.worker``
    record of a start or an adoption."""
    pids = [
        int(r["pid"])
        for r in read_records(core_fdr)
        if r.get("kind") == FdrKind.CORE_WORKER and r.get("event") in ("started", "adopted")
    ]
    return pids[-1:]


def _percentiles(values: list[float]) -> dict[str, float] | None:
    """p5, p50, p95 and max of ``values`` (None for none)."""
    if not values:
        return None
    arr = np.asarray(values, dtype=np.float64)
    return {
        "p5": round(float(np.percentile(arr, 5)), 4),
        "p50": round(float(np.percentile(arr, 50)), 4),
        "p95": round(float(np.percentile(arr, 95)), 4),
        "max": round(float(arr.max()), 4),
    }
