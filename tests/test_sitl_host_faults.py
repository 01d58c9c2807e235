"""The SITL's host faults without a flight: the map cell the tile_corrupt fault overwrites is the one the
aircraft reaches, the daemon's store masks it, and the run's copy of the cache gets its exact bytes back;
the shared cache is never touched."""

from __future__ import annotations

import hashlib
import os
import time
from pathlib import Path

import numpy as np
import pytest

from daemon_harness import build_small_cache
from gps_denied_onboard.components.c6_tiles.store import TileStore
from gps_denied_onboard.sitl.host_faults import TILE_CORRUPT_LEAD_S, HostFaults
from gps_denied_onboard.sitl.render import MapRenderer
from gps_denied_onboard.sitl.scenario import Scenario, ScenarioError, scenario_from_mapping


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _scenario(faults: list[dict[str, object]]) -> Scenario:
    """A short straight flight over the map with ``faults``."""
    return scenario_from_mapping(
        {
            "name": "t",
            "alt_agl_m": 100.0,
            "waypoints": {"frame": "map_relative", "points": [[0.3, 0.3], [0.7, 0.7]]},
            "faults": faults,
        }
    )


def test_tile_corrupt_hits_the_cell_ahead_and_restores_its_bytes(tmp_path: Path) -> None:
    """At the window's start the cell under the aircraft 3 s later is overwritten in the run's copy (the
    daemon's open store masks it and reports that cell); at its end the copy is byte-identical again."""
    map_path, cache = build_small_cache(tmp_path)
    shared_sha = _sha(cache / TileStore.open(cache).manifest.mosaic_name)
    scenario = _scenario([{"kind": "tile_corrupt", "from_s": 5.0, "to_s": 6.0}])
    traj = scenario.resolve(MapRenderer(map_path).bbox_lonlat, 400.0)
    injected: list[dict] = []
    host = HostFaults(scenario, traj, tmp_path / "work", cache, injected)
    (tmp_path / "work").mkdir()
    setup = host.prepare()
    assert setup.cache_dir is not None and setup.cache_dir != cache
    daemon_store = TileStore.open(setup.cache_dir)
    seen: list[dict] = []
    daemon_store.on_corrupt = seen.append
    mosaic = setup.cache_dir / daemon_store.manifest.mosaic_name
    before = _sha(mosaic)
    fault = scenario.faults[0]
    host._inject(fault, True, 5.0)
    assert _sha(mosaic) != before
    hit = injected[-1]
    truth = traj.truth_at(5.0 + TILE_CORRUPT_LEAD_S)
    tile_id = daemon_store.tiles_near(truth.lat_deg, truth.lon_deg, 200.0, k=1)[0][0]
    chip = daemon_store.chip(tile_id, 3 * daemon_store.tile_size_px)
    assert [(s["x"], s["y"]) for s in seen] == [(hit["x"], hit["y"])]
    assert not np.all(chip.pixels().any(axis=-1)), "the corrupt cell was not masked"
    host._inject(fault, False, 6.0)
    assert _sha(mosaic) == before and injected[-1]["restored"] == 1
    assert _sha(cache / daemon_store.manifest.mosaic_name) == shared_sha
    host.finish(tmp_path / "work" / "fdr")


def test_clock_jump_and_ort_fault_files_are_what_libfaketime_and_the_hook_read(tmp_path: Path) -> None:
    """clock_jump writes the host's total offset for libfaketime (the daemon preloads it, monotonic left
    alone); ort_fault writes the count the C7 hook consumes."""
    pytest.importorskip("libfaketime")
    scenario = _scenario(
        [
            {"kind": "clock_jump", "at_s": 1.0, "step_s": -30.0},
            {"kind": "clock_jump", "at_s": 2.0, "step_s": 3600.0},
            {"kind": "ort_fault", "at_s": 1.5, "count": 4},
        ]
    )
    host = HostFaults(scenario, None, tmp_path, tmp_path, [])  # type: ignore[arg-type]
    setup = host.prepare()
    assert setup.env["LD_PRELOAD"].endswith("libfaketime.so.1") and Path(setup.env["LD_PRELOAD"]).is_file()
    assert setup.env["FAKETIME_DONT_FAKE_MONOTONIC"] == "1"
    offset_file = Path(setup.env["FAKETIME_TIMESTAMP_FILE"])
    assert offset_file.read_text().strip() == "+0"
    jumps = [f for f in scenario.faults if f.kind.value == "clock_jump"]
    host._inject(jumps[0], True, 1.0)
    assert offset_file.read_text().strip() == "-30.000"
    host._inject(jumps[1], True, 2.0)
    assert offset_file.read_text().strip() == "+3570.000"
    ort = next(f for f in scenario.faults if f.kind.value == "ort_fault")
    host._inject(ort, True, 1.5)
    assert Path(setup.env["GDNAV_TEST_ORT_FAULT_FILE"]).read_text().strip() == "4"


