"""JSON from outside the process (a file, a socket), parsed so that no input can crash the caller.

``loads(data, max_bytes=..., what=...)`` returns the parsed value or raises ``BoundedJsonError``, a
``ValueError``, so every caller's existing "not JSON" branch handles it. Refused: more than ``max_bytes``
(checked before parsing), not UTF-8, not JSON, and nesting deeper than CPython's decoder can follow (it
raises ``RecursionError`` there, which no caller expected: one such FDR line crashed every start).
"""

from __future__ import annotations

import json
from typing import Any


class BoundedJsonError(ValueError):
    """The input is too large, not UTF-8, not JSON, or nested too deeply: ``reason`` is ``size``,
    ``depth``, ``utf8`` or ``syntax``, and the message says which."""

    def __init__(self, message: str, *, reason: str) -> None:
        super().__init__(message)
        self.reason = reason


def loads(data: str | bytes | bytearray, *, max_bytes: int, what: str = "JSON") -> Any:
    """Parse ``data`` (see the module docstring); ``what`` names the input in the message."""
    if len(data) > max_bytes:
        raise BoundedJsonError(
            f"{what}: {len(data)} bytes, more than the {max_bytes} accepted", reason="size"
        )
    try:
        return json.loads(data)
    except RecursionError:
        raise BoundedJsonError(f"{what}: nested too deeply to parse", reason="depth") from None
    except UnicodeDecodeError as exc:
        raise BoundedJsonError(f"{what}: not UTF-8 (byte {exc.start}: {exc.reason})", reason="utf8") from None
    except ValueError as exc:
        raise BoundedJsonError(f"{what}: not valid JSON ({exc})", reason="syntax") from None
