"""``gdnav sitl run``: fly a scenario against the daemon, in real time, over real sockets.

1. Build (or reuse) the tile cache from ``--map`` (default: the embedded procedural demo map).
2. Start the camera (TCP frame server) and the autopilot (pymavlink, UDP) on loopback.
3. Start the daemon as its own process, unmodified, with ``config/sitl.yaml`` (+ the ports and paths
   of this run as ``--set`` overrides), and wait for its HEARTBEAT.
4. Fly: ATTITUDE at 50 Hz, ALTITUDE/VFR_HUD at 10 Hz, SYSTEM_TIME/HEARTBEAT at 1 Hz, HOME_POSITION
   every 2 s; nav frames rendered from the truth (from ``--appearance`` when given) at the scenario's
   frame rate, stamped with their exposure time.
5. SIGTERM the daemon, time its exit, score what the autopilot side received (``sitl.report``).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import hashlib
import itertools
import json
import math
import os
import platform
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink import mavutil

from gps_denied_onboard.camera.stream import encode_frame
from gps_denied_onboard.components.c13_fdr import read_records
from gps_denied_onboard.config import Config, ConfigError, load_config
from gps_denied_onboard.constants import CORE_FDR_SUBDIR, FRAME_STREAM_MAGIC
from gps_denied_onboard.helpers.process import die_with_parent
from gps_denied_onboard.sitl.autopilot import ReceivedMessage, SimAutopilot
from gps_denied_onboard.sitl.frame_server import FrameServer
from gps_denied_onboard.sitl.host_faults import HostFaultError, HostFaults
from gps_denied_onboard.sitl.photometric import PhotometricModel, degrade_for_gap
from gps_denied_onboard.sitl.render import MapRenderer, RenderError
from gps_denied_onboard.sitl.report import (
    SentFrame,
    analyse,
    plot_report,
    refused_fixes_line,
    restart_recovery,
    score,
)
from gps_denied_onboard.sitl.scenario import (
    Fault,
    FaultKind,
    Scenario,
    ScenarioError,
    SpoofedSource,
    Trajectory,
    load_scenario,
    spoofed_start_from_yaml,
)

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_CONFIG = REPO_ROOT / "config" / "sitl.yaml"
DAEMON_READY_TIMEOUT_S = 90.0
DAEMON_STOP_TIMEOUT_S = 10.0
ATTITUDE_HZ = 50.0
#: How often the daemon's resident memory is sampled, s.
RSS_SAMPLE_S = 5.0
#: RSS growth is measured from this far into the flight (start-up and caches warm first), s.
RSS_WARMUP_S = 60.0
GRAVITY_M_S2 = 9.80665
#: The simulated accelerometer's fixed bias and white noise (1-sigma per sample), body FRD, m/s^2.
IMU_BIAS_M_S2 = np.array([0.02, -0.02, 0.03])
IMU_NOISE_M_S2 = 0.05
#: The simulated autopilot's roll and pitch error in ATTITUDE, radians: a fixed bias (an AHRS a little off
#: level plus a camera mount calibrated to a fraction of a degree), a slow wander (first-order
#: Gauss-Markov: 1-sigma, correlation time s) and a little white noise per message. An AHRS's attitude is
#: a filter's output, smooth from one message to the next: the daemon's VO assumes 0.05 deg between
#: frames (``c1_vio/homography_vo.py``), and this gives about 0.04. The nav camera sees the true
#: attitude; only what the autopilot reports is off. The daemon leans on this attitude when the image
#: cannot pin the camera's tilt (``c4_pose/solver.py``), so a perfect one here would hide its error:
#: ``pose.attitude_sigma_deg`` (0.5) must cover bias and wander together.
ATTITUDE_BIAS_RAD = (math.radians(0.2), math.radians(-0.15))
ATTITUDE_WANDER_RAD = math.radians(0.1)
ATTITUDE_WANDER_TAU_S = 5.0
ATTITUDE_NOISE_RAD = math.radians(0.01)
ALTITUDE_HZ = 10.0
#: Before the flight the simulated autopilot has GNSS: it sends its position on the ground this often, Hz,
#: stating this horizontal accuracy, m (GPS_RAW_INT.h_acc), unless a spoofed start says otherwise.
GROUND_FIX_HZ = 2.0
GROUND_FIX_H_ACC_M = 1.5
#: Default seconds between the last frame and the daemon's SIGTERM (its last outputs still arrive).
TAIL_S = 1.5


class SitlError(RuntimeError):
    """The simulation cannot run (bad map, scenario, config) or the daemon did not come up."""


@dataclass(frozen=True)
class SitlOptions:
    map_path: Path | None
    scenario: str
    report_path: Path
    appearance_path: Path | None = None
    config_path: Path | None = None
    overrides: tuple[str, ...] = ()
    workdir: Path | None = None
    duration_s: float | None = None
    quiet: bool = False
    #: Seconds between the last frame and SIGTERM; 0 stops the daemon while it is still in frames.
    tail_s: float = TAIL_S
    #: Where the map caches (one per map, named by its hash) are kept; default: the workdir. Flights over
    #: the same map may share one (``gdnav bench flights``), one flight at a time.
    cache_root: Path | None = None
    #: The scenario's ``spoofed_start`` replaced by this YAML mapping (``--spoofed-start``); None: as it is.
    spoofed_start: str | None = None


def _send_from_a_fresh_port(packet: bytes, port: int) -> int:
    """``packet`` to 127.0.0.1:``port`` from a new socket (a new source port), closed at once; 1 if sent."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.sendto(packet, ("127.0.0.1", port))
        except OSError:
            return 0
        return 1


def _die_with_parent() -> None:
    """In the child before exec: SIGTERM when the process that started it dies, so a runner killed
    outright leaves no daemon behind."""
    die_with_parent(signal.SIGTERM)


def _child_setup(nice: int | None) -> Callable[[], None]:
    """What runs in the daemon's child before exec: ``_die_with_parent``, and its nice value set from the
    first instruction on, as the unit's ``Nice=`` does (the daemon itself can set it only after its
    imports and its configuration; where this process may not lower it, it stays)."""

    def setup() -> None:
        _die_with_parent()
        if nice is not None:
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, 0, nice)

    return setup


def daemon_ready(received: Sequence[ReceivedMessage]) -> bool:
    """Whether the daemon has said it is up: a HEARTBEAT out of MAV_STATE_BOOT (its start-up beacon sends
    BOOT while the fix path loads, ``daemon.beacon``)."""
    boot = mavutil.mavlink.MAV_STATE_BOOT
    return any(m.type == "HEARTBEAT" and m.fields.get("system_status") != boot for m in received)


