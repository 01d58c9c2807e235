"""F8 resume state: the daemon's last 3D estimate in a file of its own, apart from the FDR (issue 27), and
the autopilot's flight phase (armed, landed state) that decides whether HOME may be a prior."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as D

from gps_denied_onboard.components.c5_estimator.prior import ResumeState
from gps_denied_onboard.components.c5_estimator.resume_state import (
    MAX_BYTES,
    ResumeStateFile,
    checksum,
    default_path,
    read_resume_state,
)
from gps_denied_onboard.components.c8_mavlink.vehicle_state import FlightPhase, VehicleStateTracker

NOW_S = 1_800_000_000.0
STATE = ResumeState(47.002, 8.003, 4.5, int((NOW_S - 2.0) * 1e6))


def test_resume_state_round_trips_atomically(tmp_path: Path) -> None:
    """Written, replaced, read back; no temporary file is left behind."""
    store = ResumeStateFile(default_path(tmp_path))
    assert store.path == tmp_path / "resume_state.json"
    assert store.write(ResumeState(1.0, 2.0, 3.0, 5), provenance="x", written_unix_s=NOW_S)
    assert store.write(STATE, provenance="satellite_anchored", written_unix_s=NOW_S)
    assert read_resume_state(store.path, NOW_S) == STATE
    assert json.loads(store.path.read_text())["provenance"] == "satellite_anchored"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["resume_state.json"]
    assert read_resume_state(tmp_path / "absent.json", NOW_S) is None


def test_resume_state_is_written_where_the_recorder_made_no_directory(tmp_path: Path) -> None:
    """On a full disk the recorder never creates its directory: the state file's writer does."""
    store = ResumeStateFile(default_path(tmp_path / "fdr"))
    assert store.write(STATE, provenance="p", written_unix_s=NOW_S)
    assert read_resume_state(store.path, NOW_S) == STATE


def test_resume_state_write_failure_is_counted_not_raised(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("")
    store = ResumeStateFile(tmp_path / "file" / "resume_state.json")
    assert not store.write(STATE, provenance="p", written_unix_s=NOW_S)
    assert not store.write(STATE, provenance="p", written_unix_s=NOW_S)
    assert (store.writes, store.failures) == (0, 2)


def _good() -> dict[str, Any]:
    return {
        "version": 2,
        "lat_deg": STATE.lat_deg,
        "lon_deg": STATE.lon_deg,
        "horiz_sigma_m": STATE.horiz_sigma_m,
        "time_unix_usec": STATE.time_unix_usec,
        "provenance": "satellite_anchored",
        "written_unix_s": NOW_S,
    }


def _signed(fields: dict[str, Any]) -> bytes:
    """``fields`` as the file, with the checksum they give (a well-formed file saying something wrong)."""
    return json.dumps({**fields, "crc32": checksum(fields)}).encode()


def _damaged() -> bytes:
    """A good file with one digit of the latitude changed: still JSON, still a position on the Earth."""
    good = _signed(_good()).decode()
    assert "47.002" in good
    return good.replace("47.002", "47.012").encode()


@pytest.mark.parametrize(
    ("content", "reason"),
    [
        (b"[" * 2000 + b"]" * 2000, "nested too deeply"),
        (b"{not json", "not JSON"),
        (b"\xff\xfe", "not JSON"),
        (b"[1, 2]", "expected a JSON object"),
        (b" " * (MAX_BYTES + 1), "larger than"),
        (_signed({**_good(), "version": 1}), "version 1, expected 2"),
        (_damaged(), "checksum mismatch"),
        (json.dumps(_good()).encode(), "crc32 is None"),
        (json.dumps({**_good(), "crc32": True}).encode(), "crc32 is True"),
        (_signed({**_good(), "lat_deg": "47"}), "lat_deg is '47'"),
        (_signed({**_good(), "lat_deg": True}), "lat_deg is True"),
        (_signed({**_good(), "horiz_sigma_m": float("inf")}), "horiz_sigma_m is inf"),
        (_signed({**_good(), "horiz_sigma_m": 0.0}), "expected > 0"),
        (_signed({**_good(), "lat_deg": 91.0}), "not on the Earth"),
        (_signed({**_good(), "time_unix_usec": 1.5}), "time_unix_usec is 1.5"),
        (_signed({**_good(), "time_unix_usec": int((NOW_S + 60) * 1e6)}), "in the future"),
    ],
)
def test_resume_state_refuses_a_corrupt_or_hostile_file_in_one_line(
    tmp_path: Path, content: bytes, reason: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """Refused, logged once with the reason, and treated as absent: never a crash, never a prior."""
    path = tmp_path / "resume_state.json"
    path.write_bytes(content)
    assert read_resume_state(path, NOW_S) is None
    out = capsys.readouterr()
    lines = [ln for ln in (out.out + out.err).splitlines() if "c5.resume_state.refused" in ln]
    assert len(lines) == 1 and reason in lines[0], out


def test_resume_state_refuses_what_is_not_a_regular_file(tmp_path: Path) -> None:
    """A FIFO (would block a reader), a directory, a symlink: refused without blocking."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    assert read_resume_state(fifo, NOW_S) is None
    assert read_resume_state(tmp_path, NOW_S) is None
    target = tmp_path / "real.json"
    ResumeStateFile(target).write(STATE, provenance="p", written_unix_s=NOW_S)
    link = tmp_path / "link.json"
    link.symlink_to(target)
    assert read_resume_state(link, NOW_S) is None
    assert read_resume_state(target, NOW_S) == STATE


def _decoded(build: Any) -> Any:
    tx = D.MAVLink(None, srcSystem=1, srcComponent=1)
    return D.MAVLink(None).decode(bytearray(build(tx).pack(tx)))


def _heartbeat(armed: bool) -> Any:
    mode = D.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (D.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
    return _decoded(
        lambda mav: mav.heartbeat_encode(D.MAV_TYPE_QUADROTOR, D.MAV_AUTOPILOT_ARDUPILOTMEGA, mode, 0, 4)
    )


def _landed(state: int) -> Any:
    return _decoded(lambda mav: mav.extended_sys_state_encode(D.MAV_VTOL_STATE_UNDEFINED, state))


def test_tracker_reports_armed_landed_state_and_when_last_on_the_ground() -> None:
    """HEARTBEAT's armed flag and EXTENDED_SYS_STATE.landed_state, each forgotten after link_timeout_s;
    the last "on the ground" (disarmed or ON_GROUND) is remembered for the run."""
    tracker = VehicleStateTracker(1, 0.3, 1.0, 3.0, clock=lambda: NOW_S)
    assert tracker.flight_phase(NOW_S) == FlightPhase(None, None, None)
    assert tracker.handle(_heartbeat(False), NOW_S - 10.0)
    assert tracker.handle(_landed(D.MAV_LANDED_STATE_ON_GROUND), NOW_S - 9.0)
    assert tracker.handle(_heartbeat(True), NOW_S - 1.0)
    assert tracker.handle(_landed(D.MAV_LANDED_STATE_IN_AIR), NOW_S - 0.5)
    assert tracker.flight_phase(NOW_S) == FlightPhase(True, D.MAV_LANDED_STATE_IN_AIR, NOW_S - 9.0)
    assert tracker.flight_phase(NOW_S + 10.0) == FlightPhase(None, None, NOW_S - 9.0)
    assert not tracker.handle(_landed(D.MAV_LANDED_STATE_UNDEFINED), NOW_S)  # says nothing: not kept
    assert tracker.flight_phase(NOW_S).landed_state == D.MAV_LANDED_STATE_IN_AIR
