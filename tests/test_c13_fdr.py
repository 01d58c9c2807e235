"""C13 flight data recorder: round trip, rotation, size bound, torn lines, concurrency, conversion, errors."""

from __future__ import annotations

import enum
import errno
import json
import math
import os
import shutil
import threading
import uuid
from pathlib import Path

import numpy as np
import pytest

from gps_denied_onboard.components.c13_fdr import FdrClient, FlightDataRecorder, list_segments, read_records
from gps_denied_onboard.constants import FdrKind, Provenance

_MARKERS = (FdrKind.FDR_OPENED, FdrKind.FDR_CLOSED)


def _data(directory: Path) -> list[dict]:
    """The records a test wrote, without the recorder's own run markers."""
    return [r for r in read_records(directory) if r["kind"] not in _MARKERS]


class _FakeClock:
    def __init__(self, t: float = 1_717_000_000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        self.t += 0.001
        return self.t


def test_fdr_round_trip_in_order(tmp_path: Path) -> None:
    """Records come back in order with t_unix_s, kind, seq and their fields."""
    with FlightDataRecorder(tmp_path, 1 << 20, 1 << 16, clock=_FakeClock()) as fdr:
        assert isinstance(fdr, FdrClient)
        for i in range(20):
            fdr.record(FdrKind.FRAME, {"frame": i, "provenance": Provenance.SATELLITE_ANCHORED})
    recs = _data(tmp_path)
    assert [r["frame"] for r in recs] == list(range(20))
    assert [r["seq"] for r in recs] == list(range(2, 22))  # seq 1 is fdr.opened
    assert all(r["kind"] == "pipeline.frame" and r["provenance"] == "satellite_anchored" for r in recs)
    assert recs[0]["t_unix_s"] == pytest.approx(1_717_000_000.002)
    assert fdr.records_written == 22 and fdr.errors == 0  # with fdr.opened and fdr.closed
    names = [p.name for p in list_segments(tmp_path)]
    assert len(names) == 1 and names[0].startswith("fdr-20240529T") and names[0].endswith("-000001.jsonl")


def test_fdr_reserved_field_names_do_not_clobber(tmp_path: Path) -> None:
    """A field called kind/seq is kept under <name>_field."""
    with FlightDataRecorder(tmp_path, 1 << 20, 1 << 16) as fdr:
        fdr.record("x", {"kind": "mine", "seq": 99})
    (rec,) = _data(tmp_path)
    assert rec["kind"] == "x" and rec["seq"] == 2
    assert rec["kind_field"] == "mine" and rec["seq_field"] == 99


def test_fdr_rotation_and_size_bound(tmp_path: Path) -> None:
    """Segments rotate at segment_bytes and the directory never exceeds max_bytes."""
    seg, cap = 1 << 14, 1 << 16
    fdr = FlightDataRecorder(tmp_path, cap, seg, clock=_FakeClock())
    payload = "x" * 500
    for i in range(1000):
        fdr.record(FdrKind.FRAME, {"i": i, "pad": payload})
        on_disk = sum(p.stat().st_size for p in list_segments(tmp_path))
        assert on_disk <= cap
    fdr.close()
    segs = list_segments(tmp_path)
    assert len(segs) >= 3
    assert all(p.stat().st_size <= seg for p in segs)
    assert fdr.segments_deleted > 0
    recs = _data(tmp_path)
    idx = [r["i"] for r in recs]
    assert idx == list(range(idx[0], 1000))  # the newest survive, contiguous and in order
    assert fdr.total_bytes == sum(p.stat().st_size for p in segs)


def test_fdr_size_bound_counts_previous_runs(tmp_path: Path) -> None:
    """Segments left by an earlier run count towards max_bytes and are deleted first."""
    seg, cap = 1 << 14, 1 << 16
    with FlightDataRecorder(tmp_path, cap, seg, clock=_FakeClock(1_700_000_000.0)) as old:
        for i in range(150):
            old.record("old", {"i": i, "pad": "y" * 400})
    old_segs = set(list_segments(tmp_path))
    with FlightDataRecorder(tmp_path, cap, seg, clock=_FakeClock(1_800_000_000.0)) as new:
        for i in range(150):
            new.record("new", {"i": i, "pad": "z" * 400})
    assert sum(p.stat().st_size for p in list_segments(tmp_path)) <= cap
    assert not old_segs <= set(list_segments(tmp_path))  # some old segments were deleted
    kinds = [r["kind"] for r in _data(tmp_path)]
    assert kinds[-1] == "new" and kinds == sorted(kinds, key=lambda k: k == "new")  # old before new


def test_fdr_torn_last_line_is_skipped(tmp_path: Path) -> None:
    """A crash mid-write leaves a torn line; the reader skips it and keeps everything before."""
    with FlightDataRecorder(tmp_path, 1 << 20, 1 << 16) as fdr:
        for i in range(5):
            fdr.record("k", {"i": i})
    (seg,) = list_segments(tmp_path)
    with seg.open("ab") as fh:
        fh.write(b'{"t_unix_s": 1.0, "kind": "k", "seq": 6, "i": ')
    assert [r["i"] for r in _data(tmp_path)] == [0, 1, 2, 3, 4]


def test_fdr_failed_write_does_not_glue_next_record(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """After a short write (disk full), the next record starts on a new line and reads back."""
    fdr = FlightDataRecorder(tmp_path, 1 << 20, 1 << 16)
    fdr.record("k", {"i": 0})
    real_write = os.write
    calls = {"n": 0}

    def short_then_full(fd: int, data: bytes) -> int:
        calls["n"] += 1
        if calls["n"] == 1:
            return real_write(fd, bytes(data)[:7])
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "write", short_then_full)
    fdr.record("k", {"i": 1})  # must not raise
    monkeypatch.setattr(os, "write", real_write)
    fdr.record("k", {"i": 2})
    fdr.close()
    assert fdr.errors == 1 and fdr.records_dropped == 1 and fdr.records_written == 4  # + the markers
    assert [r["i"] for r in _data(tmp_path)] == [0, 2]


def test_fdr_concurrent_writers_keep_lines_whole(tmp_path: Path) -> None:
    """Eight threads writing at once: every record reads back whole, seq unique, across rotations."""
    fdr = FlightDataRecorder(tmp_path, 1 << 24, 1 << 14)
    n_threads, n_each = 8, 300

    def writer(k: int) -> None:
        for i in range(n_each):
            fdr.record("w", {"thread": k, "i": i, "pad": "p" * (i % 50)})

    threads = [threading.Thread(target=writer, args=(k,)) for k in range(n_threads)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    fdr.close()
    recs = _data(tmp_path)
    assert len(recs) == n_threads * n_each
    assert sorted(r["seq"] for r in recs) == list(range(2, n_threads * n_each + 2))
    assert [r["seq"] for r in recs] == sorted(r["seq"] for r in recs)
    for k in range(n_threads):
        assert [r["i"] for r in recs if r["thread"] == k] == list(range(n_each))
    assert len(list_segments(tmp_path)) > 1


class _Color(enum.Enum):
    RED = 1


def test_fdr_converts_numpy_uuid_enum_tuple(tmp_path: Path) -> None:
    """numpy arrays/scalars, UUIDs, enums, tuples, tuple keys and inf convert to JSON and back."""
    fid = uuid.uuid4()
    with FlightDataRecorder(tmp_path, 1 << 20, 1 << 16) as fdr:
        fdr.record(
            "c",
            {
                "arr": np.arange(6, dtype=np.float32).reshape(2, 3),
                "f32": np.float32(1.5),
                "i64": np.int64(7),
                "b": np.bool_(True),
                "frame_id": fid,
                "color": _Color.RED,
                "prov": Provenance.NO_ESTIMATE,
                "tile_id": (18, 50.45, 30.52),
                "by_tile": {(18, 1, 2): 3},
                "age": math.inf,
                "obj": object(),
            },
        )
    (rec,) = _data(tmp_path)
    assert rec["arr"] == [[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]]
    assert rec["f32"] == 1.5 and rec["i64"] == 7 and rec["b"] is True
    assert rec["frame_id"] == str(fid) and rec["color"] == 1 and rec["prov"] == "no_estimate"
    assert rec["tile_id"] == [18, 50.45, 30.52] and rec["by_tile"] == {"[18, 1, 2]": 3}
    assert rec["age"] == math.inf and rec["obj"].startswith("<object")
    raw = list_segments(tmp_path)[0].read_text().splitlines()[1]
    assert json.loads(raw)["frame_id"] == str(fid)


def test_fdr_directory_replaced_by_file_does_not_raise(tmp_path: Path) -> None:
    """When the FDR directory is gone (replaced by a file), record() counts errors and never raises."""
    d = tmp_path / "fdr"
    fdr = FlightDataRecorder(d, 1 << 16, 1 << 14)
    fdr.record("k", {"i": 0})
    shutil.rmtree(d)
    d.write_text("not a directory")
    for i in range(200):  # forces a rotation, whose open fails
        fdr.record("k", {"i": i, "pad": "q" * 200})
    assert fdr.errors > 0 and fdr.records_dropped > 0
    fdr.close()
    fdr.record("k", {"i": -1})  # after close: dropped, no raise
    assert list(read_records(d)) == []


def test_fdr_rejects_segment_larger_than_budget(tmp_path: Path) -> None:
    """segment_bytes > max_bytes is a configuration error at construction."""
    with pytest.raises(ValueError, match="segment_bytes"):
        FlightDataRecorder(tmp_path, 1000, 2000)
