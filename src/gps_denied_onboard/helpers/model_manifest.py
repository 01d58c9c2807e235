"""Model-directory manifest: what each exported model file is, where it came from, and its hashes.

``<model_dir>/manifest.json`` lists every model file with its own sha256, the source weights (name,
sha256, licence, official URL), the engine signature the file was exported with, the export parameters
and the creation time. The daemon calls ``verify_model_dir`` at start-up and refuses a directory whose
files are missing or changed.

Example::

    {"format": 1,
     "models": [{"file": "aliked-t16-480x640-k1024.onnx", "sha256": "...",
                 "source": {"name": "aliked-t16", "sha256": "...", "licence": "BSD-3-Clause", "url": "..."},
                 "signature": {"label": "...", "inputs": [...], "outputs": [...]},
                 "params": {"variant": "t16", "top_k": 1024, "height": 480, "width": 640, "opset": 17},
                 "created": "2026-01-01T00:00:00+00:00"}]}
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Final

from gps_denied_onboard.helpers import bounded_json
from gps_denied_onboard.helpers.inference_contract import EngineSignature, TensorSpec
from gps_denied_onboard.helpers.weight_pins import ALL_WEIGHTS, sha256_file

MANIFEST_NAME = "manifest.json"
MANIFEST_FORMAT = 1
#: ``params.precision`` of a model file; an entry without it is an fp32 export.
PRECISION_FP32: Final[str] = "fp32"
PRECISION_INT8: Final[str] = "int8"
PRECISIONS: Final[tuple[str, ...]] = (PRECISION_FP32, PRECISION_INT8)


class ModelDirError(RuntimeError):
    """The model directory or its manifest is missing, malformed, or does not match the files."""

    def __init__(self, message: str, *, path: str) -> None:
        super().__init__(f"{path}: {message}")
        self.path = path


@dataclass(frozen=True)
class ModelSource:
    """Where the weights behind a model file came from."""

    name: str
    sha256: str
    licence: str
    url: str


@dataclass(frozen=True)
class ModelEntry:
    """One model file of the directory."""

    file: str  # file name relative to the model directory
    sha256: str
    source: ModelSource
    signature: EngineSignature
    params: dict[str, Any] = field(default_factory=dict)
    created: str = ""  # ISO 8601 UTC


def entry_precision(entry: ModelEntry) -> str:
    """``params.precision`` of a manifest entry (``fp32`` when absent: every export before quantisation)."""
    return str(entry.params.get("precision", PRECISION_FP32))


def _signature_to_json(signature: EngineSignature) -> dict[str, Any]:
    def specs(items: tuple[TensorSpec, ...]) -> list[dict[str, Any]]:
        return [{"name": s.name, "rank": s.rank, "dtype": s.dtype} for s in items]

    return {"label": signature.label, "inputs": specs(signature.inputs), "outputs": specs(signature.outputs)}


def _signature_from_json(data: dict[str, Any]) -> EngineSignature:
    def specs(items: list[dict[str, Any]]) -> tuple[TensorSpec, ...]:
        return tuple(TensorSpec(name=s["name"], rank=s["rank"], dtype=s["dtype"]) for s in items)

    return EngineSignature(label=data["label"], inputs=specs(data["inputs"]), outputs=specs(data["outputs"]))


def _entry_to_json(entry: ModelEntry) -> dict[str, Any]:
    return {
        "file": entry.file,
        "sha256": entry.sha256,
        "source": vars(entry.source).copy(),
        "signature": _signature_to_json(entry.signature),
        "params": dict(entry.params),
        "created": entry.created,
    }


def _entry_from_json(data: dict[str, Any]) -> ModelEntry:
    return ModelEntry(
        file=data["file"],
        sha256=data["sha256"],
        source=ModelSource(**data["source"]),
        signature=_signature_from_json(data["signature"]),
        params=dict(data.get("params", {})),
        created=data.get("created", ""),
    )


def read_manifest(model_dir: str | Path) -> tuple[ModelEntry, ...]:
    """Parse ``<model_dir>/manifest.json``; ``ModelDirError`` if missing or malformed."""
    path = Path(model_dir) / MANIFEST_NAME
    try:
        data = bounded_json.loads(path.read_bytes(), max_bytes=1 << 20, what="model manifest")
    except FileNotFoundError:
        raise ModelDirError("no model manifest; export or import the models first", path=str(path)) from None
    except (OSError, ValueError) as exc:  # ValueError: not UTF-8 (UnicodeDecodeError) or not JSON
        raise ModelDirError(f"unreadable manifest: {exc}", path=str(path)) from exc
    if not isinstance(data, dict) or data.get("format") != MANIFEST_FORMAT:
        raise ModelDirError(f"expected manifest format {MANIFEST_FORMAT}", path=str(path))
    try:
        return tuple(_entry_from_json(item) for item in data["models"])
    except (KeyError, TypeError) as exc:
        raise ModelDirError(f"malformed manifest entry: {exc!r}", path=str(path)) from exc


def write_manifest(model_dir: str | Path, entry: ModelEntry) -> Path:
    """Add ``entry`` to the directory's manifest (replacing an entry for the same file); atomic write.

    ``entry.created`` is filled with the current UTC time when empty. Returns the manifest path.
    """
    root = Path(model_dir)
    path = root / MANIFEST_NAME
    entries = [e for e in read_manifest(root) if e.file != entry.file] if path.exists() else []
    if not entry.created:
        created = datetime.now(timezone.utc).isoformat(timespec="seconds")
        entry = ModelEntry(entry.file, entry.sha256, entry.source, entry.signature, entry.params, created)
    entries.append(entry)
    document = {"format": MANIFEST_FORMAT, "models": [_entry_to_json(e) for e in entries]}
    fd, tmp_name = tempfile.mkstemp(prefix=".manifest.", dir=root)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as stream:
            json.dump(document, stream, indent=2)
            stream.write("\n")
        os.replace(tmp_name, path)
    finally:
        Path(tmp_name).unlink(missing_ok=True)
    return path


def verify_model_dir(model_dir: str | Path) -> tuple[ModelEntry, ...]:
    """Check every listed model file exists and matches its sha256, and known sources match their pins.

    Returns the entries. Raises ``ModelDirError`` naming the first offending file.
    """
    root = Path(model_dir)
    if not root.is_dir():
        raise ModelDirError("model directory does not exist", path=str(root))
    entries = read_manifest(root)
    if not entries:
        raise ModelDirError("manifest lists no model", path=str(root / MANIFEST_NAME))
    for entry in entries:
        file_path = root / entry.file
        if not file_path.is_file():
            raise ModelDirError("model file listed in the manifest is missing", path=str(file_path))
        actual = sha256_file(file_path)
        if actual != entry.sha256:
            raise ModelDirError(
                f"sha256 {actual} differs from the manifest's {entry.sha256}; re-export the model",
                path=str(file_path),
            )
        data_file = entry.params.get("data_file")
        if data_file:  # external weights of a large graph (``<file>.data``): hashed like the graph
            data_path = root / str(data_file)
            if not data_path.is_file():
                raise ModelDirError("external weights file of the model is missing", path=str(data_path))
            data_actual = sha256_file(data_path)
            if data_actual != entry.params.get("data_sha256"):
                raise ModelDirError(
                    f"sha256 {data_actual} differs from the manifest's {entry.params.get('data_sha256')}; "
                    "re-export the model",
                    path=str(data_path),
                )
        known = ALL_WEIGHTS.get(entry.source.name)
        if known is not None and known.sha256 != entry.source.sha256:
            raise ModelDirError(
                f"exported from {entry.source.name} weights with sha256 {entry.source.sha256}, "
                f"not the pinned {known.sha256}",
                path=str(file_path),
            )
    return entries
