"""What a daemon run was started from, pinned by sha256: the fields ``gdnav run`` adds to ``daemon.config``.

Cheap on purpose: the config file and the two manifests are hashed, never the map mosaic (the cache
manifest pins every artifact's sha256, and the daemon verified them when it opened the cache). Model
files listed in a model directory's manifest take their sha256 from it (verified at start-up too); model
files given by path are hashed here (ONNX files of a few to tens of MB).

Nothing here raises: a file that cannot be read gets a null sha256 and a line in ``input_errors``, so a
recorder field never stops a start the runtime root has already accepted. See docs/fdr.md
(``daemon.config``).
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from gps_denied_onboard.components.c10_cache_build.manifest import MANIFEST_NAME as CACHE_MANIFEST_NAME
from gps_denied_onboard.components.c10_cache_build.manifest import sha256_file
from gps_denied_onboard.helpers import bounded_json
from gps_denied_onboard.helpers.model_manifest import MANIFEST_NAME as MODEL_MANIFEST_NAME
from gps_denied_onboard.helpers.model_manifest import ModelDirError, read_manifest


def _sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def run_inputs(
    config_file: str | Path | None,
    *,
    overrides: Sequence[str] = (),
    cache_dir: str | Path,
    model_dir: str | Path | None = None,
    model_files: Iterable[str | Path | None] = (),
) -> dict[str, Any]:
    """The ``daemon.config`` fields that pin this run's inputs (see docs/fdr.md):

    ``config_file``, ``config_sha256`` (the file's bytes; null without a file), ``config_overrides``
    (``--set`` items, in order), ``cache_dir``, ``cache_manifest_sha256``, ``cache_manifest_files``
    (artifacts the manifest lists), ``model_dir``, ``model_manifest_sha256``, ``models`` (a list of
    ``{"file", "sha256", "from": "manifest" | "computed"}``) and ``input_errors``.
    """
    errors: list[str] = []

    def read(path: Path, what: str) -> bytes | None:
        try:
            return path.read_bytes()
        except OSError as exc:
            errors.append(f"{what}: {path}: {exc.strerror or exc}")
            return None

    out: dict[str, Any] = {}
    config_bytes = read(Path(config_file), "config") if config_file is not None else None
    out["config_file"] = str(config_file) if config_file is not None else None
    out["config_sha256"] = _sha256_bytes(config_bytes) if config_bytes is not None else None
    out["config_overrides"] = list(overrides)

    cache_manifest = Path(cache_dir) / CACHE_MANIFEST_NAME
    raw = read(cache_manifest, "cache manifest")
    files: int | None = None
    if raw is not None:
        try:
            artifacts = bounded_json.loads(raw, max_bytes=1 << 20, what="cache manifest").get("artifacts")
            files = len(artifacts) if isinstance(artifacts, dict) else None
        except (ValueError, AttributeError) as exc:
            errors.append(f"cache manifest: {cache_manifest}: not a JSON object ({exc})")
    out["cache_dir"] = str(cache_dir)
    out["cache_manifest_sha256"] = _sha256_bytes(raw) if raw is not None else None
    out["cache_manifest_files"] = files

    models: list[dict[str, Any]] = []
    pinned: dict[Path, str] = {}
    out["model_dir"] = str(model_dir) if model_dir is not None else None
    out["model_manifest_sha256"] = None
    if model_dir is not None:
        root = Path(model_dir)
        raw = read(root / MODEL_MANIFEST_NAME, "model manifest")
        if raw is not None:
            out["model_manifest_sha256"] = _sha256_bytes(raw)
            try:
                for entry in read_manifest(root):
                    path = root / entry.file
                    pinned[path.resolve()] = entry.sha256
                    models.append({"file": str(path), "sha256": entry.sha256, "from": "manifest"})
            except ModelDirError as exc:
                errors.append(f"model manifest: {exc}")
    for item in model_files:
        if item is None:
            continue
        path = Path(item)
        if path.resolve() in pinned:
            continue  # already listed from the manifest
        try:
            digest: str | None = sha256_file(path)
        except OSError as exc:
            errors.append(f"model: {path}: {exc.strerror or exc}")
            digest = None
        models.append({"file": str(path), "sha256": digest, "from": "computed"})
    out["models"] = models
    out["input_errors"] = errors
    return out
