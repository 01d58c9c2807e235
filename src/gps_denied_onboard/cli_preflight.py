"""``gdnav preflight --config FILE``: everything that can be checked before flight, as a pass/fail table.

Input: the profile, ``--set`` overrides, ``--offline``, ``--timeout``. Output: one row per check, in
``CHECKS`` order, each saying what it checked and what it measured (or ``--json``); exit 0 when no check
fails (a skipped check is not a failure), 2 when the configuration is refused, 3 when any other check
fails, with one ``gdnav:`` line on stderr naming the first failure. Nothing is sent to the autopilot but
requests (TIMESYNC, PARAM_REQUEST_READ for PX4's ``EKF2_AGP0_*`` where GLOBAL_POSITION_SENSOR is an output),
and nothing is recorded in the FDR.

Rule: the checks call the composition root's own functions (``runtime_root.compose``) and the MAVLink
link's own port probe, so a pass means ``gdnav run`` gets past the same step: ``config``, ``cache``,
``models``, ``vpr``, ``tile_features``, ``calibration``, ``signing_key``, ``fdr``, ``mavlink_port``,
``camera`` and ``autopilot`` (online only), ``start_point``.

What each check does: docs/companion.md, "Preflight checks".
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import errno
import json
import math
import os
import shutil
import socket
import stat
import sys
import tempfile
import time
from collections.abc import AsyncGenerator, Callable
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

from gps_denied_onboard.components.c8_mavlink.px4_params import PX4_AGP_PARAMS, px4_agp_problems
from gps_denied_onboard.config import Config, ConfigError, load_config
from gps_denied_onboard.logging_setup import configure_logging

if TYPE_CHECKING:
    from collections.abc import Mapping

# Same values as ``cli``'s (not imported: ``cli`` imports this module).
EXIT_OK, EXIT_CONFIG, EXIT_RESOURCE = 0, 2, 3

#: Check names, in the order they run and are printed (also the ``name`` of each ``--json`` row).
CHECKS: Final[tuple[str, ...]] = (
    "config",
    "cache",
    "models",
    "vpr",
    "tile_features",
    "map_fields",
    "calibration",
    "signing_key",
    "fdr",
    "mavlink_port",
    "camera",
    "autopilot",
    "start_point",
)
#: Checks that need the camera and the autopilot to be there; ``--offline`` skips them.
ONLINE_CHECKS: Final[frozenset[str]] = frozenset({"camera", "autopilot"})
#: Default of ``--timeout``: the wait for the first frame and for HEARTBEAT + a TIMESYNC answer, s.
DEFAULT_TIMEOUT_S: Final[float] = 10.0
#: How often the autopilot check polls the link, s.
_POLL_INTERVAL_S: Final[float] = 0.02
#: PARAM_REQUEST_READ is asked again for the parameters not answered after this long, s.
_PARAM_RETRY_S: Final[float] = 0.5


class Status(str, Enum):
    PASS = "pass"
    FAIL = "fail"
    SKIP = "skip"


@dataclass(frozen=True)
class CheckResult:
    """One row of the table."""

    name: str
    status: Status
    #: What was checked (a path, a URL, a strategy).
    checked: str
    #: What was measured, or what is wrong.
    detail: str
    #: Wall time the check took, s.
    seconds: float = 0.0


class CheckFailed(Exception):
    """A check's failure: ``detail`` says what is wrong (the row's detail)."""

    def __init__(self, detail: str) -> None:
        super().__init__(detail)
        self.detail = detail


class _Skipped(Exception):
    """A check that does not apply: ``detail`` says why."""

    def __init__(self, detail: str) -> None:
        super().__init__(detail)
        self.detail = detail


class _DiscardFdr:
    """The matcher's FDR client during the models check: the preflight records nothing in the FDR."""

    def record(self, kind: str, fields: Mapping[str, object]) -> None:
        del kind, fields


def _refusals() -> tuple[type[Exception], ...]:
    """Typed refusals of the composition root and the link; a check that raises one fails with its
    message. Anything else is a bug and keeps its traceback."""
    from gps_denied_onboard.components.c8_mavlink import MavlinkConfigError
    from gps_denied_onboard.runtime_root import StartupError

    return (StartupError, MavlinkConfigError, CheckFailed)


