"""Hostile or broken files the daemon and its tools read (FDR segments, cache manifests, replay frames,
configuration) give one plain line and an exit code, or a skipped and counted record: never a traceback.
The commands run as real `gdnav` processes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from gps_denied_onboard.components.c5_estimator.prior import read_previous_run
from gps_denied_onboard.components.c13_fdr import FlightDataRecorder, read_records_newest_first
from gps_denied_onboard.components.c13_fdr.reader import FdrReader, scan
from gps_denied_onboard.components.c13_fdr.recorder import MAX_RECORD_BYTES, parse_line

NOW_USEC = 1_717_000_000_000_000
#: One FDR line nested far past what CPython's JSON decoder follows (it raised RecursionError).
NESTED_LINE = (
    b'{"t_unix_s":1717000000.5,"kind":"mavlink.estimate","x":' + b"[" * 100_000 + b"]" * 100_000 + b"}\n"
)


def _gdnav(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gps_denied_onboard.cli", *args],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=cwd,
    )


def _one_line(proc: subprocess.CompletedProcess[str], code: int) -> str:
    """Exit ``code``, no traceback, and the last stderr line a plain ``gdnav:`` line; returns it."""
    assert proc.returncode == code, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    line = proc.stderr.strip().splitlines()[-1]
    assert line.startswith("gdnav: "), proc.stderr[-3000:]
    return line


def _fdr_with(tmp_path: Path, *hostile: bytes) -> Path:
    """A real recorder's segment with three 3D estimates, then ``hostile`` lines appended to it."""
    d = tmp_path / "fdr"
    with FlightDataRecorder(d, max_bytes=1 << 20, segment_bytes=1 << 16) as fdr:
        for k in range(3):
            fdr.record(
                "mavlink.estimate",
                {
                    "time_unix_usec": NOW_USEC + k,
                    "fix_type": 3,
                    "lat_deg": 47.0 + k,
                    "lon_deg": 8.0,
                    "horiz_sigma_m": 2.0,
                },
            )
    seg = sorted(d.glob("fdr-*.jsonl"))[-1]
    with seg.open("ab") as fh:
        for line in hostile:
            fh.write(line)
    return d


# --- FDR lines --------------------------------------------------------------------------------------


def test_fdr_nested_line_is_skipped_by_the_startup_read(tmp_path: Path) -> None:
    """A deeply nested line (RecursionError in the decoder: `gdnav run` crashed at every start) is
    skipped, and the resume state behind it is still found."""
    d = _fdr_with(tmp_path, NESTED_LINE)
    previous = read_previous_run(read_records_newest_first(d))
    assert previous.last_3d is not None and previous.last_3d.lat_deg == 49.0


def test_fdr_infinite_time_record_is_skipped_by_the_startup_read(tmp_path: Path) -> None:
    """A 3D estimate whose time_unix_usec is Infinity (int() raises OverflowError) is skipped."""
    bad = b'{"t_unix_s":1717000001.0,"kind":"mavlink.estimate","seq":9,"fix_type":3,"lat_deg":1.0,'
    bad += b'"lon_deg":2.0,"horiz_sigma_m":1.0,"time_unix_usec":Infinity}\n'
    previous = read_previous_run(read_records_newest_first(_fdr_with(tmp_path, bad)))
    assert previous.last_3d is not None and previous.last_3d.lat_deg == 49.0


def test_fdr_line_over_the_size_bound_is_refused_unparsed() -> None:
    """A line longer than MAX_RECORD_BYTES is not parsed (nor held whole by the readers)."""
    big = b'{"t_unix_s":1.0,"kind":"x","pad":"' + b"a" * MAX_RECORD_BYTES + b'"}\n'
    assert parse_line(big) is None
    assert parse_line(b'{"t_unix_s":1.0,"kind":"x"}\n') == {"t_unix_s": 1.0, "kind": "x"}


def test_fdr_reader_counts_hostile_lines_as_bad(tmp_path: Path) -> None:
    """FdrReader skips a nested line, a line over the size bound and a record with a huge or
    non-numeric time, counts the unreadable lines in the run, and its typed accessors skip the rest."""
    big = b'{"t_unix_s":1.0,"kind":"x","pad":"' + b"a" * (MAX_RECORD_BYTES + 10) + b'"}\n'
    odd = b'{"t_unix_s":"soon","kind":"mavlink.estimate","seq":"x","fix_type":3}\n'
    huge = b'{"t_unix_s":' + b"9" * 400 + b',"kind":"pipeline.fix","seq":1e999}\n'
    d = _fdr_with(tmp_path, NESTED_LINE, big, odd, huge)
    reader = FdrReader(d)
    runs = reader.runs()
    assert sum(r.bad_lines for r in runs) == 2
    assert len(list(reader.estimates())) == 3
    assert list(reader.fixes()) == []
    found = scan(d)
    assert (found.records, found.torn_lines, found.corrupt_lines) == (7, 0, 2)
    assert found.first_corrupt is not None and "nested too deeply" in found.first_corrupt


def test_fdr_scan_tells_torn_lines_from_corrupt_ones(tmp_path: Path) -> None:
    """A write cut short by a crash is torn (expected); JSON that is no record is corrupt."""
    found = scan(_fdr_with(tmp_path, b'{"t_unix_s":1.0,"ki\n', b"[1, 2]\n"))
    assert (found.torn_lines, found.corrupt_lines) == (1, 1)
    assert found.first_corrupt is not None and "not a record" in found.first_corrupt


def test_cli_fdr_summary_with_a_nested_line_exits_0(tmp_path: Path) -> None:
    """`gdnav fdr summary` reads past the nested line and counts it."""
    d = _fdr_with(tmp_path, NESTED_LINE)
    proc = _gdnav(tmp_path, "fdr", "summary", str(d), "--json")
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout)
    assert sum(r["bad_lines"] for r in summary["runs"]) == 1


@pytest.mark.parametrize(
    "command",
    [("fdr", "boresight"), ("replay", "--report", "r.json", "--fdr")],
    ids=["boresight", "replay"],
)
def test_cli_fdr_readers_with_a_nested_line_refuse_in_one_line(
    tmp_path: Path, command: tuple[str, ...]
) -> None:
    """`fdr boresight` and `replay --fdr` skip the nested line and refuse the FDR (it tracked no frame)
    with one line and exit 3."""
    d = _fdr_with(tmp_path, NESTED_LINE)
    line = _one_line(_gdnav(tmp_path, *command, str(d)), 3)
    assert "no run tracked any frame" in line
