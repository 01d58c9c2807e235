"""``<model_dir>/verification.json``: which exported families passed ``gdnav models verify``.

Written by ``models.reference_check`` (build time, torch); read here without torch by the composition root
(``matcher.strategy: auto`` uses only verified families). A record names the files' sha256, so a file that
was re-exported after its check counts as unverified.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Final

from gps_denied_onboard.helpers import bounded_json
from gps_denied_onboard.models.manifest import ModelEntry

VERIFICATION_NAME: Final[str] = "verification.json"


def read_verification(model_dir: Path) -> dict[str, Any]:
    """``{family: record}`` from the directory's verification file; empty when absent or unreadable."""
    try:
        data = bounded_json.loads(
            (Path(model_dir) / VERIFICATION_NAME).read_bytes(), max_bytes=1 << 20, what="verification"
        )
    except (OSError, ValueError):
        return {}
    families = data.get("families") if isinstance(data, dict) else None
    return families if isinstance(families, dict) else {}


def family_verified(model_dir: Path, family: str, extractor: ModelEntry, matcher: ModelEntry) -> bool:
    """True when ``family`` passed the reference check with exactly these two files."""
    record = read_verification(model_dir).get(family)
    if not isinstance(record, dict) or record.get("passed") is not True:
        return False
    ext, lg = record.get("extractor") or {}, record.get("matcher") or {}
    return (ext.get("file"), ext.get("sha256"), lg.get("file"), lg.get("sha256")) == (
        extractor.file,
        extractor.sha256,
        matcher.file,
        matcher.sha256,
    )
