"""The log's lines reach stderr whole: one write a record, its newline included.

The navigator core and its vision worker write to one stderr (the unit's journal stream, the SITL
harness's log file). A record written in two parts, itself and then its newline, let the other
process's record in between: two JSON objects on one line (seen in the faults flight's log)."""

from __future__ import annotations

import json
import sys

import pytest
import structlog

from gps_denied_onboard.logging_setup import configure_logging


class _Writes:
    """A stderr that keeps each write call apart."""

    def __init__(self) -> None:
        self.calls: list[str] = []

    def write(self, text: str) -> int:
        self.calls.append(text)
        return len(text)

    def flush(self) -> None:
        pass


def test_every_record_is_one_write_ending_in_its_newline(monkeypatch: pytest.MonkeyPatch) -> None:
    writes = _Writes()
    monkeypatch.setattr(sys, "stderr", writes)
    try:
        configure_logging("info")
        log = structlog.get_logger("test")
        for k in range(3):
            log.info("test.event", k=k, text="x" * 300)
    finally:
        monkeypatch.undo()
        configure_logging("info")  # back on the real stderr for the tests after this one
    assert len(writes.calls) == 3, writes.calls
    for k, call in enumerate(writes.calls):
        assert call.endswith("\n") and call.count("\n") == 1, call
        assert json.loads(call)["k"] == k