def spawn_daemon(
    cmd: list[str], log_file: Any, env: dict[str, str], *, nice: int | None = None
) -> subprocess.Popen[bytes]:
    """The daemon under test as a child process that dies with this one (SIGTERM, SIGKILL or a crash
    of the runner alike), at nice value ``nice`` from its start (its ``daemon.process_nice``)."""
    preexec = _child_setup(nice) if sys.platform == "linux" else None
    return subprocess.Popen(cmd, stdout=log_file, stderr=log_file, env=env, preexec_fn=preexec)


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _sha_prefix(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()[:12]


def _intersect(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float, float]:
    box = (max(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), min(a[3], b[3]))
    if not (box[0] < box[2] and box[1] < box[3]):
        raise SitlError(f"--map and --appearance do not overlap: {a} vs {b}")
    return box


class _Flight:
    def __init__(
        self,
        opts: SitlOptions,
        scenario: Scenario,
        trajectory: Trajectory,
        renderer: MapRenderer,
        config_path: Path,
        cache_dir: Path,
        workdir: Path,
        ground_alt_amsl_m: float,
        daemon_nice: int | None = None,
    ) -> None:
        self.opts = opts
        self.daemon_nice = daemon_nice
        self.scenario = scenario
        self.traj = trajectory
        self.renderer = renderer
        self.config_path = config_path
        self.cache_dir = cache_dir
        self.workdir = workdir
        self.ground_alt_amsl_m = ground_alt_amsl_m
        self.calib = scenario.calibration()
        self.photometric = PhotometricModel(scenario.photometric)
        self.frames: list[SentFrame] = []
        self.t0_unix_s = 0.0
        self.daemon_exit_code: int | None = None
        self.end_unix_s: float | None = None
        #: Faults injected on the camera and MAVLink side, for the report.
        self.faults_injected: list[dict[str, Any]] = []
        #: (flight time s, daemon RSS MiB), sampled every RSS_SAMPLE_S.
        self.rss_mib: list[tuple[float, float]] = []
        #: (flight time s, host stall counters), sampled with the RSS (see ``host_stall_counters``).
        self.host_samples: list[tuple[float, dict[str, float]]] = []
        #: Unix times at which the daemon was killed, and at which its replacement was started.
        self.restarts: list[dict[str, float]] = []
        self._imu_rng = np.random.default_rng(11)
        self._attitude_rng = np.random.default_rng(12)
        self._attitude_wander_rad = self._attitude_rng.normal(0.0, ATTITUDE_WANDER_RAD, 2)
        self.daemon_stop_s: float | None = None
        #: Faults of the daemon's host (clock, ONNX Runtime, map cells, FDR disk: ``sitl.host_faults``).
        self.host = HostFaults(scenario, trajectory, workdir, cache_dir, self.faults_injected)
        self.host_setup = self.host.prepare()
        if self.host_setup.cache_dir is not None:
            self.cache_dir = self.host_setup.cache_dir

    def _say(self, msg: str) -> None:
        if not self.opts.quiet:
            print(f"[sitl] {msg}", flush=True)

    def _start_point(self, source: SpoofedSource) -> tuple[float, float]:
        """Where the flight starts as ``source`` tells it: the truth, or dragged by the spoofed start."""
        start = self.traj.truth_at(0.0)
        spoof = self.scenario.spoofed_start
        if spoof is None or source not in spoof.sources:
            return start.lat_deg, start.lon_deg
        ltp = self.traj.origin
        ned = ltp.to_ned(start.lat_deg, start.lon_deg, self.ground_alt_amsl_m)
        ned[:2] += np.asarray(spoof.offset_ne_m)
        lat, lon, _alt = ltp.to_geodetic(ned)
        return float(lat), float(lon)

    def _spoofed_config(self) -> list[str]:
        """The daemon's configured start when the spoofed start drags it (before the run's overrides, which
        may still set their own)."""
        spoof = self.scenario.spoofed_start
        if spoof is None or SpoofedSource.CONFIG not in spoof.sources:
            return []
        lat, lon = self._start_point(SpoofedSource.CONFIG)
        return [f"init.lat_deg={lat:.9f}", f"init.lon_deg={lon:.9f}", f"init.sigma_m={spoof.sigma_m:g}"]

    def _daemon_cmd(self, mav_port: int, cam_port: int) -> list[str]:
        sets = [
            f"camera.source=tcp://127.0.0.1:{cam_port}",
            f"mavlink.url=udpin:127.0.0.1:{mav_port}",
            f"cache.dir={self.cache_dir}",
            f"fdr.dir={self.workdir / 'fdr'}",
            f"camera.intrinsics.width_px={self.calib.width_px}",
            f"camera.intrinsics.height_px={self.calib.height_px}",
            f"camera.intrinsics.fx_px={self.calib.fx_px}",
            f"camera.intrinsics.fy_px={self.calib.fy_px}",
            f"camera.intrinsics.cx_px={self.calib.cx_px}",
            f"camera.intrinsics.cy_px={self.calib.cy_px}",
            *self._spoofed_config(),
            *self._vision_worker_override(),
            *self.opts.overrides,
            *self.host_setup.overrides,
        ]
        cmd = [sys.executable, "-m", "gps_denied_onboard.cli", "run", "--config", str(self.config_path)]
        for s in sets:
            cmd += ["--set", s]
        return cmd

    def _vision_worker_override(self) -> list[str]:
        split = self.scenario.vision_worker
        return [] if split is None else [f"daemon.vision_worker={'true' if split else 'false'}"]

    def _daemon_env(self) -> dict[str, str]:
        return {**os.environ, "PYTHONUNBUFFERED": "1", **self.host_setup.env}

    def _specific_force_body(self, t_s: float, truth: Any) -> tuple[float, float, float]:
        """What an accelerometer on the vehicle reads at ``t_s``: the truth's acceleration (central
        difference of its velocity) minus gravity, in body FRD, with a fixed bias and white noise."""
        h = 0.01
        t_lo = max(0.0, t_s - h)
        accel_ned = (self.traj.truth_at(t_s + h).vel_ned_m_s - self.traj.truth_at(t_lo).vel_ned_m_s) / (
            t_s + h - t_lo
        )
        specific_ned = accel_ned - np.array([0.0, 0.0, GRAVITY_M_S2])
        body = truth.attitude.R_ned_body().T @ specific_ned
        body = body + IMU_BIAS_M_S2 + self._imu_rng.normal(0.0, IMU_NOISE_M_S2, 3)
        return float(body[0]), float(body[1]), float(body[2])

    def _attitude_error_rad(self) -> tuple[float, float]:
        """(roll, pitch) error of the next ATTITUDE message (see ``ATTITUDE_BIAS_RAD``); one step of the
        wander per message, at ``ATTITUDE_HZ``."""
        a = math.exp(-1.0 / (ATTITUDE_HZ * ATTITUDE_WANDER_TAU_S))
        rng = self._attitude_rng
        self._attitude_wander_rad = a * self._attitude_wander_rad + math.sqrt(1.0 - a * a) * rng.normal(
            0.0, ATTITUDE_WANDER_RAD, 2
        )
        noise = rng.normal(0.0, ATTITUDE_NOISE_RAD, 2)
        err = np.asarray(ATTITUDE_BIAS_RAD) + self._attitude_wander_rad + noise
        return float(err[0]), float(err[1])

    def _send_telemetry(self, ap: SimAutopilot, now: float, *, full: bool) -> None:
        t_s = max(0.0, now - self.t0_unix_s) if self.t0_unix_s else 0.0
        truth = self.traj.truth_at(t_s)
        flying = bool(self.t0_unix_s)
        if not (flying and self.scenario.fault_at(FaultKind.ATTITUDE_ABSENT, t_s)):
            if flying and self.scenario.fault_at(FaultKind.ATTITUDE_NAN, t_s):
                ap.send_attitude(now, math.nan, math.nan, math.nan)
            else:
                d_roll, d_pitch = self._attitude_error_rad()
                d_yaw = 0.0
                offset = self.scenario.fault_at(FaultKind.ATTITUDE_OFFSET, t_s) if flying else None
                if offset is not None:
                    d_roll += math.radians(offset.offset_deg[0])
                    d_pitch += math.radians(offset.offset_deg[1])
                    d_yaw = math.radians(offset.offset_deg[2])
                ap.send_attitude(
                    now, truth.roll_rad + d_roll, truth.pitch_rad + d_pitch, truth.yaw_rad + d_yaw
                )
            ap.send_highres_imu(now, self._specific_force_body(t_s, truth))
        if full:
            if flying:
                alt_rel = truth.alt_agl_m  # home is on the flat ground
                ap.send_altitude(now, truth.alt_amsl_m, alt_rel, truth.alt_agl_m)
                speed = float(np.hypot(truth.vel_ned_m_s[0], truth.vel_ned_m_s[1]))
                ap.send_vfr_hud(
                    speed,
                    float(np.degrees(truth.yaw_rad)) % 360.0,
                    truth.alt_amsl_m,
                    -float(truth.vel_ned_m_s[2]),
                )
            else:  # before the flight the vehicle stands at home (where the flight starts), disarmed
                ground = truth.alt_amsl_m - truth.alt_agl_m
                ap.send_altitude(now, ground, 0.0, 0.0)
                ap.send_vfr_hud(0.0, float(np.degrees(truth.yaw_rad)) % 360.0, ground, 0.0)
            m = mavutil.mavlink
            landed = m.MAV_LANDED_STATE_IN_AIR if flying else m.MAV_LANDED_STATE_ON_GROUND
            ap.send_extended_sys_state(landed)

    async def _telemetry(self, ap: SimAutopilot, stop: asyncio.Event) -> None:
        start = self.traj.truth_at(0.0)
        ground_amsl_m = start.alt_amsl_m - start.alt_agl_m  # the true ground: what it measured at home
        home_lat, home_lon = self._start_point(SpoofedSource.HOME)
        ap_lat, ap_lon = self._start_point(SpoofedSource.AUTOPILOT)
        spoof = self.scenario.spoofed_start
        h_acc_m = spoof.sigma_m if spoof is not None and SpoofedSource.AUTOPILOT in spoof.sources else None
        k = 0
        next_t = time.time()
        while not stop.is_set():
            now = time.time()
            if self.t0_unix_s and self.scenario.link_down_at(now - self.t0_unix_s):
                ap.poll(discard=True)  # the link is cut: nothing sent, nothing of the daemon's arrives
            else:
                full = k % int(ATTITUDE_HZ / ALTITUDE_HZ) == 0
                self._send_telemetry(ap, now, full=full)
                if k % int(ATTITUDE_HZ) == 0:
                    ap.send_heartbeat(armed=bool(self.t0_unix_s))
                    ap.send_system_time(now)
                if k % int(2 * ATTITUDE_HZ) == 0:
                    ap.send_home(home_lat, home_lon, ground_amsl_m)
                if not self.t0_unix_s and k % int(ATTITUDE_HZ / GROUND_FIX_HZ) == 0:
                    # on the ground, before the denial, the autopilot has its GNSS (maybe spoofed)
                    ap.send_ground_fix(now, ap_lat, ap_lon, ground_amsl_m, h_acc_m or GROUND_FIX_H_ACC_M)
                ap.poll()
            k += 1
            next_t += 1.0 / ATTITUDE_HZ
            await asyncio.sleep(max(0.0, next_t - time.time()))

    def _render(self, index: int, t_s: float) -> tuple[bytes, Any]:
        truth = self.traj.truth_at(t_s)
        img = self.renderer.render(self.calib, truth.lat_deg, truth.lon_deg, truth.alt_agl_m, truth.attitude)
        img = self.photometric.apply(img, index)
        gap = self.scenario.gap_at(t_s)
        if gap is not None:
            img = degrade_for_gap(img, gap)
        # The camera is on the daemon's host: it stamps with that host's wall clock (clock_jump steps it).
        wall_s = self.t0_unix_s + t_s + self.scenario.wall_step_s(t_s)
        stamp_us = round((wall_s + self.scenario.stamp_offset_s(t_s)) * 1e6)
        return encode_frame(img, seq=index, exposure_time_unix_usec=stamp_us), truth

    def _bad_frame(self, kind: FaultKind, seq: int, stamp_us: int) -> bytes:
        """A malformed frame message of ``kind`` (see the scenario's ``faults``)."""
        w, h = self.calib.width_px, self.calib.height_px
        if kind is FaultKind.WRONG_SIZE_FRAME:
            return encode_frame(np.zeros((100, 100, 3), np.uint8), seq=seq, exposure_time_unix_usec=stamp_us)
        if kind is FaultKind.CORRUPT_FRAME:
            good = bytearray(
                encode_frame(np.full((h, w, 3), 90, np.uint8), seq=seq, exposure_time_unix_usec=stamp_us)
            )
            (hlen,) = struct.unpack(">I", good[4:8])
            body = 8 + hlen + 4
            good[body : body + 64] = b"\x00" * 64  # a valid header, the JPEG destroyed
            return bytes(good)
        # bomb: the header says the calibrated size, the PNG's own IHDR says 20000x20000
        ihdr = struct.pack(">IIBBBBB", 20000, 20000, 8, 0, 0, 0, 0)
        chunk = struct.pack(">I", len(ihdr)) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
        idat_data = zlib.compress(b"\x00" * 4096)
        idat = struct.pack(">I", len(idat_data)) + b"IDAT" + idat_data
        idat += struct.pack(">I", zlib.crc32(b"IDAT" + idat_data))
        payload = b"\x89PNG\r\n\x1a\n" + chunk + idat
        header = json.dumps(
            {
                "seq": seq,
                "exposure_time_unix_usec": stamp_us,
                "encoding": "png",
                "width_px": w,
                "height_px": h,
            }
        ).encode()
        return (
            FRAME_STREAM_MAGIC
            + struct.pack(">I", len(header))
            + header
            + struct.pack(">I", len(payload))
            + payload
        )

    async def _camera(self, server: FrameServer, stop: asyncio.Event) -> None:
        loop = asyncio.get_running_loop()
        prev_t = -1.0
        stalled: Fault | None = None
        for index, t_s in enumerate(self.traj.frame_times_s()):
            if stop.is_set():
                return
            bad = self.scenario.instant_faults(prev_t, float(t_s))
            if bad:
                # Half a frame period before the good frame: the daemon's newest-wins queue would drop a
                # bad frame followed at once by a good one before a busy track worker could take it.
                t_bad = float(t_s) - (float(t_s) - max(prev_t, 0.0)) / 2.0
                await asyncio.sleep(max(0.0, self.t0_unix_s + t_bad - time.time()))
                for fault in bad:
                    wall_s = self.t0_unix_s + t_bad + self.scenario.wall_step_s(t_bad)
                    await server.send(self._bad_frame(fault.kind, 10_000_000 + index, round(wall_s * 1e6)))
                    self.faults_injected.append({"kind": fault.kind.value, "t_s": round(float(t_s), 3)})
            await asyncio.sleep(max(0.0, self.t0_unix_s + float(t_s) - time.time()))
            prev_t = float(t_s)
            stall = self.scenario.fault_at(FaultKind.CAMERA_STALL, float(t_s))
            if stall is not None:
                if stall is not stalled:
                    stalled = stall
                    dropped = stall.reconnect and server.drop_client()
                    self.faults_injected.append(
                        {"kind": stall.kind.value, "t_s": round(float(t_s), 3), "connection_dropped": dropped}
                    )
                continue  # the camera sends nothing
            message, truth = await loop.run_in_executor(None, self._render, index, float(t_s))
            await server.send(message)
            self.frames.append(
                SentFrame(
                    index,
                    round((self.t0_unix_s + float(t_s)) * 1e6),
                    float(t_s),
                    truth.lat_deg,
                    truth.lon_deg,
                    truth.alt_agl_m,
                )
            )

    async def _flood(self, mav_port: int, stop: asyncio.Event) -> None:
        """During ``mavlink_flood`` windows: random bytes and truncated MAVLink 2 packets to the daemon's
        MAVLink port, at the fault's rate, in 10 ms batches."""
        floods = [f for f in self.scenario.faults if f.kind is FaultKind.MAVLINK_FLOOD]
        if not floods:
            return
        rng = np.random.default_rng(5)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.setblocking(False)
            sent = 0
            while not stop.is_set():
                t_s = time.time() - self.t0_unix_s
                fault = self.scenario.fault_at(FaultKind.MAVLINK_FLOOD, t_s)
                if fault is not None:
                    for _ in range(max(1, round(fault.rate_hz / 100.0))):
                        n = int(rng.integers(1, 280))
                        junk = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
                        if sent % 2:
                            junk = b"\xfd" + junk  # looks like the start of a MAVLink 2 frame
                        with contextlib.suppress(OSError):
                            sock.sendto(junk, ("127.0.0.1", mav_port))
                        sent += 1
                elif t_s > max(f.to_s for f in floods):
                    break
                await asyncio.sleep(0.01)
            self.faults_injected.append({"kind": FaultKind.MAVLINK_FLOOD.value, "datagrams": sent})

    async def _source_flood(self, mav_port: int, stop: asyncio.Event) -> None:
        """During ``source_flood`` windows: one well-formed, unsigned MAVLink 2 HEARTBEAT of a ground station
        from each of ``rate_hz`` fresh source ports a second (a new socket each, closed at once), in 10 ms
        batches: a stranger must neither become a recipient of the daemon's output nor slow it."""
        floods = [f for f in self.scenario.faults if f.kind is FaultKind.SOURCE_FLOOD]
        if not floods:
            return
        mav = mavutil.mavlink.MAVLink(None, srcSystem=200, srcComponent=190)
        packet = bytes(mav.heartbeat_encode(6, 8, 0, 0, 0).pack(mav))
        sent = 0
        while not stop.is_set():
            t_s = time.time() - self.t0_unix_s
            fault = self.scenario.fault_at(FaultKind.SOURCE_FLOOD, t_s)
            if fault is not None:
                for _ in range(max(1, round(fault.rate_hz / 100.0))):
                    sent += _send_from_a_fresh_port(packet, mav_port)
            elif t_s > max(f.to_s for f in floods):
                break
            await asyncio.sleep(0.01)
        self.faults_injected.append({"kind": FaultKind.SOURCE_FLOOD.value, "datagrams": sent})

    async def _impostor(self, ap: SimAutopilot, mav_port: int, stop: asyncio.Event) -> None:
        """During ``impostor`` windows: from one UDP socket of its own (another source port), messages that
        claim the autopilot's system and component ids, ``rate_hz`` a second in 10 ms batches: its
        HEARTBEAT in every batch, ATTITUDE with NaN, huge and out-of-order values, SYSTEM_TIME going back
        and TIMESYNC requests. The output must stay with the autopilot (issue 36: it followed the
        impostor, and the autopilot got no GPS_INPUT for 19.9 s and 35.8 s). Whatever reaches the
        impostor's socket is counted (``received_datagrams``: none expected)."""
        faults = [f for f in self.scenario.faults if f.kind is FaultKind.IMPOSTOR]
        if not faults:
            return
        mav = mavutil.mavlink.MAVLink(None, srcSystem=ap.system_id, srcComponent=1)
        m = mavutil.mavlink
        nan, huge = math.nan, 1e30

        def packets(k: int, now: float) -> list[bytes]:
            boot_ms = max(0, int((now - ap.boot_time_unix_s) * 1000))
            hostile = [
                mav.heartbeat_encode(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 4, 4),
                mav.attitude_encode(boot_ms, nan, nan, nan, 0.0, 0.0, 0.0),
                mav.attitude_encode((boot_ms + 3_600_000 * (k % 2)) & 0xFFFFFFFF, huge, -huge, huge, 0, 0, 0),
                mav.attitude_encode(max(0, boot_ms - 60_000), 0.5, -0.5, 3.0, 0.0, 0.0, 0.0),
                mav.system_time_encode(int((now - 3600.0 * (1 + k % 5)) * 1e6), max(0, boot_ms - 1000 * k)),
                mav.timesync_encode(0, k),
            ]
            return [bytes(p.pack(mav)) for p in hostile]

        sent = received = 0
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.setblocking(False)
            k = 0
            while not stop.is_set():
                t_s = time.time() - self.t0_unix_s
                fault = self.scenario.fault_at(FaultKind.IMPOSTOR, t_s)
                if fault is not None:
                    batch = packets(k, time.time())
                    for i in range(max(1, round(fault.rate_hz / 100.0))):
                        packet = batch[0 if i == 0 else 1 + (k + i) % (len(batch) - 1)]  # HEARTBEAT first
                        with contextlib.suppress(OSError):
                            sock.sendto(packet, ("127.0.0.1", mav_port))
                            sent += 1
                    k += 1
                elif t_s > max(f.to_s for f in faults):
                    break
                while True:
                    try:
                        sock.recv(65535)
                    except OSError:
                        break
                    received += 1
                await asyncio.sleep(0.01)
        self.faults_injected.append(
            {"kind": FaultKind.IMPOSTOR.value, "messages": sent, "received_datagrams": received}
        )

    async def _sample_rss(self, procs: list[subprocess.Popen[bytes]], stop: asyncio.Event) -> None:
        """The daemon's resident memory every RSS_SAMPLE_S (Linux /proc; nothing elsewhere)."""
        while not stop.is_set():
            try:
                status = Path(f"/proc/{procs[-1].pid}/status").read_text()
            except OSError:
                return
            t_s = round(time.time() - self.t0_unix_s, 1)
            for line in status.splitlines():
                if line.startswith("VmRSS:"):
                    kib = float(line.split()[1])
                    self.rss_mib.append((t_s, round(kib / 1024.0, 1)))
            counters = host_stall_counters()
            if counters is not None:
                self.host_samples.append((t_s, counters))
            # wake at once when the flight ends: the final poll of the autopilot side must not wait
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(stop.wait(), RSS_SAMPLE_S)

    def _spoof_resume_state(self, t_kill_unix_s: float) -> None:
        """With a spoofed start that drags the ``resume`` source: the daemon's resume state file (in its
        FDR directory) says the killed run's last 3D estimate was the truth at the kill, dragged by the
        offset, at the stated sigma; newer than anything in the FDR, so the restarted daemon resumes
        from it (a valid file, checksum included: what a wrong state looks like, not a damaged one)."""
        spoof = self.scenario.spoofed_start
        if spoof is None or SpoofedSource.RESUME not in spoof.sources:
            return
        from gps_denied_onboard.components.c5_estimator.prior import ResumeState
        from gps_denied_onboard.components.c5_estimator.resume_state import ResumeStateFile, default_path

        truth = self.traj.truth_at(max(0.0, t_kill_unix_s - self.t0_unix_s))
        ltp = self.traj.origin
        ned = ltp.to_ned(truth.lat_deg, truth.lon_deg, self.ground_alt_amsl_m)
        ned[:2] += np.asarray(spoof.offset_ne_m)
        lat, lon, _alt = ltp.to_geodetic(ned)
        state = ResumeState(float(lat), float(lon), spoof.sigma_m, round(t_kill_unix_s * 1e6))
        ResumeStateFile(default_path(self.workdir / "fdr")).write(
            state, provenance="satellite_anchored", written_unix_s=t_kill_unix_s
        )
        self.faults_injected.append(
            {"kind": "spoofed_resume_state", "t_s": round(t_kill_unix_s - self.t0_unix_s, 3)}
        )

    async def _restarter(self, cmd: list[str], log_file: Any, procs: list[subprocess.Popen[bytes]]) -> None:
        """SIGKILL the daemon at each scheduled flight time and start the same command again at once."""
        for at_s in self.scenario.daemon_restarts_s:
            await asyncio.sleep(max(0.0, self.t0_unix_s + at_s - time.time()))
            old = procs[-1]
            t_kill = time.time()
            old.kill()
            await asyncio.get_running_loop().run_in_executor(None, old.wait)
            if at_s in self.scenario.daemon_restarts_wipe_fdr:  # a restart with no FDR at all
                shutil.rmtree(self.workdir / "fdr", ignore_errors=True)
            self._spoof_resume_state(t_kill)
            procs.append(spawn_daemon(cmd, log_file, self._daemon_env(), nice=self.daemon_nice))
            self.restarts.append({"killed_unix_s": t_kill, "restarted_unix_s": time.time()})
            self._say(f"daemon killed (SIGKILL) at {at_s:.1f} s and restarted: pid {procs[-1].pid}")

    async def fly(self) -> SimAutopilot:
        server = FrameServer()
        cam_port = await server.start()
        mav_port = _free_udp_port()
        ap = SimAutopilot(daemon_port=mav_port, unix_offset_s=self.scenario.autopilot_unix_offset_s)
        log_path = self.workdir / "daemon.log"
        stop = asyncio.Event()
        cmd = self._daemon_cmd(mav_port, cam_port)
        with log_path.open("wb") as log_file:
            procs = [spawn_daemon(cmd, log_file, self._daemon_env(), nice=self.daemon_nice)]
            proc = procs[0]
            restarter: asyncio.Task[None] | None = None
            try:
                telemetry = asyncio.create_task(self._telemetry(ap, stop), name="sitl_telemetry")
                self._say(f"daemon pid {proc.pid}; waiting for it to be ready (log: {log_path})")
                deadline = time.time() + DAEMON_READY_TIMEOUT_S
                while not daemon_ready(ap.received):
                    if proc.poll() is not None:
                        raise SitlError(
                            f"daemon exited with code {proc.returncode} before it was ready (a HEARTBEAT "
                            f"out of MAV_STATE_BOOT); see {log_path}"
                        )
                    if time.time() > deadline:
                        raise SitlError(
                            f"the daemon was not ready (a HEARTBEAT out of MAV_STATE_BOOT) in "
                            f"{DAEMON_READY_TIMEOUT_S:.0f} s; see {log_path}"
                        )
                    await asyncio.sleep(0.1)
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(server.client_connected.wait(), 10.0)
                self.t0_unix_s = time.time() + 0.2
                if FaultKind.CLOCK_JUMP in self.host.kinds:  # steps land at whole seconds (host_faults)
                    self.t0_unix_s = float(math.ceil(self.t0_unix_s))
                self._say(
                    f"flying '{self.scenario.name}': {self.traj.duration_s:.0f} s, "
                    f"{len(self.traj.frame_times_s())} frames"
                )
                if self.scenario.daemon_restarts_s:
                    restarter = asyncio.create_task(self._restarter(cmd, log_file, procs), name="restarter")
                side_tasks = [
                    asyncio.create_task(self._flood(mav_port, stop), name="sitl_flood"),
                    asyncio.create_task(self._source_flood(mav_port, stop), name="sitl_source_flood"),
                    asyncio.create_task(self._impostor(ap, mav_port, stop), name="sitl_impostor"),
                    asyncio.create_task(self._sample_rss(procs, stop), name="sitl_rss"),
                    asyncio.create_task(self.host.run(self.t0_unix_s, stop), name="sitl_host_faults"),
                ]
                await self._camera(server, stop)
                if restarter is not None:
                    await restarter
                proc = procs[-1]
                await asyncio.sleep(self.opts.tail_s)
                self.end_unix_s = time.time()
                stop.set()
                await asyncio.gather(*side_tasks)
                await telemetry
                ap.poll()
            finally:
                stop.set()
                if restarter is not None and not restarter.done():
                    restarter.cancel()
                proc = procs[-1]
                t_term = time.monotonic()
                if proc.poll() is None:
                    proc.send_signal(signal.SIGTERM)
                try:
                    self.daemon_exit_code = await asyncio.get_running_loop().run_in_executor(
                        None, lambda: proc.wait(DAEMON_STOP_TIMEOUT_S)
                    )
                    self.daemon_stop_s = time.monotonic() - t_term
                except subprocess.TimeoutExpired:
                    proc.kill()
                    self.daemon_exit_code = proc.wait()
                await server.close()
        ap.poll()
        return ap


def _build_vpr_index(daemon_cfg: Config, cache_dir: Path, *, progress: bool) -> None:
    """The appearance index the daemon's VPR strategy will search (``gdnav cache vpr`` does the same):
    dense RootSIFT for ``vlad``, the exported XFeat extractor (``vpr.xfeat_weights_path`` or the one in
    ``matcher.model_dir``) for ``vlad_xfeat``; nothing for ``geo_prior``."""
    from gps_denied_onboard.components.c10_cache_build.vpr_index import build_vlad_index

    strategy = daemon_cfg.vpr.strategy
    if strategy == "vlad":
        build_vlad_index(cache_dir, progress=progress)
    elif strategy == "vlad_xfeat":
        from gps_denied_onboard.components.c2_vpr.learned_local import (
            XFeatDescriber,
            default_xfeat_params,
            find_xfeat_extractor,
        )
        from gps_denied_onboard.components.c7_inference import OnnxInferenceRuntime
        from gps_denied_onboard.components.c7_inference.protocol import EngineLoadError
        from gps_denied_onboard.helpers.model_manifest import ModelDirError

        weights, model_dir = daemon_cfg.vpr.xfeat_weights_path, daemon_cfg.matcher.model_dir
        try:
            if weights:
                path = Path(weights)
            elif model_dir is not None:
                path = find_xfeat_extractor(model_dir)
            else:
                raise SitlError("vpr.strategy vlad_xfeat needs vpr.xfeat_weights_path or matcher.model_dir")
            describer = XFeatDescriber(OnnxInferenceRuntime(intra_op_threads=2), path)
        except (ModelDirError, EngineLoadError, OSError) as exc:
            raise SitlError(f"vpr.strategy vlad_xfeat: {exc}") from exc
        build_vlad_index(cache_dir, default_xfeat_params(), describer=describer, progress=progress)


def _build_tile_features(daemon_cfg: Config, cache_dir: Path, *, progress: bool) -> None:
    """The learned matcher's precomputed tile features (``gdnav cache features`` does the same), built
    with the matcher the daemon will build."""
    from gps_denied_onboard.components.c3_matcher.base import NULL_FDR
    from gps_denied_onboard.components.c3_matcher.learned import LearnedPairMatcher
    from gps_denied_onboard.components.c10_cache_build.tile_features import build_tile_features
    from gps_denied_onboard.runtime_root.compose import StartupError, create_matcher, resolve_matcher

    try:
        config = resolve_matcher(daemon_cfg)
        matcher = create_matcher(config, {}, NULL_FDR)
    except StartupError as exc:
        raise SitlError(f"matcher.tile_features require: {exc}") from exc
    if not isinstance(matcher, LearnedPairMatcher):
        raise SitlError(f"matcher.tile_features require: {config.matcher.strategy!r} has no tile features")
    build_tile_features(cache_dir, matcher, progress=progress)


def run_sitl(opts: SitlOptions) -> dict[str, Any]:
    """Fly one scenario and return the report (also written to ``opts.report_path`` with a PNG)."""
    from gps_denied_onboard.components.c10_cache_build import CacheBuildError, build_cache_from_geotiff
    from gps_denied_onboard.components.c10_cache_build.map_fields import build_map_fields

    workdir = opts.workdir or opts.report_path.parent / "work"
    workdir.mkdir(parents=True, exist_ok=True)
    opts.report_path.parent.mkdir(parents=True, exist_ok=True)
    config_path = opts.config_path or DEFAULT_CONFIG
    if not config_path.is_file():
        raise SitlError(f"daemon profile {config_path} not found; pass --config")
    try:
        daemon_cfg = load_config(config_path, opts.overrides)
    except ConfigError as exc:
        raise SitlError(str(exc)) from exc
    ground_alt = daemon_cfg.terrain.ground_alt_amsl_m

    map_path = opts.map_path
    if map_path is None:
        from gps_denied_onboard.sitl.demo_map import generate_demo_map

        map_path = workdir / "demo_map.tif"
        if not map_path.is_file():
            generate_demo_map(map_path)
    try:
        scenario = load_scenario(opts.scenario)
        if opts.spoofed_start is not None:
            scenario = dataclasses.replace(
                scenario, spoofed_start=spoofed_start_from_yaml(opts.spoofed_start, "--spoofed-start")
            )
        map_renderer = MapRenderer(map_path)
        renderer = MapRenderer(opts.appearance_path) if opts.appearance_path else map_renderer
    except (ScenarioError, RenderError) as exc:
        raise SitlError(str(exc)) from exc
    bbox = map_renderer.bbox_lonlat
    if opts.appearance_path:
        bbox = _intersect(bbox, renderer.bbox_lonlat)
    try:
        trajectory = scenario.resolve(bbox, ground_alt)
    except ScenarioError as exc:
        raise SitlError(str(exc)) from exc
    if opts.duration_s is not None:
        trajectory = dataclasses.replace(trajectory, duration_s=min(trajectory.duration_s, opts.duration_s))

    cache_source = map_path
    if scenario.map_edits:
        from gps_denied_onboard.sitl.map_edit import MapEditError, apply_map_edits

        edited = workdir / f"map-{_sha_prefix(map_path)}-{scenario.name}.tif"
        try:
            cache_source = apply_map_edits(
                map_path, edited, trajectory, scenario.map_edits, map_renderer.ground_gsd_m
            )
        except MapEditError as exc:
            raise SitlError(str(exc)) from exc
    cache_dir = (opts.cache_root or workdir) / f"cache-{_sha_prefix(cache_source)}"
    t_cache = time.monotonic()
    try:
        build_cache_from_geotiff(cache_source, cache_dir, progress=not opts.quiet)
        build_map_fields(cache_dir, progress=not opts.quiet)  # as `gdnav cache build` does
        _build_vpr_index(daemon_cfg, cache_dir, progress=not opts.quiet)
        if daemon_cfg.matcher.tile_features == "require":  # the daemon refuses to start without them
            _build_tile_features(daemon_cfg, cache_dir, progress=not opts.quiet)
    except CacheBuildError as exc:
        raise SitlError(f"cannot build the cache from {map_path}: {exc}") from exc
    cache_s = time.monotonic() - t_cache

    shutil.rmtree(workdir / "fdr", ignore_errors=True)  # this run's records only
    try:
        flight = _Flight(
            opts,
            scenario,
            trajectory,
            renderer,
            config_path,
            cache_dir,
            workdir,
            ground_alt,
            daemon_nice=daemon_cfg.daemon.process_nice,
        )
    except HostFaultError as exc:
        raise SitlError(str(exc)) from exc
    try:
        ap = asyncio.run(flight.fly())
    finally:
        flight.host.finish(workdir / "fdr")

    def truth_at_unix(t_unix_s: float) -> tuple[float, float]:
        # Not clamped at the scenario's duration: the simulated vehicle flies on along its path during the
        # tail (its telemetry says so), and a truth frozen there would score a moving estimate as wrong.
        s = trajectory.truth_at(max(0.0, t_unix_s - flight.t0_unix_s))
        return s.lat_deg, s.lon_deg

    records = [*read_records(workdir / "fdr"), *read_records(workdir / "fdr" / CORE_FDR_SUBDIR)]
    report = score(flight.frames, ap.received, truth_at_unix, records, end_unix_s=flight.end_unix_s)
    ap.close()
    report["analysis"] = analyse(report, records, truth_at_unix)
    report.update(
        {
            "scenario": scenario.name,
            "map": str(map_path),
            "appearance": str(opts.appearance_path) if opts.appearance_path else None,
            "daemon_config": str(config_path),
            "daemon_overrides": list(opts.overrides),
            "matcher": _matcher_in_use(workdir / "daemon.log") or daemon_cfg.matcher.strategy,
            "daemon_exit_code": flight.daemon_exit_code,
            "daemon_restarts": restart_recovery(flight.restarts, ap.received, records),
            "faults_injected": flight.faults_injected,
            "t0_unix_s": flight.t0_unix_s,
            "daemon_rss_mib": _rss_summary(flight.rss_mib),
            "host_stalls": host_stall_summary(flight.host_samples),
            "daemon_stop_s": flight.daemon_stop_s,
            "cache_build_s": round(cache_s, 2),
            "heartbeats_received": len(ap.of_type("HEARTBEAT")),
            "machine": {
                "platform": platform.platform(),
                "cpus": os.cpu_count(),
                "python": platform.python_version(),
            },
            "daemon_log": str(workdir / "daemon.log"),
            "fdr_dir": str(workdir / "fdr"),
        }
    )
    opts.report_path.write_text(json.dumps(report, indent=2))
    plot_report(report, opts.report_path.with_suffix(".png"), title=f"{scenario.name} on {map_path.name}")
    return report


def host_stall_counters(proc: Path = Path("/proc")) -> dict[str, float] | None:
    """Cumulative counters of the host that tell a stall of the whole machine from one of the daemon, in
    seconds: the pressure-stall time during which every task waited on I/O (``io_full_s``) or on memory
    reclaim (``memory_full_s``), during which some task waited for a CPU (``cpu_some_s``) (Linux PSI,
    ``/proc/pressure``), and the CPU time the hypervisor gave to other guests (``steal_s``, ``/proc/stat``,
    at USER_HZ 100). A counter the kernel does not offer is left out; None when there is none at all."""
    out: dict[str, float] = {}
    for resource, line_kind in (("io", "full"), ("memory", "full"), ("cpu", "some")):
        try:
            text = (proc / "pressure" / resource).read_text()
        except OSError:
            continue
        for line in text.splitlines():
            fields = line.split()
            if fields and fields[0] == line_kind:
                total = next((f for f in fields if f.startswith("total=")), None)
                if total is not None:
                    out[f"{resource}_{line_kind}_s"] = int(total.split("=", 1)[1]) / 1e6
    try:
        cpu = (proc / "stat").read_text().splitlines()[0].split()
        if cpu[0] == "cpu" and len(cpu) > 8:
            out["steal_s"] = int(cpu[8]) / 100.0
    except (OSError, IndexError, ValueError):
        pass
    return out or None


def host_stall_summary(samples: list[tuple[float, dict[str, float]]]) -> dict[str, Any]:
    """For each host counter, its largest increase between two consecutive samples and where (flight
    time of the later sample): a stall of the daemon that coincides with one of these was the machine's."""
    worst: dict[str, dict[str, float]] = {}
    for (_t0, a), (t1, b) in itertools.pairwise(samples):
        for key in a.keys() & b.keys():
            inc = round(b[key] - a[key], 3)
            if key not in worst or inc > worst[key]["increase_s"]:
                worst[key] = {"increase_s": inc, "at_s": t1}
    return {"sample_s": RSS_SAMPLE_S, "samples": len(samples), "largest_increase": worst}


def _rss_summary(samples: list[tuple[float, float]]) -> dict[str, Any]:
    """Resident memory samples and the growth after warm-up: last sample vs the first one at or after
    RSS_WARMUP_S (None for a shorter flight)."""
    warm = [mib for t, mib in samples if t >= RSS_WARMUP_S]
    growth = (warm[-1] - warm[0]) / warm[0] if len(warm) >= 2 and warm[0] > 0 else None
    return {
        "samples": samples,
        "max": max((mib for _, mib in samples), default=None),
        "growth_after_warmup_frac": None if growth is None else round(growth, 4),
    }


def _matcher_in_use(log_path: Path) -> str | None:
    """The C3 strategies the daemon actually built (its c3.matcher.ready events), e.g. what 'auto' chose:
    one name, or the effort ladder's, cheapest rung first, joined by '+' ('orientation_corr+classical')."""
    built: list[str] = []
    area_first = False
    try:
        for line in log_path.read_text(errors="replace").splitlines():
            if '"c3.matcher.ready"' in line:
                name = str(json.loads(line).get("strategy"))
                if name not in built:
                    built.append(name)
            elif '"c3.matcher.auto_selected"' in line and json.loads(line).get("area_rung"):
                area_first = True
    except (OSError, ValueError):
        return None
    if area_first and "orientation_corr" in built:
        built.remove("orientation_corr")
        built.insert(0, "orientation_corr")
    return "+".join(built) or None


def summary_lines(report: dict[str, Any]) -> list[str]:
    h, lat = report["horizontal_error_m"], report["latency_ms"]

    def f(v: float | None, unit: str) -> str:
        return "n/a" if v is None else f"{v:.2f} {unit}"

    stream, cons = report["stream"], report["consistency"]
    iv = stream.get("interval_ms") or {}
    analysis = report.get("analysis") or {}
    offset = analysis.get("accepted_fix_offset_m")
    fixes = (
        f"fixes         {analysis.get('accepted_fixes')} accepted, "
        f"{analysis.get('accepted_fixes_beyond_3sigma')} beyond 3 sigma; shared offset "
        + (
            "n/a"
            if offset is None
            else f"{offset['length']:.2f} m (north {offset['north']:+.2f}, east {offset['east']:+.2f})"
        )
    )
    return [
        f"scenario      {report['scenario']}  (map {Path(report['map']).name}, matcher {report['matcher']})",
        f"frames        {report['frames']} sent, {report['frames_answered']} answered with GPS_INPUT",
        f"availability  {report['availability']:.3f}",
        f"horiz error   p50 {f(h['p50'], 'm')}  p95 {f(h['p95'], 'm')}  max {f(h['max'], 'm')}",
        f"latency       p50 {f(lat['p50'], 'ms')}  p95 {f(lat['p95'], 'ms')}  "
        f"(fix age p50 {f(report['fix_age_ms']['p50'], 'ms')})",
        f"consistency   {f(cons['within_2sigma'], '')} within 2 sigma, "
        f"{cons['beyond_3sigma']} beyond 3 sigma",
        f"GPS_INPUT     {report['gps_input_received']} msgs, interval mean {f(iv.get('mean_ms'), 'ms')} "
        f"p99 {f(iv.get('p99_ms'), 'ms')} max {f(iv.get('max_ms'), 'ms')}; ArduPilot health tripped: "
        f"{stream['health']['tripped']}, failsafe: {stream.get('ekf_failsafe_land_s')}"
        if stream.get("autopilot") != "px4"
        else f"GLOBAL_POS_S  {report['gps_input_received']} msgs, interval mean {f(iv.get('mean_ms'), 'ms')} "
        f"p99 {f(iv.get('p99_ms'), 'ms')} max {f(iv.get('max_ms'), 'ms')}; PX4 position timeouts "
        f"{stream.get('position_timeouts_s')}",
        *(
            [
                f"speed acc     p50 {f(sa.get('p50'), 'm/s')}  p95 {f(sa.get('p95'), 'm/s')}; "
                f"EKF3 glitch spans {report.get('glitch_spans_s', [])}"
            ]
            if (sa := report.get("speed_accuracy_m_s") or {})
            else []
        ),
        fixes,
        *([f"              {refused}"] if (refused := refused_fixes_line(analysis)) else []),
        *(
            [
                f"attempts      {analysis.get('fdr_fix_attempts')} at {rate:.2f}/s; exposure to judged fix "
                f"p50 {f(judged.get('p50'), 'ms')}  p95 {f(judged.get('p95'), 'ms')}; by rung "
                f"{analysis.get('rung_attempts')}"
            ]
            if (rate := analysis.get("fix_attempts_per_s")) is not None
            and (judged := analysis.get("judged_fix_latency_ms") or {}) is not None
            else []
        ),
        f"provenance    {report['provenance_counts']}",
        f"daemon exit   code {report['daemon_exit_code']} after SIGTERM in {f(report['daemon_stop_s'], 's')}",
    ]


def run_sitl_cli(args: argparse.Namespace) -> int:
    opts = SitlOptions(
        map_path=args.map,
        scenario=args.scenario,
        report_path=args.report,
        appearance_path=args.appearance,
        config_path=args.config,
        overrides=tuple(args.set or ()),
        workdir=args.workdir,
        duration_s=args.duration,
        quiet=args.quiet,
        spoofed_start=getattr(args, "spoofed_start", None),
    )
    report = run_sitl(opts)
    for line in summary_lines(report):
        print(line)
    print(f"report        {opts.report_path} (+ {opts.report_path.with_suffix('.png').name})")
    return 0 if report["daemon_exit_code"] == 0 else 1