#: A process that reads the wall clock from four threads for ``argv[1]`` seconds and prints how far its
#: wall clock is from true time (its monotonic clock is not faked) at the start and at the end.
_CLOCK_READERS = """
import sys, threading, time
def offset():
    return time.time() - (time.monotonic() + BASE)
BASE = time.time() - time.monotonic()
start = offset()
end_at = time.monotonic() + float(sys.argv[1])
def read():
    while time.monotonic() < end_at:
        time.time()
threads = [threading.Thread(target=read) for _ in range(4)]
[t.start() for t in threads]
[t.join() for t in threads]
print(f"{start:.3f} {offset():.3f}")
"""


@pytest.mark.slow
def test_a_clock_step_reaches_a_process_reading_the_clock_from_many_threads(tmp_path: Path) -> None:
    """The daemon's environment for clock_jump (libfaketime preloaded): four threads read the wall clock
    without pause while the offset file is rewritten with each step, and the process lives and sees the
    step. libfaketime re-reading the file on every read (FAKETIME_NO_CACHE) ended such a process within
    6 s in 3 of 3 runs ("failed to parse FAKETIME timestamp", exit 1), as it ended one daemon in a
    `faults` flight; once per wall second it survived 3 of 3 (about 3 million reads each)."""
    import subprocess
    import sys
    import time

    pytest.importorskip("libfaketime")
    scenario = _scenario(
        [
            {"kind": "clock_jump", "at_s": 1.0, "step_s": 30.0},
            {"kind": "clock_jump", "at_s": 2.0, "step_s": -10.0},
            {"kind": "clock_jump", "at_s": 3.0, "step_s": 20.0},
        ]
    )
    host = HostFaults(scenario, None, tmp_path, tmp_path, [])  # type: ignore[arg-type]
    setup = host.prepare()
    proc = subprocess.Popen(
        [sys.executable, "-c", _CLOCK_READERS, "6"],
        env={**os.environ, **setup.env},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    for fault in scenario.faults:  # one step about every 0.4 s, then the last one stays
        time.sleep(0.4)
        host._inject(fault, True, fault.from_s)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    start, end = (float(v) for v in out.split())
    assert abs(start) < 0.5 and end == pytest.approx(40.0, abs=0.5), out


def _cpu_ticks(pid: int) -> int:
    """User + system CPU time the process has used, clock ticks (/proc/<pid>/stat fields 14 and 15)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])


def test_cpu_hogs_run_busy_processes_at_nice_zero_for_the_window(tmp_path: Path) -> None:
    """The window's start starts ``processes`` processes that burn CPU, at nice 0 where the runner may
    set it (the report says which nice they got); its end kills them all, and so does the flight's end."""
    scenario = _scenario([{"kind": "cpu_hogs", "from_s": 5.0, "to_s": 6.0, "processes": 2}])
    traj = scenario.resolve((8.0, 47.0, 8.01, 47.01), 400.0)
    injected: list[dict] = []
    (tmp_path / "work").mkdir()
    host = HostFaults(scenario, traj, tmp_path / "work", tmp_path, injected)
    fault = scenario.faults[0]
    assert fault.processes == 2
    host._inject(fault, True, 5.0)
    started = injected[-1]
    assert started["kind"] == "cpu_hogs" and started["phase"] == "start" and len(started["pids"]) == 2
    before = [_cpu_ticks(pid) for pid in started["pids"]]
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline and not all(
        _cpu_ticks(pid) - b >= 10 for pid, b in zip(started["pids"], before, strict=True)
    ):
        time.sleep(0.05)
    assert all(_cpu_ticks(pid) - b >= 10 for pid, b in zip(started["pids"], before, strict=True))
    if os.geteuid() == 0:
        assert started["nice"] == [0, 0]
    else:
        assert started["nice"] == [os.getpriority(os.PRIO_PROCESS, 0)] * 2
    host._inject(fault, False, 6.0)
    assert injected[-1] == {"kind": "cpu_hogs", "t_s": 6.0, "stopped": 2, "phase": "end"}
    assert not any(Path(f"/proc/{pid}").exists() for pid in started["pids"])
    host._inject(fault, True, 5.0)
    again = injected[-1]["pids"]
    host.finish(tmp_path / "fdr")  # the flight ends inside the window
    assert not any(Path(f"/proc/{pid}").exists() for pid in again)


@pytest.mark.parametrize(
    ("fault", "message"),
    [
        ({"kind": "cpu_hogs", "from_s": 1.0, "to_s": 2.0, "processes": 0}, "expected an integer >= 1"),
        ({"kind": "cpu_hogs", "from_s": 1.0, "to_s": 2.0, "processes": 65}, "at most 64 busy processes"),
        ({"kind": "camera_stall", "from_s": 1.0, "to_s": 2.0, "processes": 2}, "processes"),
    ],
)
def test_a_cpu_hogs_fault_that_cannot_be_right_is_refused_by_name(fault: dict, message: str) -> None:
    with pytest.raises(ScenarioError, match=message):
        _scenario([fault])
