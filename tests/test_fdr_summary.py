"""C13 finished: the documented schema, run markers with recovery on open, the reader's runs, and
`gdnav fdr summary` as a real process."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from gps_denied_onboard.components.c13_fdr import (
    FdrReader,
    FdrReadError,
    FlightDataRecorder,
    RunStop,
    list_segments,
    read_records,
)
from gps_denied_onboard.constants import FdrKind

REPO = Path(__file__).resolve().parents[1]
T0 = 1_717_000_000.0


class _Clock:
    """Advances 0.1 s per call: ten records make one second of flight."""

    def __init__(self, t: float) -> None:
        self.t = t

    def __call__(self) -> float:
        self.t += 0.1
        return self.t


def _kinds() -> dict[str, str]:
    return {name: value for name, value in vars(FdrKind).items() if name.isupper()}


def _fly(fdr: FlightDataRecorder, n_frames: int, *, lat0: float = 47.0) -> None:
    """Records of the real kinds with the fields the daemon writes (pipeline.py, daemon/service.py)."""
    fdr.record(
        FdrKind.PROVENANCE_CHANGED, {"old": "no_estimate", "new": "satellite_anchored", "reason": None}
    )
    for i in range(n_frames):
        t_us = int(fdr.started_unix_s * 1e6) + i * 333_000
        fdr.record(
            FdrKind.FRAME,
            {
                "frame_seq": i,
                "exposure_time_unix_usec": t_us,
                "provenance": "satellite_anchored",
                "vo_ok": True,
                "vo_reason": None,
                "lat_deg": lat0 + i * 1e-5,
                "lon_deg": 8.0,
                "horiz_sigma_m": 3.0,
            },
        )
        accepted = i % 2 == 0
        fdr.record(
            FdrKind.FIX,
            {
                "frame_seq": i,
                "exposure_time_unix_usec": t_us,
                "fix_accepted": accepted,
                "inliers": 120 if accepted else 12,
                "residual_px": 1.1,
                "no_fix_reason": None if accepted else "insufficient_inliers",
            },
        )
        fdr.record(
            FdrKind.ESTIMATE_SENT,
            {
                "time_unix_usec": t_us,
                "provenance": "satellite_anchored",
                "fix_type": 3,
                "lat_deg": lat0 + i * 1e-5,
                "lon_deg": 8.0,
                "horiz_sigma_m": 3.0 + i,
                "last_fix_age_s": 0.2,
                "sent": 2,
            },
        )
    fdr.record(FdrKind.FRAME_ERROR, {"frame_seq": n_frames, "stage": "decode", "error": "bad magic"})
    fdr.record(
        FdrKind.FRAME_REFUSED,
        {
            "frame_seq": n_frames + 1,
            "exposure_time_unix_usec": 0,
            "reason": "stale",
            "ahead_of_clock_s": -9.0,
        },
    )
    fdr.record(
        FdrKind.PROVENANCE_CHANGED,
        {"old": "satellite_anchored", "new": "visual_propagated", "reason": "insufficient_inliers"},
    )


@pytest.fixture
def crashed_then_clean(tmp_path: Path) -> Path:
    """Run 1 crashes (a torn last line, no fdr.closed); run 2 flies and stops cleanly."""
    d = tmp_path / "fdr"
    first = FlightDataRecorder(d, 1 << 20, 1 << 16, clock=_Clock(T0))
    _fly(first, 10)
    with list_segments(d)[-1].open("ab") as fh:  # killed mid-write
        fh.write(b'{"t_unix_s":1717000099.0,"kind":"mavlink.estimate","seq":99,"lat_d')
    with FlightDataRecorder(d, 1 << 20, 1 << 16, clock=_Clock(T0 + 100.0)) as second:
        _fly(second, 5, lat0=47.1)
    return d


def test_fdr_every_kind_is_documented() -> None:
    """docs/fdr.md has a section for every FdrKind and none for a kind that does not exist."""
    doc = (REPO / "docs" / "fdr.md").read_text()
    documented = set(re.findall(r"^### `([^`]+)`$", doc, flags=re.M))
    kinds = set(_kinds().values())
    assert kinds - documented == set(), f"FdrKind values missing from docs/fdr.md: {kinds - documented}"
    assert documented - kinds == set(), f"docs/fdr.md documents unknown kinds: {documented - kinds}"


def test_fdr_markers_open_and_close_a_run(tmp_path: Path) -> None:
    """fdr.opened is the first record (pid, start time), fdr.closed the last, once even if closed twice."""
    fdr = FlightDataRecorder(tmp_path, 1 << 20, 1 << 16, clock=_Clock(T0))
    fdr.record(FdrKind.FRAME, {"frame_seq": 0})
    fdr.close()
    fdr.close()
    recs = list(read_records(tmp_path))
    assert [r["kind"] for r in recs] == [FdrKind.FDR_OPENED, FdrKind.FRAME, FdrKind.FDR_CLOSED]
    opened, closed = recs[0], recs[-1]
    assert opened["pid"] == os.getpid() and opened["seq"] == 1
    assert opened["started_unix_s"] == pytest.approx(T0 + 0.1) == opened["t_unix_s"]
    assert opened["previous_segment"] is None and opened["previous_torn_lines"] == 0
    assert closed["records_written"] == 2 and closed["errors"] == 0
    (run,) = FdrReader(tmp_path).runs()
    assert run.stop is RunStop.CLEAN and run.pid == os.getpid()


def test_fdr_recovery_on_open_terminates_and_counts_a_torn_line(crashed_then_clean: Path) -> None:
    """The second recorder finds the torn line, ends it with a newline, and says the first run crashed."""
    first_seg, *_ = list_segments(crashed_then_clean)
    assert first_seg.read_bytes().endswith(b'"lat_d\n')
    opened = [r for r in read_records(crashed_then_clean) if r["kind"] == FdrKind.FDR_OPENED]
    assert len(opened) == 2
    assert opened[1]["previous_segment"] == first_seg.name
    assert opened[1]["previous_torn_lines"] == 1 and opened[1]["previous_closed"] is False


def test_fdr_reader_reports_two_runs_one_crash(crashed_then_clean: Path) -> None:
    """runs() splits at fdr.opened: run 1 a crash with its torn line, run 2 clean; counts and rates."""
    reader = FdrReader(crashed_then_clean)
    runs = reader.runs()
    assert [r.stop for r in runs] == [RunStop.CRASH, RunStop.CLEAN]
    assert runs[0].counts[FdrKind.FRAME] == 10 and runs[1].counts[FdrKind.FRAME] == 5
    assert FdrKind.FDR_CLOSED not in runs[0].counts and runs[1].counts[FdrKind.FDR_CLOSED] == 1
    assert runs[0].bad_lines == 1 and runs[0].torn_lines_at_end == 1 and runs[1].bad_lines == 0
    assert runs[0].start_unix_s == pytest.approx(T0 + 0.1) and runs[1].start_unix_s == pytest.approx(
        T0 + 100.1
    )
    assert runs[1].rate_hz(FdrKind.FRAME) == pytest.approx(5 / runs[1].duration_s)
    assert len(list(reader.fixes())) == 15
    assert [c.new for c in reader.provenance_changes()][:2] == ["satellite_anchored", "visual_propagated"]
    assert {e.stage for e in reader.frame_errors()} == {"decode"}
    assert reader.counts()[FdrKind.ESTIMATE_SENT] == 15


def test_fdr_reader_splits_runs_of_a_recorder_without_markers(tmp_path: Path) -> None:
    """Records without fdr.opened start a new run where seq starts again; their stop is unknown."""
    lines = [
        {"t_unix_s": T0 + k, "kind": FdrKind.FRAME, "seq": s} for k, s in enumerate((1, 2, 3, 1, 2), start=1)
    ]
    (tmp_path / "fdr-20240529T163000.000Z-000001.jsonl").write_text(
        "".join(json.dumps(r) + "\n" for r in lines)
    )
    runs = FdrReader(tmp_path).runs()
    assert [(r.stop, r.counts[FdrKind.FRAME]) for r in runs] == [(RunStop.UNKNOWN, 3), (RunStop.UNKNOWN, 2)]


def test_fdr_reader_refuses_missing_and_empty(tmp_path: Path) -> None:
    """A missing path or a directory without segments is an FdrReadError naming the path."""
    with pytest.raises(FdrReadError, match="no such file"):
        FdrReader(tmp_path / "nope").runs()
    with pytest.raises(FdrReadError, match="no FDR segments"):
        FdrReader(tmp_path).runs()


def _gdnav(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gps_denied_onboard.cli", *args],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def test_gdnav_fdr_summary_prints_counts_runs_errors_and_writes_png(
    crashed_then_clean: Path, tmp_path: Path
) -> None:
    """The real CLI prints counts by kind, both runs (crash, clean), errors and the timeline; PNG is valid."""
    png = tmp_path / "out" / "fdr.png"
    result = _gdnav("fdr", "summary", str(crashed_then_clean), "--png", str(png))
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert re.search(r"^\s+pipeline\.frame\s+15$", out, flags=re.M), out
    assert re.search(r"^\s+mavlink\.estimate\s+15$", out, flags=re.M), out
    assert "CRASH, 1 torn line(s)" in out and "CLEAN" in out
    assert re.search(r"^\s+decode\s+2$", out, flags=re.M)  # frame errors by stage
    assert re.search(r"^\s+stale\s+2$", out, flags=re.M)  # refused frames by reason
    assert re.search(r"^\s+insufficient_inliers\s+7$", out, flags=re.M)  # no-fix reasons: 5 + 2
    assert "satellite_anchored -> visual_propagated  (insufficient_inliers)" in out
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000

    as_json = json.loads(_gdnav("fdr", "summary", str(crashed_then_clean), "--json").stdout)
    assert as_json["counts"] == FdrReader(crashed_then_clean).counts()
    assert [r["stop"] for r in as_json["runs"]] == ["crash", "clean"]
    assert as_json["runs"][1]["frames_per_s"] > 0


def test_gdnav_fdr_summary_reads_one_segment_file(crashed_then_clean: Path) -> None:
    """A single segment file is accepted: it holds the first (crashed) run."""
    first_seg = list_segments(crashed_then_clean)[0]
    result = _gdnav("fdr", "summary", str(first_seg), "--json")
    assert result.returncode == 0, result.stderr
    assert [r["stop"] for r in json.loads(result.stdout)["runs"]] == ["crash"]


@pytest.mark.parametrize("which", ["missing", "empty"])
def test_gdnav_fdr_summary_missing_or_empty_exits_2(tmp_path: Path, which: str) -> None:
    """A missing path or an empty directory: exit 2, one line on stderr, no traceback."""
    path = tmp_path / "nope" if which == "missing" else tmp_path
    result = _gdnav("fdr", "summary", str(path))
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and str(path) in result.stderr, result.stderr
    assert "Traceback" not in result.stderr