def _run_check(name: str, checked: str, fn: Callable[[], str]) -> CheckResult:
    t0 = time.monotonic()
    try:
        detail = fn()
    except _Skipped as exc:
        return CheckResult(name, Status.SKIP, checked, exc.detail, time.monotonic() - t0)
    except _refusals() as exc:
        return CheckResult(name, Status.FAIL, checked, str(exc), time.monotonic() - t0)
    return CheckResult(name, Status.PASS, checked, detail, time.monotonic() - t0)


def _mib(n_bytes: float) -> str:
    if n_bytes >= 1 << 30:
        return f"{n_bytes / (1 << 30):.1f} GiB"
    return f"{n_bytes / (1 << 20):.1f} MiB"


# --- offline checks -------------------------------------------------------------------------------------


def _check_names(config: Config) -> str:
    from gps_denied_onboard.runtime_root.compose import _check_strategy_names

    _check_strategy_names(config)  # as compose_root refuses them
    return f"valid (profile {config.profile})"


def _check_cache(config: Config, opened: dict[str, Any]) -> str:
    # The full check, whatever cache.verify_hashes says: preflight is where every byte is read, so that
    # the daemon's start need not (its light check: docs/design.md, "Opening the cache in constant time").
    from gps_denied_onboard.components.c10_cache_build.manifest import Verification
    from gps_denied_onboard.runtime_root.compose import open_tile_store

    t0 = time.monotonic()
    tiles = open_tile_store(config, Verification.FULL, "gdnav preflight")
    dt = time.monotonic() - t0
    opened["tiles"] = tiles
    old = (
        ""
        if tiles.manifest.has_cell_crc
        else "; built without the cell CRC table, so every start reads the whole mosaic: add it with "
        f"`gdnav cache build --source <the same source> --out {config.cache.dir}`"
    )
    return (
        f"{len(tiles)} tiles, zoom {tiles.zoom}, {tiles.gsd_m_px:.2f} m/px; sha256 of every artifact "
        f"verified in {dt:.2f} s{old}"
    )


def _check_models(config: Config, opened: dict[str, Any]) -> str:
    # The same two steps as compose_root: resolve model_dir/auto (verifies the manifest), then build the
    # strategy, which creates its ONNX Runtime sessions.
    from gps_denied_onboard.runtime_root.compose import (
        WEIGHTS_FREE_MATCHERS,
        create_matcher,
        resolve_matcher,
    )

    resolved = resolve_matcher(config)
    opened["matcher_config"] = resolved  # the model directory is hashed once, for tile_features too
    strategy = resolved.matcher.strategy
    if strategy in WEIGHTS_FREE_MATCHERS:
        chose = (
            f"; matcher.strategy {config.matcher.strategy} chose it"
            if strategy != config.matcher.strategy
            else ""
        )
        raise _Skipped(f"not needed ({strategy}{chose})")
    t0 = time.monotonic()
    create_matcher(resolved, {}, _DiscardFdr())
    dt = time.monotonic() - t0
    files = sorted(
        Path(str(value)).name
        for f in dataclasses.fields(resolved.matcher)
        if f.name.endswith("_weights_path") and (value := getattr(resolved.matcher, f.name)) is not None
    )
    manifest = f"manifest of {resolved.matcher.model_dir} verified; " if resolved.matcher.model_dir else ""
    return f"{strategy}: {manifest}{', '.join(files) or 'no model file'} loaded in {dt:.2f} s"


def _opened_tiles(opened: dict[str, Any]) -> Any:
    if "tiles" not in opened:
        raise _Skipped("not checked (the cache did not open)")
    return opened["tiles"]


def _check_vpr(config: Config, opened: dict[str, Any]) -> str:
    from gps_denied_onboard.runtime_root.compose import create_vpr

    tiles = _opened_tiles(opened)
    t0 = time.monotonic()
    vpr = create_vpr(tiles, config)
    dt = time.monotonic() - t0
    if config.vpr.strategy == "geo_prior":
        return "geo_prior: searches the tiles around the prior, no index needed"
    return f"{config.vpr.strategy}: index of {len(tiles)} tiles opened in {dt:.2f} s ({type(vpr).__name__})"


