"""Faults of the companion computer the daemon runs on, injected for real during a SITL flight.

The scenario's ``clock_jump``, ``ort_fault``, ``tile_corrupt``, ``fdr_full`` and ``cpu_hogs`` faults
(``sitl.scenario``) are not messages the simulator sends but things that happen to the daemon's host.
Each is made to happen for real, to the unmodified daemon process, without touching the machine itself:
- ``clock_jump``: the host's wall clock steps for the daemon through libfaketime (preloaded, its offset
  read from a file this module rewrites ``CLOCK_STEP_LEAD_S`` before a whole second, re-read once per
  wall second; the monotonic clock is not faked); the SITL camera stamps with the stepped clock
  (``Scenario.wall_step_s``); the autopilot's clock does not step;
- ``ort_fault``: ONNX Runtime itself refuses the next ``count`` runs through the C7 test hook
  (``GDNAV_TEST_ORT_FAULT_FILE``); with a weights-free matcher the count is never consumed;
- ``tile_corrupt``: the map cell under the aircraft's position 3 s later is overwritten with noise in the
  run's own copy of the cache, in place, and put back at the window's end;
- ``fdr_full``: the FDR's directory is a tmpfs mounted for the run, filled to its last byte by a ballast
  file during the window; the records are copied to ``<workdir>/fdr`` afterwards. Mounting needs root;
  without it the run is refused with a message naming the fault;
- ``cpu_hogs``: ``processes`` busy processes (each a Python interpreter spinning) at nice 0 for the
  window, each in its own session, killed at the window's end or when the flight ends (``CpuHogs``).

Why libfaketime is re-read only once a second, and the rest in full: docs/design.md,
"`sitl/host_faults.py`: host faults".
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import importlib.util
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np

from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.components.c7_inference.onnx_runtime import ORT_FAULT_FILE_ENV
from gps_denied_onboard.components.c10_cache_build.manifest import Verification
from gps_denied_onboard.sitl.scenario import Fault, FaultKind, Scenario, Trajectory

#: How far ahead of the aircraft the corrupted cell lies, s (the fix path reads it when it gets there).
TILE_CORRUPT_LEAD_S = 3.0
#: Size of the flight data recorder's own file system for ``fdr_full``, MiB (the recorder's default
#: low-disk threshold is 64 MiB free: it stays "ok" until the ballast arrives).
FDR_FS_MIB = 256


class HostFaultError(RuntimeError):
    """A host fault cannot be set up on this machine (missing libfaketime, no permission to mount)."""


def libfaketime_path() -> Path:
    """The libfaketime shared library shipped by the ``libfaketime`` package (a dev dependency)."""
    spec = importlib.util.find_spec("libfaketime")
    if spec is None or not spec.submodule_search_locations:
        raise HostFaultError(
            "the clock_jump fault needs the libfaketime package (pip install libfaketime; part of the dev "
            "extra): it steps the daemon's wall clock without changing the machine's"
        )
    lib = (
        Path(next(iter(spec.submodule_search_locations)))
        / "vendor"
        / "libfaketime"
        / "src"
        / "libfaketime.so.1"
    )
    if not lib.is_file():
        raise HostFaultError(f"libfaketime package found but not its library {lib}")
    return lib


#: How long before the whole second a clock step takes effect in its offset file is rewritten, s: the
#: daemon reads the clock many times a second, so it has read the old offset in the second before.
CLOCK_STEP_LEAD_S: Final[float] = 0.25


def _write_atomic(path: Path, text: str) -> None:
    """Readers never see a half-written file (libfaketime rereads it once per wall second)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _is_mount(path: Path) -> bool:
    try:
        mounts = Path("/proc/mounts").read_text().split("\n")
    except OSError:
        return False
    return any(len(parts) > 1 and parts[1] == str(path) for parts in (m.split() for m in mounts))


@dataclass
class HostSetup:
    """What the runner changes for the daemon: extra environment, ``--set`` overrides, the cache it uses."""

    env: dict[str, str] = field(default_factory=dict)
    overrides: list[str] = field(default_factory=list)
    cache_dir: Path | None = None


#: What each busy process runs: nothing but the CPU.
_BUSY_LOOP = "while True:\n    pass\n"


def child_pids(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (Linux ``/proc``): a navigator core's vision worker."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        # pid (comm) state ppid ...: comm may hold spaces and parentheses, so split after the last ')'
        fields = stat[stat.rfind(")") + 2 :].split()
        if len(fields) > 1 and int(fields[1]) == pid:
            out.append(int(entry.name))
    return sorted(out)


