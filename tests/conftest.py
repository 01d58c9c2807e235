"""Shared fixtures: paths to the read-only shared data and models (skipped when absent)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest
import structlog

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("GDNAV_SHARED_DIR", REPO_ROOT.parent / "shared"))


def shared_path(*parts: str) -> Path:
    """A file under ../shared, or skip the test with the reason when it is not there."""
    path = SHARED.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"shared data not available: {path}")
    return path


@pytest.fixture(autouse=True)
def _restore_structlog() -> Iterator[None]:
    """The CLI configures logging for its process; a test that runs it in-process must not leave the
    next test a filtering level or a closed capture (tests that read logs with ``capture_logs`` then see
    nothing: a `gdnav bench flights` refusal did that to nine tests)."""
    saved = structlog.get_config()
    yield
    structlog.configure(**saved)


class RecordingFdr:
    """The FDR at a component's boundary: keeps what is recorded, as (kind, fields)."""

    def __init__(self) -> None:
        self.records: list[tuple[str, dict[str, object]]] = []

    def record(self, kind: str, fields: dict[str, object]) -> None:
        self.records.append((kind, dict(fields)))


@pytest.fixture
def recording_fdr() -> RecordingFdr:
    """A fresh :class:`RecordingFdr`."""
    return RecordingFdr()