def _check_tile_features(config: Config, opened: dict[str, Any]) -> str:
    from gps_denied_onboard.runtime_root.compose import WEIGHTS_FREE_MATCHERS, open_tile_features

    tiles = _opened_tiles(opened)
    if "matcher_config" not in opened:
        raise _Skipped("not checked (the matcher's model directory did not verify)")
    resolved = opened["matcher_config"]
    strategy, mode = resolved.matcher.strategy, resolved.matcher.tile_features
    if strategy in WEIGHTS_FREE_MATCHERS:
        raise _Skipped(f"not needed ({strategy} extracts chips live, cheaply)")
    if mode == "off":
        raise _Skipped("matcher.tile_features: off (every chip extracted live)")
    t0 = time.monotonic()
    feats = open_tile_features(resolved, tiles, _DiscardFdr())
    dt = time.monotonic() - t0
    if feats is None:  # auto, and absent or refused: open_tile_features raises under require
        return (
            f"{strategy}: none usable in the cache (matcher.tile_features: {mode}): every chip is "
            f"extracted live; build them with `gdnav cache features`"
        )
    return f"{strategy}: {len(feats)} tiles of precomputed features, sha256 verified, opened in {dt:.2f} s"


def _check_map_fields(config: Config, opened: dict[str, Any]) -> str:
    from gps_denied_onboard.runtime_root.compose import open_map_fields, with_area_rung

    tiles = _opened_tiles(opened)
    if "matcher_config" not in opened:
        raise _Skipped("not checked (the matcher's model directory did not verify)")
    resolved = with_area_rung(config, opened["matcher_config"], tiles)
    t0 = time.monotonic()
    fields = open_map_fields(resolved, tiles, _DiscardFdr())
    dt = time.monotonic() - t0
    if fields is None:
        info = tiles.manifest.map_fields
        has = "the cache has calibrated fields" if info is not None and info.calibrations else "none needed"
        raise _Skipped(f"not used (no rung runs orientation_corr; {has})")
    levels = ", ".join(
        f"level {c.level}: wrong places PSR <= {c.null_psr_max:.1f}, right p5 {c.right_psr_p5:.1f}"
        for c in fields.info.calibrations.values()
    )
    return f"orientation fields {fields.info.version}, sha256 verified, opened in {dt:.2f} s; {levels}"


def _check_calibration(config: Config) -> str:
    from gps_denied_onboard.runtime_root.compose import _calibration

    cal = _calibration(config)
    return (
        f"{cal.width_px}x{cal.height_px} px, fx {cal.fx_px:.1f} fy {cal.fy_px:.1f} px, "
        f"principal point ({cal.cx_px:.1f}, {cal.cy_px:.1f}), {len(cal.dist_coeffs)} distortion coefficients"
    )


def _check_signing_key(config: Config) -> str:
    from gps_denied_onboard.runtime_root.link_first import check_signing_key as check

    path = config.mavlink.signing_key_file
    if path is None:
        raise _Skipped("not configured (MAVLink unsigned)")
    check(config)
    return f"32-byte key, mode {stat.S_IMODE(Path(path).stat().st_mode):04o}"