class CpuHogs:
    """The ``cpu_hogs`` fault: busy processes on the daemon's host while it is on."""

    def __init__(self) -> None:
        self._procs: list[subprocess.Popen[bytes]] = []

    def start(self, processes: int) -> dict[str, Any]:
        """Start ``processes`` busy processes (more, if some already run); their pids and nice values."""
        started = [
            subprocess.Popen(
                [sys.executable, "-c", _BUSY_LOOP],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                start_new_session=True,
            )
            for _ in range(processes)
        ]
        self._procs += started
        nice: list[int | None] = []
        for proc in started:
            # nice 0, as ordinary load is, whatever the runner's: lowering a nice value needs
            # CAP_SYS_NICE; without it the process keeps the runner's, and the report says which
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, proc.pid, 0)
            try:
                nice.append(os.getpriority(os.PRIO_PROCESS, proc.pid))
            except OSError:
                nice.append(None)
        return {"processes": len(started), "pids": [p.pid for p in started], "nice": nice}

    def stop(self) -> dict[str, Any]:
        """Kill every busy process and wait for them."""
        procs, self._procs = self._procs, []
        for proc in procs:
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
        for proc in procs:
            proc.wait()
        return {"stopped": len(procs)}


class HostFaults:
    """Prepares, injects and cleans up the host faults of one flight (see the module docstring)."""

    def __init__(
        self,
        scenario: Scenario,
        trajectory: Trajectory,
        workdir: Path,
        cache_dir: Path,
        injected: list[dict[str, Any]],
    ) -> None:
        self.scenario = scenario
        self.traj = trajectory
        self.workdir = workdir
        self.cache_dir = cache_dir
        self.injected = injected
        self._faketime_file = workdir / "faketime_offset"
        self._ort_file = workdir / "ort_fault"
        self._fdr_fs = workdir / "fdr_fs"
        self._ballast = self._fdr_fs / "ballast"
        self._mounted = False
        self._store: TileStore | None = None
        self._restore: dict[tuple[int, int], np.ndarray] = {}
        self._hogs = CpuHogs()

    @property
    def kinds(self) -> set[FaultKind]:
        return {f.kind for f in self.scenario.faults}

    def prepare(self) -> HostSetup:
        """Set up what the faults need before the daemon starts (raises HostFaultError)."""
        setup = HostSetup()
        kinds = self.kinds
        if FaultKind.CLOCK_JUMP in kinds:
            _write_atomic(self._faketime_file, "+0\n")
            setup.env.update(
                {
                    "LD_PRELOAD": str(libfaketime_path()),
                    "FAKETIME_TIMESTAMP_FILE": str(self._faketime_file),
                    "FAKETIME_DONT_FAKE_MONOTONIC": "1",
                    # re-read at the first clock read of each wall second (see the module docstring)
                    "FAKETIME_CACHE_DURATION": "0",
                }
            )
        if FaultKind.ORT_FAULT in kinds:
            self._ort_file.unlink(missing_ok=True)
            setup.env[ORT_FAULT_FILE_ENV] = str(self._ort_file)
        if FaultKind.TILE_CORRUPT in kinds:
            run_cache = self.workdir / "cache-run"
            shutil.rmtree(run_cache, ignore_errors=True)
            shutil.copytree(self.cache_dir, run_cache)
            self.cache_dir = run_cache
            setup.cache_dir = run_cache
            self._store = TileStore.open(run_cache, Verification.LIGHT)
        if FaultKind.FDR_FULL in kinds:
            self._mount_fdr_fs()
            setup.overrides.append(f"fdr.dir={self._fdr_fs / 'fdr'}")
        return setup

    def _mount_fdr_fs(self) -> None:
        self._fdr_fs.mkdir(parents=True, exist_ok=True)
        if _is_mount(self._fdr_fs):  # left by an interrupted run
            subprocess.run(["umount", str(self._fdr_fs)], check=False, capture_output=True)
        done = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={FDR_FS_MIB}m,mode=0755", "tmpfs", str(self._fdr_fs)],
            check=False,
            capture_output=True,
            text=True,
        )
        if done.returncode != 0:
            raise HostFaultError(
                f"the fdr_full fault needs a small file system of its own for the FDR: mounting a tmpfs "
                f"on {self._fdr_fs} failed ({done.stderr.strip() or done.returncode}); run as root"
            )
        self._mounted = True

    async def run(self, t0_unix_s: float, stop: asyncio.Event) -> None:
        """Inject every host fault at its flight time (windows: start and end)."""
        events: list[tuple[float, int, Fault, bool]] = []
        for i, f in enumerate(self.scenario.faults):
            if f.kind is FaultKind.CLOCK_JUMP:  # read by the daemon at the next whole second, at_s
                events.append((f.from_s - CLOCK_STEP_LEAD_S, i, f, True))
            elif f.kind is FaultKind.ORT_FAULT:
                events.append((f.from_s, i, f, True))
            elif f.kind in (FaultKind.TILE_CORRUPT, FaultKind.FDR_FULL, FaultKind.CPU_HOGS):
                events.append((f.from_s, i, f, True))
                events.append((f.to_s, i, f, False))
        for at_s, _, fault, start in sorted(events, key=lambda e: (e[0], e[1])):
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(stop.wait(), max(0.0, t0_unix_s + at_s - time.time()))
            if stop.is_set():
                return
            self._inject(fault, start, fault.from_s if fault.kind is FaultKind.CLOCK_JUMP else at_s)

    def _inject(self, fault: Fault, start: bool, at_s: float) -> None:
        entry: dict[str, Any] = {"kind": fault.kind.value, "t_s": round(at_s, 3)}
        if fault.kind is FaultKind.CLOCK_JUMP:
            total = self.scenario.wall_step_s(at_s)
            _write_atomic(self._faketime_file, f"{total:+.3f}\n")
            entry.update(step_s=fault.step_s, wall_offset_s=total)
        elif fault.kind is FaultKind.ORT_FAULT:
            _write_atomic(self._ort_file, f"{fault.count}\n")
            entry.update(count=fault.count)
        elif fault.kind is FaultKind.TILE_CORRUPT:
            entry.update(self._corrupt_tile(at_s) if start else self._restore_tiles())
            entry["phase"] = "start" if start else "end"
        elif fault.kind is FaultKind.FDR_FULL:
            entry.update(self._fill_fdr_fs() if start else self._empty_fdr_fs())
            entry["phase"] = "start" if start else "end"
        elif fault.kind is FaultKind.CPU_HOGS:
            entry.update(self._hogs.start(fault.processes) if start else self._hogs.stop())
            entry["phase"] = "start" if start else "end"
        self.injected.append(entry)

    # -- tiles ----------------------------------------------------------------------------------------

    def _mosaic_file(self) -> tuple[Path, int, int]:
        store = self._store
        if store is None:
            raise HostFaultError("tile_corrupt without a prepared cache")
        path = self.cache_dir / store.manifest.mosaic_name
        arr = np.load(path, mmap_mode="r")
        return path, int(arr.offset), int(arr.shape[1])

    def _corrupt_tile(self, at_s: float) -> dict[str, Any]:
        store = self._store
        if store is None:
            raise HostFaultError("tile_corrupt without a prepared cache")
        truth = self.traj.truth_at(at_s + TILE_CORRUPT_LEAD_S)
        col_px, row_px = store.lonlat_to_mosaic_px(np.array(truth.lon_deg), np.array(truth.lat_deg))
        ts = store.tile_size_px
        row, col = int(row_px) // ts, int(col_px) // ts
        path, offset, width = self._mosaic_file()
        noise = np.random.default_rng(row * 10_007 + col).integers(0, 256, (ts, ts * 3), dtype=np.uint8)
        with path.open("r+b") as f:
            original = np.zeros((ts, ts * 3), np.uint8)
            for r in range(ts):
                f.seek(offset + ((row * ts + r) * width + col * ts) * 3)
                original[r] = np.frombuffer(f.read(ts * 3), np.uint8)
                f.seek(offset + ((row * ts + r) * width + col * ts) * 3)
                f.write(noise[r].tobytes())
            f.flush()
            os.fsync(f.fileno())
        self._restore.setdefault((row, col), original)
        tr = store.manifest.tile_range
        return {"x": tr.x0 + col, "y": tr.y0 + row, "zoom": store.zoom, "mosaic": str(path)}

    def _restore_tiles(self) -> dict[str, Any]:
        if not self._restore:
            return {"restored": 0}
        path, offset, width = self._mosaic_file()
        ts = self._store.tile_size_px if self._store is not None else 0
        with path.open("r+b") as f:
            for (row, col), original in self._restore.items():
                for r in range(ts):
                    f.seek(offset + ((row * ts + r) * width + col * ts) * 3)
                    f.write(original[r].tobytes())
            f.flush()
            os.fsync(f.fileno())
        n = len(self._restore)
        self._restore.clear()
        return {"restored": n}

    # -- the FDR's file system ------------------------------------------------------------------------

    def _fill_fdr_fs(self) -> dict[str, Any]:
        written = 0
        fd = os.open(self._ballast, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        try:
            for chunk in (b"\0" * (1 << 20), b"\0" * 4096):  # then page by page: to the last byte
                while True:
                    try:
                        written += os.write(fd, chunk)
                    except OSError as exc:
                        if exc.errno != errno.ENOSPC:
                            raise
                        break
        finally:
            os.close(fd)
        return {"filled_bytes": written, "free_bytes_after": shutil.disk_usage(self._fdr_fs).free}

    def _empty_fdr_fs(self) -> dict[str, Any]:
        self._ballast.unlink(missing_ok=True)
        return {"free_bytes_after": shutil.disk_usage(self._fdr_fs).free}

    # -- after the flight -----------------------------------------------------------------------------

    def finish(self, fdr_dir: Path) -> None:
        """Put everything back: tiles restored, the FDR copied to ``fdr_dir`` and its tmpfs unmounted;
        note how much of the ORT fault's count was not consumed; no busy process outlives the flight."""
        self._hogs.stop()
        with contextlib.suppress(OSError, HostFaultError):
            self._restore_tiles()
        if self._ort_file.exists():
            with contextlib.suppress(OSError, ValueError):
                self.injected.append(
                    {"kind": FaultKind.ORT_FAULT.value, "not_consumed": int(self._ort_file.read_text())}
                )
        if self._mounted:
            self._ballast.unlink(missing_ok=True)
            shutil.rmtree(fdr_dir, ignore_errors=True)
            if (self._fdr_fs / "fdr").is_dir():
                shutil.copytree(self._fdr_fs / "fdr", fdr_dir)
            subprocess.run(["umount", str(self._fdr_fs)], check=False, capture_output=True)
            self._mounted = False
