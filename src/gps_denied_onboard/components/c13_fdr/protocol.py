"""C13 contract: how components write flight-data-recorder records."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol, runtime_checkable


@runtime_checkable
class FdrClient(Protocol):
    def record(self, kind: str, fields: Mapping[str, object]) -> None:
        """Append one record of ``kind`` (see ``constants.FdrKind``). Never raises into the caller's
        hot path: a full or failing disk is counted and reported, not propagated."""
        ...