def _check_fdr(config: Config) -> str:
    from gps_denied_onboard.components.c13_fdr import list_segments

    d = Path(config.fdr.dir)
    if d.exists():
        if not d.is_dir():
            raise CheckFailed(f"{d} is not a directory")
        # Proof by writing: permission bits say nothing under a read-only mount or a sandbox.
        try:
            fd, probe = tempfile.mkstemp(dir=d, prefix=".gdnav-preflight-")
            os.close(fd)
            os.unlink(probe)
        except OSError as exc:
            raise CheckFailed(f"cannot write in {d}: {exc.strerror}") from exc
        where, writable = d, f"{d} writable"
    else:
        # The recorder creates the directory itself; a missing parent is taken for a mistyped path.
        parent = d.parent
        if not parent.is_dir():
            raise CheckFailed(f"{d} does not exist, nor does its parent {parent}")
        try:
            os.rmdir(tempfile.mkdtemp(dir=parent, prefix=".gdnav-preflight-"))
        except OSError as exc:
            raise CheckFailed(
                f"{d} does not exist and cannot be created in {parent}: {exc.strerror}"
            ) from exc
        where, writable = parent, f"{d} can be created"
    read = _read_fdr(d) if d.is_dir() else "nothing recorded yet"
    # The recorder keeps every segment under max_bytes, its own earlier ones included: they count as room.
    recorded = sum(p.stat().st_size for p in list_segments(d))
    needed = max(0, config.fdr.max_bytes - recorded)
    free = shutil.disk_usage(where).free
    budget = f"fdr.max_bytes {_mib(config.fdr.max_bytes)}, {_mib(recorded)} already recorded"
    if free < needed:
        raise CheckFailed(
            f"{_mib(free)} free on the file system of {where}, {_mib(needed)} needed ({budget}): "
            f"{_mib(needed - free)} missing"
        )
    return f"{writable}; {read}; {_mib(free)} free >= {_mib(needed)} needed ({budget})"


def _read_fdr(d: Path) -> str:
    """Read every segment as the readers do (``c13_fdr.reader.scan``): fails on what the daemon's
    start-up read would have to skip for a reason other than a torn write."""
    from gps_denied_onboard.components.c13_fdr.reader import scan

    found = scan(d)
    if found.unreadable_segments:
        more = len(found.unreadable_segments) - 1
        raise CheckFailed(
            f"{found.unreadable_segments[0]}: segment cannot be read"
            + (f" (and {more} more)" if more else "")
        )
    if found.corrupt_lines:
        raise CheckFailed(
            f"{found.corrupt_lines} line(s) the recorder never writes, first {found.first_corrupt}: "
            "damaged or tampered; move the segment away"
        )
    torn = f", {found.torn_lines} torn line(s) skipped" if found.torn_lines else ""
    return f"{found.records} records in {found.segments} segment(s) read{torn}"


def _check_start_point(config: Config, opened: dict[str, Any], *, offline: bool) -> str:
    from gps_denied_onboard.geo import haversine_m

    init = config.init
    if init.lat_deg is not None and init.lon_deg is not None:
        lat, lon, what = init.lat_deg, init.lon_deg, "init.lat_deg/lon_deg"
    elif not init.use_home_position:
        raise _Skipped("none configured (init.use_home_position: false): the search starts on the whole map")
    elif opened.get("home") is None:
        why = "skipped with --offline" if offline else "not received during the autopilot check"
        raise _Skipped(f"HOME_POSITION is the start point: {why}")
    else:
        lat, lon, what = opened["home"][0], opened["home"][1], "HOME_POSITION"
    west, south, east, north = _opened_tiles(opened).bbox_lonlat
    near_lat, near_lon = min(max(lat, south), north), min(max(lon, west), east)
    off_m = float(haversine_m(lat, lon, near_lat, near_lon))
    where = f"{what} {lat:.6f}, {lon:.6f}"
    extent = f"the map covers W {west:.5f} S {south:.5f} E {east:.5f} N {north:.5f}"
    if off_m > init.sigma_m:
        raise CheckFailed(
            f"{where} is {off_m / 1000.0:.1f} km off the map ({extent}; init.sigma_m {init.sigma_m:g} m)"
        )
    if off_m > 0.0:
        return f"{where}: {off_m:.0f} m off the map's edge, within init.sigma_m ({init.sigma_m:g} m)"
    return f"{where}: on the map"


