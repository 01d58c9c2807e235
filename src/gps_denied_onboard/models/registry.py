"""Known pretrained weights, pinned by sha256, and the two ways to obtain them: import or fetch.

The project never ships weights. A user either imports files they already have (``import_weights``) or
downloads them from the official public source (``fetch_weights``); in both cases only a file whose sha256
equals its pin (``helpers.weight_pins``) is accepted.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import urllib.error
import urllib.request
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import IO, Any

from gps_denied_onboard.helpers.weight_pins import (
    ALIKED_COMMIT,
    ALIKED_REPO_URL,
    ALL_WEIGHTS,
    KNOWN_WEIGHTS,
    PACKAGE_WEIGHTS,
    KnownWeights,
    sha256_file,
)

__all__ = [
    "ALIKED_COMMIT",
    "ALIKED_REPO_URL",
    "ALL_WEIGHTS",
    "KNOWN_WEIGHTS",
    "PACKAGE_WEIGHTS",
    "KnownWeights",
    "WeightsError",
    "WeightsFetchError",
    "WeightsHashMismatchError",
    "fetch_weights",
    "import_weights",
    "known_weights",
    "sha256_file",
    "weights_by_sha256",
]

class WeightsError(RuntimeError):
    """Weights missing, unknown, or not the pinned file; ``path`` names the file or URL concerned."""

    def __init__(self, message: str, *, path: str) -> None:
        super().__init__(f"{path}: {message}")
        self.path = path


class WeightsHashMismatchError(WeightsError):
    """A file's sha256 is not the pinned one (wrong, corrupted or tampered file)."""

    def __init__(self, *, path: str, expected: str, actual: str) -> None:
        super().__init__(f"sha256 {actual} does not match the pinned {expected}; file refused", path=path)
        self.expected = expected
        self.actual = actual


class WeightsFetchError(WeightsError):
    """Download from the official URL failed (no network, HTTP error, timeout)."""


def known_weights(name: str) -> KnownWeights:
    """Registry entry by name; ``KeyError`` listing the valid names if unknown."""
    try:
        return KNOWN_WEIGHTS[name]
    except KeyError:
        raise KeyError(f"unknown weights {name!r}; valid: {sorted(KNOWN_WEIGHTS)}") from None


def weights_by_sha256(sha256: str) -> KnownWeights | None:
    """Registry entry whose pin is ``sha256``, or None."""
    return next((w for w in KNOWN_WEIGHTS.values() if w.sha256 == sha256), None)


def _select(names: Iterable[str] | None) -> list[KnownWeights]:
    return [known_weights(n) for n in names] if names is not None else list(KNOWN_WEIGHTS.values())


def _install_verified(write: Callable[[IO[bytes]], None], weights: KnownWeights, dest_dir: Path) -> Path:
    """Write to a temporary file in ``dest_dir``, check the pin, then rename: no partial file is left."""
    dest = dest_dir / weights.filename
    fd, tmp_name = tempfile.mkstemp(prefix=f".{weights.filename}.", dir=dest_dir)
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "wb") as stream:
            write(stream)
        actual = sha256_file(tmp)
        if actual != weights.sha256:
            raise WeightsHashMismatchError(path=str(dest), expected=weights.sha256, actual=actual)
        os.replace(tmp, dest)
    finally:
        tmp.unlink(missing_ok=True)
    return dest


def import_weights(
    src_dir: str | Path, dest_dir: str | Path, names: Iterable[str] | None = None
) -> list[Path]:
    """Copy pinned weights from ``src_dir`` into ``dest_dir``, refusing any file whose sha256 differs.

    Args:
        src_dir: directory holding files named as in the registry (e.g. ``aliked-t16.pth``).
        dest_dir: model directory (created if needed).
        names: registry names to import; None imports every known file present in ``src_dir``.

    Returns:
        Paths of the files now in ``dest_dir`` (already-present verified files are kept as they are).

    Raises:
        WeightsError: a requested file is missing, or nothing known is in ``src_dir``.
        WeightsHashMismatchError: a source file is not the pinned file (nothing is copied for it).
    """
    src, dest_root = Path(src_dir), Path(dest_dir)
    wanted = _select(names)
    if names is None:
        wanted = [w for w in wanted if (src / w.filename).is_file()]
        if not wanted:
            expected = ", ".join(w.filename for w in KNOWN_WEIGHTS.values())
            raise WeightsError(f"no known weights file here (expected one of: {expected})", path=str(src))
    dest_root.mkdir(parents=True, exist_ok=True)
    imported = []
    for weights in wanted:
        source = src / weights.filename
        if not source.is_file():
            raise WeightsError(f"missing {weights.name} weights", path=str(source))
        actual = sha256_file(source)
        if actual != weights.sha256:
            raise WeightsHashMismatchError(path=str(source), expected=weights.sha256, actual=actual)
        target = dest_root / weights.filename
        if target.is_file() and sha256_file(target) == weights.sha256:
            imported.append(target)
            continue

        def copy(stream: IO[bytes], source: Path = source) -> None:
            with open(source, "rb") as src_stream:
                shutil.copyfileobj(src_stream, stream)

        imported.append(_install_verified(copy, weights, dest_root))
    return imported


def fetch_weights(
    dest_dir: str | Path,
    names: Iterable[str] | None = None,
    *,
    timeout_s: float = 60.0,
    urlopen: Callable[..., Any] = urllib.request.urlopen,
) -> list[Path]:
    """Download pinned weights from their official URLs into ``dest_dir`` and verify their sha256.

    Args:
        dest_dir: model directory (created if needed).
        names: registry names; None fetches all.
        timeout_s: socket timeout per request.
        urlopen: injectable for tests (same signature as ``urllib.request.urlopen``).

    Raises:
        WeightsFetchError: the URL cannot be reached (e.g. an offline machine); the message says how to
            import the files instead.
        WeightsHashMismatchError: the downloaded bytes are not the pinned file (nothing is kept).
    """
    dest_root = Path(dest_dir)
    dest_root.mkdir(parents=True, exist_ok=True)
    fetched = []
    for weights in _select(names):
        target = dest_root / weights.filename
        if target.is_file() and sha256_file(target) == weights.sha256:
            fetched.append(target)
            continue

        def download(stream: IO[bytes], weights: KnownWeights = weights) -> None:
            try:
                with urlopen(weights.url, timeout=timeout_s) as response:
                    shutil.copyfileobj(response, stream)
            except (urllib.error.URLError, OSError) as exc:
                raise WeightsFetchError(
                    f"cannot download {weights.name} ({exc}). Without internet access, copy "
                    f"{weights.filename} from {ALIKED_REPO_URL} (commit {ALIKED_COMMIT}, models/) onto this "
                    "machine and use import_weights()",
                    path=weights.url,
                ) from exc

        fetched.append(_install_verified(download, weights, dest_root))
    return fetched
