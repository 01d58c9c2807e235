"""Test harness: a real daemon process on loopback, with a small real cache and a real autopilot link."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def build_small_cache(root: Path) -> tuple[Path, Path]:
    """A 600 m procedural map and its cache (real GeoTIFF, real cache build). Returns (map, cache)."""
    from gps_denied_onboard.components.c10_cache_build import build_cache_from_geotiff
    from gps_denied_onboard.sitl.demo_map import generate_demo_map

    map_path = root / "map.tif"
    cache = root / "cache"
    if not map_path.exists():
        generate_demo_map(map_path, size_m=600.0, gsd_m=0.5)
    build_cache_from_geotiff(map_path, cache, progress=False)
    return map_path, cache


@dataclass
class DaemonProcess:
    proc: subprocess.Popen[bytes]
    mav_port: int
    cam_port: int
    log_path: Path
    fdr_dir: Path

    def log_text(self) -> str:
        return self.log_path.read_text(errors="replace")

    def stop(self, timeout_s: float = 10.0) -> int:
        if self.proc.poll() is None:
            self.proc.terminate()
        try:
            return self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait()


def daemon_command(mav_port: int, cam_port: int, fdr_dir: Path, *overrides: str) -> list[str]:
    """`gdnav run --config config/sitl.yaml` on loopback ports and an FDR directory of its own, plus
    ``overrides`` (KEY.PATH=VALUE)."""
    profile = REPO / "config" / "sitl.yaml"
    cmd = [sys.executable, "-m", "gps_denied_onboard.cli", "run", "--config", str(profile)]
    for item in (
        f"camera.source=tcp://127.0.0.1:{cam_port}",
        f"mavlink.url=udpin:127.0.0.1:{mav_port}",
        f"fdr.dir={fdr_dir}",
        *overrides,
    ):
        cmd += ["--set", item]
    return cmd


def start_daemon(
    workdir: Path, cache: Path, *, extra_env: dict[str, str] | None = None, overrides: tuple[str, ...] = ()
) -> DaemonProcess:
    mav_port, cam_port = free_udp_port(), free_tcp_port()
    log_path = workdir / "daemon.log"
    fdr_dir = workdir / "fdr"
    cmd = daemon_command(mav_port, cam_port, fdr_dir, f"cache.dir={cache}", *overrides)
    with log_path.open("wb") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=log, env={**os.environ, **(extra_env or {})})
    return DaemonProcess(proc, mav_port, cam_port, log_path, fdr_dir)


def wait_for(predicate, timeout_s: float, interval_s: float = 0.05) -> bool:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(interval_s)
    return False


def fly_small_map(
    root: Path, scenario: str, *, overrides: tuple[str, ...] = ("matcher.strategy=classical",), **options: Any
) -> dict[str, Any]:
    """One ``gdnav sitl run`` flight over the small procedural map (its cache built under ``root``), with
    the weights-free matcher unless ``overrides`` say otherwise; the report is ``root/out/report.json``.
    ``options``: further ``SitlOptions`` fields (``duration_s``, ``tail_s``...)."""
    from gps_denied_onboard.sitl.runner import SitlOptions, run_sitl

    root.mkdir(parents=True, exist_ok=True)
    map_path, _cache = build_small_cache(root)
    return run_sitl(
        SitlOptions(
            map_path=map_path,
            scenario=scenario,
            report_path=root / "out" / "report.json",
            workdir=root / "work",
            quiet=True,
            overrides=overrides,
            **options,
        )
    )


def demo_at_frame_rate(root: Path, frame_rate_hz: float) -> Path:
    """The bundled demo scenario with another camera frame rate, written under ``root``."""
    import yaml

    from gps_denied_onboard.sitl.scenario import BUILTIN_SCENARIOS_DIR

    demo = yaml.safe_load((BUILTIN_SCENARIOS_DIR / "demo.yaml").read_text())
    path = root / f"demo_{frame_rate_hz:g}hz.yaml"
    path.write_text(yaml.safe_dump({**demo, "name": path.stem, "frame_rate_hz": frame_rate_hz}))
    return path