def _check_mavlink_port(config: Config, *, offline: bool, timeout_s: float) -> str:
    from gps_denied_onboard.components.c8_mavlink.link import _UDP_LISTEN_SCHEMES, _refuse_taken_udp_port

    url = config.mavlink.url
    if url.startswith(_UDP_LISTEN_SCHEMES):
        _refuse_taken_udp_port(url)
        return "UDP port not bound by another process"
    if url.startswith("udpout:"):
        raise _Skipped("udpout: sends only, nothing to bind")
    if url.startswith("tcp:"):
        if offline:
            raise _Skipped("tcp: client endpoint, not connected with --offline")
        host, _, port = url.split(":", 1)[1].rpartition(":")
        t0 = time.monotonic()
        try:
            with socket.create_connection((host, int(port)), timeout=timeout_s):
                pass
        except OSError as exc:
            raise CheckFailed(f"TCP connect to {host}:{port} failed: {exc.strerror or exc}") from exc
        return f"TCP {host}:{port} accepted a connection in {time.monotonic() - t0:.2f} s"
    if not url.startswith("/"):
        raise _Skipped("not a device path, UDP or TCP URL; not probed")
    # A serial device: opened the way pymavlink opens it, and closed again at once.
    try:
        fd = os.open(url, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError as exc:
        hint = " (is the service user in the dialout group?)" if exc.errno == errno.EACCES else ""
        raise CheckFailed(f"serial device {url} cannot be opened: {exc.strerror}{hint}") from exc
    os.close(fd)
    return f"serial device opens read-write (baud {config.mavlink.baud})"


# --- online checks --------------------------------------------------------------------------------------


async def _check_camera(config: Config, timeout_s: float) -> str:
    from gps_denied_onboard.camera.stream import FrameStreamError
    from gps_denied_onboard.runtime_root.compose import _calibration, open_camera_source

    cal = _calibration(config)
    source = open_camera_source(config)
    frames = source.frames()
    t0 = time.monotonic()
    try:
        frame = await asyncio.wait_for(anext(frames), timeout_s)
    except asyncio.TimeoutError as exc:
        raise CheckFailed(f"no frame within {timeout_s:g} s") from exc
    finally:
        if isinstance(frames, AsyncGenerator):
            await frames.aclose()
    waited = time.monotonic() - t0
    try:
        image = await asyncio.to_thread(frame.decode)  # OpenCV decode: off the event loop
    except FrameStreamError as exc:
        raise CheckFailed(f"first frame does not decode: {exc}") from exc
    h, w = image.shape[:2]
    if (w, h) != (cal.width_px, cal.height_px):
        raise CheckFailed(f"frame is {w}x{h} px, the calibration is for {cal.width_px}x{cal.height_px} px")
    return f"{w}x{h} px frame decoded after {waited:.2f} s"


def _read_px4_params(
    config: Config, link: Any, tracker: Any, deadline: float
) -> dict[str, float | None] | None:
    """PX4's ``EKF2_AGP0_*`` as read back before ``deadline`` (monotonic), or None when there is nothing to
    check: GLOBAL_POSITION_SENSOR is not among the outputs, or the autopilot is not PX4."""
    from gps_denied_onboard.components.c8_mavlink.messages import DIALECT

    if (
        "global_position_sensor" not in config.mavlink.outputs
        or tracker.autopilot_kind != DIALECT.MAV_AUTOPILOT_PX4
    ):
        return None
    values: dict[str, float | None] = dict.fromkeys(PX4_AGP_PARAMS)
    asked_at = -math.inf
    while time.monotonic() < deadline and any(value is None for value in values.values()):
        if time.monotonic() - asked_at > _PARAM_RETRY_S:
            link.request_params(tuple(name for name, value in values.items() if value is None))
            asked_at = time.monotonic()
        link.poll()
        values = {name: tracker.param(name) for name in PX4_AGP_PARAMS}
        time.sleep(_POLL_INTERVAL_S)
    return values


def _check_autopilot(config: Config, timeout_s: float, opened: dict[str, Any] | None = None) -> str:
    from gps_denied_onboard.components.c8_mavlink import MavlinkLink, TimeSource
    from gps_denied_onboard.runtime_root.link_first import make_tracker

    # As the daemon opens it (URL, signing, port probe), but listening only: with just GPS_INPUT among
    # the outputs the link sends nothing unasked, whereas vision_position_estimate would offer the
    # autopilot a global origin.
    mav = dataclasses.replace(config.mavlink, outputs=("gps_input",))
    tracker = make_tracker(config)
    link = MavlinkLink(mav, tracker)
    t0 = time.monotonic()
    heartbeat_s = time_s = None
    link.open()
    try:
        while time.monotonic() - t0 < timeout_s:
            link.poll()
            now = time.monotonic() - t0
            if heartbeat_s is None and tracker.autopilot_seen:
                heartbeat_s = now
            if time_s is None and tracker.time_source is TimeSource.TIMESYNC:
                time_s = now
            if heartbeat_s is not None and time_s is not None:
                break
            time.sleep(_POLL_INTERVAL_S)
        params = _read_px4_params(config, link, tracker, t0 + timeout_s)
    finally:
        link.close()
    if opened is not None:
        opened["home"] = tracker.home()  # for the start_point check: None when none came
    who = f"system {config.mavlink.autopilot_system_id}"
    if heartbeat_s is None:
        raise CheckFailed(f"no HEARTBEAT from {who} within {timeout_s:g} s")
    if time_s is None:
        raise CheckFailed(
            f"HEARTBEAT from {who} after {heartbeat_s:.2f} s, but no answer to TIMESYNC within "
            f"{timeout_s:g} s (time source: {tracker.time_source.value}); the daemon maps the autopilot's "
            "clock with TIMESYNC: route it between the two"
        )
    rtt = tracker.autopilot_clock.rtt_usec
    rtt_txt = f", round trip {rtt / 1000:.1f} ms" if rtt is not None else ""
    px4_txt = ""
    if params is not None:
        problems = px4_agp_problems(params, sensor_id=config.mavlink.global_position_sensor_id)
        if problems:
            raise CheckFailed("; ".join(p.detail for p in problems))
        px4_txt = ", PX4's EKF2_AGP0_ID, _CTRL and _DELAY are set for GLOBAL_POSITION_SENSOR"
    return (
        f"HEARTBEAT from {who} after {heartbeat_s:.2f} s, TIMESYNC answered after {time_s:.2f} s{rtt_txt}"
        f"{px4_txt}"
    )


async def _online(
    config: Config, timeout_s: float, opened: dict[str, Any] | None = None
) -> tuple[CheckResult, CheckResult]:
    """The camera and the autopilot checks, side by side (each waits up to ``timeout_s``)."""

    async def camera() -> CheckResult:
        t0 = time.monotonic()
        try:
            detail = await _check_camera(config, timeout_s)
        except _refusals() as exc:
            return CheckResult("camera", Status.FAIL, config.camera.source, str(exc), time.monotonic() - t0)
        return CheckResult("camera", Status.PASS, config.camera.source, detail, time.monotonic() - t0)

    autopilot = asyncio.to_thread(
        _run_check, "autopilot", config.mavlink.url, lambda: _check_autopilot(config, timeout_s, opened)
    )
    cam, ap = await asyncio.gather(camera(), autopilot)
    return cam, ap


# --- the command ----------------------------------------------------------------------------------------


def run_checks(config: Config, checked_config: str, *, offline: bool, timeout_s: float) -> list[CheckResult]:
    """Every check after ``config`` (already loaded), in ``CHECKS`` order."""
    opened: dict[str, Any] = {}  # the cache and the resolved matcher, once, for the checks that use them
    results = [
        _run_check("config", checked_config, lambda: _check_names(config)),
        _run_check("cache", config.cache.dir, lambda: _check_cache(config, opened)),
        _run_check(
            "models", f"matcher.strategy {config.matcher.strategy}", lambda: _check_models(config, opened)
        ),
        _run_check("vpr", f"vpr.strategy {config.vpr.strategy}", lambda: _check_vpr(config, opened)),
        _run_check(
            "tile_features",
            f"matcher.tile_features {config.matcher.tile_features}",
            lambda: _check_tile_features(config, opened),
        ),
        _run_check(
            "map_fields",
            f"matcher.strategy {config.matcher.strategy}",
            lambda: _check_map_fields(config, opened),
        ),
        _run_check(
            "calibration",
            config.camera.calibration_file or "camera.intrinsics",
            lambda: _check_calibration(config),
        ),
        _run_check(
            "signing_key",
            config.mavlink.signing_key_file or "mavlink.signing_key_file",
            lambda: _check_signing_key(config),
        ),
        _run_check("fdr", config.fdr.dir, lambda: _check_fdr(config)),
        _run_check(
            "mavlink_port",
            config.mavlink.url,
            lambda: _check_mavlink_port(config, offline=offline, timeout_s=timeout_s),
        ),
    ]
    if offline:
        results += [
            CheckResult("camera", Status.SKIP, config.camera.source, "skipped (--offline)"),
            CheckResult("autopilot", Status.SKIP, config.mavlink.url, "skipped (--offline)"),
        ]
    else:
        results += asyncio.run(_online(config, timeout_s, opened))
    checked = (
        "init.lat_deg/lon_deg"
        if config.init.lat_deg is not None and config.init.lon_deg is not None
        else "HOME_POSITION"
    )
    results.append(
        _run_check("start_point", checked, lambda: _check_start_point(config, opened, offline=offline))
    )
    return results


def format_table(results: list[CheckResult]) -> str:
    header = ("check", "result", "checked", "detail")
    rows = [header] + [(r.name, r.status.value.upper(), r.checked, r.detail) for r in results]
    widths = [max(len(row[i]) for row in rows) for i in range(3)]
    return "\n".join(
        "  ".join(cell.ljust(width) for cell, width in zip(row[:3], widths, strict=True)) + "  " + row[3]
        for row in rows
    )


def _to_json(results: list[CheckResult], code: int) -> dict[str, Any]:
    return {
        "ok": code == EXIT_OK,
        "exit_code": code,
        "checks": [
            {**dataclasses.asdict(r), "status": r.status.value, "seconds": round(r.seconds, 3)}
            for r in results
        ],
    }


def _cmd_preflight(args: argparse.Namespace) -> int:
    # Error-level JSON log lines only: the table is the report, and it goes to stdout.
    configure_logging("error", json=True)
    checked_config = str(args.config) + (f" (+{len(args.set)} --set)" if args.set else "")
    try:
        config = load_config(args.config, args.set or ())
    except ConfigError as exc:
        results = [CheckResult("config", Status.FAIL, checked_config, str(exc))] + [
            CheckResult(name, Status.SKIP, "", "not checked (configuration refused)") for name in CHECKS[1:]
        ]
        code = EXIT_CONFIG
    else:
        results = run_checks(config, checked_config, offline=args.offline, timeout_s=args.timeout)
        code = EXIT_RESOURCE if any(r.status is Status.FAIL for r in results) else EXIT_OK
    print(json.dumps(_to_json(results, code), indent=2) if args.json else format_table(results))
    failed = [r for r in results if r.status is Status.FAIL]
    if failed:
        more = f" (and {len(failed) - 1} more failed check(s))" if len(failed) > 1 else ""
        print(f"gdnav: preflight: {failed[0].name}: {failed[0].detail}{more}", file=sys.stderr)
    return code


def _positive_seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, got {text!r}")
    return value


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``preflight``; returns its parser."""
    p = subparsers.add_parser(
        "preflight",
        help="check everything that can be checked before flight (pass/fail table)",
        description="Check the profile, the cache (hashes), the models, the calibration, the signing key, "
        "the FDR directory and the MAVLink port, then (unless --offline) that the camera delivers a frame "
        "and the autopilot its HEARTBEAT and a TIMESYNC answer. Exit 0: all pass; 2: bad profile; 3: another "
        "check failed.",
    )
    p.add_argument("--config", required=True, type=Path, help="YAML profile, e.g. config/airborne.yaml")
    p.add_argument(
        "--set", action="append", metavar="KEY.PATH=VALUE", help="override one setting (repeatable)"
    )
    p.add_argument("--offline", action="store_true", help="skip the camera and autopilot checks")
    p.add_argument(
        "--timeout",
        type=_positive_seconds,
        default=DEFAULT_TIMEOUT_S,
        metavar="S",
        help="how long to wait for the camera's first frame and for the autopilot's messages, s "
        f"(default {DEFAULT_TIMEOUT_S:g})",
    )
    p.add_argument("--json", action="store_true", help="print the checks as one JSON object")
    p.set_defaults(func=_cmd_preflight)
    return p
