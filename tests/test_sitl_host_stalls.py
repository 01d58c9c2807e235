"""The soak's host counters: what tells a stall of the whole machine from a stall of the daemon."""

from __future__ import annotations

from pathlib import Path

import pytest

from gps_denied_onboard.sitl.runner import host_stall_counters, host_stall_summary


def _proc(root: Path, *, io: str, stat: str) -> Path:
    (root / "pressure").mkdir(parents=True)
    (root / "pressure" / "io").write_text(io)
    (root / "stat").write_text(stat)
    return root


def test_counters_are_read_in_seconds_and_missing_ones_left_out(tmp_path: Path) -> None:
    proc = _proc(
        tmp_path,
        io="some avg10=0.59 avg60=1.47 avg300=2.50 total=164831405\n"
        "full avg10=0.55 avg60=1.42 avg300=2.44 total=114983798\n",
        stat="cpu  1356141 990629 321072 1844693 13639 0 4609 2053 0 0\ncpu0 1 2 3 4 5 6 7 8 9 10\n",
    )
    assert host_stall_counters(proc) == {"io_full_s": pytest.approx(114.983798), "steal_s": 20.53}
    assert host_stall_counters(tmp_path / "absent") is None


def test_the_largest_increase_names_the_sample_after_the_stall() -> None:
    samples = [
        (5.0, {"io_full_s": 10.0, "steal_s": 1.0}),
        (10.0, {"io_full_s": 10.5, "steal_s": 1.0}),
        (35.0, {"io_full_s": 30.5, "steal_s": 1.2}),  # a 25 s stall, nearly all of it waiting on I/O
        (40.0, {"io_full_s": 30.6, "steal_s": 1.2}),
    ]
    worst = host_stall_summary(samples)["largest_increase"]
    assert worst["io_full_s"] == {"increase_s": 20.0, "at_s": 35.0}
    assert worst["steal_s"] == {"increase_s": 0.2, "at_s": 35.0}


@pytest.mark.skipif(not Path("/proc/stat").exists(), reason="Linux /proc only")
def test_this_host_offers_at_least_its_steal_time() -> None:
    counters = host_stall_counters()
    assert counters is not None and counters["steal_s"] >= 0.0
