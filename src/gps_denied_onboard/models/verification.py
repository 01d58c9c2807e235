"""``<model_dir>/verification.json``: which exported families passed ``gdnav models verify``.

Written by ``models.reference_check`` (build time, torch); read here without torch by the composition root
(``matcher.strategy: auto`` uses only verified families). A record names the files' sha256, so a file that
was re-exported after its check counts as unverified.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Final

from gps_denied_onboard.helpers import bounded_json
from gps_denied_onboard.helpers.model_manifest import PRECISION_FP32, ModelEntry

VERIFICATION_NAME: Final[str] = "verification.json"


def verification_key(family: str, precision: str = PRECISION_FP32) -> str:
    """Key of a family's record: the family for its fp32 export, ``<family>.<precision>`` otherwise (the
    int8 files of ``gdnav models quantize`` are verified on their own, against a floor of their own)."""
    return family if precision == PRECISION_FP32 else f"{family}.{precision}"


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


def family_verified(
    model_dir: Path, family: str, extractor: ModelEntry, matcher: ModelEntry, precision: str = PRECISION_FP32
) -> bool:
    """True when ``family`` at ``precision`` passed the reference check with exactly these two files."""
    record = read_verification(model_dir).get(verification_key(family, precision))
    if not isinstance(record, dict) or record.get("passed") is not True:
        return False
    ext, lg = record.get("extractor") or {}, record.get("matcher") or {}
    return (ext.get("file"), ext.get("sha256"), lg.get("file"), lg.get("sha256")) == (
        extractor.file,
        extractor.sha256,
        matcher.file,
        matcher.sha256,
    )
